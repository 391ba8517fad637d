"""Calibration: fit parameters to measurements by SD-weighted least squares.

A `Problem` (from a TOML file, `read_problem`) names the free parameters (bounds, log or
linear transform), the fixed ones, the measurements (`data.read_measurements`) and the
protocol of each condition. Its residuals r_i = (model_i − mean_i)/sd_i are a jit-able,
differentiable function of the free parameters; χ² = Σ r_i² is −2 log L + const of a
Gaussian likelihood.

Coordinates: t = log θ or θ (the transform), inside the bounds' box.

* `fit`: Levenberg–Marquardt in the box (`numerics.LevenbergMarquardt`: active-set
  steps, Nielsen's damping, exact forward-mode Jacobians with Broyden updates between
  them) from a Latin-hypercube design of starts inside the bounds (plus the base
  values), batched with `vmap` when `[fit] batch > 1`.
* `fisher`: the Laplace approximation at the optimum from the exact Jacobian:
  covariance (JᵀJ)⁻¹ in t, standard errors, correlations.
* `profiles`: profile likelihoods, re-optimising the other parameters at each point;
  a parameter is identifiable when its profile rises by χ²₁,₀.₉₅ = 3.84 on both sides
  within its bounds.
"""

from __future__ import annotations

import dataclasses
import functools
import math
import pathlib
from typing import NamedTuple

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import optimistix as optx

from .. import cache, io, plots
from ..data import DataError, Observation, read_measurements
from ..io import InputError, params_from_table, read_toml
from ..limits import ResourceError, check_count, check_intervals, check_study
from ..numerics import LevenbergMarquardt
from ..params import FIELDS, Params, nondimensionalise, suggest
from ..protocol import Protocol, in_table, save_times
from ..result import RESULTS, observe
from ..simulate import simulate
from ..state import State
from ._problem_files import ModelSettings, bounds, settings, table, unit_latin_hypercube
from .priors import Prior, default_prior, read_prior

CHI2_95 = 3.841458820694124
"""95 % quantile of χ² with one degree of freedom: the profile-likelihood threshold."""


class FreeParameter(NamedTuple):
    name: str
    lower: float
    upper: float
    transform: str  # "log" or "linear"
    prior: Prior | None = None  # None: flat in the fit coordinate (`default_prior`)

    @property
    def prior_density(self) -> Prior:
        return default_prior(self.transform) if self.prior is None else self.prior

    def to_t(self, value):
        return jnp.log(value) if self.transform == "log" else jnp.asarray(value, float)

    def from_t(self, t):
        return jnp.exp(t) if self.transform == "log" else t

    @property
    def t_bounds(self):
        f = math.log if self.transform == "log" else float
        return f(self.lower), f(self.upper)


@dataclasses.dataclass(frozen=True)
class FitSettings:
    """Multi-start Levenberg–Marquardt and profile settings."""

    starts: int = 8
    seed: int = 0
    batch: int = 1  # starts per vmapped batch
    max_steps: int = 60
    rtol: float = 1e-5  # LM stops when steps in t and changes of r are below 1e-5, or χ² changes by < 1e-5 χ²
    profile_points: int = 4  # per side
    profile_max_steps: int = 30

    def __post_init__(self):
        for name in ("starts", "profile_points"):
            check_count(name, getattr(self, name))

    @property
    def simultaneous(self) -> int:
        """Starts solved at once: `batch`, or all of them where they are fewer."""
        return min(self.batch, self.starts)


def _seeded(params: Params, grid) -> dict:
    """The outputs of the seeded state (docs/model.md §2) that it determines."""
    return observe(State.initial(nondimensionalise(params), grid), params, grid)


