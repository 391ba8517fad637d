"""Bayesian calibration: the posterior of a calibration problem's free parameters,
sampled with NUTS (blackjax), diagnosed with ArviZ (docs/model.md §9).

The posterior of the free parameters θ given data y is

    p(θ | y) ∝ exp(−χ²(θ)/2) · Π_i p_i(θ_i)        inside the bounds,

with χ² the SD-weighted sum of squares of `calibration.Problem.residuals` and p_i the
priors (`priors.Prior`). NUTS samples it in unbounded coordinates u, mapped onto the
bounds of the fit coordinate t (ln θ or θ) by a soft box (`t_from_u`): t = u inside,
bent onto the bounds within a few widths δ = 5 % of the range; the density in u carries
the Jacobian |dθ/du|. Where the posterior piles up against a bound (k_a and k_c,max of
the Engelmayr problem) the logistic map t = lo + (hi − lo)·σ(u) would stretch that
corner into long arms of shrinking width, which NUTS crosses only with a small step;
the soft box keeps the ridge straight and of one width. The gradient of ln p comes
from forward-mode differentiation of the residuals (a handful of tangents through the
coupled solve), wrapped as a custom VJP so that blackjax's `jax.grad` uses it.

The sampler's coordinates follow the posterior's longest ridge as the profile
likelihood traces it (`trace_ridge`: the leading parameter pinned, the others
re-optimised) and a second ridge across it (`trace_second_ridge`), straightened by
shears (`u_from_w`) and whitened (`whitening`), then corrected twice during the
warmup where the chains find the posterior's mass off the profile's ridge, of another
width, or piled along it (`fit_correction`, `z_from_v`). Chains run batched under `vmap`, split over
the devices when there are several (`split_cpu`: the command line makes a CPU device
per chain where the density is a coupled run, one per core where it is cheap),
each with its own warmup (Stan's window adaptation of the step size and a dense mass
matrix). R-hat, effective sample sizes and quantiles are
ArviZ's.
"""

from __future__ import annotations

import dataclasses
import functools
import json
import math
import pathlib
import statistics
import time
from typing import NamedTuple

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from .. import cache
from ..limits import MAX_SWEEP_POINTS
from ._problem_files import ModelSettings
from .calibration import Problem
from .sweep import even_batches, use_cpu_devices, vmap_over_devices


def import_arviz():
    """ArviZ, imported without its notice about a future major version."""
    import warnings

    with warnings.catch_warnings():
        warnings.simplefilter("ignore", FutureWarning)
        import arviz
    return arviz


@dataclasses.dataclass(frozen=True)
class SamplerSettings:
    """NUTS settings: chains (batched with vmap), warmup and kept draws per chain."""

    chains: int = 4
    warmup: int = 300
    samples: int = 800
    seed: int = 0
    target_acceptance: float = 0.8
    max_tree_depth: int = 6  # at most 2⁶ − 1 leapfrog steps a draw
    warmup_tree_depth: int = 4  # at most 2⁴ − 1 a warmup draw: early steps must not run to the cap
    initial_step_size: float = 0.1  # the warmup's first, in the whitened coordinates z
    jitter: float = 0.5  # spread of the chains' starts around the ridge, in z (`whitening`)
    corrections: int = 2  # the warmup in corrections + 1 equal parts, the coordinates corrected between them (`correct`)
    pool: bool = True  # the draws use the chains' pooled step size and mass matrix (`pooled_adaptation`)

    def __post_init__(self):
        for name in ("warmup", "samples"):  # each chain's draws are kept (warmup: its positions)
            if self.chains * getattr(self, name) > MAX_SWEEP_POINTS:
                raise ValueError(f"chains x {name} = {self.chains} x {getattr(self, name)} = {self.chains * getattr(self, name):.3g} "
                                 f"draws; at most {MAX_SWEEP_POINTS}")


def check_size(problem: Problem, settings: SamplerSettings) -> None:
    """A `limits.ResourceError` where the chains' log-density gradients, taken at once,
    would not fit in memory (before the fit that precedes the sampling runs)."""
    problem.check_memory("the posterior", settings.chains, reverse=True)


# ---------------------------------------------------------------------------------------
# Coordinates and density
# ---------------------------------------------------------------------------------------


SOFT_EDGE = 0.05  # δ of the soft box, as a fraction of the range of t


def _t_bounds(free):
    """(lo, hi) of t for `free`, NumPy arrays: what the compiled maps below take (the
    maps between u, t, w and z are compiled once per shape; called eagerly, as the
    whitening calls them, their operations would each compile on their own)."""
    lo, hi = zip(*(f.t_bounds for f in free))
    return np.asarray(lo, float), np.asarray(hi, float)


def t_from_u(free, u):
    """The fit coordinate t (ln θ or θ) of u for the free parameters `free`: the soft box
    t = lo + δ·[s((u − lo)/δ) − s((u − hi)/δ)], s the softplus function, a smooth
    increasing map of the real line onto (lo, hi) that is t ≈ u a few δ inside."""
    return _t_of_u(*_t_bounds(free), u)


@jax.jit
def _t_of_u(lo, hi, u):
    d = SOFT_EDGE * (hi - lo)
    return lo + d * (jax.nn.softplus((u - lo) / d) - jax.nn.softplus((u - hi) / d))


def u_from_t(free, t, margin: float = 1e-3):
    """The unbounded coordinate of t (`t_from_u` inverted in closed form), t first moved
    `margin` of the range inside the bounds (an optimum on a bound has no finite u)."""
    return _u_of_t(*_t_bounds(free), t, margin)


@jax.jit
def _u_of_t(lo, hi, t, margin):
    d = SOFT_EDGE * (hi - lo)
    t = jnp.clip(jnp.asarray(t), lo + margin * (hi - lo), hi - margin * (hi - lo))
    a = (t - lo) / d
    return lo + d * (a + jnp.log(-jnp.expm1(-a))) - d * jnp.log(-jnp.expm1((t - hi) / d))


def log_dt_du(free, u):
    """ln(dt/du) of `t_from_u`, each coordinate: σ((u − lo)/δ) − σ((u − hi)/δ) in logs."""
    return _log_dt_du(*_t_bounds(free), u)


@jax.jit
def _log_dt_du(lo, hi, u):
    d = SOFT_EDGE * (hi - lo)
    return jax.nn.log_sigmoid((u - lo) / d) + jax.nn.log_sigmoid(-(u - hi) / d) + jnp.log(-jnp.expm1(-(hi - lo) / d))


def log_prior_u(free, u):
    """Σ ln p_i(θ_i) + ln|dθ_i/du_i|: the priors of `free` as a density in u."""
    t = t_from_u(free, u)
    total = jnp.sum(log_dt_du(free, u))
    for i, f in enumerate(free):
        value = f.from_t(t[i])
        total += f.prior_density.log_density(value) + (t[i] if f.transform == "log" else 0.0)  # dθ/dt = θ
    return total


def log_likelihood_t(problem: Problem):
    """−χ²(t)/2 with its gradient by forward mode (custom VJP): −∞ with a zero gradient
    where the model fails."""

    def residuals_twice(t):
        r = problem.residuals(t)
        return r, r

    @jax.custom_vjp
    def log_likelihood(t):
        return _value_and_grad(t)[0]

    def _value_and_grad(t):
        J, r = jax.jacfwd(residuals_twice, has_aux=True)(t)
        ok = jnp.all(jnp.isfinite(r)) & jnp.all(jnp.isfinite(J))
        r0 = jnp.where(ok, r, 0.0)
        value = jnp.where(ok, -0.5 * jnp.sum(r0**2), -jnp.inf)
        grad = jnp.where(ok, -(jnp.where(ok, J, 0.0).T @ r0), 0.0)
        return value, grad

    def bwd(grad, cotangent):
        return (cotangent * grad,)

    log_likelihood.defvjp(_value_and_grad, bwd)  # the forward pass keeps the gradient as its residual
    return log_likelihood


def log_density_fn(problem: Problem):
    """ln p(u | y) up to a constant, differentiable in u."""
    log_likelihood = log_likelihood_t(problem)

    def log_density(u):
        return log_likelihood(t_from_u(problem.free, u)) + log_prior_u(problem.free, u)

    return log_density


# ---------------------------------------------------------------------------------------
# Sampling
# ---------------------------------------------------------------------------------------


