"""Posterior sampling: the sampler against known posteriors (simulation-based
calibration), the priors and their transforms, the gradient of the log density, the
command and its files."""

import json
import math

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jaxtissue.io import InputError
from jaxtissue.studies import posterior as post
from jaxtissue.studies.calibration import FreeParameter
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
    (u, _, div, *_), *_ = post.run_chains(programs, np.zeros((4, 2)) + 3.0, np.eye(2), settings, args=jnp.asarray(y))
    draws = u.reshape(-1, 2)
    se = np.sqrt(np.diag(cov) / 500)  # ≥ the Monte Carlo error of 2000 draws with ESS ≥ 500
    assert np.all(np.abs(draws.mean(axis=0) - mean) < 4 * se)
    np.testing.assert_allclose(np.cov(draws.T), cov, rtol=0.15, atol=0.05 * np.max(np.diag(cov)))
    assert div.sum() == 0


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


# ---- the calibration problem's posterior and the command

HEADER = "observableId,simulationConditionId,time,measurement,noiseParameters,unit,source\n"
WEEK = 604800.0


@pytest.fixture(scope="module")
def static_problem(tmp_path_factory):
    """A small static problem: DNA and collagen at 1–3 weeks, with SDs of 5 %, from the
    default parameters; k_m0 and E_m0 free (E_m0 unseen by these data). A second
    condition, "repeat", holds the same culture's 3-week collagen: what the posterior
    command holds out and predicts."""
    from helpers import TINY_MODEL

    import jaxtissue as jt
    from jaxtissue.studies import calibration as cal

    folder = tmp_path_factory.mktemp("posterior")
    r = jt.simulate(jt.Params(), jt.Protocol.static(), 3 * WEEK, jt.Grid(1, 8), coupling_interval_s=WEEK)
    rows = []
    for q, unit in (("dna_ug_per_g", "ug/g"), ("collagen_mg_per_g", "mg/g")):
        for w in (1, 2, 3):
            v = float(getattr(r, q)[r.index(w * WEEK)])
            rows.append(f"{q},static,{w * WEEK},{v!r},{0.05 * v!r},{unit},\n")
    v = float(r.collagen_mg_per_g[r.index(3 * WEEK)])
    rows.append(f"collagen_mg_per_g,repeat,{3 * WEEK},{v!r},{0.05 * v!r},mg/g,\n")
    (folder / "m.csv").write_text(HEADER + "".join(rows))
    (folder / "problem.toml").write_text(
        'measurements = "m.csv"\n[parameters.free]\n'
        'k_m0 = { bounds = [5e-8, 1e-6], transform = "log" }\n'
        'E_m0_kPa_per_ug_g = { bounds = [0.2, 5.0], transform = "linear", prior = { normal = [1.0, 0.5] } }\n'
        '[conditions.static]\nregime = "static"\n[conditions.repeat]\nregime = "static"\n' + TINY_MODEL + "rtol = 1e-8\natol = 1e-11\n[fit]\nstarts = 1\nmax_steps = 20\nprofile_points = 2\n")
    return cal.read_problem(folder / "problem.toml"), folder


def test_log_likelihood_gradient_matches_central_differences(static_problem):
    problem, _ = static_problem
    f = jax.jit(post.log_likelihood_t(problem))
    g = jax.jit(jax.grad(post.log_likelihood_t(problem)))
    t = problem.t_from_values([1.5e-7, 1.2])
    ad = np.asarray(g(t))
    for i in range(2):
        e = np.zeros(2)
        e[i] = 1e-4
        fd = (float(f(t + e)) - float(f(t - e))) / 2e-4
        assert ad[i] == pytest.approx(fd, rel=1e-4, abs=1e-8), i


@pytest.fixture(scope="module")
def sampled(static_problem):
    """`jaxtissue calibrate --posterior` on the small problem: its folder and stdout."""
    import contextlib
    import io

    from jaxtissue.cli import main

    _, folder = static_problem
    out = folder / "fit"
    argv = ["calibrate", str(folder / "problem.toml"), "--no-profiles", "--posterior", "--chains", "2", "--warmup", "40",
            "--samples", "40", "--hold-out", "repeat", "--out", str(out)]
    stdout = io.StringIO()
    with contextlib.redirect_stdout(stdout):
        assert main(argv) == 0
    return out, stdout.getvalue()