@dataclasses.dataclass(frozen=True, eq=False)  # hashed by identity: compiled solvers are cached per problem
class Problem:
    base: Params
    free: tuple[FreeParameter, ...]
    observations: tuple[Observation, ...]
    conditions: dict  # name -> Protocol
    model: ModelSettings = ModelSettings()
    fit: FitSettings = FitSettings()
    name: str = "calibration"

    def __post_init__(self):
        self._plan()  # validates the observation times

    # ---- coordinates
    @property
    def names(self) -> tuple[str, ...]:
        return tuple(f.name for f in self.free)

    def t_bounds(self):
        lo, hi = zip(*(f.t_bounds for f in self.free))
        return jnp.asarray(lo), jnp.asarray(hi)

    def t_from_values(self, values) -> jax.Array:
        return jnp.stack([f.to_t(v) for f, v in zip(self.free, values)])

    def values_from_t(self, t) -> jax.Array:
        return jnp.stack([f.from_t(t[i]) for i, f in enumerate(self.free)])

    def params(self, t) -> Params:
        """The full parameter set at transformed free values t."""
        return self.base.replace(**dict(zip(self.names, self.values_from_t(t))))

    # ---- the model
    def check_memory(self, what: str, runs: int, reverse: bool) -> None:
        """`limits.check_study` for `runs` simultaneous runs of this problem's model to its
        last observation (`reverse`: with a reverse pass)."""
        t_end = max([o.time_s for o in self.observations] + [0.0])
        check_study(what, self.model.grid("flex"), t_end, self.model.coupling_interval_s, runs, reverse=reverse)

    def _plan(self):
        """(condition, t_end) of each simulation, checking that every observation
        time is one of its save times."""
        plan = []
        for name, protocol in self.conditions.items():
            times = [o.time_s for o in self.observations if o.regime in (name, "seeded")]
            t_end = max(times + [0.0])
            if t_end <= 0:
                continue
            try:
                check_intervals(t_end, self.model.coupling_interval_s, name="time")
            except ResourceError as err:
                raise InputError(f"the last observation of condition {name!r}: {err}") from None
            saved = save_times(t_end, self.model.coupling_interval_s)
            for o in self.observations:
                if o.regime == name and np.min(np.abs(saved - o.time_s)) > 1e-6 * max(1.0, o.time_s):
                    raise InputError(
                        f"observation {o.quantity} ({name}) at time {o.time_s:g} s: not a save time; "
                        f"use 0, multiples of coupling_interval_s = {self.model.coupling_interval_s:g} s, or 3 weeks"
                    )
            plan.append((name, t_end))
        if not plan:
            raise InputError("no observation at a time > 0 in any condition of the problem")
        return plan

    def simulate(self, params: Params) -> dict:
        """`{condition: Result}` up to each condition's last observation. A static
        condition observed at one time after seeding keeps only its end state there
        (`save="end"`: one solve); a static series is solved interval by interval (the
        model's `SolverOptions`), with no host callback: the programs are cached and
        saved (docs/numerics.md, "Compilation")."""
        m = self.model
        return {
            name: simulate(params, self.conditions[name], t_end, m.grid(self.conditions[name].regime),
                           coupling_interval_s=m.coupling_interval_s, beam=m.beam(), options=m.options(),
                           save="end" if self._end_only(name) else "intervals")
            for name, t_end in self._plan()
        }

    def _end_only(self, name: str) -> bool:
        times = {o.time_s for o in self.observations if o.regime == name}
        return self.conditions[name].regime == "static" and len(times) == 1 and min(times) > 0

    def model_values(self, t) -> jax.Array:
        """The model's value for each observation (`observations` order); at t = 0 in a
        condition kept at its end only, the seeded state's (no loading: no force)."""
        params = self.params(t)
        results = self.simulate(params)
        first = next(iter(results))
        seeded = _seeded(params, self.model.grid("static")) if any(map(self._end_only, results)) else {}
        out = []
        for o in self.observations:
            name = first if o.regime == "seeded" else o.regime
            r = results[name]
            if not self._end_only(name):
                out.append(getattr(r, o.quantity)[r.index(o.time_s)])
            elif o.time_s == 0:
                out.append(seeded.get(o.quantity, jnp.zeros(())))
            else:  # a failed solve leaves a finite state at its end: invalid, as a series' unreached times are
                solved = (r.status != RESULTS.max_steps_reached) & (r.status != RESULTS.growth_failed)
                out.append(jnp.where(solved, getattr(r, o.quantity)[-1], jnp.nan))
        return jnp.stack(out)

    def data(self):
        """(means, SDs) of the observations; the SD of ln(value) where the noise is log-normal."""
        return (np.array([o.mean for o in self.observations]), np.array([o.sd for o in self.observations]))

    def log_normal(self) -> np.ndarray:
        """Which observations have log-normal noise (docs/model.md §9)."""
        return np.array([o.noise == "log-normal" for o in self.observations])

    def residuals(self, t) -> jax.Array:
        """(model − mean)/sd, or (ln model − ln mean)/sd for log-normal noise, at
        transformed free values t (docs/model.md §9)."""
        return self.residuals_of(self.model_values(t))

    def residuals_of(self, model) -> jax.Array:
        """The residuals of given model values (last axis: the observations)."""
        mean, sd = self.data()
        model, log = jnp.asarray(model), self.log_normal()
        if not log.any():  # no log terms in the compiled residuals
            return (model - mean) / sd
        return jnp.where(log, jnp.log(jnp.where(log, model, 1.0)) - np.log(np.where(log, mean, 1.0)), model - mean) / sd

    def model_from_residuals(self, r) -> np.ndarray:
        """The model values whose residuals are r (last axis: the observations)."""
        return self.with_noise(self.data()[0], r)

    def with_noise(self, model, z):
        """Model values plus measurement noise with standard normal draws z (broadcast
        against `model`, last axis: the observations)."""
        _, sd = self.data()
        log, noise = self.log_normal(), sd * np.asarray(z)
        return np.where(log, model * np.exp(np.where(log, noise, 0.0)), model + noise)