class Draws(NamedTuple):
    u: np.ndarray  # (chains, draws, k)
    t: np.ndarray  # fit coordinate
    values: np.ndarray  # natural units
    log_density: np.ndarray  # (chains, draws)
    diverging: np.ndarray
    acceptance_rate: np.ndarray
    leapfrog_steps: np.ndarray
    step_size: np.ndarray  # (chains,)
    inverse_mass_matrix: np.ndarray  # (chains, k, k), in the sampler's coordinates v (`u_from_v`), not u
    seconds: dict  # "warmup", "sampling"


def laplace_inverse_mass(problem: Problem, t_best, jacobian) -> np.ndarray:
    """The warmup's first inverse mass matrix: the Laplace covariance of t at the
    optimum, (JᵀJ + Σ₀⁻¹)⁻¹ with J = ∂r/∂t and Σ₀ = diag((hi − lo)²/12), the variance of
    a flat prior (which keeps directions the data leave free at the prior's width),
    taken as the covariance in u, where u = t off the walls. Not dt/du at the optimum:
    where the optimum lies on a bound, as k_a's of the Engelmayr problem does, dt/du ≈ 0
    there would make the parameter look free in u and hide the ridge that ties it to
    others."""
    lo, hi = _t_bounds(problem.free)
    J = np.asarray(jacobian)
    return np.linalg.inv(J.T @ J + np.diag(12.0 / (hi - lo) ** 2))


