"""The posterior sampler against known posteriors (simulation-based calibration, a
closed-form posterior), the priors and their transforms, chains over devices, and the
risk measures of design under uncertainty. The study built on it:
tests/test_posterior_study.py."""

import dataclasses
import math
import statistics

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jaxtissue.io import InputError
from jaxtissue.studies import posterior as post
from jaxtissue.studies.calibration import FitSettings, FreeParameter
from jaxtissue.studies.priors import Prior, read_prior

# ---- the sampler on a posterior known in closed form

A = np.array([[1.0, 0.5], [0.3, 1.2], [0.8, -0.4]])
NOISE = 0.5
SBC = post.SamplerSettings(chains=2, warmup=150, samples=100, max_tree_depth=5)


def _linear_gaussian(u, y):
    """ln p(θ | y) of y = Aθ + N(0, NOISE²), prior θ ~ N(0, I)."""
    r = (y - jnp.asarray(A) @ u) / NOISE
    return -0.5 * jnp.sum(r**2) - 0.5 * jnp.sum(u**2)


def simulation_based_calibration(datasets: int, seed: int = 0):
    """Ranks of the true θ among the posterior draws, over `datasets` data sets drawn from
    the prior predictive; and whether each central 90 % interval covers the truth."""
    programs = post.nuts_programs(_linear_gaussian, SBC)
    rng = np.random.default_rng(seed)
    ranks, covered = [], []
    for n in range(datasets):
        theta = rng.normal(size=2)
        y = A @ theta + NOISE * rng.normal(size=3)
        settings = post.SamplerSettings(**{**SBC.__dict__, "seed": n})
        (u, *_), *_ = post.run_chains(programs, rng.normal(size=(SBC.chains, 2)), np.eye(2), settings, args=jnp.asarray(y))
        draws = u.reshape(-1, 2)[::2]  # thinned: ranks need nearly independent draws
        ranks.append((draws < theta).sum(axis=0))
        lo, hi = np.quantile(draws, [0.05, 0.95], axis=0)
        covered.append((lo <= theta) & (theta <= hi))
    return np.array(ranks), len(draws), np.array(covered)


def _uniformity_p_value(ranks, n_draws, bins=5):
    """χ² test of the rank histogram against the uniform one."""
    from scipy.stats import chi2

    counts = np.histogram(ranks, bins=bins, range=(0, n_draws + 1))[0]
    expected = len(ranks) / bins
    return chi2.sf(np.sum((counts - expected) ** 2 / expected), bins - 1)


def _coverage_bounds(n, level=0.9):
    from scipy.stats import binom

    return binom.ppf(0.001, n, level) / n, binom.ppf(0.999, n, level) / n


def _check_sbc(datasets):
    ranks, n_draws, covered = simulation_based_calibration(datasets)
    lo, hi = _coverage_bounds(covered.size)
    coverage = covered.mean()
    p = [_uniformity_p_value(ranks[:, i], n_draws) for i in range(2)]
    print(f"SBC over {datasets} data sets: 90 % intervals cover the truth in {coverage:.3f} "
          f"(99.8 % binomial range [{lo:.3f}, {hi:.3f}]); rank-uniformity p = {p[0]:.3f}, {p[1]:.3f}")
    assert lo <= coverage <= hi
    assert min(p) > 1e-3


def test_simulation_based_calibration_on_a_linear_gaussian_posterior():
    _check_sbc(40)


@pytest.mark.slow
def test_simulation_based_calibration_on_a_linear_gaussian_posterior_200_data_sets():
    _check_sbc(200)


def test_draws_match_the_closed_form_posterior():
    """Mean and covariance of the draws against the conjugate posterior's."""
    y = np.array([0.7, -0.2, 1.1])
    precision = A.T @ A / NOISE**2 + np.eye(2)
    cov = np.linalg.inv(precision)
    mean = cov @ A.T @ y / NOISE**2
    settings = post.SamplerSettings(chains=4, warmup=200, samples=500)
    programs = post.nuts_programs(_linear_gaussian, settings)
    (u, _, div, *_), step_size, imm, *_ = post.run_chains(programs, np.zeros((4, 2)) + 3.0, np.eye(2), settings,
                                                           args=jnp.asarray(y))
    assert np.all(step_size == step_size[0]) and np.all(imm == imm[0])  # the chains' pooled adaptation
    draws = u.reshape(-1, 2)
    se = np.sqrt(np.diag(cov) / 500)  # ≥ the Monte Carlo error of 2000 draws with ESS ≥ 500
    assert np.all(np.abs(draws.mean(axis=0) - mean) < 4 * se)
    np.testing.assert_allclose(np.cov(draws.T), cov, rtol=0.15, atol=0.05 * np.max(np.diag(cov)))
    assert div.sum() == 0


def test_pooled_adaptation_is_the_geometric_mean_step_and_the_mean_metric():
    steps = np.array([0.1, 0.4, 0.2, 0.2])
    imms = np.stack([np.diag([1.0, 2.0]), np.diag([3.0, 2.0]), np.eye(2), [[1.0, 0.5], [0.5, 2.0]]])
    step, imm = post.pooled_adaptation(steps, imms)
    np.testing.assert_allclose(step, np.full(4, 0.2), rtol=1e-15)
    np.testing.assert_allclose(imm, np.broadcast_to([[1.5, 0.125], [0.125, 1.75]], (4, 2, 2)), rtol=1e-15)


# ---- priors and the unbounded coordinates


FREE = (
    FreeParameter("k_m0", 5e-8, 1e-6, "log"),  # log-uniform by default
    FreeParameter("lumping_C", 0.0, 2.0, "linear"),  # uniform by default
    FreeParameter("k_a", 2e-6, 2e-5, "log", Prior("log-normal", 6e-6, 0.4)),
    FreeParameter("E_m0_kPa_per_ug_g", 0.1, 5.0, "linear", Prior("normal", 1.0, 0.8)),
)


def _prior_cdf(f, x):
    """CDF of f's prior (truncated to its bounds) by quadrature in θ."""
    grid = np.linspace(f.lower, f.upper, 200001)[1:]
    density = np.exp(np.asarray(f.prior_density.log_density(jnp.asarray(grid))))
    cdf = np.cumsum(density)
    return np.interp(x, grid, cdf / cdf[-1])