# ---------------------------------------------------------------------------------------
# Fitting
# ---------------------------------------------------------------------------------------


def latin_hypercube(problem: Problem, n: int, seed: int) -> np.ndarray:
    """n starts in t: the base values (clipped into the bounds) and n − 1 points of a
    Latin hypercube over the transformed bounds."""
    lo, hi = (np.asarray(b) for b in problem.t_bounds())
    base = np.asarray(problem.t_from_values([getattr(problem.base, f) for f in problem.names]))
    strata = unit_latin_hypercube(max(n - 1, 0), len(lo), np.random.default_rng(seed))
    starts = np.concatenate([np.clip(base, lo, hi)[None], lo + (hi - lo) * strata])
    return starts[:n]


class FitResult(NamedTuple):
    t: np.ndarray  # best, transformed
    values: np.ndarray  # best, natural units
    chi2: float
    starts_t: np.ndarray  # (starts, k)
    ends_t: np.ndarray
    chi2_all: np.ndarray  # per start, final χ²
    steps_all: np.ndarray  # LM steps per start
    converged_all: np.ndarray
    residual_evaluations: int  # all starts: residuals alone (one model evaluation each)
    jacobian_evaluations: int  # forward-mode Jacobians with their residuals (~3 evaluations' cost each)
    jacobian: np.ndarray  # ∂r/∂t at the best end (exact: the solve's own where it converged)


@functools.lru_cache(maxsize=8)
def _jitted(program, problem: Problem):
    """`program` jitted for `problem`: its compiled programs are freed with the problem's
    once 8 other problems' have been used since."""
    return eqx.filter_jit(program)


def _residuals_program(problem: Problem, t):
    return problem.residuals(t)


def _jacobian_program(problem: Problem, t):
    return jax.jacfwd(problem.residuals)(t)


def _compiled(problem: Problem, jacobian: bool):
    """`f(t)`: the problem's compiled residuals or their forward-mode Jacobian (as
    `lm_solver`'s, compiled once per problem and saved where the command line saves its
    programs)."""
    program = _jacobian_program if jacobian else _residuals_program
    return functools.partial(cache.call, _jitted(program, problem), problem)


def _lm_program(problem: Problem, batch: int, t0, args):
    s = problem.fit
    solve = lm_solve(problem, max(s.max_steps, s.profile_max_steps))
    if batch == 1:  # not vmapped: under `vmap` the solve's Jacobian refresh would run every step
        return jax.tree_util.tree_map(lambda x: x[None], solve(t0[0], args))
    return jax.vmap(solve, in_axes=(0, None))(t0, args)


def lm_solver(problem: Problem, batch: int):
    """`solve(t0, args)`: the problem's compiled LM solve (`lm_solve`) of `batch` starts
    t0 at a time. Compiled once per problem (the fit and the profiles' points share it)
    and, where `cache.saved_executables` is on (the command line), saved: a second
    `jaxtissue calibrate` of the same problem loads it instead of tracing it again
    (named by the problem's values, `cache.call`)."""
    return functools.partial(cache.call, _jitted(_lm_program, problem), problem, batch)


def pinned(i: int, t_i: float, max_steps: int, also: tuple[int, float] = (-1, 0.0)):
    """`lm_solve`'s args: free parameter i pinned at t_i (i = −1: none) and `also` a
    second (j, t_j), at most `max_steps` steps (typed alike for every call, so that the
    compiled solve is reused)."""
    return (np.asarray([i, also[0]], np.int64), np.asarray([t_i, also[1]], np.float64), np.asarray(max_steps, np.int64))


def unpinned(max_steps: int):
    """`lm_solve`'s args for a fit of every free parameter."""
    return pinned(-1, 0.0, max_steps)