def test_calibrate_posterior_command_writes_inference_data(static_problem, sampled):
    import arviz as az

    problem, _ = static_problem
    out, stdout = sampled
    assert "posterior: 80 draws" in stdout
    idata = az.from_netcdf(out / "posterior.nc")
    assert {"posterior", "sample_stats", "observed_data", "posterior_predictive"} <= set(idata.groups())
    assert idata.posterior["k_m0"].shape == (2, 40) and "diverging" in idata.sample_stats
    np.testing.assert_allclose(idata.observed_data["y"].values, problem.data()[0][:-1])  # the repeat held out
    summary = json.loads((out / "summary.json").read_text())
    assert set(summary["posterior"]) == {"k_m0", "E_m0_kPa_per_ug_g"}
    for v in summary["posterior"].values():
        assert {"mean", "sd", "q05", "q50", "q95", "r_hat", "ess_bulk"} <= set(v) and v["q05"] <= v["q50"] <= v["q95"]
    assert summary["posterior"]["k_m0"]["constrained_by"] == "data"  # the data see k_m0 …
    assert summary["posterior"]["E_m0_kPa_per_ug_g"]["constrained_by"] == "prior"  # … not the modulus
    assert {"divergences", "sampling_seconds", "predictive_check"} <= set(summary)
    assert "## Posterior (NUTS)" in (out / "report.md").read_text()
    [held] = summary["held_out"]  # the repeat culture, predicted from the static data's posterior
    assert held["observation"].startswith("collagen_mg_per_g|repeat") and held["inside"] and held["lower"] < held["data"] < held["upper"]
    assert "held out collagen_mg_per_g|repeat" in stdout and len(summary["observations"]) == 6
    assert {"pairs.png", "traces.png"} <= {p.name for p in out.iterdir()}


def test_hold_out_refuses_what_it_cannot_do(static_problem):
    problem, _ = static_problem
    with pytest.raises(InputError, match="`hold_out` = 'flex': no observation of that condition; allowed: repeat, static"):
        post.hold_out(problem, "flex")
    with pytest.raises(InputError, match="no observation left to calibrate on"):
        post.hold_out(post.hold_out(problem, "repeat")[0], "static")


def test_calibrate_posterior_bad_flags_exit_2(static_problem, capsys):
    from jaxtissue.cli import main

    _, folder = static_problem
    with pytest.raises(SystemExit) as exit_:
        main(["calibrate", str(folder / "problem.toml"), "--posterior", "--chains", "0", "--out", str(folder / "x")])
    assert exit_.value.code == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "--chains" in err and not (folder / "x").exists()
    assert main(["calibrate", str(folder / "problem.toml"), "--hold-out", "repeat", "--out", str(folder / "x")]) == 2
    assert "--hold-out needs --posterior" in capsys.readouterr().err and not (folder / "x").exists()


def test_predict_command_gives_bands_that_hold_the_draws(sampled, capsys):
    import xarray as xr

    from jaxtissue.cli import main

    folder, _ = sampled
    out = folder.parent / "predicted"
    assert main(["predict", "--posterior", str(folder), "--regime", "static", "--t-end", str(2 * WEEK), "--draws", "6",
                 "--out", str(out)]) == 0
    assert "collagen_mg_per_g at" in capsys.readouterr().out
    ds = xr.open_dataset(out / "predict.nc", engine="h5netcdf")
    assert ds["collagen_mg_per_g"].shape[0] == 6 and ds["time_s"].values[-1] == pytest.approx(2 * WEEK)
    c = ds["collagen_mg_per_g"].values
    assert np.all(ds["collagen_mg_per_g_q05"].values <= ds["collagen_mg_per_g_q95"].values)
    np.testing.assert_allclose(ds["collagen_mg_per_g_q50"].values, np.median(c, axis=0))
    assert not ds["failed"].values.any() and np.ptp(c[:, -1]) > 0  # the draws differ, so does their collagen
    summary = json.loads((out / "summary.json").read_text())
    assert summary["draws"] == 6 and "collagen_mg_per_g" in summary["at_t_end"]
    assert (out / "bands.png").is_file()