def test_a_flat_likelihood_samples_each_prior_in_its_bounds():
    """With no data the sampler's draws (in u, mapped back to θ) follow each prior: the
    Jacobian of every transform is right. Kolmogorov–Smirnov distance against the CDF."""
    settings = post.SamplerSettings(chains=4, warmup=300, samples=1000)
    programs = post.nuts_programs(lambda u, args: post.log_prior_u(FREE, u), settings)
    (u, *_), *_ = post.run_chains(programs, np.zeros((4, len(FREE))), np.eye(len(FREE)), settings)
    t = np.asarray(jax.vmap(lambda x: post.t_from_u(FREE, x))(jnp.asarray(u.reshape(-1, len(FREE)))))
    for i, f in enumerate(FREE):
        theta = np.sort(np.asarray(f.from_t(t[:, i])))
        assert f.lower <= theta[0] and theta[-1] <= f.upper
        empirical = np.arange(1, len(theta) + 1) / len(theta)
        ks = np.max(np.abs(empirical - _prior_cdf(f, theta)))
        assert ks < 0.08, (f.name, ks)  # ~4/√ESS with ESS ≳ 2500


def test_prior_sd_in_the_fit_coordinate():
    f = FREE[0]  # log-uniform: uniform in ln θ
    assert f.prior_density.sd_in("log", f.lower, f.upper) == pytest.approx(math.log(f.upper / f.lower) / math.sqrt(12), rel=1e-3)
    g = FREE[3]
    assert g.prior_density.sd_in("linear", 0.1, 100.0) == pytest.approx(0.8 * 0.86, rel=0.1)  # truncated below at 0.1


@pytest.mark.parametrize("spec, message", [
    ("flat", "prior = 'flat'; allowed"),
    ({"normal": [1.0]}, "expected two numbers [mean, sd]"),
    ({"normal": [1.0, -1.0]}, "sd = -1 must be > 0"),
    ({"normal": [9.0, 1.0]}, "mean = 9 must lie in the bounds [0.5, 2]"),
    ({"gamma": [1.0, 1.0]}, "allowed"),
])
def test_bad_priors_name_the_key(spec, message):
    with pytest.raises(InputError) as err:
        read_prior(spec, 0.5, 2.0, "p.toml: [parameters.free] k_a")
    assert str(err.value).startswith("p.toml: [parameters.free] k_a prior") and message in str(err.value)


def test_u_round_trips_and_stays_inside_the_bounds():
    t = jnp.asarray([f.t_bounds[0] for f in FREE])  # on the lower bounds
    u = post.u_from_t(FREE, t)
    assert np.all(np.isfinite(np.asarray(u)))
    back = np.asarray(post.t_from_u(FREE, u))
    lo, hi = (np.array(x) for x in zip(*(f.t_bounds for f in FREE)))
    assert np.all((back > lo) & (back < lo + 2e-3 * (hi - lo)))
    mid = jnp.asarray((lo + hi) / 2)
    np.testing.assert_allclose(np.asarray(post.t_from_u(FREE, post.u_from_t(FREE, mid))), np.asarray(mid), rtol=1e-12)


def _unit_square_moments(log_density, n, box=((0.0, 1.0), (0.0, 1.0))):
    """Means and SDs of (a, b) under exp(log_density(a, b)) on `box` ([0, 1]²), by the
    midpoint rule on an n × n grid."""
    (a0, a1), (b0, b1) = box
    grid = (np.arange(n) + 0.5) / n
    a, b = np.meshgrid(a0 + (a1 - a0) * grid, b0 + (b1 - b0) * grid, indexing="ij")
    w = np.exp(log_density(a, b))
    mean = np.array([np.sum(w * a), np.sum(w * b)]) / np.sum(w)
    return mean, np.sqrt(np.array([np.sum(w * a**2), np.sum(w * b**2)]) / np.sum(w) - mean**2)


@pytest.mark.slow  # the default run: test_a_flat_likelihood_samples_each_prior_in_its_bounds, test_the_leader_map_spreads_a_pile_against_a_bound
def test_a_posterior_piled_against_two_bounds_mixes():
    """A narrow ridge t₂ ≈ t₁ whose mass piles into the corner of the box at the lower
    bounds (as k_c,max and k_a of the Engelmayr problem do), where the soft box's walls
    carry the mass: the draws' means against quadrature of the density, no divergent
    draw (the logistic map gave 5 of these 1600)."""
    free = (FreeParameter("a", 0.0, 1.0, "linear"), FreeParameter("b", 0.0, 1.0, "linear"))
    width, rate = 0.02, 6.0

    def log_likelihood(t):
        return -0.5 * ((t[1] - t[0]) / width) ** 2 - rate * (t[0] + t[1])

    settings = post.SamplerSettings(chains=4, warmup=200, samples=400)
    programs = post.nuts_programs(lambda u, args: log_likelihood(post.t_from_u(free, u)) + post.log_prior_u(free, u), settings)
    (u, _, div, _, steps), *_ = post.run_chains(programs, np.full((4, 2), 0.3) + 0.05 * np.arange(4)[:, None], np.eye(2) * 0.1,
                                                settings, chunk=400)
    t = np.asarray(post.t_from_u(free, jnp.asarray(u)))
    az = post.import_arviz()
    idata = az.from_dict(posterior={"t": t})
    ess, r_hat = (np.asarray(f(idata)["t"].values) for f in (az.ess, az.rhat))
    exact, sd = _unit_square_moments(lambda a, b: np.asarray(log_likelihood(jnp.stack([a, b]))), 3000)
    print(f"corner ridge: means {t.reshape(-1, 2).mean(axis=0).round(4)} (quadrature {exact.round(4)}), ESS {ess.round()}, "
          f"R-hat {r_hat.round(4)}, {steps.mean():.1f} leapfrog steps a draw, {int(div.sum())} divergent")
    assert np.all(np.abs(t.reshape(-1, 2).mean(axis=0) - exact) < 4 * sd / np.sqrt(ess))
    assert np.all(r_hat < 1.05) and div.sum() == 0