class _LMResult(NamedTuple):
    t: jax.Array
    chi2: jax.Array
    steps: jax.Array
    converged: jax.Array
    evaluations: jax.Array  # of the residuals alone
    jacobians: jax.Array  # forward-mode Jacobians, each with the residuals
    jac: jax.Array  # ∂r/∂t at t: exact where `jac_exact` (a converged solve), else Broyden-updated
    jac_exact: jax.Array


def lm_solve(problem: Problem, max_steps: int, record=None):
    """An LM solve `solve(t0, (i, t_i, steps))` of at most `min(steps, max_steps)` steps,
    with free parameters i[n] pinned at t_i[n] (i[n] = −1: none; `pinned`), returning an
    `_LMResult`.
    `record(chi2)`: called with χ² of every point evaluated (the benchmark's clock)."""
    tol = problem.fit.rtol
    solver = LevenbergMarquardt(rtol=tol, atol=tol, ftol=tol, lower=problem.t_bounds()[0], upper=problem.t_bounds()[1],
                                cap_steps=True, record=record)

    def pin(t, args):
        i, t_i, _ = args
        for n in range(2):
            t = jnp.where(jnp.arange(t.shape[0]) == i[n], t_i[n], t)
        return t

    def residual(t, args):
        return problem.residuals(pin(t, args))

    def solve(t0, args):
        t0 = pin(t0, args)
        sol = optx.least_squares(residual, solver, t0, args, max_steps=max_steps, throw=False)
        last = sol.state.residual
        return _LMResult(sol.value, jnp.sum(last**2), sol.stats["num_steps"], sol.result == optx.RESULTS.successful,
                         sol.stats["residual_evaluations"], sol.stats["jacobian_evaluations"], sol.state.jac, sol.state.exact)

    return solve


def fit(problem: Problem, progress=None) -> FitResult:
    """Multi-start Levenberg–Marquardt; `progress(n)` is called after each batch."""
    s = problem.fit
    starts = latin_hypercube(problem, s.starts, s.seed)
    solve = lm_solver(problem, s.simultaneous)
    runs = []
    for b in range(0, len(starts), s.simultaneous):
        t0 = jnp.asarray(starts[b : b + s.simultaneous])
        pad = s.simultaneous - t0.shape[0]  # keep one compiled batch shape
        out = solve(jnp.concatenate([t0, jnp.repeat(t0[-1:], pad, axis=0)]), unpinned(s.max_steps))
        runs.append(jax.tree_util.tree_map(lambda x: np.asarray(x)[: t0.shape[0]], out))
        if progress is not None:
            progress(t0.shape[0])
    ends, chi2, steps, ok, evaluations, jacobians, jac, exact = (np.concatenate(a) for a in zip(*runs))
    chi2 = np.where(np.isfinite(chi2), chi2, np.inf)
    best = int(np.argmin(chi2))
    if not exact[best]:  # the solve stopped at its step limit: compute the Jacobian there
        jac[best] = np.asarray(_compiled(problem, jacobian=True)(jnp.asarray(ends[best])))
        jacobians[best] += 1
    return FitResult(
        t=ends[best], values=np.asarray(problem.values_from_t(jnp.asarray(ends[best]))), chi2=float(chi2[best]),
        starts_t=starts, ends_t=ends, chi2_all=chi2, steps_all=steps, converged_all=ok,
        residual_evaluations=int(np.sum(evaluations)), jacobian_evaluations=int(np.sum(jacobians)), jacobian=jac[best],
    )


# ---------------------------------------------------------------------------------------
# Uncertainty and identifiability
# ---------------------------------------------------------------------------------------


class Fisher(NamedTuple):
    jacobian: np.ndarray  # ∂r/∂t, (observations, free)
    covariance_t: np.ndarray
    standard_errors: np.ndarray  # natural units (delta method)
    standard_errors_t: np.ndarray
    correlation: np.ndarray


def fisher(problem: Problem, t, jacobian=None) -> Fisher:
    """Laplace approximation at t: Σ_t = (JᵀJ)⁺ with the exact J = ∂r/∂t (`jacobian`,
    e.g. the fit's own at its optimum, or computed here)."""
    J = np.asarray(_compiled(problem, jacobian=True)(jnp.asarray(t)) if jacobian is None else jacobian)
    cov = np.linalg.pinv(J.T @ J)
    se_t = np.sqrt(np.maximum(np.diag(cov), 0.0))
    values = np.asarray(problem.values_from_t(jnp.asarray(t)))
    se = np.array([v * s if f.transform == "log" else s for f, v, s in zip(problem.free, values, se_t)])
    with np.errstate(invalid="ignore", divide="ignore"):
        corr = cov / np.outer(se_t, se_t)
    return Fisher(J, cov, se, se_t, corr)