def _broken(folder):
    (folder / "broken").mkdir(exist_ok=True)
    (folder / "broken" / "posterior.nc").write_text("not NetCDF")
    return folder / "broken"


@pytest.mark.parametrize("make, message", [
    (lambda d: d / "nowhere", "no posterior.nc there"),
    (_broken, "not a jaxtissue posterior"),
])
def test_predict_without_a_posterior_exits_2(sampled, capsys, make, message):
    from jaxtissue.cli import main

    folder, _ = sampled
    source = make(folder.parent)
    out = folder.parent / "never"
    assert main(["predict", "--posterior", str(source), "--out", str(out)]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "--posterior" in err and message in err and not out.exists()


def test_fitted_file_simulates_at_the_fit_resolution_and_reproduces_the_report(sampled, capsys):
    """`jaxtissue simulate --params fitted.toml` uses the fit's [model] table and gives
    the model values the calibration reported, within 0.5 %."""
    from jaxtissue.cli import main

    folder, _ = sampled
    out = folder.parent / "simulated"
    assert main(["simulate", "--regime", "static", "--t-end", str(3 * WEEK), "--params", str(folder / "fitted.toml"),
                 "--out", str(out)]) == 0
    assert "model resolution from" in capsys.readouterr().out
    run = json.loads((out / "summary.json").read_text())
    reported = json.loads((folder / "summary.json").read_text())["observations"]
    for o in reported:
        simulated = run[o["name"]][run["times_s"].index(o["time_s"])]
        assert simulated == pytest.approx(o["model"], rel=5e-3), o


_CHAINS_OVER_DEVICES = """
import sys, numpy as np, jax, jax.numpy as jnp
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


def test_chains_split_over_devices_give_the_same_draws(tmp_path):
    """Four chains over two CPU devices (a process of its own: the device count is
    fixed at start-up) draw what they draw on one device."""
    import os
    import pathlib
    import subprocess
    import sys

    here = pathlib.Path(__file__).resolve().parent
    env = dict(os.environ, XLA_FLAGS="--xla_force_host_platform_device_count=2", PYTHONPATH=str(here))
    out = subprocess.run([sys.executable, "-c", _CHAINS_OVER_DEVICES, str(tmp_path / "u.npy")], env=env, capture_output=True,
                         text=True, timeout=300)
    assert out.returncode == 0, out.stderr[-2000:]
    assert out.stdout.strip().splitlines()[-1] == "2"
    s = _split_chains_settings()
    (u, *_), *_ = post.run_chains(post.nuts_programs(_linear_gaussian, s), np.arange(8.0).reshape(4, 2), np.eye(2), s,
                                  args=jnp.asarray([0.7, -0.2, 1.1]))
    np.testing.assert_allclose(np.load(tmp_path / "u.npy"), u, rtol=1e-9, atol=1e-12)


# ---- protocol design under uncertainty


def test_risk_measures_and_chance_constraints():
    """The quantile risk takes the unfavourable tail; a ceiling met by its p-quantile
    holds for at least a fraction p of the draws (and a floor by its (1 − p)-quantile)."""
    from jaxtissue.studies.robust import Uncertainty

    rng = np.random.default_rng(0)
    J = rng.normal(size=200)
    u = Uncertainty("p", ("k_m0",), np.zeros((1, 1)), risk="quantile", quantile=0.05, constraint_probability=0.9)
    assert float(u.objective(jnp.asarray(J), +1)) == pytest.approx(np.quantile(J, 0.05))
    assert float(u.objective(jnp.asarray(J), -1)) == pytest.approx(np.quantile(J, 0.95))
    values = rng.lognormal(size=(200, 2))
    ceiling, floor = np.asarray(u.limit_values(jnp.asarray(values), ["ceiling", "floor"]))
    assert np.mean(values[:, 0] <= ceiling) >= 0.9 and np.mean(values[:, 1] >= floor) >= 0.9
    mean = Uncertainty("p", ("k_m0",), np.zeros((1, 1)))
    np.testing.assert_allclose(np.asarray(mean.limit_values(jnp.asarray(values), ["ceiling", "floor"])), values.mean(axis=0))


ROBUST = """
objective = "total_collagen"
t_end_s = 1814400.0
[constraints]
post_force_max_N = 0.02
[uncertainty]
posterior = "{posterior}"
{extra}
[optimizer]
starts = 1
steps = 4
learning_rate = 0.3
inner_steps = 2
grid_points = 3
""" + "\n[model]\nny = 8\nflex_nx = 2\nbeam_segments = 8\nbeam_steps_per_cycle = 24\ncoupling_interval_s = 604800.0\n"


@pytest.mark.parametrize("extra, message", [
    ('risk = "quantile"\nquantile = 1.5', "[uncertainty] quantile = 1.5 must be a number in (0, 1)"),
    ("constraint_probability = 0", "constraint_probability = 0 must be a number in (0, 1)"),
    ('risk = "worst"', "risk = 'worst'; allowed: 'mean', 'quantile'"),
    ("draws = 70\ncheck_draws = 20", "draws + check_draws = 90 exceeds the posterior's 80 draws"),
])
def test_bad_uncertainty_tables_exit_2(sampled, capsys, extra, message):
    from jaxtissue.cli import main

    folder, _ = sampled
    problem = folder.parent / "robust_bad.toml"
    problem.write_text(ROBUST.format(posterior=folder.name, extra=extra))
    out = folder.parent / "never"
    assert main(["optimize", str(problem), "--out", str(out)]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and message in err and not out.exists()


def test_uncertainty_needs_a_posterior_there(sampled, capsys):
    from jaxtissue.cli import main

    folder, _ = sampled
    problem = folder.parent / "robust_missing.toml"
    problem.write_text(ROBUST.format(posterior="no_such_folder", extra=""))
    assert main(["optimize", str(problem), "--out", str(folder.parent / "never")]) == 2
    assert "[uncertainty] posterior = " in capsys.readouterr().err


@pytest.mark.slow
def test_robust_design_meets_its_declared_probability_on_fresh_draws(sampled):
    """A chance-constrained design over 8 posterior draws, checked on 40 fresh ones
    beside the point-estimate optimum."""
    from jaxtissue.cli import main

    folder, _ = sampled
    problem = folder.parent / "robust.toml"
    problem.write_text(ROBUST.format(posterior=folder.name, extra='risk = "quantile"\nquantile = 0.1\n'
                                                                     "constraint_probability = 0.9\ndraws = 8\ncheck_draws = 40"))
    out = folder.parent / "robust_out"
    assert main(["optimize", str(problem), "--out", str(out), "--no-progress"]) == 0
    r = json.loads((out / "summary.json").read_text())["robust"]
    for key in ("robust_optimum", "point_estimate_optimum"):
        assert {"objective", "objective_mean", "constraint_probability", "protocol"} <= set(r[key])
    p = r["robust_optimum"]["constraint_probability"]
    print(f"fresh draws: robust optimum meets the limit in {p:.2f}, the point-estimate optimum in "
          f"{r['point_estimate_optimum']['constraint_probability']:.2f} (declared 0.9)")
    assert p >= 0.9 - 2 * math.sqrt(0.09 / 40)
    assert "## Under uncertainty" in (out / "report.md").read_text()


def test_reproduce_bands_from_a_posterior_folder(sampled):
    """`reproduce.calibrated_bands`: the static and flex cases over posterior draws."""
    import jaxtissue as jt

    folder, _ = sampled
    bands = jt.reproduce.calibrated_bands(t_end_s=WEEK, draws=3, folder=folder)
    assert set(bands) == {"static", "flex"}
    for b in bands.values():
        assert b["draws"] == 3 and b["failed"] == 0 and b["time_s"][-1] == pytest.approx(WEEK)
        lo, mid, hi = b["collagen_mg_per_g"]
        assert np.all(lo <= mid) and np.all(mid <= hi) and mid[-1] > 0
    assert bands["flex"]["post_force_max_N"][1][-1] > 0 == bands["static"]["post_force_max_N"][1][-1]
    assert jt.reproduce.calibrated_bands(folder=folder.parent / "none") is None