@dataclasses.dataclass(frozen=True)
class _StandIn:
    """What `post.sample` asks of a calibration problem, for linear free parameters
    `free` and residuals given by a subclass."""

    free: tuple = ()
    fit: FitSettings = FitSettings()  # the solver that traces the ridge (`post.trace_ridge`)

    def values_from_t(self, t):
        return t

    def t_bounds(self):
        return tuple(jnp.asarray(b) for b in zip(*(f.t_bounds for f in self.free)))


@dataclasses.dataclass(frozen=True)
class _RidgeInSeconds(_StandIn):
    """A stand-in calibration problem: θ₂ = 0.9 θ₁ + 1e-6 to ±1e-7, θ₁ = 5e-6 ± 1e-6 (rates
    in 1/s, linear coordinates), flat priors in [1e-6, 2.5e-5]: a thin ridge in units
    10⁻⁵ wide, as k_c,max and k_a are."""

    free: tuple = (FreeParameter("k_c_max", 1e-6, 2.5e-5, "linear"), FreeParameter("k_a", 1e-6, 2.5e-5, "linear"))

    def residuals(self, t):
        return jnp.stack([(t[0] - 5e-6) / 1e-6, (t[1] - 0.9 * t[0] - 1e-6) / 1e-7])


RIDGE_IN_SECONDS_SD = np.array([1e-6, math.hypot(0.9e-6, 1e-7)])  # the Gaussian's SDs of θ₁, θ₂


def test_whitening_is_at_home_in_any_units():
    """The sampler's coordinates on a ridge in parameters ~1e-5 wide (linear
    coordinates): standard normal z maps to the Gaussian's SDs in t, centred within
    half an SD of its mean (the centre comes from the profile's knots), so the mass
    matrix's adaptation sees O(1) scales (the draws themselves:
    test_sample_is_at_home_in_any_units, slow)."""
    problem = _RidgeInSeconds()
    t_best = jnp.asarray([5e-6, 5.5e-6])
    white = post.whitening(problem, t_best, jax.jacfwd(problem.residuals)(t_best))
    z = np.random.default_rng(0).normal(size=(4000, 2))
    t = np.asarray(post.t_from_u(problem.free, post.u_from_z(problem.free, white.args(), jnp.asarray(z))))
    np.testing.assert_allclose(t.std(axis=0), RIDGE_IN_SECONDS_SD, rtol=0.1)
    assert np.all(np.abs(t.mean(axis=0) - [5e-6, 5.5e-6]) < 0.5 * RIDGE_IN_SECONDS_SD)
    assert np.all(np.abs(white.z0) < 5)  # the chains' starts: O(1) in z


@pytest.mark.slow  # the default run: test_whitening_is_at_home_in_any_units
def test_sample_is_at_home_in_any_units():
    """`post.sample` on a ridge in parameters ~1e-5 wide (linear coordinates): it runs in
    whitened coordinates, so the mass matrix's adaptation sees O(1) scales; means and
    SDs against the Gaussian's, few leapfrog steps."""
    problem = _RidgeInSeconds()
    t_best = jnp.asarray([5e-6, 5.5e-6])
    draws = post.sample(problem, t_best, jax.jacfwd(problem.residuals)(t_best), post.SamplerSettings(chains=2, warmup=150, samples=200))
    az = post.import_arviz()
    ess = np.asarray(az.ess(az.from_dict(posterior={"t": draws.t}))["t"].values)
    mean, sd = draws.t.reshape(-1, 2).mean(axis=0), draws.t.reshape(-1, 2).std(axis=0)
    exact_sd = RIDGE_IN_SECONDS_SD
    print(f"ridge in 1/s: means {mean} (exact 5e-6, 5.5e-6), SDs {sd} (exact {exact_sd}), ESS {ess.round()}, "
          f"{draws.leapfrog_steps.mean():.1f} leapfrog steps a draw")
    assert np.all(np.abs(mean - [5e-6, 5.5e-6]) < 4 * exact_sd / np.sqrt(ess))
    np.testing.assert_allclose(sd, exact_sd, rtol=0.25)
    assert draws.leapfrog_steps.mean() < 8 and draws.diverging.sum() == 0


@dataclasses.dataclass(frozen=True)
class _RidgeFromACorner(_StandIn):
    """A stand-in calibration problem whose optimum lies on two bounds: θ₂ = 0.9 θ₁ to
    ±0.01, θ₁ = 0 ± 0.3 (half of it outside the box), flat priors in [0, 1]: a thin ridge
    running out of the corner, as k_c,max–k_a of the Engelmayr problem does."""

    free: tuple = (FreeParameter("a", 0.0, 1.0, "linear"), FreeParameter("b", 0.0, 1.0, "linear"))

    def residuals(self, t):
        return jnp.stack([(t[1] - 0.9 * t[0]) / 0.01, t[0] / 0.3])


def test_whitening_follows_a_ridge_out_of_an_optimum_on_the_bounds():
    """The sampler's coordinates at an optimum on two bounds: standard normal z maps to
    points along the ridge running out of the corner (the Laplace covariance in t, not in
    u, where dt/du ≈ 0 would hide it), with the posterior's means and SDs (quadrature) to
    within a fraction of an SD, and O(1) starts (the draws themselves:
    test_sample_follows_a_ridge_out_of_an_optimum_on_the_bounds, slow)."""
    problem = _RidgeFromACorner()
    t_best = jnp.zeros(2)
    white = post.whitening(problem, t_best, jax.jacfwd(problem.residuals)(t_best))
    z = np.random.default_rng(0).normal(size=(4000, 2))
    t = np.asarray(post.t_from_u(problem.free, post.u_from_z(problem.free, white.args(), jnp.asarray(z))))
    exact, sd = _unit_square_moments(lambda a, b: -0.5 * (((b - 0.9 * a) / 0.01) ** 2 + (a / 0.3) ** 2), 2000)
    assert np.all(np.abs(t.mean(axis=0) - exact) < 0.25 * sd)
    np.testing.assert_allclose(t.std(axis=0), sd, rtol=0.25)
    assert np.std(t[:, 1] - 0.9 * t[:, 0]) < 0.03  # across the ridge: its width, 0.01
    assert np.all(np.abs(white.z0) < 5)