class Profile(NamedTuple):
    name: str
    values: np.ndarray  # natural units, ascending, including the optimum
    chi2: np.ndarray
    identifiable: bool
    interval: tuple  # 95 % profile-likelihood interval (None where unbounded)


def _crossing(xs, ys, level):
    """First x where the piecewise-linear y(x) reaches `level`, walking from xs[0]."""
    for k in range(1, len(xs)):
        if ys[k] >= level > ys[k - 1]:
            return xs[k - 1] + (level - ys[k - 1]) * (xs[k] - xs[k - 1]) / (ys[k] - ys[k - 1])
    return None


def pinned_walk(problem: Problem, t_start, i: int, xs, also: tuple[int, float] = (-1, 0.0), stop=None, progress=None):
    """Free parameter i pinned at each of `xs` in turn (and `also`, (j, t_j), held), the
    others re-optimised by the fit's solver from the previous point, starting at
    `t_start`: the optima t (points, k) and their χ² (inf where the model failed).
    Ends after a point whose χ² fails or meets `stop(χ²)`. The profiles' and the
    posterior's ridges' walk."""
    solve = lm_solver(problem, 1)  # the fit's own when its batch is 1
    t, ts, chi2s = jnp.asarray(t_start)[None], [], []
    for x in xs:
        t, c, *_ = solve(t, pinned(i, float(x), problem.fit.profile_max_steps, also))
        ts.append(np.asarray(t[0]))
        chi2s.append(float(c[0]) if np.isfinite(float(c[0])) else np.inf)
        if progress is not None:
            progress(1)
        if not np.isfinite(chi2s[-1]) or (stop is not None and stop(chi2s[-1])):
            break
    return np.reshape(ts, (len(ts), np.size(t_start))), np.asarray(chi2s)


def profiles(problem: Problem, best: FitResult, se_t, progress=None) -> list[Profile]:
    """Profile likelihood of every free parameter: on each side of the optimum,
    `profile_points` values spaced to span 4 standard errors (or up to the bound), the
    others re-optimised from the previous point (`pinned_walk`)."""
    s = problem.fit
    lo, hi = (np.asarray(b) for b in problem.t_bounds())
    level = best.chi2 + CHI2_95
    out = []
    for i, f in enumerate(problem.free):
        sides = {}
        for direction, bound in ((-1, lo[i]), (1, hi[i])):
            span = abs(bound - best.t[i])
            if np.isfinite(se_t[i]) and se_t[i] > 0:
                span = min(span, 4 * se_t[i])
            xs = best.t[i] + direction * span * np.arange(1, s.profile_points + 1) / s.profile_points
            _, chi2 = pinned_walk(problem, best.t, i, xs, stop=lambda c: c > level + 2 * CHI2_95, progress=progress)
            sides[direction] = (np.append(best.t[i], xs[: len(chi2)]), np.append(best.chi2, chi2))
        crossing = {d: _crossing(*sides[d], level) for d in sides}
        xs = np.concatenate([sides[-1][0][::-1], sides[1][0][1:]])
        ys = np.concatenate([sides[-1][1][::-1], sides[1][1][1:]])
        values = np.asarray(jax.vmap(f.from_t)(jnp.asarray(xs)))
        interval = tuple(None if crossing[d] is None else float(f.from_t(crossing[d])) for d in (-1, 1))
        out.append(Profile(f.name, values, ys, all(c is not None for c in crossing.values()), interval))
    return out


# ---------------------------------------------------------------------------------------
# Problem files
# ---------------------------------------------------------------------------------------

_TOP = {"name", "measurements", "parameters", "conditions", "model", "fit"}
_PROTOCOL = {"regime", "period_s", "post_displacement_mm", "hold_fraction", "lumping", "pins", "stage_length_s"}


def free_parameter(name: str, low: float, high: float, transform: str, prior, where: str) -> FreeParameter:
    """A checked `FreeParameter`: bounds in the field's range, the transform, the prior
    in its problem-file form (`priors.read_prior`; None: the default)."""
    info = FIELDS[name]
    if not (low < high and info.contains(low) and info.contains(high)):
        raise InputError(f"{where} bounds = [{low:g}, {high:g}] must have low < high, both in {info.range_text()} {info.unit}")
    if transform not in ("log", "linear"):
        raise InputError(f"{where} transform = {transform!r}; allowed: 'log', 'linear'")
    if transform == "log" and low <= 0:
        raise InputError(f"{where}: a log transform needs low > 0, got {low:g}")
    return FreeParameter(name, low, high, transform, None if prior is None else read_prior(prior, low, high, where))