def nuts_programs(log_density, settings: SamplerSettings, phases: int = 1):
    """Jitted (adapt, draws) for `log_density(u, args)`, batched over chains.

    `adapt(keys, u0, imm0, args)`: window adaptation (dense mass matrix seeded with imm0)
    of each chain from its start u0, `settings.warmup // phases` steps, returning its
    state, step size, inverse mass matrix and the positions it passed through;
    `draws(keys, state, step_size, imm, args)`: one NUTS draw per key (keys of
    shape (chains, n, 2)), returning the final state and (position, log density,
    divergent, acceptance rate, leapfrog steps) of each draw."""
    import blackjax

    def adapt(key, u0, imm0, args):
        warmup = blackjax.window_adaptation(blackjax.nuts, lambda u: log_density(u, args), is_mass_matrix_diagonal=False,
                                            initial_inverse_mass_matrix=imm0, imm_shrinkage_to_previous=10.0,
                                            initial_step_size=settings.initial_step_size,
                                            target_acceptance_rate=settings.target_acceptance,
                                            max_num_doublings=settings.warmup_tree_depth)
        (state, parameters), info = warmup.run(key, u0, num_steps=settings.warmup // phases)
        return state, parameters["step_size"], parameters["inverse_mass_matrix"], info.state.position

    def draws(keys, state, step_size, inverse_mass_matrix, args):
        kernel = blackjax.nuts(lambda u: log_density(u, args), step_size, inverse_mass_matrix,
                               max_num_doublings=settings.max_tree_depth)

        def one(state, key):
            state, info = kernel.step(key, state)
            return state, (state.position, state.logdensity, info.is_divergent, info.acceptance_rate,
                           info.num_integration_steps)

        return jax.lax.scan(one, state, keys)

    adapt = vmap_over_devices(adapt, settings.chains, (0, 0, None, None))
    draws = vmap_over_devices(draws, settings.chains, (0, 0, 0, 0, None))
    return jax.jit(adapt), jax.jit(draws)


def split_cpu(problem: Problem, chains: int) -> bool:
    """Split a CPU into JAX devices for `chains` (`sweep.use_cpu_devices`; only before
    JAX starts its backends). Where a log density is a coupled flex run, a device per
    chain: each chain then runs its own NUTS trees instead of waiting for the longer
    tree of a batch-mate (the Engelmayr posterior samples 1.4× faster on 2 cores). Where
    every condition is static, a device per core: the chains batched on each share the
    per-operation overhead that dominates a cheap density (1.3× faster than a device
    per chain); also for more than 16 chains a core. Returns whether the setting was made."""
    import os

    observed = {o.regime for o in problem.observations} & set(problem.conditions)  # the conditions simulated
    coupled = any(problem.conditions[c].regime == "flex" for c in observed)
    cores = os.cpu_count() or 1
    return use_cpu_devices(chains if coupled and chains <= 16 * cores else min(chains, cores))


def run_chains(programs, u0, imm0, settings: SamplerSettings, args=(), progress=None, chunk: int = 50, refit=None,
               phases: int = 2):
    """Warmup then `settings.samples` draws per chain with `nuts_programs`' pair, the
    draws in chunks (one compiled chunk length) with `progress(n)` after each.
    `refit(path, end, args) -> (args, u)`: the warmup runs in `phases` parts (programs
    built with as many), and between two parts `refit` turns the earlier part's positions
    `path` (chains, steps, k) and end points into new args and starts for the next, which
    starts from the earlier's inverse mass matrix averaged over the chains. The draws run
    with the chains' pooled step size and metric where `settings.pool`
    (`pooled_adaptation`). Returns (position, log density, divergent, acceptance, leapfrog steps) arrays of
    shape (chains, samples, ...), the step sizes, inverse mass matrices and seconds, and
    the args the draws ran with."""
    adapt, draws = programs
    chunk = min(chunk, settings.samples)
    key_warmup, key_draws = jax.random.split(jax.random.PRNGKey(settings.seed))
    chains = np.shape(u0)[0]
    seconds = {}
    start = time.perf_counter()
    phases = phases if refit is not None else 1
    keys = jax.random.split(key_warmup, max(phases, 2) * chains).reshape(-1, chains, 2)
    state, step_size, imm, path = jax.block_until_ready(adapt(keys[0], jnp.asarray(u0), jnp.asarray(imm0), args))
    for phase in range(1, phases):
        if progress is not None:
            progress(settings.warmup // phases)
        args, u1 = refit(np.asarray(path), np.asarray(state.position), args)
        imm0 = np.mean(np.asarray(imm), axis=0)  # the next part starts from this one's metric, pooled over the chains
        state, step_size, imm, path = jax.block_until_ready(adapt(keys[phase], jnp.asarray(u1), jnp.asarray(imm0), args))
    seconds["warmup"] = time.perf_counter() - start
    if settings.pool:
        step_size, imm = pooled_adaptation(step_size, imm)
    if progress is not None:
        progress(settings.warmup - settings.warmup // phases * (phases - 1))
    start = time.perf_counter()
    keys = jax.random.split(key_draws, chains * settings.samples).reshape(chains, settings.samples, -1)
    parts = []
    for b in range(0, settings.samples, chunk):
        k = keys[:, b : b + chunk]
        n = k.shape[1]
        if n < chunk:
            k = jnp.concatenate([k, keys[:, : chunk - n]], axis=1)
        state, out = draws(k, state, step_size, imm, args)
        parts.append(jax.tree_util.tree_map(lambda x: np.asarray(x)[:, :n], out))
        if progress is not None:
            progress(n)
    seconds["sampling"] = time.perf_counter() - start
    arrays = tuple(np.concatenate(a, axis=1) for a in zip(*parts))
    return arrays, np.asarray(step_size), np.asarray(imm), seconds, args


def pooled_adaptation(step_size, inverse_mass_matrix):
    """The chains' warmup estimates pooled, the same for every chain: the geometric mean
    of the step sizes (chains,) and the mean of the inverse mass matrices (chains, k, k)
    (docs/numerics.md, "Posterior sampling"). The chains sample one posterior, and each
    warmup estimates its own from a hundred-odd correlated positions: their spread is
    noise, which would leave chains with trajectories of different lengths that mix at
    different rates."""
    step_size, imm = np.asarray(step_size), np.asarray(inverse_mass_matrix)
    return (np.full_like(step_size, np.exp(np.mean(np.log(step_size)))),
            np.broadcast_to(imm.mean(axis=0), imm.shape).copy())


class Ridge(NamedTuple):
    """A ridge of the posterior, traced as a profile likelihood traces it: the free
    parameter `leader` pinned at the knots `x` (its fit coordinate, increasing), the
    others re-optimised, with the parameter `held` pinned at each of the m values `at`
    (m = 1 and held = leader: nothing else held). Per position (first axis): `t`
    (knots, k) the profile optima, `chi2` their χ² (inf at padding), `y` (knots, k) the
    offsets in u (in w of the ridges applied before it, `u_from_w`) of every parameter
    but leader and held (columns zero) and `slope` dy/dx: the shear that straightens the
    ridge; all zero where it does not."""

    leader: int
    held: int
    at: np.ndarray  # (m,)
    x: np.ndarray  # (m, knots)
    t: np.ndarray  # (m, knots, k)
    chi2: np.ndarray  # (m, knots)
    y: np.ndarray  # (m, knots, k)
    slope: np.ndarray  # (m, knots, k)

    @classmethod
    def from_profiles(cls, leader: int, held: int, at, profiles) -> "Ridge":
        """The ridge of profiles (x, t, χ², y), one per position `at`: the slopes
        `_knot_slopes`', every profile padded to the same number of knots (at least
        two) along its straight extension, where its interpolant is unchanged."""
        n = max(2, max(len(x) for x, *_ in profiles))
        rows = []
        for x, t, chi2, y in profiles:
            slope = _knot_slopes(x, y) if len(x) > 1 else np.zeros_like(y)
            extra = np.arange(1, n - len(x) + 1) * (x[-1] - x[-2] if len(x) > 1 else 1.0)
            rows.append((np.append(x, x[-1] + extra), np.concatenate([t, np.repeat(t[-1:], len(extra), axis=0)]),
                         np.append(chi2, np.full(len(extra), np.inf)), np.concatenate([y, y[-1] + extra[:, None] * slope[-1]]),
                         np.concatenate([slope, np.repeat(slope[-1:], len(extra), axis=0)])))
        return cls(leader, held, np.asarray(at, float), *(np.stack(column) for column in zip(*rows)))

    def arrays(self):
        """(leader, held, at, x, y, slope) as JAX arrays: what `u_from_w` takes inside a program."""
        return tuple(jnp.asarray(a) for a in (self.leader, self.held, self.at, self.x, self.y, self.slope))

    def profile(self):
        """(x, t, χ²) of the middle position's profile."""
        m = len(self.at) // 2
        return self.x[m], self.t[m], self.chi2[m]

    def along(self, values) -> np.ndarray:
        """The points (n, k) of `profile` with the leader at `values` (n,), interpolated
        linearly between its knots."""
        x, t, _ = self.profile()
        return np.stack([np.interp(values, x, t[:, j]) for j in range(t.shape[1])], axis=-1)


def _segment(x, knots):
    """(j, h, s): the knot interval [knots[j], knots[j + 1]] of x, its width, and x's
    place in it (0 to 1 between the end knots; beyond them, the end interval's s, which
    the callers do not use). s is not clipped: at a knot a clip's tie would halve its
    derivative."""
    j = jnp.clip(jnp.searchsorted(knots, x) - 1, 0, knots.shape[0] - 2)
    h = knots[j + 1] - knots[j]
    return j, h, (x - knots[j]) / h


def _hermite(x, knots, y, slope):
    """The cubic Hermite interpolant of (y, slope) at the knots (C¹), straight beyond them."""
    j, h, s = _segment(x, knots)
    inside = (((2 * s - 3) * s**2 + 1) * y[j] + ((s - 2) * s + 1) * s * h * slope[j]
              + (3 - 2 * s) * s**2 * y[j + 1] + (s - 1) * s**2 * h * slope[j + 1])
    below = y[0] + slope[0] * (x - knots[0])
    above = y[-1] + slope[-1] * (x - knots[-1])
    return jnp.where(x < knots[0], below, jnp.where(x > knots[-1], above, inside))


def _hermite_slope(x, knots, y, slope):
    """d/dx of `_hermite`."""
    j, h, s = _segment(x, knots)
    inside = (6 * (s - 1) * s * (y[j] - y[j + 1]) / h + ((3 * s - 4) * s + 1) * slope[j] + (3 * s - 2) * s * slope[j + 1])
    return jnp.where(x < knots[0], slope[0], jnp.where(x > knots[-1], slope[-1], inside))


def _knot_slopes(x, y, xp=np):
    """dy/dx at the knots: the spacing-weighted mean of the neighbouring secants."""
    d = xp.diff(y, axis=0) / xp.diff(x)[:, None]
    if x.shape[0] == 2:
        return xp.concatenate([d, d])
    left, right = xp.diff(x)[:-1, None], xp.diff(x)[1:, None]
    return xp.concatenate([d[:1], (right * d[:-1] + left * d[1:]) / (left + right), d[-1:]])


def _shear(lo, hi, ridge_arrays, v):
    """The offsets of `Ridge` at the leader's and the held parameter's t of v (u or w:
    neither coordinate moves under the shear), for v of shape (..., k): each position's
    Hermite interpolant along the leader, blended across the positions by the Hermite
    interpolant of their weights in t_held (C¹, straight beyond the end positions)."""
    leader, held, at, x, y, slope = ridge_arrays
    t = _t_of_u(lo, hi, v)
    m = at.shape[0]
    eye = jnp.eye(m)
    blend_slope = _knot_slopes(at, eye, jnp) if m > 1 else None

    def one(t_leader, t_held):
        along = jax.vmap(_hermite, in_axes=(None, 0, 0, 0))(t_leader, x, y, slope)
        weights = _hermite(t_held, at, eye, blend_slope) if m > 1 else jnp.ones(1)
        return weights @ along

    return jnp.vectorize(one, signature="(),()->(k)")(jnp.take(t, leader, axis=-1), jnp.take(t, held, axis=-1))


def u_from_w(free, ridges_arrays, w):
    """u of the ridge coordinates w, `ridges_arrays` a sequence of `Ridge.arrays()`: the
    shears applied innermost (last) first. Each moves every parameter j but its leader
    and held parameter by y_j, j's profile optimum at their t (`Ridge`): unit Jacobian,
    and a ridge curved along the leader's axis made straight."""
    return _u_of_w(*_t_bounds(free), tuple(ridges_arrays), w)


@jax.jit
def _u_of_w(lo, hi, ridges_arrays, w):
    for arrays in reversed(ridges_arrays):
        w = w + _shear(lo, hi, arrays, w)
    return w


def w_from_u(free, ridges_arrays, u):
    """`u_from_w` inverted."""
    return _w_of_u(*_t_bounds(free), tuple(ridges_arrays), u)


@jax.jit
def _w_of_u(lo, hi, ridges_arrays, u):
    for arrays in ridges_arrays:
        u = u - _shear(lo, hi, arrays, u)
    return u


def _profile(problem: Problem, t_start, i: int, per_side: int, also: int = -1):
    """Free parameter i pinned at `per_side` points from `t_start` to each of its bounds
    (1 % of its range short), the others but `also` (held at t_start) re-optimised
    (`calibration.pinned_walk`): knots x (increasing), the optima t (knots, k) and their
    χ², points where the model failed left out."""
    from .calibration import pinned_walk

    lo, hi = _t_bounds(problem.free)
    margin, held = 0.01 * (hi[i] - lo[i]), (also, float(t_start[also]) if also >= 0 else 0.0)
    x0 = float(t_start[i])
    walks = [np.array([x0])] + [x0 + np.arange(1, per_side + 1) / per_side * (end - x0)
                                for end in (lo[i] + margin, hi[i] - margin) if abs(end - x0) > margin]
    xs, ts, chi2s = [], [], []
    for points in walks:
        t, chi2 = pinned_walk(problem, t_start, i, points, also=held)
        ok = np.isfinite(chi2)
        xs.append(points[: len(chi2)][ok])
        ts.append(t[ok])
        chi2s.append(chi2[ok])
    x, t, chi2 = np.concatenate(xs), np.concatenate(ts), np.concatenate(chi2s)
    order = np.argsort(x)
    return x[order], t[order], chi2[order]


def _u_on_ridge(free, t):
    """u of profile optima t, those on a bound taken to the bound in u (t a fraction
    ln 2 of δ inside): where the soft box keeps a posterior piled against that bound."""
    return u_from_t(free, jnp.asarray(t), margin=SOFT_EDGE * np.log(2.0))


def _leading(cov, scale, exclude=()):
    """The (at most two) parameters that lead the principal axis of `cov` scaled by the
    flat prior's SDs `scale`, leaving out `exclude`."""
    keep = np.setdiff1d(np.arange(len(scale)), exclude)
    sub = cov[np.ix_(keep, keep)] / np.outer(scale[keep], scale[keep])
    axis = np.abs(np.linalg.eigh(sub)[1][:, -1])
    order = np.argsort(-axis)
    return [int(keep[j]) for j in order[:2] if axis[j] >= 0.3] or [int(keep[order[0]])]


def trace_ridge(problem: Problem, t_best, cov, per_side: int = 8) -> Ridge:
    """The ridge along the principal axis of the Laplace covariance `cov` (scaled by the
    flat prior's): each of the (at most two) parameters that lead that axis is pinned at
    `per_side` points from the optimum to each of its bounds and the others re-optimised
    (`_profile`). The leader is the first whose profile keeps the others 2 % of their
    ranges off their bounds, and its profile is the shear; where none does, the ridge runs
    into a corner of the box, which no smooth shear follows, and the first candidate's
    profile is kept without one."""
    lo, hi = _t_bounds(problem.free)
    traced = []
    for i in _leading(cov, (hi - lo) / np.sqrt(12.0)):
        x, t, chi2 = _profile(problem, t_best, i, per_side)
        flat = np.zeros((len(x), len(t_best)))
        others, room = np.arange(len(t_best)) != i, 0.02 * (hi - lo)
        if len(x) > 1 and np.all((t[:, others] > lo[others] + room[others]) & (t[:, others] < hi[others] - room[others])):
            y = np.array(_u_on_ridge(problem.free, t) - _u_on_ridge(problem.free, t_best))
            y[:, i] = 0.0
            return Ridge.from_profiles(i, i, [t_best[i]], [(x, t, chi2, y)])
        traced.append(Ridge.from_profiles(i, i, [t_best[i]], [(x, t, chi2, flat)]))
    return traced[0]


SECOND_RIDGE_WIDTH = 0.3  # a second shear where a parameter's SD given the leader is ≥ 0.3 of its flat prior's
SECOND_RIDGE_AT = (0.1, 0.5, 0.9)  # the leader's profile-posterior quantiles it is traced at


def trace_second_ridge(problem: Problem, t_best, cov, ridge: Ridge, per_side: int = 8):
    """A second shear, applied before `ridge`'s (`u_from_w`), for a parameter j that
    stays wide given the leader i (conditional SD in the Laplace covariance `cov` at least
    `SECOND_RIDGE_WIDTH` of its flat prior's, the largest on the principal axis given the
    leader) and bends the others as it moves, by an amount that may change along the
    ridge (the Engelmayr problem's lumping_C shifts the k_c,max–k_a ridge by several of
    its widths, most where k_a meets its bound): j's profile (`_profile`) with i held at
    each of the `SECOND_RIDGE_AT` quantiles of its profile posterior, from `ridge`'s
    point there, taken through the first shear: x = t_from_u of j's coordinate there,
    y the others' offsets from the optimum's. None where no parameter is that wide or
    `ridge` carries no shear."""
    if not straightens(ridge):
        return None
    i = ridge.leader
    lo, hi = _t_bounds(problem.free)
    scale = (hi - lo) / np.sqrt(12.0)
    given = cov - np.outer(cov[:, i], cov[i]) / cov[i, i]
    j = _leading(given, scale, exclude=(i,))[0]
    if np.sqrt(given[j, j]) < SECOND_RIDGE_WIDTH * scale[j]:
        return None
    first = (ridge.arrays(),)
    reference = np.asarray(w_from_u(problem.free, first, _u_on_ridge(problem.free, t_best)))
    at = np.interp(SECOND_RIDGE_AT, *_cumulative(_profile_posterior(problem, ridge), ridge.profile()[0]))
    profiles = []
    for start in ridge.along(at):
        _, t, chi2 = _profile(problem, start, j, per_side, also=i)
        u = np.array(_u_on_ridge(problem.free, t))
        u[:, j] = np.asarray(u_from_t(problem.free, jnp.asarray(t)))[:, j]  # j's own knots unclipped: distinct, in place
        v = np.asarray(w_from_u(problem.free, first, jnp.asarray(u)))
        x = np.asarray(t_from_u(problem.free, jnp.asarray(v)))[:, j]
        y = v - reference
        y[:, [i, j]] = 0.0
        order = np.argsort(x)
        profiles.append((x[order], t[order], chi2[order], y[order]))
    return Ridge.from_profiles(j, i, at, profiles)


def straightens(ridge: Ridge) -> bool:
    """Whether `ridge` carries a shear (`trace_ridge`)."""
    return bool(np.any(ridge.y) or np.any(ridge.slope))


class Whitening(NamedTuple):
    """The sampler's coordinates z: u = `u_from_w`(ridges, c + L z), and the chains'
    starts `z0` along the ridges. `ridges`: the leading ridge (`trace_ridge`), then the
    second where there is one (`trace_second_ridge`)."""

    ridges: tuple
    c: np.ndarray
    L: np.ndarray
    z0: np.ndarray

    def args(self):
        """(c, L, ridges' arrays) as JAX arrays: the `args` of `whitened_programs`, `u_from_z`."""
        return jnp.asarray(self.c), jnp.asarray(self.L), tuple(r.arrays() for r in self.ridges)


def u_from_z(free, args, z):
    """u of the sampler's coordinates z (shape (..., k)), args = `Whitening.args()`."""
    c, L, ridges_arrays = args
    return u_from_w(free, ridges_arrays, c + z @ L.T)


def _profile_posterior(problem: Problem, ridge: Ridge) -> np.ndarray:
    """Weights of the knots of `ridge`'s profile (`Ridge.profile`) under its leader's
    profile posterior, exp(−χ²/2) × prior × knot spacing, normalised."""
    x, _, chi2 = ridge.profile()
    f = problem.free[ridge.leader]
    log_p = -0.5 * chi2 + np.asarray(f.prior_density.log_density(f.from_t(jnp.asarray(x))))
    log_p = log_p + (x if f.transform == "log" else 0.0)
    p = np.exp(log_p - log_p.max()) * np.gradient(x)
    return p / p.sum()


def _cumulative(p, x):
    """(the cumulative weight at each knot's midpoint, x): `np.interp` of levels over it
    gives quantiles of the weights p at the knots x."""
    return np.cumsum(p) - 0.5 * p, x


def _quantiles(p, x, n: int) -> np.ndarray:
    """n evenly spaced quantiles of the weights p at the knots x."""
    return np.interp((np.arange(n) + 0.5) / n, *_cumulative(p, x))


def whitening(problem: Problem, t_best, jacobian, chains: int = 4, jitter: float = 0.5, seed: int = 0) -> Whitening:
    """The sampler's coordinates (docs/numerics.md, "Posterior sampling"): the ridge
    (`trace_ridge`) and a second one (`trace_second_ridge`), straightened by `u_from_w`
    where they can be, then w = c + L z with c the ridges' centre and L Lᵀ the Laplace
    covariance of t (`laplace_inverse_mass`) given each sheared leader, whose own
    variance is that of its profile posterior (exp(−χ²/2) × prior at the knots): the
    Laplace Gaussian knows a ridge's direction at the optimum, not its length. Without a
    shear the added variance runs along the Laplace covariance's own ridge direction.
    Every coordinate of z is O(1) whatever the parameters' units (the warmup shrinks its
    estimates towards 10⁻³·I, which would swamp a coordinate 10⁻⁵ wide). The chains
    start on the ridges with each leader at evenly spaced quantiles of its profile
    posterior (the second's in reverse order), plus N(0, jitter²·I) in z: over-dispersed
    along the longest directions, where R-hat must see chains disagree."""
    cov = laplace_inverse_mass(problem, t_best, jacobian)
    ridge = trace_ridge(problem, t_best, cov)
    k = len(t_best)
    second = trace_second_ridge(problem, t_best, cov, ridge)
    ridges = (ridge,) if second is None else (ridge, second)
    arrays = tuple(r.arrays() for r in ridges)
    p = [_profile_posterior(problem, r) for r in ridges]
    x = [r.profile()[0] for r in ridges]
    mean = [float(q @ xr) for q, xr in zip(p, x)]
    variance = [float(q @ (xr - m) ** 2) for q, xr, m in zip(p, x, mean)]
    i = ridge.leader
    if straightens(ridge):
        lead = np.array([r.leader for r in ridges])
        rest = np.setdiff1d(np.arange(k), lead)
        given = np.zeros((k, k))
        given[np.ix_(rest, rest)] = cov[np.ix_(rest, rest)] - cov[np.ix_(rest, lead)] @ np.linalg.solve(
            cov[np.ix_(lead, lead)], cov[np.ix_(lead, rest)])
        given[lead, lead] = np.maximum(variance, np.diag(cov)[lead])
        cov = given
    else:
        direction = cov[:, i] / cov[i, i]
        cov = cov + max(variance[0] - cov[i, i], 0.0) * np.outer(direction, direction)
    # the centre and the starts: points of the leading profile, its leader at its mean
    # and quantiles; the second leader (in w) likewise, in reverse order
    along = ridge.along(np.append(mean[0], _quantiles(p[0], x[0], chains)))
    w = np.array(w_from_u(problem.free, arrays, u_from_t(problem.free, jnp.asarray(along))))
    if second is not None:
        j, x2 = second.leader, np.append(mean[1], _quantiles(p[1], x[1], chains)[::-1])
        w[:, j] = np.asarray(u_from_t(problem.free, jnp.asarray(np.outer(x2, np.ones(k)))))[:, j]
    c = w[0]
    L = np.linalg.cholesky(cov)
    z0 = np.linalg.solve(L, (w[1:] - c).T).T + jitter * np.random.default_rng(seed).normal(size=(chains, k))
    return Whitening(ridges, c, L, z0)


CORRECTION_BINS = 5  # slices of the leader's coordinate the warmup's correction is measured in
CORRECTION_LEVELS = (0.05, 0.25, 0.5, 0.75, 0.95)  # the leader's quantiles its own map sends to the normal's
CORRECTION_NORMAL = np.array([statistics.NormalDist().inv_cdf(q) for q in CORRECTION_LEVELS])  # the normal's, there
CORRECTION_SCALE = 10.0  # its widths are kept within [1/10, 10] of z's
CORRECTION_MIN_POINTS = 100  # warmup positions it needs (chains × half a warmup part); fewer: no correction
CORRECTION_AUTOCORRELATION = 4.0  # warmup positions per independent one, for the correction's noise


class Correction(NamedTuple):
    """The warmup's correction of `whitening`'s z (`z_from_v`). The leader's coordinate:
    z_l = g(v_l), g the monotone cubic Hermite interpolant through (`q_v`, `q_z`) with
    slopes `q_slope` (straight beyond the end knots). The others, along z_l: the mean
    m_j and log width ln s_j of every other z_j, as cubic Hermite interpolants through
    their values at the knots `x` (m straight beyond the end knots, ln s flat at and
    beyond them). The leader's own columns of m and ln s are zero."""

    lead: jax.Array  # () int: the leader's index in z
    x: jax.Array  # (knots,)
    m: jax.Array  # (knots, k)
    m_slope: jax.Array
    log_s: jax.Array
    log_s_slope: jax.Array
    q_v: jax.Array  # (levels,): normal quantiles
    q_z: jax.Array  # (levels,): the leader's quantiles in z
    q_slope: jax.Array


def no_correction(k: int, lead: int = 0, knots: int = CORRECTION_BINS) -> Correction:
    """The identity: z = v."""
    zero = jnp.zeros((knots, k))
    q = jnp.asarray(CORRECTION_NORMAL)
    return Correction(jnp.asarray(lead), jnp.arange(knots, dtype=float), zero, zero, zero, zero, q, q, jnp.ones_like(q))


def _along_leader(correction: Correction, x):
    """(m, ln s) of `correction` at the leader's z, x of shape (...)."""
    c = correction
    curve = jax.vmap(_hermite, in_axes=(None, None, 1, 1), out_axes=-1)

    def one(x):
        return curve(x, c.x, c.m, c.m_slope), curve(x, c.x, c.log_s, c.log_s_slope)

    return jnp.vectorize(one, signature="()->(k),(k)")(x)


def _leader_z(correction: Correction, v_lead):
    """(z_l, ln g'(v_l)): the leader's map of `Correction`."""
    c = correction
    return (_hermite(v_lead, c.q_v, c.q_z, c.q_slope),
            jnp.log(_hermite_slope(v_lead, c.q_v, c.q_z, c.q_slope)))


def _leader_v(correction: Correction, z_lead, iterations: int = 60):
    """The leader's map inverted: straight beyond the end knots, bisection between them."""
    c = correction
    z_lead = jnp.asarray(z_lead)
    lo, hi = jnp.full_like(z_lead, c.q_v[0]), jnp.full_like(z_lead, c.q_v[-1])

    def halve(_, bracket):
        lo, hi = bracket
        mid = 0.5 * (lo + hi)
        above = _hermite(mid, c.q_v, c.q_z, c.q_slope) > z_lead
        return jnp.where(above, lo, mid), jnp.where(above, mid, hi)

    lo, hi = jax.lax.fori_loop(0, iterations, halve, (lo, hi))
    below = c.q_v[0] + (z_lead - c.q_z[0]) / c.q_slope[0]
    beyond = c.q_v[-1] + (z_lead - c.q_z[-1]) / c.q_slope[-1]
    return jnp.where(z_lead < c.q_z[0], below, jnp.where(z_lead > c.q_z[-1], beyond, 0.5 * (lo + hi)))


@jax.jit
def z_from_v(correction: Correction, v):
    """z_l = g(v_l) for the leader l and z_j = m_j(z_l) + s_j(z_l)·v_j for every other
    j, with ln|dz/dv| = ln g'(v_l) + Σ_j ln s_j(z_l): a triangular map, one to one
    since g' > 0 and every s_j > 0."""
    z_lead, log_g = _leader_z(correction, jnp.take(v, correction.lead, axis=-1))
    m, log_s = _along_leader(correction, z_lead)
    z = m + jnp.exp(log_s) * v
    lead = jnp.arange(v.shape[-1]) == correction.lead
    return jnp.where(lead, z_lead[..., None], z), jnp.sum(log_s, axis=-1) + log_g


@jax.jit
def v_from_z(correction: Correction, z):
    """`z_from_v` inverted."""
    z = jnp.asarray(z)
    z_lead = jnp.take(z, correction.lead, axis=-1)
    m, log_s = _along_leader(correction, z_lead)
    lead = jnp.arange(z.shape[-1]) == correction.lead
    return jnp.where(lead, _leader_v(correction, z_lead)[..., None], (z - m) * jnp.exp(-log_s))


_mean_curve = jax.jit(lambda correction, x: _along_leader(correction, x)[0])


def _increasing(a) -> np.ndarray:
    """Knot positions a made strictly increasing (ties and reversals lifted by 1e-9 steps)."""
    return a[0] + np.maximum.accumulate(a - a[0]) + 1e-9 * np.arange(len(a))


def _monotone_slopes(x, y) -> np.ndarray:
    """Knot slopes of increasing data (x, y) that keep its cubic Hermite interpolant
    increasing (`_knot_slopes` capped at 2.5 times each adjacent secant: Fritsch and
    Carlson's sufficient condition with room to spare)."""
    d = np.diff(y) / np.diff(x)
    s = _knot_slopes(x, y[:, None])[:, 0]
    s[:-1], s[1:] = np.minimum(s[:-1], 2.5 * d), np.minimum(s[1:], 2.5 * d)
    return s


def _leader_quantiles(x, independent: float) -> np.ndarray:
    """The `CORRECTION_LEVELS` quantiles of the leader's coordinate x, each shrunk towards
    the standard normal's by what its noise cannot tell from them (James–Stein): the
    quantile at level q of n = `independent` points of spread σ has variance
    q(1 − q)σ² / (n φ(z_q)²); σ measured between the outer levels."""
    normal, levels = CORRECTION_NORMAL, np.asarray(CORRECTION_LEVELS)
    raw = np.quantile(x, levels)
    sigma = (raw[-1] - raw[0]) / (normal[-1] - normal[0])
    density = np.exp(-0.5 * normal**2) / math.sqrt(2 * math.pi)
    noise = levels * (1 - levels) * sigma**2 / (independent * density**2)
    off = raw - normal
    off *= np.clip(1.0 - noise / np.maximum(off**2, 1e-300), 0.0, 1.0)
    return _increasing(normal + off)


def fit_correction(positions, lead: int, bins: int = CORRECTION_BINS) -> Correction:
    """The correction measured on warmup positions (n, k) in z. The leader's map sends
    the `CORRECTION_LEVELS` quantiles of the points' leader coordinate to those of the
    standard normal (`_leader_quantiles`): a posterior piled against a bound along the
    ridge, which the profile cannot see, is spread over as many units of v as the rest.
    The others: the points sorted by their leader coordinate into `bins` slices of equal
    counts, each slice's mean of the leader coordinate a knot, its means and SDs of the
    others the values of m and s there (s kept within `CORRECTION_SCALE` of 1). Where
    the posterior's ridge departs from the profile's (a corner the shears do not
    follow, a width that changes along the ridge), z given its leader is off centre or
    not of unit width; v given its leader is, to the extent the slices see it."""
    p = np.asarray(positions, float)
    q_z = _leader_quantiles(p[:, lead], len(p) / CORRECTION_AUTOCORRELATION)
    slices = np.array_split(np.argsort(p[:, lead], kind="stable"), bins)
    x = _increasing(np.array([p[i, lead].mean() for i in slices]))
    # the means, then the widths about the mean curve (not about each slice's mean, which
    # would count the curve's change across a slice as width)
    m = np.array([p[i].mean(axis=0) for i in slices])
    m_slope = _knot_slopes(x, m)
    shape = no_correction(p.shape[1], lead, bins)._replace(x=jnp.asarray(x), m=jnp.asarray(m), m_slope=jnp.asarray(m_slope))
    curve = np.asarray(_mean_curve(shape, jnp.asarray(p[:, lead])))
    sd = np.sqrt([np.mean((p[i] - curve[i]) ** 2, axis=0) for i in slices])
    sd = np.clip(sd, 1 / CORRECTION_SCALE, CORRECTION_SCALE)
    log_s = np.log(sd)
    # both shrunk towards the identity by what the slices cannot tell from noise
    # (James–Stein), the warmup's points taken as `CORRECTION_AUTOCORRELATION` times fewer
    # independent ones
    n = np.array([len(i) for i in slices])[:, None] / CORRECTION_AUTOCORRELATION
    m *= np.clip(1.0 - sd**2 / n / np.maximum(m**2, 1e-300), 0.0, 1.0)
    log_s *= np.clip(1.0 - 0.5 / n / np.maximum(log_s**2, 1e-300), 0.0, 1.0)
    m[:, lead], log_s[:, lead] = 0.0, 0.0
    log_s_slope = _knot_slopes(x, log_s)
    log_s_slope[[0, -1]] = 0.0  # flat at the end knots, as beyond them
    return Correction(jnp.asarray(lead), *(jnp.asarray(a) for a in (x, m, _knot_slopes(x, m), log_s, log_s_slope,
                                                                    CORRECTION_NORMAL, q_z,
                                                                    _monotone_slopes(CORRECTION_NORMAL, q_z))))


@functools.lru_cache(maxsize=4)
def whitened_programs(problem: Problem, settings: SamplerSettings):
    """`nuts_programs` of the posterior in the corrected coordinates v (`z_from_v` of
    `whitening`'s z), with args = (`Whitening.args()`, `Correction`); their warmup in
    `warmup_phases(settings)` parts, `correct` run between them. Jitted here (the
    compiled programs are freed with the functions returned) and named by the problem's
    and the settings' values: where the command line saves its programs, a second run
    loads them (`cache.call`)."""
    program = eqx.filter_jit(_whitened_program)
    return tuple(functools.partial(cache.call, program, problem, settings, warmup_phases(settings), which)
                 for which in (0, 1))


def _log_density_in_v(problem: Problem):
    """ln p in the sampler's coordinates v, `(v, args) -> float` (`whitened_programs`)."""
    log_density = log_density_fn(problem)

    def in_v(v, args):
        white, correction = args
        z, log_det = z_from_v(correction, v)
        return log_density(u_from_z(problem.free, white, z)) + log_det

    return in_v


def _whitened_program(problem: Problem, settings: SamplerSettings, phases: int, which: int, *args):
    """`nuts_programs`' adapt (`which` 0) or draws (1) of `_log_density_in_v(problem)` on `args`."""
    return nuts_programs(_log_density_in_v(problem), settings, phases)[which](*args)


def u_from_v(problem: Problem, args, v):
    """u of the sampler's coordinates v, args = (`Whitening.args()`, `Correction`)."""
    white, correction = args
    return u_from_z(problem.free, white, z_from_v(correction, v)[0])


# compiled for `sample`'s conversion of the draws (eager, each small op compiles on its own)
_u_from_v = jax.jit(u_from_v, static_argnums=0)
_values_from_t = jax.jit(lambda problem, t: jax.vmap(jax.vmap(problem.values_from_t))(t), static_argnums=0)


def sampler_args(white: Whitening) -> tuple:
    """The args of `whitened_programs` before the warmup's correction: (`white.args()`,
    `no_correction`)."""
    return white.args(), no_correction(white.c.size, white.ridges[0].leader)


def warmup_phases(settings: SamplerSettings) -> int:
    """The parts the warmup of `whitened_programs` runs in: `settings.corrections` + 1
    where each part leaves at least `CORRECTION_MIN_POINTS` positions in its second half
    to measure the correction on, else 1 (the warmup in one piece, uncorrected)."""
    phases = settings.corrections + 1
    steps = settings.warmup // phases
    return phases if settings.corrections > 0 and settings.chains * (steps - steps // 2) >= CORRECTION_MIN_POINTS else 1


def warmup_refit(settings: SamplerSettings):
    """`run_chains`' `refit` for `whitened_programs`: `correct`, or None where the warmup
    runs in one piece (`warmup_phases`)."""
    return correct if warmup_phases(settings) > 1 else None


def correct(path, end, args):
    """`run_chains`' `refit` for args = (`Whitening.args()`, `Correction`): `refit_correction`."""
    white, old = args
    correction, v = refit_correction(path, end, old)
    return (white, correction), v


def refit_correction(path, end, old: Correction):
    """The correction (`fit_correction`, `old`'s leader) from the second half of a warmup
    part's positions `path` (chains, steps, k) in the coordinates v of the correction
    `old` it ran with, and the chains' end points in the new v."""
    k = path.shape[-1]
    z = np.asarray(z_from_v(old, jnp.asarray(path[:, path.shape[1] // 2 :].reshape(-1, k)))[0])
    correction = fit_correction(z, int(old.lead))
    return correction, np.asarray(v_from_z(correction, z_from_v(old, jnp.asarray(end))[0]))


def sample(problem: Problem, t_best, jacobian, settings: SamplerSettings = SamplerSettings(), progress=None) -> Draws:
    """NUTS draws of the posterior in `whitening`'s coordinates around `t_best`, the
    fit's optimum, corrected between the parts of the warmup where it is long enough
    (`warmup_phases`). `progress(n)` is called after each warmup part and after each
    chunk of draws."""
    white = whitening(problem, t_best, jacobian, settings.chains, settings.jitter, settings.seed)
    (v, lp, div, acc, steps), step_size, imm, seconds, args = run_chains(
        whitened_programs(problem, settings), white.z0, np.eye(white.c.size), settings, args=sampler_args(white),
        progress=progress, refit=warmup_refit(settings), phases=warmup_phases(settings))
    u = np.asarray(_u_from_v(problem, args, jnp.asarray(v)))
    t = np.asarray(t_from_u(problem.free, jnp.asarray(u)))
    values = np.asarray(_values_from_t(problem, jnp.asarray(t)))
    return Draws(u, t, values, lp, div, acc, steps, step_size, imm, seconds)


def model_values(problem: Problem, t, batch: int = 25, progress=None) -> np.ndarray:
    """The model's value of each observation at every draw: t of shape (..., k) →
    (..., observations), at most `batch` draws at a time under vmap, each batch split
    over the devices (`sweep.even_batches`)."""
    flat = np.asarray(t).reshape(-1, np.shape(t)[-1])
    size = even_batches(len(flat), batch)
    r = np.concatenate(_in_batches(_batched_residuals(problem, size), flat, size, progress))
    return problem.model_from_residuals(r).reshape(*np.shape(t)[:-1], -1)


def _residual_batch(problem: Problem, size: int, rows):
    """`problem.residuals` of each of the `size` rows, split over the devices."""
    return vmap_over_devices(problem.residuals, size)(rows)


@functools.lru_cache(maxsize=4)
def _batched_residuals(problem: Problem, size: int):
    """`_residual_batch` for `problem`, jitted once per problem: named by its values where
    the command line saves its programs, so that a second run loads it (`cache.call`)."""
    return functools.partial(cache.call, eqx.filter_jit(_residual_batch), problem, size)


def _in_batches(run, rows: np.ndarray, batch: int, progress=None) -> list:
    """`run` (jitted, vmapped) over `rows` `batch` at a time, the last batch padded with
    copies of its last row (one compiled batch shape); the outputs, padding dropped."""
    out = []
    for b in range(0, len(rows), batch):
        x = rows[b : b + batch]
        padded = np.concatenate([x, np.repeat(x[-1:], batch - len(x), axis=0)])
        out.append(jax.tree_util.tree_map(lambda a: np.asarray(a)[: len(x)], run(jnp.asarray(padded))))
        if progress is not None:
            progress(len(x))
    return out


# ---------------------------------------------------------------------------------------
# ArviZ: InferenceData, diagnostics
# ---------------------------------------------------------------------------------------


def observation_labels(problem: Problem) -> list[str]:
    return [f"{o.quantity}|{o.regime}|{o.time_s:g}s" for o in problem.observations]


def inference_data(problem: Problem, draws: Draws, model: np.ndarray):
    """An ArviZ `InferenceData`: posterior (natural units), sample_stats (with
    `diverging`), observed_data, posterior_predictive (`y`: model plus the measurement
    noise; `model`: without it), constant_data (the data's SDs)."""
    az = import_arviz()

    mean, sd = problem.data()
    noisy = problem.with_noise(model, np.random.default_rng(draws.u.shape[1] + 1).normal(size=model.shape))
    coords = {"observation": observation_labels(problem)}
    dims = {"y": ["observation"], "model": ["observation"], "sd": ["observation"]}
    idata = az.from_dict(
        posterior={n: draws.values[..., i] for i, n in enumerate(problem.names)},
        sample_stats={"diverging": draws.diverging, "lp": draws.log_density, "acceptance_rate": draws.acceptance_rate,
                      "n_steps": draws.leapfrog_steps,
                      "step_size": np.repeat(draws.step_size[:, None], draws.u.shape[1], axis=1)},
        posterior_predictive={"y": noisy, "model": model},
        observed_data={"y": mean},
        constant_data={"sd": sd},
        coords=coords, dims=dims,
    )
    idata.posterior.attrs.update({
        "problem": problem.name, "free_parameters": list(problem.names),
        "model_settings": json.dumps(dataclasses.asdict(problem.model)),  # the resolution `predict` simulates with
        "warmup_seconds": draws.seconds["warmup"], "sampling_seconds": draws.seconds["sampling"]})
    return idata


def contraction(problem: Problem, draws: Draws) -> np.ndarray:
    """Posterior contraction 1 − Var_post(t)/Var_prior(t) of each free parameter in its
    fit coordinate: near 1 where the data pin it down, near 0 where only its prior does."""
    post_var = np.var(draws.t.reshape(-1, draws.t.shape[-1]), axis=0)
    prior_var = np.array([f.prior_density.sd_in(f.transform, f.lower, f.upper) ** 2 for f in problem.free])
    return 1.0 - post_var / prior_var


CONSTRAINED = 0.5
"""Contraction above which a parameter counts as constrained by the data."""


def posterior_summary(problem: Problem, draws: Draws, idata) -> dict:
    """`summary.json`'s `posterior`, `divergences`, `sampling_seconds` and friends."""
    az = import_arviz()

    stats = az.summary(idata, var_names=list(problem.names), kind="diagnostics", round_to="none")  # R-hat < 1.01 needs 3 digits
    shrink = contraction(problem, draws)
    out = {}
    for i, n in enumerate(problem.names):
        v = draws.values[..., i].ravel()
        q05, q50, q95 = np.quantile(v, [0.05, 0.5, 0.95])
        out[n] = {"mean": float(v.mean()), "sd": float(v.std(ddof=1)), "q05": float(q05), "q50": float(q50), "q95": float(q95),
                  "r_hat": float(stats.loc[n, "r_hat"]), "ess_bulk": float(stats.loc[n, "ess_bulk"]),
                  "ess_tail": float(stats.loc[n, "ess_tail"]), "contraction": float(shrink[i]),
                  "constrained_by": "data" if shrink[i] > CONSTRAINED else "prior",
                  "prior": problem.free[i].prior_density.describe()}
    return {
        "posterior": out,
        "divergences": int(draws.diverging.sum()),
        "draws": int(draws.diverging.size),
        "chains": int(draws.u.shape[0]),
        "step_size": draws.step_size.tolist(),
        "mean_leapfrog_steps": float(draws.leapfrog_steps.mean()),
        "warmup_seconds": draws.seconds["warmup"],
        "sampling_seconds": draws.seconds["sampling"],
    }


def predictive_check(problem: Problem, model_draws: np.ndarray, level: float = 0.9) -> list[dict]:
    """Each observation against the `level` posterior predictive interval of its value
    (model draws plus measurement noise)."""
    mean, sd = problem.data()
    rng = np.random.default_rng(1)
    flat = model_draws.reshape(-1, model_draws.shape[-1])
    y = problem.with_noise(flat, rng.normal(size=flat.shape))
    lo, hi = np.quantile(y, [(1 - level) / 2, (1 + level) / 2], axis=0)
    return [{"observation": label, "data": float(m), "lower": float(a), "upper": float(b), "inside": bool(a <= m <= b)}
            for label, m, a, b in zip(observation_labels(problem), mean, lo, hi)]


# ---------------------------------------------------------------------------------------
# The study: sample, check, files
# ---------------------------------------------------------------------------------------


class Posterior(NamedTuple):
    draws: Draws
    model: np.ndarray  # (chains, draws, observations): model values at each draw
    idata: object  # arviz.InferenceData
    summary: dict  # `posterior_summary` + "predictive_check"


def hold_out(problem: Problem, condition: str) -> tuple[Problem, Problem]:
    """(fitted, held out): `problem` without the observations of `condition`, and with
    only those; an `InputError` if there are none to hold out or none left to fit."""
    from ..io import InputError

    held = tuple(o for o in problem.observations if o.regime == condition)
    kept = tuple(o for o in problem.observations if o.regime != condition)
    if not held:
        conditions = sorted({o.regime for o in problem.observations} - {"seeded"})
        raise InputError(f"`hold_out` = {condition!r}: no observation of that condition; allowed: {', '.join(conditions)}")
    if not any(o.regime != "seeded" for o in kept):
        raise InputError(f"`hold_out` = {condition!r}: no observation left to calibrate on")
    return dataclasses.replace(problem, observations=kept), dataclasses.replace(problem, observations=held)


def run(cal, settings: SamplerSettings = SamplerSettings(), progress: bool = False, held_out: Problem | None = None) -> Posterior:
    """Sample the posterior of a finished calibration (`calibration.Calibration`) from its
    optimum, evaluate the model at every draw, diagnose with ArviZ. `held_out`: a
    problem of observations left out of the calibration (`hold_out`), predicted from
    the posterior and checked against its 90 % predictive intervals."""
    from tqdm.auto import tqdm

    problem = cal.problem
    check_size(problem, settings)
    with tqdm(total=settings.warmup + settings.samples, desc="posterior: NUTS", unit="draw", disable=not progress) as bar:
        draws = sample(problem, cal.fit.t, cal.fit.jacobian, settings, progress=bar.update)
    # the held-out observations are evaluated with the fitted ones: one program for both
    both = problem if held_out is None else dataclasses.replace(problem, observations=problem.observations + held_out.observations)
    with tqdm(total=draws.t.shape[0] * draws.t.shape[1], desc="posterior: model at draws", unit="draw", disable=not progress) as bar:
        values = model_values(both, draws.t, progress=bar.update)
    model, predicted = np.split(values, [len(problem.observations)], axis=-1)
    idata = inference_data(problem, draws, model)
    summary = posterior_summary(problem, draws, idata)
    summary["predictive_check"] = predictive_check(problem, model)
    if held_out is not None:
        summary["held_out"] = predictive_check(held_out, predicted)
    return Posterior(draws, model, idata, summary)


def report(problem: Problem, result: Posterior) -> str:
    """The posterior section of the calibration report."""
    s = result.summary
    n = s["draws"]
    lines = ["", "## Posterior (NUTS)", "",
             f"{s['chains']} chains × {n // s['chains']} draws after warmup, in {s['warmup_seconds']:.0f} s of warmup and "
             f"{s['sampling_seconds']:.0f} s of sampling; {s['divergences']} divergent transitions "
             f"({100 * s['divergences'] / n:.1f} %); {s['mean_leapfrog_steps']:.1f} leapfrog steps a draw on average. "
             "Files: posterior.nc (ArviZ InferenceData), pairs.png, traces.png.", "",
             "| parameter | prior | median | 90 % interval | R-hat | bulk ESS | contraction | constrained by |",
             "|---|---|---|---|---|---|---|---|"]
    for name, v in s["posterior"].items():
        lines.append(f"| {name} | {v['prior']} | {v['q50']:.4g} | [{v['q05']:.4g}, {v['q95']:.4g}] | {v['r_hat']:.3f} | "
                     f"{v['ess_bulk']:.0f} | {v['contraction']:.2f} | {'**data**' if v['constrained_by'] == 'data' else 'prior only'} |")
    data = [k for k, v in s["posterior"].items() if v["constrained_by"] == "data"]
    prior = [k for k, v in s["posterior"].items() if v["constrained_by"] != "data"]
    lines += ["", f"Contraction is 1 − Var(posterior)/Var(prior) in the fit coordinate: the data constrain "
              f"{', '.join(data) or 'no parameter'} (contraction > {CONSTRAINED}); "
              f"{', '.join(prior) or 'no parameter'} {'is' if len(prior) == 1 else 'are'} set mostly by the prior and the bounds."]
    bad = [k for k, v in s["posterior"].items() if not (v["r_hat"] < 1.01 and v["ess_bulk"] >= 400)]
    if bad:
        lines.append(f"Not converged to R-hat < 1.01 with bulk ESS ≥ 400: {', '.join(bad)}; run more draws (`--samples`) or chains.")
    outside = [c["observation"] for c in s["predictive_check"] if not c["inside"]]
    lines += ["", "Posterior predictive check (model at each draw plus the measurement noise): "
              + (f"outside the 90 % predictive interval: {', '.join(outside)}." if outside
                 else "every observation lies inside its 90 % predictive interval.")]
    if "held_out" in s:
        lines += ["", "### Held-out observations", "",
                  "Left out of the calibration and predicted from its posterior (model plus measurement noise):", "",
                  "| observation | data | 90 % predictive interval | inside |", "|---|---|---|---|"]
        for c in s["held_out"]:
            lines.append(f"| {c['observation']} | {c['data']:.4g} | [{c['lower']:.4g}, {c['upper']:.4g}] | "
                         f"{'yes' if c['inside'] else '**no**'} |")
        n_in = sum(c["inside"] for c in s["held_out"])
        lines += ["", f"{n_in} of {len(s['held_out'])} held-out observations fall inside their 90 % predictive interval."]
    return "\n".join(lines) + "\n"


def write(cal, result: Posterior, folder) -> None:
    """Add the posterior to a calibration's folder: posterior.nc, the figures, and the
    posterior's part of summary.json and report.md."""
    from .. import io, plots
    from . import calibration

    folder = pathlib.Path(folder)
    problem = cal.problem
    io.atomic_write(folder / "posterior.nc", lambda f: f.write(_netcdf_bytes(result.idata)))
    io.write_json(folder / "summary.json", {**calibration.summary(cal), **result.summary})
    io.atomic_write_text(folder / "report.md", calibration.report(cal) + report(problem, result))
    plots.posterior_pairs(problem.names, result.draws.values, result.draws.diverging, folder / "pairs.png", reference=cal.fit.values)
    plots.posterior_traces(problem.names, result.draws.values, folder / "traces.png")
    y = result.idata.posterior_predictive["y"].values  # the draws' model values plus the measurement noise
    y = y.reshape(-1, y.shape[-1])
    plots.fit_against_data(problem.observations, cal.model, folder / "fit.png", band=np.quantile(y, [0.05, 0.95], axis=0))


def _netcdf_bytes(idata) -> bytes:
    import os
    import tempfile

    fd, path = tempfile.mkstemp(suffix=".nc")
    os.close(fd)
    try:
        idata.to_netcdf(path, engine="h5netcdf")
        with open(path, "rb") as f:
            return f.read()
    finally:
        os.unlink(path)


# ---------------------------------------------------------------------------------------
# Posterior predictive of any protocol
# ---------------------------------------------------------------------------------------


class Saved(NamedTuple):
    """A posterior as `write` left it: draws in natural units, the fitted parameter set
    they replace values of, the model resolution the posterior was sampled with, and
    the data it was conditioned on."""

    names: tuple[str, ...]
    values: np.ndarray  # (chains, draws, k)
    base: object  # Params
    model: ModelSettings
    observations: list  # of (quantity, condition, time_s, mean, sd)


def read_saved(folder) -> Saved:
    """The posterior in `folder` (a `jaxtissue calibrate --posterior` output); an
    `InputError` naming `posterior` if it is missing or unreadable."""
    import xarray as xr

    from ..io import InputError, read_params_toml

    folder = pathlib.Path(folder)
    path = folder / "posterior.nc"
    if not path.is_file():
        raise InputError(f"`posterior` {folder}: no posterior.nc there (write one with `jaxtissue calibrate PROBLEM.toml --posterior --out DIR`)")
    try:
        posterior = xr.open_dataset(path, group="posterior", engine="h5netcdf").load()
        observed = xr.open_dataset(path, group="observed_data", engine="h5netcdf").load()
        sd = xr.open_dataset(path, group="constant_data", engine="h5netcdf").load()["sd"].values
        names = tuple(np.atleast_1d(posterior.attrs["free_parameters"]).tolist())
        model = ModelSettings(**json.loads(posterior.attrs["model_settings"]))
        values = np.stack([posterior[n].values for n in names], axis=-1)
    except (OSError, KeyError, ValueError, TypeError) as err:
        raise InputError(f"`posterior` {path}: not a jaxtissue posterior ({type(err).__name__}: {err})") from None
    base = read_params_toml(folder / "fitted.toml")
    observations = []
    for label, mean, s in zip(observed["observation"].values, observed["y"].values, sd):
        quantity, condition, time_s = str(label).split("|")
        observations.append((quantity, condition, float(time_s.rstrip("s")), float(mean), float(s)))
    return Saved(names, values, base, model, observations)


@eqx.filter_jit
def _predict_batch(base, names, protocol, t_end_s, grid, coupling_interval_s, beam, options, size, values):
    """`predict`'s scalar outputs and failure flags of a batch of `size` draws (rows of `values`)."""
    from ..result import SCALARS
    from ..simulate import simulate

    def one(v):
        r = simulate(base.replace(**dict(zip(names, v))), protocol, t_end_s, grid, coupling_interval_s=coupling_interval_s,
                     beam=beam, options=options)
        return {k: getattr(r, k) for k in SCALARS}, r.failed

    return vmap_over_devices(one, size)(values)


def predict(saved: Saved, protocol, t_end_s: float, draws: int = 100, seed: int = 0, batch: int = 32, progress=None):
    """Posterior predictive of every scalar output over time: `draws` posterior draws
    (chosen at random, without replacement) simulated with `protocol` at the posterior's
    model resolution, at most `batch` at a time under vmap, each batch split over the
    devices (`sweep.even_batches`). An `xarray.Dataset` of each output per (draw,
    time_s), plus `<output>_q05`, `_q50`, `_q95` per time."""
    import xarray as xr

    from ..protocol import save_times
    from ..result import OUTPUTS, SCALARS

    flat = saved.values.reshape(-1, saved.values.shape[-1])
    pick = np.random.default_rng(seed).choice(len(flat), size=min(draws, len(flat)), replace=False)
    chosen = flat[pick]
    m = saved.model
    grid = m.grid(protocol.regime)

    size = even_batches(len(chosen), batch)
    run = functools.partial(cache.call, _predict_batch, saved.base, tuple(saved.names), protocol, t_end_s, grid,
                            m.coupling_interval_s, m.beam(), m.options(), size)
    parts = _in_batches(run, chosen, size, progress)
    times = save_times(t_end_s, m.coupling_interval_s)
    failed = np.concatenate([p[1] for p in parts])
    data = {}
    for k in SCALARS:
        a = np.concatenate([p[0][k] for p in parts])
        data[k] = (("draw", "time_s"), a, {"units": OUTPUTS[k].unit, "long_name": OUTPUTS[k].description})
        ok = a[~failed]
        for q in (5, 50, 95):
            data[f"{k}_q{q:02d}"] = (("time_s",), np.quantile(ok, q / 100, axis=0) if len(ok) else np.full(len(times), np.nan),
                                     {"units": OUTPUTS[k].unit})
    for n, i in zip(saved.names, range(len(saved.names))):
        data[n] = (("draw",), chosen[:, i])
    data["failed"] = (("draw",), failed)
    return xr.Dataset(data, coords={"time_s": times, "draw": np.arange(len(chosen))},
                      attrs={"regime": protocol.regime, "period_s": np.asarray(protocol.period_s, float),
                             "post_displacement_mm": np.asarray(protocol.post_displacement_mm, float), "draws": len(chosen)})