@pytest.mark.slow  # the default run: test_whitening_follows_a_ridge_out_of_an_optimum_on_the_bounds
def test_sample_follows_a_ridge_out_of_an_optimum_on_the_bounds():
    """The whitening takes the Laplace covariance in t, not in u: at an optimum on a
    bound dt/du ≈ 0, which hid the ridge (both parameters looked free; 8-9 leapfrog steps
    a draw and bulk ESS ~120 of 1000 draws). Means against quadrature, ESS, steps."""
    problem = _RidgeFromACorner()
    t_best = jnp.zeros(2)
    draws = post.sample(problem, t_best, jax.jacfwd(problem.residuals)(t_best), post.SamplerSettings(chains=4, warmup=200, samples=250))
    az = post.import_arviz()
    ess = np.asarray(az.ess(az.from_dict(posterior={"t": draws.t}))["t"].values)
    exact, sd = _unit_square_moments(lambda a, b: -0.5 * (((b - 0.9 * a) / 0.01) ** 2 + (a / 0.3) ** 2), 2000)
    mean = draws.t.reshape(-1, 2).mean(axis=0)
    print(f"ridge out of a corner: means {mean.round(4)} (quadrature {exact.round(4)}), bulk ESS {ess.round()}, "
          f"{draws.leapfrog_steps.mean():.1f} leapfrog steps a draw, {int(draws.diverging.sum())} divergent")
    assert np.all(np.abs(mean - exact) < 4 * sd / np.sqrt(ess))
    # the steps a draw tell the two apart; one run's bulk ESS is noisy (105–575 over seeds 0–11, round-off changes
    # the chains): its floor keeps the means' check above meaningful
    assert np.all(ess > 80) and draws.leapfrog_steps.mean() < 7 and draws.diverging.sum() < 0.01 * draws.diverging.size


@dataclasses.dataclass(frozen=True)
class _CurvedRidge(_StandIn):
    """A stand-in calibration problem with a banana: b = a² to ±0.03, a = 0 ± 0.6, flat
    priors in [−1.5, 1.5] × [−0.5, 2.5]. Its ridge bends by 2.25 over the box, 75 of its
    widths, which no linear metric straightens."""

    free: tuple = (FreeParameter("a", -1.5, 1.5, "linear"), FreeParameter("b", -0.5, 2.5, "linear"))

    def residuals(self, t):
        return jnp.stack([(t[1] - t[0] ** 2) / 0.03, t[0] / 0.6])


def test_sample_straightens_a_curved_ridge():
    """The ridge coordinates (`post.trace_ridge`, `post.u_from_w`) follow the profile of
    the leading parameter, so NUTS sees a straight ridge: means against quadrature, ESS,
    leapfrog steps a draw."""
    problem = _CurvedRidge()
    t_best = jnp.zeros(2)
    draws = post.sample(problem, t_best, jax.jacfwd(problem.residuals)(t_best), post.SamplerSettings(chains=4, warmup=200, samples=250))
    az = post.import_arviz()
    ess = np.asarray(az.ess(az.from_dict(posterior={"t": draws.t}))["t"].values)
    exact, sd = _unit_square_moments(lambda a, b: -0.5 * (((b - a**2) / 0.03) ** 2 + (a / 0.6) ** 2), 2000, ((-1.5, 1.5), (-0.5, 2.5)))
    mean = draws.t.reshape(-1, 2).mean(axis=0)
    print(f"curved ridge: means {mean.round(4)} (quadrature {exact.round(4)}), bulk ESS {ess.round()}, "
          f"{draws.leapfrog_steps.mean():.1f} leapfrog steps a draw, {int(draws.diverging.sum())} divergent")
    assert np.all(np.abs(mean - exact) < 4 * sd / np.sqrt(ess))
    assert np.all(ess > 250) and draws.leapfrog_steps.mean() < 7 and draws.diverging.sum() == 0


@dataclasses.dataclass(frozen=True)
class _TwistedSheet(_StandIn):
    """A stand-in calibration problem whose ridge bends along two parameters, by an
    amount along one that changes with the other, as the Engelmayr k_c,max–k_a ridge
    bends with k_a and with lumping_C, most where k_a meets its bound: b = a² + a·s + s²/2
    to ±0.03, a = 0 ± 0.6, s = 0 ± 0.8, flat priors in [−1.5, 1.5]² × [−1, 6]."""

    free: tuple = (FreeParameter("a", -1.5, 1.5, "linear"), FreeParameter("b", -1.0, 6.0, "linear"),
                   FreeParameter("s", -1.5, 1.5, "linear"))

    def residuals(self, t):
        return jnp.stack([(t[1] - t[0] ** 2 - t[0] * t[2] - 0.5 * t[2] ** 2) / 0.03, t[0] / 0.6, t[2] / 0.8])


def _sheet_moments():
    """Means and SDs of (a, b, s) under `_TwistedSheet`'s posterior: a and s independent
    truncated normals (b's band lies inside its bounds), b = a² + a·s + s²/2 + N(0, 0.03²)."""
    moments = []
    for sd in (0.6, 0.8):
        x = -1.5 + 3.0 * (np.arange(20000) + 0.5) / 20000
        w = np.exp(-0.5 * (x / sd) ** 2)
        moments.append([np.sum(w * x**n) / np.sum(w) for n in (2, 4)])
    (a2, a4), (s2, s4) = moments
    return np.array([0.0, a2 + 0.5 * s2, 0.0]), np.sqrt([a2, a4 - a2**2 + a2 * s2 + 0.25 * (s4 - s2**2) + 0.03**2, s2])


def _twisted_sheet_whitening():
    problem = _TwistedSheet()
    t_best = jnp.zeros(3)
    J = jax.jacfwd(problem.residuals)(t_best)
    return problem, t_best, J, post.whitening(problem, t_best, J)