def read_problem(path, overrides: dict | None = None) -> Problem:
    """A `Problem` from a TOML file (see `calibrate/engelmayr2005.toml`); every mistake
    is an `InputError` naming the file and the key. `overrides` replace [fit] keys."""
    path = pathlib.Path(path)
    doc, _ = read_toml(path, "problem", _TOP)
    where = str(path)
    if "measurements" not in doc or not isinstance(doc["measurements"], str):
        raise InputError(f"{where}: measurements = \"FILE.csv\" (relative to the problem file) is required")
    try:
        observations = read_measurements(path.parent / doc["measurements"])
    except DataError as err:
        raise InputError(str(err)) from None

    parameters = table(doc, "parameters", where, {"free", "fixed"})
    fixed = table(parameters, "fixed", where)
    base = params_from_table(fixed, f"{where} [parameters.fixed]")

    free = []
    for name, spec in table(parameters, "free", where).items():
        key = f"[parameters.free] {name}"
        if name not in FIELDS:
            raise InputError(f"{where}: unknown parameter {name!r} in [parameters.free]; {suggest(name, FIELDS)}")
        if name in fixed:
            raise InputError(f"{where}: {name} is both free and fixed")
        if not isinstance(spec, dict) or "bounds" not in spec:
            raise InputError(f"{where}: {key} must be {{ bounds = [low, high], transform = \"log\" | \"linear\" }}")
        for k in spec:
            if k not in ("bounds", "transform", "start", "prior"):
                raise InputError(f"{where}: unknown key {k!r} in {key}; {suggest(k, ['bounds', 'transform', 'start', 'prior'])}")
        low, high = bounds(spec["bounds"], f"{where}: {key} bounds")
        free.append(free_parameter(name, low, high, spec.get("transform", "log"), spec.get("prior"), f"{where}: {key}"))
        if "start" in spec:
            start = spec["start"]
            if isinstance(start, bool) or not isinstance(start, (int, float)) or not low <= start <= high:
                raise InputError(f"{where}: {key} start = {start!r} must be a number in [{low:g}, {high:g}]")
            base = base.replace(**{name: float(start)})
    if not free:
        raise InputError(f"{where}: [parameters.free] names no parameter to fit")

    conditions = {}
    for name, spec in table(doc, "conditions", where).items():
        if not isinstance(spec, dict):
            raise InputError(f"{where}: [conditions.{name}] must be a table")
        for k in spec:
            if k not in _PROTOCOL:
                raise InputError(f"{where}: unknown key {k!r} in [conditions.{name}]; {suggest(k, sorted(_PROTOCOL))}")
        try:
            if "stage_length_s" in spec:  # a schedule: one period and amplitude per stage
                if spec.get("regime") != "flex":
                    raise ValueError("a schedule (stage_length_s) needs regime = \"flex\"")
                conditions[name] = Protocol.schedule(**{k: v for k, v in spec.items() if k != "regime"})
            else:
                conditions[name] = Protocol(**spec)
        except (TypeError, ValueError) as err:
            raise InputError(f"{where}: [conditions.{name}] {in_table(err)}") from None
    if not conditions:
        raise InputError(f"{where}: [conditions] defines no condition (e.g. [conditions.static] regime = \"static\")")
    for o in observations:
        if o.regime != "seeded" and o.regime not in conditions:
            raise InputError(f"{where}: measurement condition {o.regime!r} has no [conditions.{o.regime}]; {suggest(o.regime, conditions)}")

    fit_table = dict(table(doc, "fit", where))
    fit_table.update(overrides or {})
    model = settings(ModelSettings, table(doc, "model", where), where, "model")
    fit_settings = settings(FitSettings, fit_table, where, "fit")
    try:  # the observation times against the model's save times (`Problem._plan`)
        return Problem(base=base, free=tuple(free), observations=observations, conditions=conditions, model=model,
                       fit=fit_settings, name=str(doc.get("name", path.stem)))
    except InputError as err:
        raise InputError(f"{where}: {err}") from None


def fitted_model(path) -> ModelSettings | None:
    """The `[model]` table of a fitted parameter file (`write`): the resolution its
    values were fitted at; None for a file without one."""
    doc, _ = read_toml(path, "parameter", {"parameters", "model"} | set(FIELDS))
    if "model" not in doc:
        return None
    return settings(ModelSettings, table(doc, "model", str(path)), str(path), "model")