def test_whitening_traces_both_ridges_of_a_twisted_sheet():
    """`post.whitening` on the sheet b = a² + a·s + s²/2: the first ridge along s, the
    second along a traced at three positions of s (one position alone leaves the twist
    a·s: b off by up to ±1.5, 50 of the ridge's widths). Sampling in these coordinates:
    the slow test below; the two shears' inverse and gradient:
    `test_ridge_coordinates_invert_and_differentiate`."""
    *_, white = _twisted_sheet_whitening()
    assert [(r.leader, r.held, len(r.at)) for r in white.ridges] == [(2, 2, 1), (0, 2, 3)]


@pytest.mark.slow  # the default run: test_whitening_traces_both_ridges_of_a_twisted_sheet, test_sample_straightens_a_curved_ridge
def test_sample_straightens_a_twisted_sheet():
    """Two shears (`post.trace_ridge`, then `post.trace_second_ridge` traced at three
    positions of the leader) make the sheet b = a² + a·s + s²/2 flat: means and SDs
    against quadrature, ESS, leapfrog steps a draw."""
    problem, t_best, J, white = _twisted_sheet_whitening()
    assert [(r.leader, r.held, len(r.at)) for r in white.ridges] == [(2, 2, 1), (0, 2, 3)]
    draws = post.sample(problem, t_best, J, post.SamplerSettings(chains=4, warmup=200, samples=250))
    az = post.import_arviz()
    ess = np.asarray(az.ess(az.from_dict(posterior={"t": draws.t}))["t"].values)
    exact, sd = _sheet_moments()
    mean = draws.t.reshape(-1, 3).mean(axis=0)
    print(f"twisted sheet: means {mean.round(4)} (quadrature {exact.round(4)}), SDs {draws.t.reshape(-1, 3).std(axis=0).round(4)} "
          f"({sd.round(4)}), bulk ESS {ess.round()}, {draws.leapfrog_steps.mean():.1f} leapfrog steps a draw, "
          f"{int(draws.diverging.sum())} divergent")
    assert np.all(np.abs(mean - exact) < 4 * sd / np.sqrt(ess))
    np.testing.assert_allclose(draws.t.reshape(-1, 3).std(axis=0), sd, rtol=0.15)
    assert np.all(ess > 250) and draws.leapfrog_steps.mean() < 7 and draws.diverging.sum() == 0


def test_ridge_coordinates_invert_and_differentiate():
    """The shear `u_from_w`: with the knots of y = x² and its exact slopes, the cubic
    Hermite interpolant is exact (it reproduces cubics) and straight beyond the knots;
    `w_from_u` inverts it; with the two shears `whitening` builds for a twisted sheet,
    z ↦ u inverts and the log density in z has the gradient of central differences."""
    problem = _CurvedRidge()
    free = problem.free
    x = np.linspace(-1.2, 1.0, 7)
    y = np.stack([np.zeros(7), x**2], axis=-1)
    ridge = post.Ridge(0, 0, np.zeros(1), x[None], y[None], np.zeros((1, 7)), y[None], np.stack([np.zeros(7), 2 * x], axis=-1)[None])
    w = np.stack([np.linspace(-1.6, 1.6, 41), np.random.default_rng(0).normal(size=41) * 0.05], axis=-1)
    u = np.asarray(jax.vmap(lambda v: post.u_from_w(free, (ridge.arrays(),), v))(jnp.asarray(w)))
    t_a = np.asarray(post.t_from_u(free, jnp.asarray(u)))[:, 0]
    expected = np.where(t_a < -1.2, 1.44 - 2.4 * (t_a + 1.2), np.where(t_a > 1.0, 1.0 + 2.0 * (t_a - 1.0), t_a**2))
    np.testing.assert_allclose(u[:, 0], w[:, 0], atol=0)
    np.testing.assert_allclose(u[:, 1] - w[:, 1], expected, atol=1e-12)
    np.testing.assert_allclose(post.w_from_u(free, (ridge.arrays(),), jnp.asarray(u)), w, atol=1e-12)

    # a ridge along a traced at two positions of a held s, one profile of 3 knots padded to
    # the other's 7: at each position the shear is that profile's own, beyond its knots too;
    # halfway, their mean; and w_from_u inverts it
    free3 = _TwistedSheet().free
    short = np.linspace(-0.5, 0.5, 3)
    y7, y3 = (np.stack([np.zeros(len(v)), f, np.zeros(len(v))], axis=-1) for v, f in ((x, x**2), (short, -short)))
    profiles = [(x, np.zeros((7, 3)), np.zeros(7), y7), (short, np.zeros((3, 3)), np.zeros(3), y3)]
    ridge = post.Ridge.from_profiles(0, 2, [0.0, 1.0], profiles)
    assert ridge.x.shape == (2, 7) and np.all(np.isinf(ridge.chi2[1, 3:]))
    a = np.linspace(-1.4, 1.4, 29)
    shift = {}
    for s_ in (0.0, 0.5, 1.0):  # s's t
        w = np.asarray(post.u_from_t(free3, jnp.asarray(np.stack([a, 0.1 * a, np.full_like(a, s_)], axis=-1))))
        u = np.asarray(post.u_from_w(free3, (ridge.arrays(),), jnp.asarray(w)))
        np.testing.assert_allclose(post.w_from_u(free3, (ridge.arrays(),), jnp.asarray(u)), w, atol=1e-12)
        shift[s_] = u - w
        if s_ != 0.5:
            alone = post.Ridge.from_profiles(0, 2, [0.0], [profiles[int(s_)]]).arrays()
            np.testing.assert_allclose(shift[s_], np.asarray(post.u_from_w(free3, (alone,), jnp.asarray(w))) - w, atol=1e-12)
    np.testing.assert_allclose(shift[1.0][:, 1], -a, atol=1e-12)
    np.testing.assert_allclose(shift[0.5], 0.5 * (shift[0.0] + shift[1.0]), atol=1e-12)
    lone = post.Ridge.from_profiles(0, 0, [0.0], [(np.zeros(1), np.zeros((1, 3)), np.zeros(1), np.zeros((1, 3)))])
    assert lone.x.shape == (1, 2) and not post.straightens(lone)
    np.testing.assert_allclose(post.u_from_w(free3, (lone.arrays(),), jnp.asarray(w)), w, atol=0)

    sheet = _TwistedSheet()
    t_best = jnp.zeros(3)
    white = post.whitening(sheet, t_best, jax.jacfwd(sheet.residuals)(t_best))
    assert len(white.ridges) == 2 and all(post.straightens(r) for r in white.ridges)
    z = np.random.default_rng(1).normal(size=(20, 3))
    u = post.u_from_z(sheet.free, white.args(), jnp.asarray(z))
    np.testing.assert_allclose(np.linalg.solve(white.L, (post.w_from_u(sheet.free, white.args()[2], u) - white.c).T).T, z, atol=1e-10)
    log_density = post.log_density_fn(sheet)
    f = jax.jit(lambda z: log_density(post.u_from_z(sheet.free, white.args(), z)))
    z, h = jnp.asarray([0.3, -0.4, 0.7]), 1e-5
    fd = [(f(z + h * e) - f(z - h * e)) / (2 * h) for e in jnp.eye(3)]
    np.testing.assert_allclose(jax.grad(f)(z), fd, rtol=1e-6)


def test_warmup_correction_inverts_and_measures_a_ridge_the_shears_miss():
    """`post.fit_correction` on points whose z_1 given the leader z_0 is off centre (by
    z_0²) and of a width that changes 4-fold between its knots: in v, each slice of the
    leader between the knots has z_1 centred and of unit width; on standard normal points
    it stays near the identity (shrunk). `z_from_v` inverts, its log-determinant is that
    of the Jacobian, the log density in v differentiates."""
    rng = np.random.default_rng(0)
    lead = rng.normal(size=4000)
    z = np.stack([lead, lead**2 + 0.5 * np.exp(0.5 * lead) * rng.normal(size=4000), rng.normal(size=4000)], axis=-1)
    correction = post.fit_correction(z, 0)
    v = np.asarray(post.v_from_z(correction, jnp.asarray(z)))
    np.testing.assert_allclose(v[:, 0], z[:, 0], atol=0.15)  # a normal leader keeps (nearly) its coordinate
    x = np.asarray(correction.x)
    inside = np.flatnonzero((lead > x[0]) & (lead < x[-1]))
    chunks = np.array_split(inside[np.argsort(lead[inside])], 6)
    misfit = {name: np.array([abs(y[c, 1].mean()) + abs(np.log(y[c, 1].std())) for c in chunks]) for name, y in (("z", z), ("v", v))}
    print(f"slices off centre + off unit width (log): z {misfit['z'].round(2)}, v {misfit['v'].round(2)}")
    assert np.all(misfit["v"] < 0.5 * misfit["z"]) and misfit["v"].mean() < 0.25 * misfit["z"].mean()
    assert np.all(np.abs(v[:, 2] - z[:, 2]) < 0.1 * (1 + np.abs(z[:, 2])))  # independent of the leader: left nearly alone
    noise = post.fit_correction(rng.normal(size=(200, 3)), 1)
    assert np.max(np.abs(np.asarray(noise.m))) < 0.1 and np.max(np.abs(np.asarray(noise.log_s))) < 0.3

    back, log_det = post.z_from_v(correction, jnp.asarray(v))
    np.testing.assert_allclose(back, z, atol=1e-10)
    for point in v[:5]:
        J = jax.jacfwd(lambda x: post.z_from_v(correction, x)[0])(jnp.asarray(point))
        np.testing.assert_allclose(post.z_from_v(correction, jnp.asarray(point))[1], np.linalg.slogdet(J)[1], atol=1e-12)
    identity = post.no_correction(3, 1)
    np.testing.assert_allclose(post.z_from_v(identity, jnp.asarray(z[:10]))[0], z[:10], atol=1e-14)
    np.testing.assert_allclose(post.v_from_z(identity, jnp.asarray(z[:10])), z[:10], atol=1e-14)

    def log_density(x):
        y, log_j = post.z_from_v(correction, x)
        return -0.5 * jnp.sum(y**2) + log_j

    x, h = jnp.asarray([0.4, -0.3, 0.8]), 1e-5
    fd = [(log_density(x + h * e) - log_density(x - h * e)) / (2 * h) for e in jnp.eye(3)]
    np.testing.assert_allclose(jax.grad(log_density)(x), fd, rtol=1e-6)


def _funnel(v, correction):
    """A 2-D funnel in the sampler's coordinates v (`post.z_from_v`): a ~ N(0, 1),
    b | a ~ N(0, (0.1·e^(a/2))²), b's width changing 7-fold over a's ±2 SD, which no
    mass matrix follows."""
    z, log_j = post.z_from_v(correction, v)
    a, b = z[0], z[1]
    return -0.5 * a**2 - 0.5 * (b / (0.1 * jnp.exp(0.5 * a))) ** 2 - 0.5 * a + log_j


@pytest.mark.slow  # the default run: test_warmup_correction_inverts_and_measures_a_ridge_the_shears_miss
def test_the_warmup_correction_speeds_up_a_ridge_of_changing_width():
    """On the funnel (`_funnel`), the correction measured halfway through the warmup
    (`run_chains(refit=...)`) lets NUTS take longer steps: more effective samples of a per
    leapfrog step than the same warmup and draws without it, divergences under 1 % of the
    draws, and a's mean and SD right."""
    settings = post.SamplerSettings(chains=4, warmup=200, samples=250)

    def refit(path, end, correction):  # `posterior.correct` without the whitening
        return post.refit_correction(path, end, correction)

    az = post.import_arviz()
    start = np.random.default_rng(0).normal(size=(4, 2)) * [1.0, 0.1]
    results = {}
    for phases, fit in ((1, None), (post.warmup_phases(settings), refit)):
        (v, _, div, _, steps), _, _, _, correction = post.run_chains(post.nuts_programs(_funnel, settings, phases), start,
                                                                     np.eye(2), settings, args=post.no_correction(2),
                                                                     refit=fit, phases=phases)
        a = np.asarray(post.z_from_v(correction, jnp.asarray(v))[0])[..., 0]
        ess = float(az.ess(a))
        results[phases] = (1000 * ess / steps.sum(), a.mean(), a.std(), ess, steps.mean(), int(div.sum()))
    print("funnel: ESS of a per 1000 leapfrog steps, its mean, SD, ESS, steps a draw, divergent: without the correction "
          f"{np.round(results[1], 3)}, with it {np.round(results[phases], 3)}")
    assert results[phases][0] > 1.5 * results[1][0] and results[phases][5] < 0.01 * settings.chains * settings.samples
    assert abs(results[phases][1]) < 4 / np.sqrt(results[phases][3]) and abs(results[phases][2] - 1.0) < 0.15