# ---------------------------------------------------------------------------------------
# The whole study: fit, uncertainty, profiles, files
# ---------------------------------------------------------------------------------------


class Calibration(NamedTuple):
    problem: Problem
    fit: FitResult
    fisher: Fisher
    profiles: list  # of Profile ([] if skipped)
    model: np.ndarray  # model values at the optimum, `problem.observations` order
    jacobian_check: float  # max |J − J_FD| / max |J| at the optimum (central differences)
    seconds: dict  # "fit", "uncertainty", "profiles"


def jacobian_fd_error(problem: Problem, t, J, h=1e-3) -> float:
    """Max deviation of the exact Jacobian from central differences (step h in t),
    relative to the largest entry."""
    res = _compiled(problem, jacobian=False)
    cols = []
    for i in range(len(t)):
        e = np.zeros(len(t))
        e[i] = h
        cols.append((np.asarray(res(jnp.asarray(t + e))) - np.asarray(res(jnp.asarray(t - e)))) / (2 * h))
    fd = np.stack(cols, axis=1)
    return float(np.max(np.abs(fd - J)) / np.max(np.abs(J)))


def calibrate(problem: Problem, with_profiles: bool = True, progress: bool = False) -> Calibration:
    """Fit (multi-start LM), Laplace approximation, profile likelihoods."""
    import time

    from tqdm.auto import tqdm

    # its Jacobians are forward mode: a tangent per free parameter
    problem.check_memory("the calibration", problem.fit.simultaneous * (1 + len(problem.free)), reverse=False)
    seconds = {}
    t0 = time.perf_counter()
    with tqdm(total=problem.fit.starts, desc="fit: starts", unit="start", disable=not progress) as bar:
        best = fit(problem, progress=bar.update)
    seconds["fit"] = time.perf_counter() - t0
    t0 = time.perf_counter()
    fi = fisher(problem, best.t, best.jacobian)
    model = problem.model_from_residuals(np.asarray(_compiled(problem, jacobian=False)(jnp.asarray(best.t))))
    check = jacobian_fd_error(problem, best.t, fi.jacobian)
    seconds["uncertainty"] = time.perf_counter() - t0
    profs = []
    if with_profiles:
        t0 = time.perf_counter()
        with tqdm(total=2 * problem.fit.profile_points * len(problem.free), desc="profiles", unit="point", disable=not progress) as bar:
            profs = profiles(problem, best, fi.standard_errors_t, progress=bar.update)
        seconds["profiles"] = time.perf_counter() - t0
    return Calibration(problem, best, fi, profs, model, check, seconds)


def summary(cal: Calibration) -> dict:
    """The `summary.json` of `jaxtissue calibrate`."""
    p, f = cal.problem, cal.fit
    identifiable = {pr.name: pr.identifiable for pr in cal.profiles} if cal.profiles else {
        n: bool(np.isfinite(se) and se_t < 1.0) for n, se, se_t in zip(p.names, cal.fisher.standard_errors, cal.fisher.standard_errors_t)
    }
    return {
        "problem": p.name,
        "parameters": dict(zip(p.names, f.values.tolist())),
        "standard_errors": dict(zip(p.names, cal.fisher.standard_errors.tolist())),
        "profile_intervals_95": {pr.name: list(pr.interval) for pr in cal.profiles},
        "identifiable": identifiable,
        "chi2": f.chi2,
        "observations": [
            {"name": o.quantity, "regime": o.regime, "time_s": o.time_s, "data_mean": o.mean, "data_sd": o.sd, "noise": o.noise,
             "model": float(m), "residual": float(r)}
            for o, m, r in zip(p.observations, cal.model, np.asarray(p.residuals_of(cal.model)))
        ],
        "correlation": {n: dict(zip(p.names, row.tolist())) for n, row in zip(p.names, cal.fisher.correlation)},
        "starts": {"chi2": f.chi2_all.tolist(), "lm_steps": f.steps_all.tolist(), "converged": f.converged_all.tolist()},
        "model_evaluations": {"residuals": f.residual_evaluations, "jacobians": f.jacobian_evaluations},
        "jacobian_vs_central_differences": cal.jacobian_check,
        "seconds": cal.seconds,
    }