def test_the_correction_is_differentiable_at_its_knots():
    """`z_from_v` at a point where the leader sits exactly on a knot of its map and z_l
    on a knot of the other coordinates' curves: its Jacobian equals central differences
    and its log-determinant is the one `z_from_v` returns (one-sided clipping at a knot
    would halve the derivative there)."""
    c = post.no_correction(2)
    q_z = jnp.asarray([-1.4, -0.5, 0.0, 0.8, 1.9])  # the leader's map: knots q_v at these values
    c = c._replace(q_z=q_z, q_slope=jnp.asarray([0.9, 1.1, 1.3, 1.0, 0.7]), x=jnp.asarray([-2.0, -1.0, -0.5, 0.5, 1.5]),
                   m=c.m.at[:, 1].set(jnp.asarray([0.3, -0.2, 0.1, 0.4, 0.0])), m_slope=c.m_slope.at[:, 1].set(0.2),
                   log_s=c.log_s.at[:, 1].set(jnp.asarray([0.1, -0.3, 0.2, 0.0, -0.1])), log_s_slope=c.log_s_slope.at[:, 1].set(-0.4))
    v = jnp.asarray([float(c.q_v[1]), 0.7])  # z_l = q_z[1] = -0.5 = x[2]
    z, log_det = post.z_from_v(c, v)
    assert float(z[0]) == pytest.approx(-0.5, abs=1e-15)
    jac = jax.jacfwd(lambda v: post.z_from_v(c, v)[0])(v)
    fd = np.stack([(post.z_from_v(c, v + e)[0] - post.z_from_v(c, v - e)[0]) / 2e-6 for e in 1e-6 * jnp.eye(2)], axis=1)
    np.testing.assert_allclose(jac, fd, rtol=1e-4, atol=1e-8)  # FD across a jump in the curvature
    assert float(jnp.log(jnp.abs(jnp.linalg.det(jac)))) == pytest.approx(float(log_det), abs=1e-12)


def test_the_leader_map_spreads_a_pile_against_a_bound():
    """`post.fit_correction`'s map of the leader: points of a leader piled against a wall
    (exponential, z ≥ 0) come out with the normal's quantiles at `CORRECTION_LEVELS` (up
    to the knots' small shrinkage) and close to normal between them; the map is
    increasing, inverts, and its log-derivative is in the log-determinant (checked
    against the Jacobian)."""
    rng = np.random.default_rng(1)
    lead = rng.exponential(size=4000)
    z = np.stack([lead, rng.normal(size=4000)], axis=-1)
    correction = post.fit_correction(z, 0)
    v = np.asarray(post.v_from_z(correction, jnp.asarray(z)))
    levels = np.asarray(post.CORRECTION_LEVELS)
    normal = np.array([statistics.NormalDist().inv_cdf(q) for q in levels])
    np.testing.assert_allclose(np.quantile(v[:, 0], levels), normal, atol=0.02)  # less the knots' shrinkage: 4000 points
    # between the levels, five times closer to the normal's quantiles than the exponential's own
    inner = np.linspace(0.06, 0.94, 45)
    off_v = np.abs(np.quantile(v[:, 0], inner) - [statistics.NormalDist().inv_cdf(q) for q in inner]).max()
    off_z = np.abs(np.quantile((z[:, 0] - z[:, 0].mean()) / z[:, 0].std(), inner) - [statistics.NormalDist().inv_cdf(q) for q in inner]).max()
    print(f"leader map: largest quantile offset from the normal's, 6-94 %: v {off_v:.3f}, z standardised {off_z:.3f}")
    assert off_v < 0.2 * off_z
    grid = jnp.linspace(-6.0, 6.0, 2001)
    mapped = np.asarray(post.z_from_v(correction, jnp.stack([grid, jnp.zeros_like(grid)], axis=-1))[0][:, 0])
    assert np.all(np.diff(mapped) > 0)
    np.testing.assert_allclose(post.z_from_v(correction, jnp.asarray(v))[0], z, atol=1e-10)
    for point in v[:5]:
        J = jax.jacfwd(lambda x: post.z_from_v(correction, x)[0])(jnp.asarray(point))
        np.testing.assert_allclose(post.z_from_v(correction, jnp.asarray(point))[1], np.linalg.slogdet(J)[1], atol=1e-12)


def test_the_leader_map_keeps_what_its_noise_cannot_explain():
    """The leader's knots (`post.fit_correction`): of 200 points of a standard normal
    leader, the normal's quantiles themselves (the points' own are off by their noise,
    which is not worth a map); of 800 points of a leader shifted by 2 and wider by 1.5,
    the points' own quantiles, little shrunk."""
    rng = np.random.default_rng(2)
    normal = np.array([statistics.NormalDist().inv_cdf(q) for q in post.CORRECTION_LEVELS])
    z = rng.normal(size=(200, 3))
    own = np.quantile(z[:, 0], post.CORRECTION_LEVELS)
    assert np.abs(own - normal).max() > 0.05  # what a map of the points' own quantiles would move
    np.testing.assert_allclose(post.fit_correction(z, 0).q_z, normal, atol=1e-8)
    z = rng.normal(size=(800, 3))
    z[:, 0] = 2.0 + 1.5 * z[:, 0]
    own = np.quantile(z[:, 0], post.CORRECTION_LEVELS)
    q_z = post.fit_correction(z, 0).q_z
    np.testing.assert_allclose(q_z, own, atol=0.1)
    assert np.all(np.abs(q_z - normal) > 0.5)