def report(cal: Calibration) -> str:
    """A Markdown report: fitted values, uncertainty, fit against data, diagnosis."""
    s = summary(cal)
    p = cal.problem
    lines = [f"# Calibration: {p.name}", ""]
    n_good = int(np.sum(cal.fit.chi2_all <= cal.fit.chi2 + 0.1))
    lines += [
        f"Best χ² = {cal.fit.chi2:.4g} over {len(p.observations)} observations and {len(p.free)} free parameters; "
        f"{n_good} of {len(cal.fit.chi2_all)} starts ended within Δχ² < 0.1 of it (waterfall.png). "
        f"{cal.fit.residual_evaluations} evaluations of the residuals and {cal.fit.jacobian_evaluations} forward-mode "
        f"Jacobians in {cal.seconds['fit']:.0f} s. "
        f"The exact Jacobian agrees with central differences to {cal.jacobian_check:.1e} (relative to its largest entry).",
        "",
        "## Parameters",
        "",
        "| parameter | fitted | standard error | 95 % profile interval | identifiable |",
        "|---|---|---|---|---|",
    ]
    for name in p.names:
        lo, hi = s["profile_intervals_95"].get(name, [None, None])
        interval = "—" if name not in s["profile_intervals_95"] else f"[{'bound' if lo is None else f'{lo:.4g}'}, {'bound' if hi is None else f'{hi:.4g}'}]"
        lines.append(f"| {name} ({FIELDS[name].unit}) | {s['parameters'][name]:.4g} | {s['standard_errors'][name]:.2g} | {interval} | {'yes' if s['identifiable'][name] else '**no**'} |")
    lines += ["", "## Model against data", "", "| observable | condition | time (s) | data | model | residual (SDs) |", "|---|---|---|---|---|---|"]
    off = []
    for o in s["observations"]:
        z = o["residual"]
        spread = f"× e^±{o['data_sd']:g}" if o["noise"] == "log-normal" else f"± {o['data_sd']:g}"
        lines.append(f"| {o['name']} | {o['regime']} | {o['time_s']:g} | {o['data_mean']:g} {spread} | {o['model']:.4g} | {z:+.2f} |")
        if abs(z) > 1:
            off.append(f"{o['name']} ({o['regime']}, {z:+.2f} SD)")
    lines += [""]
    if off:
        lines.append("Outside 1 SD at the best fit: " + ", ".join(off) + ". No start found a lower χ², and along each "
                     "parameter's profile (profiles.png) χ² never drops below the optimum's, so within the bounds the "
                     "free parameters cannot bring them closer without moving other observations further away.")
    else:
        lines.append("Every model value lies within 1 SD of its data point.")
    weak = [n for n in p.names if not s["identifiable"][n]]
    strong = [(a, b, cal.fisher.correlation[i, j]) for i, a in enumerate(p.names) for j, b in enumerate(p.names) if j > i and abs(cal.fisher.correlation[i, j]) > 0.95]
    lines += ["", "## Identifiability", ""]
    if weak:
        lines.append("Not identifiable from these data (the profile stays below χ²_min + 3.84 up to a bound): " + ", ".join(weak) + ".")
    else:
        lines.append("Every free parameter is identifiable: its profile rises above χ²_min + 3.84 on both sides.")
    if strong:
        lines.append("Strongly correlated pairs (|ρ| > 0.95, Laplace approximation): " + ", ".join(f"{a}–{b} ({r:+.3f})" for a, b, r in strong) + ".")
    lines += ["", "Files: summary.json, fitted.toml (`jaxtissue simulate --params fitted.toml`, at the fit's `[model]` resolution), waterfall.png, fit.png, profiles.png, correlation.png.", ""]
    return "\n".join(lines)


def write(cal: Calibration, folder) -> None:
    """summary.json, fitted.toml, report.md and the figures into `folder`."""
    folder = pathlib.Path(folder)
    io.write_json(folder / "summary.json", summary(cal))
    io.write_params_toml(cal.problem.params(jnp.asarray(cal.fit.t)), folder / "fitted.toml", model=dataclasses.asdict(cal.problem.model))
    io.atomic_write_text(folder / "report.md", report(cal))
    plots.waterfall(cal.fit.chi2_all, folder / "waterfall.png")
    plots.fit_against_data(cal.problem.observations, cal.model, folder / "fit.png")
    plots.correlation(cal.problem.names, cal.fisher.correlation, folder / "correlation.png")
    if cal.profiles:
        plots.likelihood_profiles(cal.profiles, cal.fit.chi2, CHI2_95, dict(zip(cal.problem.names, cal.fit.values)), folder / "profiles.png")