_CHAINS_OVER_DEVICES = """
import sys
from jaxtissue.studies import sweep
assert sweep.use_cpu_devices(4)  # as `jaxtissue calibrate --posterior` does for 4 chains of a coupled density
import numpy as np, jax, jax.numpy as jnp
jax.config.update("jax_enable_x64", True)
from jaxtissue.studies import posterior as post
from test_posterior import _linear_gaussian, _split_chains_settings
s = _split_chains_settings()
(u, *_), *_ = post.run_chains(post.nuts_programs(_linear_gaussian, s), np.arange(8.0).reshape(4, 2), np.eye(2), s,
                              args=jnp.asarray([0.7, -0.2, 1.1]))
np.save(sys.argv[1], u)
print(len(jax.devices()))
"""


def _split_chains_settings():
    return post.SamplerSettings(chains=4, warmup=40, samples=20)


@pytest.mark.slow  # a process of its own; the default run: test_the_cpu_is_split_a_device_per_chain_for_coupled_densities
def test_chains_split_over_devices_give_the_same_draws(tmp_path):
    """Four chains over four CPU devices, one a chain as the command line makes them for
    a coupled density (a process of its own: the device count is fixed at start-up),
    draw what they draw on one device."""
    import os
    import pathlib
    import subprocess
    import sys

    here = pathlib.Path(__file__).resolve().parent
    env = {**{k: v for k, v in os.environ.items() if k != "XLA_FLAGS"}, "PYTHONPATH": str(here)}
    out = subprocess.run([sys.executable, "-c", _CHAINS_OVER_DEVICES, str(tmp_path / "u.npy")], env=env, capture_output=True,
                         text=True, timeout=300)
    assert out.returncode == 0, out.stderr[-2000:]
    assert out.stdout.strip().splitlines()[-1] == "4"
    s = _split_chains_settings()
    (u, *_), *_ = post.run_chains(post.nuts_programs(_linear_gaussian, s), np.arange(8.0).reshape(4, 2), np.eye(2), s,
                                  args=jnp.asarray([0.7, -0.2, 1.1]))
    np.testing.assert_allclose(np.load(tmp_path / "u.npy"), u, rtol=1e-7, atol=1e-9)  # batches of 1 round differently


# ---- protocol design under uncertainty


def _violation(kinds, limits):
    """Per-draw relative violations (≤ 0 where met) of ceilings and floors at `limits`."""
    return lambda v: jnp.stack([v[:, j] / L - 1.0 if kind == "ceiling" else 1.0 - v[:, j] / L
                                for j, (kind, L) in enumerate(zip(kinds, limits))], axis=1)


def test_risk_measures_and_chance_constraints():
    """The quantile risk takes the unfavourable tail; a chance constraint holds all limits
    together: where the judged values meet them, at least k = ⌈p·(n + 1)⌉ draws meet
    every limit, and where they break one, fewer than k do (counted draw by draw)."""
    from jaxtissue.studies.robust import Uncertainty, chance_rank, fewest_draws

    rng = np.random.default_rng(0)
    J = rng.normal(size=200)
    u = Uncertainty("p", ("k_m0",), np.zeros((1, 1)), risk="quantile", quantile=0.05, constraint_probability=0.9)
    assert float(u.objective(jnp.asarray(J), +1)) == pytest.approx(np.quantile(J, 0.05))
    assert float(u.objective(jnp.asarray(J), -1)) == pytest.approx(np.quantile(J, 0.95))
    assert [fewest_draws(p) for p in (0.5, 0.9, 0.95, 0.975)] == [1, 9, 19, 39]
    assert chance_rank(0.95, 19) == 19 and chance_rank(0.95, 40) == 39 and chance_rank(0.95, 16) == 16
    kinds = ["ceiling", "floor"]
    verdicts = set()
    for n, p in ((200, 0.9), (19, 0.95), (7, 0.5), (40, 0.975), (60, 0.9)):
        c = dataclasses.replace(u, constraint_probability=p)
        k = chance_rank(p, n)
        assert k / (n + 1) >= p - 1e-12
        for trial in range(20):
            values = rng.lognormal(size=(n, 2))
            limits = np.quantile(values, [rng.uniform(0.7, 1.0), rng.uniform(0.0, 0.3)], axis=0).diagonal()
            judged = np.asarray(c.limit_values(jnp.asarray(values), _violation(kinds, limits)))
            meets = judged[0] <= limits[0] and judged[1] >= limits[1]
            every = np.sum((values[:, 0] <= limits[0]) & (values[:, 1] >= limits[1]))  # draws meeting both
            assert meets == (every >= k), (n, p, trial, every, k)
            assert any(np.array_equal(judged, row) for row in values)  # one draw's values
            verdicts.add(meets)
    assert verdicts == {True, False}  # both outcomes were exercised
    # with one limit the judged value is the k-th smallest (ceiling) or largest (floor)
    values = rng.lognormal(size=(40, 1))
    c = dataclasses.replace(u, constraint_probability=0.9)
    k = chance_rank(0.9, 40)
    assert float(c.limit_values(jnp.asarray(values), _violation(["ceiling"], [1.0]))[0]) == np.sort(values[:, 0])[k - 1]
    assert float(c.limit_values(jnp.asarray(values), _violation(["floor"], [1.0]))[0]) == np.sort(values[:, 0])[40 - k]
    values = rng.lognormal(size=(40, 2))
    mean = Uncertainty("p", ("k_m0",), np.zeros((1, 1)))
    np.testing.assert_allclose(np.asarray(mean.limit_values(jnp.asarray(values), _violation(kinds, [1.0, 1.0]))), values.mean(axis=0))




def test_the_cpu_is_split_a_device_per_chain_for_coupled_densities(monkeypatch):
    """`split_cpu`: a device per chain where a log density is a coupled flex run, a
    device per core (at most one a chain) where every condition is static."""
    import os
    import pathlib

    from jaxtissue.studies import calibration

    asked = []
    monkeypatch.setattr(post, "use_cpu_devices", lambda n: asked.append(n) or True)
    full = calibration.read_problem(pathlib.Path(__file__).parents[1] / "calibrate" / "engelmayr2005.toml")
    static, _ = post.hold_out(full, "flex")
    assert post.split_cpu(full, 4) and post.split_cpu(static, 4) and post.split_cpu(static, 1)
    assert asked == [4, min(4, os.cpu_count()), 1]
