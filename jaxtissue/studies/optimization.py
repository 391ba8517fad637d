"""Protocol optimisation: gradient-based design of conditioning protocols.

A `Design` (from TOML, `read_design`) names an objective (`OBJECTIVES`, each a small
function of a `Result`), bounds on the period and post displacement, limits on peak
post force, peak surface strain or final EI (`CONSTRAINTS`), the model parameters and
the model's resolution. The decision variables are each stage's period and post
displacement: one stage is the paper's constant protocol, several a piecewise-constant
schedule (`Protocol.schedule`).

* Bounds by reparametrisation: θ = lo + (hi − lo) σ(z) (in log θ for the period), so
  every iterate lies inside them.
* Constraints g = value/limit − 1 ≤ 0 (ceilings; 1 − value/limit for floors) by an
  augmented Lagrangian, L = f + (1/2ρ) Σ [max(0, λ + ρ g)² − λ²], with the limits
  tightened by a small `margin`; the multipliers are updated λ ← max(0, λ + ρ g)
  every `inner_steps`.
* `optimize`: Adam (optax) on L with its gradient through the whole coupled run
  (forward mode for up to 8 decision variables, reverse mode beyond), from
  several starts at once (`vmap`): the best grid point and a Latin hypercube. Every
  iterate is recorded; the answer is the best iterate that meets every constraint.
* `grid_search`: the brute-force comparison, a jitted, vmapped batch over an n × n grid
  of constant protocols within the same bounds.
"""

from __future__ import annotations

import dataclasses
import math
import pathlib
import time
from typing import NamedTuple

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import optax

from .. import cache, io, plots
from ..io import InputError, number, params_from_table, read_params_toml, read_toml
from ..limits import MAX_SWEEP_POINTS, SUPPORTED, check_count, check_study
from ..params import Params, suggest
from ..protocol import LUMPING_RULES, THREE_WEEKS_S, Protocol, interval_bounds
from ..simulate import simulate
from ._problem_files import ModelSettings, bounds, settings, table, unit_latin_hypercube
from .objectives import CONSTRAINTS, OBJECTIVES, conditioning_dose
from .robust import Uncertainty, chance_rank, check, read_uncertainty
from .sweep import vmap_over_devices

VARIABLES = ("period_s", "post_displacement_mm")
DEFAULT_BOUNDS = {"period_s": (0.25, 10.0), "post_displacement_mm": (0.0, 10.0)}
BASELINE = {"period_s": 1.0, "post_displacement_mm": 5.0}  # the paper's protocol


# ---------------------------------------------------------------------------------------
# The design problem
# ---------------------------------------------------------------------------------------


@dataclasses.dataclass(frozen=True)
class OptimizerSettings:
    """Multi-start Adam on the augmented Lagrangian, and the comparison grid."""

    starts: int = 4
    steps: int = 40
    learning_rate: float = 0.15  # Adam step in the unbounded coordinates z
    inner_steps: int = 10  # Adam steps between multiplier updates
    penalty: float = 20.0  # ρ of the augmented Lagrangian (constraints are relative)
    margin: float = 0.002  # the limits are tightened by this fraction inside the optimiser
    grid_points: int = 16  # per axis of the brute-force grid (constant protocols)
    grid_chunk: int = 64  # protocols per vmapped batch
    seed: int = 0

    def __post_init__(self):
        check_count("starts", self.starts)
        if self.grid_points**2 > MAX_SWEEP_POINTS:
            raise ValueError(f"grid_points = {self.grid_points} is a grid of {self.grid_points**2:.3g} protocols; at most "
                             f"{MAX_SWEEP_POINTS} (grid_points <= {math.isqrt(MAX_SWEEP_POINTS)})")


DESIGN_MODEL = ModelSettings(coupling_interval_s=2.016e5)  # 3 intervals a week: weekly stages align


@dataclasses.dataclass(frozen=True, eq=False)  # hashed by identity: compiled functions are cached per design
class Design:
    objective: str
    params: Params = Params()
    bounds: dict = dataclasses.field(default_factory=lambda: dict(DEFAULT_BOUNDS))
    constraints: dict = dataclasses.field(default_factory=dict)  # name -> limit
    stages: int = 1
    stage_length_s: float = 604800.0
    t_end_s: float = THREE_WEEKS_S
    hold_fraction: float = 0.05
    lumping: str = "dispersive"
    model: ModelSettings = DESIGN_MODEL
    settings: OptimizerSettings = OptimizerSettings()
    name: str = "design"
    uncertainty: Uncertainty | None = None  # judge protocols over posterior draws (`robust`)

    def __post_init__(self):
        if self.objective not in OBJECTIVES:
            raise InputError(f"objective = {self.objective!r}; {suggest(self.objective, OBJECTIVES)}")
        for name, limit in self.constraints.items():
            if name not in CONSTRAINTS:
                raise InputError(f"unknown constraint {name!r}; {suggest(name, CONSTRAINTS)}")
            if isinstance(limit, bool) or not isinstance(limit, (int, float)) or not (math.isfinite(limit) and limit > 0):
                raise InputError(f"constraint {name} = {limit!r} must be a positive number ({CONSTRAINTS[name].unit})")
        if self.objective == "least_conditioning" and "EI_min_N_m2" not in self.constraints:
            raise InputError("objective least_conditioning needs a target: [constraints] EI_min_N_m2 = VALUE (N m^2)")
        length = float(self.params.length_mm)
        allowed = {"period_s": (0.0, math.inf, "0 < low < high (s)"),
                   "post_displacement_mm": (0.0, length, f"0 <= low < high < {length:g} mm (the strip length)")}
        for name in self.bounds:
            if name not in VARIABLES:
                raise InputError(f"unknown bound {name!r}; {suggest(name, VARIABLES)}")
        for name in VARIABLES:
            lo, hi = self.bounds.get(name, DEFAULT_BOUNDS[name])
            amin, amax, text = allowed[name]
            ok = lo < hi and hi < amax and (lo > amin if name == "period_s" else lo >= amin)
            if not ok:
                raise InputError(f"bounds {name} = [{lo:g}, {hi:g}]; allowed: {text}")
        if not (isinstance(self.stages, int) and self.stages >= 1):
            raise InputError(f"stages = {self.stages!r} must be a positive integer")
        if not (self.stage_length_s > 0 and self.t_end_s > 0):
            raise InputError("stage_length_s and t_end_s must be positive numbers of seconds")
        if self.stages > 1 and (self.stages - 1) * self.stage_length_s >= self.t_end_s:
            raise InputError(f"stages = {self.stages} of {self.stage_length_s:g} s: the last stage would start after t_end_s = {self.t_end_s:g} s")
        if not 0 <= self.hold_fraction < 0.25:
            raise InputError(f"hold_fraction = {self.hold_fraction!r}; allowed: [0, 0.25)")

    # ---- coordinates: θ (stages, 2) in natural units; z ∈ ℝ the optimiser's
    def _t_bounds(self):
        (p_lo, p_hi), (u_lo, u_hi) = (self.bounds.get(n, DEFAULT_BOUNDS[n]) for n in VARIABLES)
        return np.array([math.log(p_lo), u_lo]), np.array([math.log(p_hi), u_hi])

    def theta_from_unit(self, s):
        """Natural values from points of the unit square (log-uniform period)."""
        lo, hi = self._t_bounds()
        t = lo + (hi - lo) * s
        return jnp.stack([jnp.exp(t[..., 0]), t[..., 1]], axis=-1)

    def unit_from_theta(self, theta):
        lo, hi = self._t_bounds()
        t = jnp.stack([jnp.log(theta[..., 0]), theta[..., 1]], axis=-1)
        return (t - lo) / (hi - lo)

    def theta_from_z(self, z):
        return self.theta_from_unit(jax.nn.sigmoid(z))

    def z_from_theta(self, theta):
        s = jnp.clip(self.unit_from_theta(theta), 1e-6, 1 - 1e-6)
        return jnp.log(s) - jnp.log1p(-s)

    def protocol(self, theta) -> Protocol:
        """The protocol of θ (stages, 2)."""
        if self.stages == 1:
            return Protocol.flex(theta[0, 0], theta[0, 1], self.hold_fraction, self.lumping)
        return Protocol.schedule(theta[:, 0], theta[:, 1], self.stage_length_s, self.hold_fraction, self.lumping)

    def constant(self, period_s, post_displacement_mm):
        """θ of a constant protocol."""
        return jnp.tile(jnp.stack([jnp.asarray(period_s, float), jnp.asarray(post_displacement_mm, float)]), (self.stages, 1))

    # ---- the model
    def evaluate_with(self, theta, params: Params, autodiff="reverse"):
        """(objective, constraint values in `constraints` order, failed) at θ with `params`."""
        m = self.model
        protocol = self.protocol(theta)
        result = simulate(params, protocol, self.t_end_s, m.grid("flex"), coupling_interval_s=m.coupling_interval_s,
                          beam=m.beam(), options=m.solver_options(autodiff))
        dose = conditioning_dose(protocol, interval_bounds(self.t_end_s, m.coupling_interval_s))
        J = OBJECTIVES[self.objective].fn(result, dose)
        values = jnp.stack([CONSTRAINTS[n].value(result) for n in self.constraints]) if self.constraints else jnp.zeros(0)
        return J, values, result.failed

    def evaluate_draws(self, theta, draws, autodiff="reverse"):
        """`evaluate_with` for each posterior draw (rows of `draws`, natural units of
        `uncertainty.names`), at once under vmap."""
        names = self.uncertainty.names
        return jax.vmap(lambda v: self.evaluate_with(theta, self.params.replace(**{n: v[i] for i, n in enumerate(names)}), autodiff))(
            jnp.asarray(draws))

    def evaluate(self, theta, autodiff="reverse"):
        """(objective, constraint values in `constraints` order, failed) at θ: with
        `uncertainty`, their risk measures over the optimisation's posterior draws."""
        u = self.uncertainty
        if u is None:
            return self.evaluate_with(theta, self.params, autodiff)
        J, values, failed = self.evaluate_draws(theta, u.split()[0], autodiff)
        return u.objective(J, OBJECTIVES[self.objective].sense), u.limit_values(values, self.violation), jnp.any(failed)

    def violation(self, values, margin=0.0):
        """g (relative; ≤ 0 where met) of constraint values, limits tightened by `margin`."""
        if not self.constraints:
            return jnp.zeros(0)
        g = []
        for k, (name, limit) in enumerate(self.constraints.items()):
            if CONSTRAINTS[name].kind == "ceiling":
                g.append(values[..., k] / (limit * (1 - margin)) - 1.0)
            else:
                g.append(1.0 - values[..., k] / (limit * (1 + margin)))
        return jnp.stack(g, axis=-1)

    @property
    def autodiff(self) -> str:
        """Forward mode for a few decision variables (cheaper to run and to compile
        here than a reverse pass), reverse mode for many."""
        return "forward" if 2 * self.stages <= 8 else "reverse"

    def lagrangian(self, z, lam, scale):
        """The augmented Lagrangian at z; aux = (θ, objective, constraint values, failed)."""
        s = self.settings
        theta = self.theta_from_z(z)
        J, values, failed = self.evaluate(theta, self.autodiff)
        f = -OBJECTIVES[self.objective].sense * J / scale
        g = self.violation(values, s.margin)
        L = f + jnp.sum(jnp.maximum(0.0, lam + s.penalty * g) ** 2 - lam**2) / (2 * s.penalty)
        return L, (theta, J, values, failed)


def _feasible(design: Design, values, failed, J):
    g = np.asarray(design.violation(jnp.asarray(values)))
    return np.all(g <= 0, axis=-1) & ~np.asarray(failed) & np.isfinite(np.asarray(J))


def _better(design: Design, a, b):
    """Is objective a better than b?"""
    return OBJECTIVES[design.objective].sense * (a - b) > 0


# ---------------------------------------------------------------------------------------
# Brute force and gradient
# ---------------------------------------------------------------------------------------


class GridResult(NamedTuple):
    periods_s: np.ndarray  # (n,)
    displacements_mm: np.ndarray  # (n,)
    objective: np.ndarray  # (n_period, n_displacement)
    values: np.ndarray  # (n_period, n_displacement, constraints)
    feasible: np.ndarray
    best: dict | None  # {"period_s", "post_displacement_mm"} of the best feasible point
    best_objective: float
    best_values: np.ndarray | None  # the constraint values there
    seconds: float
    compile_seconds: float


def _prepared(program, *args):
    """`program`'s compiled program for `args` (or, where the command line saves its
    programs, loaded: `cache.prepared`), and the seconds that took. Jitted here: the
    compiled program is freed with the function returned."""
    t0 = time.perf_counter()
    run = cache.prepared(eqx.filter_jit(program), *args)
    return run, time.perf_counter() - t0


def _evaluate(design: Design, theta):
    return design.evaluate(theta)


def _grid_batch(design: Design, thetas):
    """`design.evaluate` of the protocols θ (rows of `thetas`) at once, over the devices."""
    return vmap_over_devices(design.evaluate, thetas.shape[0])(thetas)


def _adam(settings: OptimizerSettings):
    schedule = optax.cosine_decay_schedule(settings.learning_rate, settings.steps, alpha=0.1)
    return optax.apply_if_finite(optax.adam(schedule), max_consecutive_errors=settings.steps)


def _adam_steps(design: Design, z, state, lam, scale):
    """An Adam step on the augmented Lagrangian from each start (rows of z, their Adam
    states and multipliers) at once, over the devices: (z, state, (θ, objective,
    constraint values, failed) at the z stepped from)."""
    opt = _adam(design.settings)
    grad = (jax.jacfwd if design.autodiff == "forward" else jax.grad)(design.lagrangian, has_aux=True)

    def step(z, state, lam, scale):
        dz, aux = grad(z, lam, scale)
        updates, state = opt.update(dz, state, z)
        return optax.apply_updates(z, updates), state, aux

    return vmap_over_devices(step, z.shape[0], (0, 0, 0, None))(z, state, lam, scale)


def grid_search(design: Design, progress=None) -> GridResult:
    """The objective on an n × n grid of constant protocols (period log-spaced), as
    jitted vmapped batches; `progress(k)` after each batch."""
    s = design.settings
    n = s.grid_points
    unit = np.linspace(0.0, 1.0, n)
    corners = np.asarray(design.theta_from_unit(jnp.asarray(np.stack([unit, unit], axis=-1))))
    periods, displacements = corners[:, 0], corners[:, 1]
    P, U = np.meshgrid(periods, displacements, indexing="ij")
    thetas = np.stack([np.broadcast_to(P.ravel()[:, None], (n * n, design.stages)),
                       np.broadcast_to(U.ravel()[:, None], (n * n, design.stages))], axis=-1)
    chunk = min(s.grid_chunk, n * n)
    batch, compile_s = _prepared(_grid_batch, design, jnp.zeros((chunk, design.stages, 2)))
    t0 = time.perf_counter()
    J, V, F = [], [], []
    for b in range(0, n * n, chunk):
        part = thetas[b : b + chunk]
        pad = chunk - len(part)
        out = batch(design, jnp.asarray(np.concatenate([part, np.repeat(part[-1:], pad, axis=0)])))
        J.append(np.asarray(out[0])[: len(part)])
        V.append(np.asarray(out[1])[: len(part)])
        F.append(np.asarray(out[2])[: len(part)])
        if progress is not None:
            progress(len(part))
    J, V, F = (np.concatenate(a) for a in (J, V, F))
    seconds = time.perf_counter() - t0
    feasible = _feasible(design, V, F, J)
    best, best_J, best_V = None, math.nan, None
    if np.any(feasible):
        sense = OBJECTIVES[design.objective].sense
        k = int(np.argmax(np.where(feasible, sense * J, -np.inf)))
        best, best_J, best_V = {"period_s": float(P.ravel()[k]), "post_displacement_mm": float(U.ravel()[k])}, float(J[k]), V[k]
    return GridResult(periods, displacements, J.reshape(n, n), V.reshape(n, n, -1), feasible.reshape(n, n),
                      best, best_J, best_V, seconds, compile_s)


class OptimizationResult(NamedTuple):
    path: np.ndarray  # θ per iterate and start, (steps + 1, starts, stages, 2)
    objective: np.ndarray  # (steps + 1, starts)
    values: np.ndarray  # (steps + 1, starts, constraints)
    feasible: np.ndarray  # (steps + 1, starts)
    best: np.ndarray | None  # θ (stages, 2) of the best feasible iterate
    best_objective: float
    best_values: np.ndarray | None
    best_iteration: int
    seconds: float  # after compilation
    seconds_to_best: float
    compile_seconds: float


def starting_points(design: Design, first=None) -> np.ndarray:
    """`starts` points θ: `first` (e.g. the best grid point; default the paper's
    protocol) and a Latin hypercube over the bounds."""
    s = design.settings
    first = first or BASELINE
    (p_lo, p_hi), (u_lo, u_hi) = (design.bounds.get(n, DEFAULT_BOUNDS[n]) for n in VARIABLES)
    theta0 = np.clip(np.asarray(design.constant(first["period_s"], first["post_displacement_mm"])), [p_lo, u_lo], [p_hi, u_hi])
    unit = unit_latin_hypercube(max(s.starts - 1, 0), 2 * design.stages, np.random.default_rng(s.seed))
    lhs = np.asarray(design.theta_from_unit(jnp.asarray(unit.reshape(-1, design.stages, 2))))
    return np.concatenate([np.asarray(theta0)[None], lhs])[: s.starts]


def optimize(design: Design, starts: np.ndarray, scale: float, progress=None) -> OptimizationResult:
    """Adam on the augmented Lagrangian from every start at once; `scale` normalises
    the objective (e.g. the baseline's |objective|)."""
    s = design.settings
    n_con = len(design.constraints)
    z = jnp.asarray(design.z_from_theta(jnp.asarray(starts)))
    state = jax.vmap(_adam(s).init)(z)
    lam = jnp.zeros((len(starts), n_con))
    scale = jnp.asarray(scale, float)
    batched, compile_s = _prepared(_adam_steps, design, z, state, lam, scale)
    path, J, V, F, stamps = [], [], [], [], []
    t0 = time.perf_counter()
    for k in range(s.steps + 1):
        z_new, state_new, (theta, j, values, failed) = batched(design, z, state, lam, scale)
        path.append(np.asarray(theta)), J.append(np.asarray(j)), V.append(np.asarray(values)), F.append(np.asarray(failed))
        stamps.append(time.perf_counter() - t0)
        z, state = z_new, state_new
        if n_con and (k + 1) % s.inner_steps == 0:
            lam = jnp.maximum(0.0, lam + s.penalty * design.violation(values, s.margin))
        if progress is not None:
            progress(1)
    path, J, V, F = (np.stack(a) for a in (path, J, V, F))
    feasible = _feasible(design, V, F, J)
    best, best_J, best_V, best_k = None, math.nan, None, -1
    if np.any(feasible):
        sense = OBJECTIVES[design.objective].sense
        k, i = np.unravel_index(int(np.argmax(np.where(feasible, sense * J, -np.inf))), J.shape)
        best, best_J, best_V, best_k = path[k, i], float(J[k, i]), V[k, i], int(k)
    return OptimizationResult(path, J, V, feasible, best, best_J, best_V, best_k, stamps[-1],
                              stamps[best_k] if best_k >= 0 else math.nan, compile_s)


# ---------------------------------------------------------------------------------------
# The whole study: baseline, grid, gradient optimum, files
# ---------------------------------------------------------------------------------------


class InfeasibleError(InputError):
    """No protocol within the bounds meets the constraints."""


class Study(NamedTuple):
    design: Design
    baseline_objective: float
    baseline_values: np.ndarray
    grid: GridResult
    optimum: OptimizationResult
    robust: dict | None = None  # with `uncertainty`: this optimum and the point-estimate one on fresh draws


def _limits_text(design: Design, values) -> str:
    """Each constraint's best value over `values`, e.g. 'EI_min_N_m2 <= 4.6e-07 N m^2
    everywhere (limit 1e-05)'."""
    return ", ".join(
        f"{n} {'>=' if CONSTRAINTS[n].kind == 'ceiling' else '<='} {np.nanmin(v) if CONSTRAINTS[n].kind == 'ceiling' else np.nanmax(v):.4g} "
        f"{CONSTRAINTS[n].unit} everywhere (limit {limit:g})"
        for (n, limit), v in zip(design.constraints.items(), np.moveaxis(np.asarray(values), -1, 0))
    )


def run(design: Design, progress: bool = False) -> Study:
    """Baseline (the paper's 1 Hz / 5 mm), brute-force grid, then the gradient
    optimum from the best grid point and a Latin hypercube of starts. An
    `InfeasibleError` if no grid point meets the limits."""
    from tqdm.auto import tqdm

    m = design.model
    draws = 1 if design.uncertainty is None else max(design.uncertainty.draws, design.uncertainty.check_draws)
    s = design.settings  # the starts' gradients at once, then the grid's batches forward
    check_study("the optimisation", m.grid("flex"), design.t_end_s, m.coupling_interval_s, s.starts * draws,
                reverse=design.autodiff == "reverse")
    check_study("the optimisation's grid", m.grid("flex"), design.t_end_s, m.coupling_interval_s,
                min(s.grid_chunk, s.grid_points**2) * draws, reverse=False)
    base_theta = design.constant(BASELINE["period_s"], BASELINE["post_displacement_mm"])
    J0, V0, _ = cache.call(eqx.filter_jit(_evaluate), design, base_theta)
    with tqdm(total=design.settings.grid_points**2, desc="grid", unit="protocol", disable=not progress) as bar:
        grid = grid_search(design, progress=bar.update)
    if grid.best is None:
        n = design.settings.grid_points
        raise InfeasibleError(f"no protocol of the {n} x {n} grid over the bounds meets the limits: {_limits_text(design, grid.values)}; "
                              "relax a limit or widen the bounds")
    starts = starting_points(design, grid.best)
    scale = max(abs(float(J0)), 1e-12)
    with tqdm(total=design.settings.steps + 1, desc="optimise", unit="step", disable=not progress) as bar:
        optimum = optimize(design, starts, scale, progress=bar.update)
    study = Study(design, float(J0), np.asarray(V0), grid, optimum)
    if design.uncertainty is None:
        return study
    point = run(dataclasses.replace(design, uncertainty=None), progress)  # the same problem at the point estimate
    fresh = design.uncertainty.split()[1]
    evaluate = jax.jit(design.evaluate_draws)
    robust = {
        "posterior": design.uncertainty.posterior, "risk": design.uncertainty.risk, "quantile": design.uncertainty.quantile,
        "declared_constraint_probability": design.uncertainty.constraint_probability,
        "optimisation_draws": design.uncertainty.draws,
        "robust_optimum": {"protocol": optimum_protocol(study),
                           **check(design, jnp.asarray(_theta(study)), fresh, evaluate)},
        "point_estimate_optimum": {"protocol": optimum_protocol(point),
                                   **check(design, jnp.asarray(_theta(point)), fresh, evaluate)},
    }
    return study._replace(robust=robust)


def _theta(study: Study):
    d = study.design
    if study.optimum.best is not None:
        return study.optimum.best
    return np.asarray(d.constant(study.grid.best["period_s"], study.grid.best["post_displacement_mm"]))


def optimum_protocol(study: Study) -> dict:
    """The optimum as {"period_s", "post_displacement_mm"} or a schedule."""
    d, theta = study.design, _theta(study)
    if d.stages == 1:
        return {"period_s": float(theta[0, 0]), "post_displacement_mm": float(theta[0, 1])}
    return {"stage_length_s": d.stage_length_s, "period_s": theta[:, 0].tolist(), "post_displacement_mm": theta[:, 1].tolist()}


def summary(study: Study) -> dict:
    """The `summary.json` of `jaxtissue optimize`."""
    d, g, o = study.design, study.grid, study.optimum
    found = o.best is not None
    objective = o.best_objective if found else g.best_objective
    values = o.best_values if found else g.best_values
    return {
        "problem": d.name,
        "objective_name": d.objective,
        "objective_unit": OBJECTIVES[d.objective].unit,
        "sense": "maximise" if OBJECTIVES[d.objective].sense > 0 else "minimise",
        "optimum": optimum_protocol(study),
        "objective": objective,
        "baseline": dict(BASELINE),
        "baseline_objective": study.baseline_objective,
        "grid_best": g.best,
        "grid_best_objective": g.best_objective,
        "grid_points": int(g.objective.size),
        "constraints": {
            n: {"value": float(v), "limit": limit, "kind": CONSTRAINTS[n].kind, "unit": CONSTRAINTS[n].unit,
                "satisfied": bool(v <= limit if CONSTRAINTS[n].kind == "ceiling" else v >= limit)}
            for (n, limit), v in zip(d.constraints.items(), np.asarray(values))
        },
        "bounds": {n: list(d.bounds.get(n, DEFAULT_BOUNDS[n])) for n in VARIABLES},
        "t_end_s": d.t_end_s,
        "gradient_found_optimum": found,
        "starts": o.path[0].tolist(),
        "optimizer_steps": d.settings.steps,
        "seconds": {
            "gradient_to_optimum": o.seconds_to_best, "gradient_total": o.seconds, "gradient_compile": o.compile_seconds,
            "grid_total": g.seconds, "grid_compile": g.compile_seconds,
        },
        "outside_supported": outside_supported(optimum_protocol(study)),
        **({"robust": study.robust} if study.robust is not None else {}),
    }


def outside_supported(protocol: dict) -> dict:
    """The optimum's coordinates outside the range the model and data support
    (`limits.SUPPORTED`): {name: [values outside]}."""
    out = {}
    for name in ("period_s", "post_displacement_mm"):
        lo, hi = SUPPORTED[name].low, SUPPORTED[name].high
        values = np.atleast_1d(protocol[name])
        if np.any((values < lo) | (values > hi)):
            out[name] = [float(v) for v in values if not lo <= v <= hi]
    return out


def report(study: Study) -> str:
    """A Markdown report: optimum against the paper's protocol and the grid."""
    s = summary(study)
    d = study.design
    obj = OBJECTIVES[d.objective]
    sec = s["seconds"]
    better = "better than or equal to" if not _better(d, s["grid_best_objective"], s["objective"]) else "**worse** than"
    lines = [
        f"# Protocol optimisation: {d.name}", "",
        f"Objective: {s['sense']} {obj.label} ({obj.unit}) at t = {d.t_end_s:g} s; "
        f"{'constant protocol' if d.stages == 1 else f'{d.stages} stages of {d.stage_length_s:g} s'}; bounds "
        + ", ".join(f"{n} ∈ [{lo:g}, {hi:g}]" for n, (lo, hi) in s["bounds"].items()) + ".", "",
        "| protocol | objective | " + " | ".join(d.constraints) + " |",
        "|---|---|" + "---|" * len(d.constraints),
    ]

    def row(name, J, values):
        return f"| {name} | {J:.5g} | " + " | ".join(f"{v:.4g}" for v in values) + " |"

    lines.append(row("paper (1 Hz, 5 mm)", s["baseline_objective"], study.baseline_values))
    if study.grid.best is not None:
        lines.append(row(f"best of {s['grid_points']}-point grid (T = {s['grid_best']['period_s']:.3g} s, u = {s['grid_best']['post_displacement_mm']:.3g} mm)",
                         s["grid_best_objective"], study.grid.best_values))
    opt = s["optimum"]
    if d.stages == 1:
        label = f"gradient optimum (T = {opt['period_s']:.4g} s, u = {opt['post_displacement_mm']:.4g} mm)"
    else:
        label = "gradient optimum (schedule: T = " + ", ".join(f"{v:.3g}" for v in opt["period_s"]) + " s; u = " + ", ".join(f"{v:.3g}" for v in opt["post_displacement_mm"]) + " mm)"
    lines.append(row(label, s["objective"], [c["value"] for c in s["constraints"].values()]))
    lines += ["", "Limits: " + (", ".join(f"{n} {'≤' if c['kind'] == 'ceiling' else '≥'} {c['limit']:g}{'' if c['unit'] == '1' else ' ' + c['unit']} ({'met' if c['satisfied'] else '**not met**'})"
                                    for n, c in s["constraints"].items()) or "none") + ".", ""]
    gain = (s["objective"] - s["baseline_objective"]) / abs(s["baseline_objective"]) if s["baseline_objective"] else math.nan
    lines.append(f"The optimum is {better} the best grid point and changes the objective by {100 * gain:+.1f} % against the paper's protocol.")
    if d.stages > 1:
        lines.append(_schedule_diagnosis(study, s))
    lines.append(_support_line(s["outside_supported"]))
    if study.robust is not None:
        lines += _robust_lines(study.robust, d)
    lines += [
        "", "## Cost", "",
        f"Gradient optimisation: {d.settings.starts} starts × {d.settings.steps} Adam steps, best iterate after {sec['gradient_to_optimum']:.1f} s "
        f"({sec['gradient_total']:.1f} s in all, plus {sec['gradient_compile']:.0f} s compilation). "
        f"Brute-force grid: {s['grid_points']} protocols in {sec['grid_total']:.1f} s (plus {sec['grid_compile']:.0f} s compilation).", "",
        "Files: summary.json, params.toml (`jaxtissue simulate --params params.toml`), landscape.png (objective over the constant "
        "protocols with the optimisation paths), history.png" + (", schedule.png" if d.stages > 1 else "") + ".", "",
    ]
    return "\n".join(lines)


def _support_line(outside: dict) -> str:
    ranges = ", ".join(f"{n} {SUPPORTED[n].low:g}–{SUPPORTED[n].high:g} {SUPPORTED[n].unit}" for n in ("period_s", "post_displacement_mm"))
    if not outside:
        return f"The optimum lies inside the range the model and data support ({ranges})."
    return (f"The optimum lies **outside** the range the model and data support ({ranges}): "
            + ", ".join(f"{n} = {', '.join(f'{v:.3g}' for v in vs)}" for n, vs in outside.items())
            + "; there the model extrapolates (docs/model.md §10).")


def _robust_lines(r: dict, d: Design) -> list[str]:
    u = d.uncertainty
    measure = "mean" if r["risk"] == "mean" else f"{r['quantile']:g}-quantile (the unfavourable tail)"
    p = r["declared_constraint_probability"]
    out = ["", "## Under uncertainty", "",
           f"Posterior `{r['posterior']}`: the objective is its {measure} over {r['optimisation_draws']} posterior draws"
           + (f", and all limits must hold together for {chance_rank(p, r['optimisation_draws'])} of them, so that they hold for a "
              f"fresh draw with probability at least {100 * p:g} %" if p is not None else ", the limits on the draws' mean values") + ". "
           f"Both optima, checked on {u.check_draws} fresh draws:", "",
           "| optimum | protocol | objective (risk measure) | objective (mean) | limits met in | failed |", "|---|---|---|---|---|---|"]
    for key, label in (("robust_optimum", "robust"), ("point_estimate_optimum", "point estimate")):
        c = r[key]
        proto = c["protocol"]
        text = (f"T = {proto['period_s']:.3g} s, u = {proto['post_displacement_mm']:.3g} mm" if d.stages == 1 else "schedule")
        out.append(f"| {label} | {text} | {c['objective']:.5g} | {c['objective_mean']:.5g} | {100 * c['constraint_probability']:.0f} % | {c['failed']} |")
    pe = r["point_estimate_optimum"]
    out += ["", f"The point-estimate protocol breaks a limit for {100 * (1 - pe['constraint_probability']):.0f} % of plausible tissues."]
    proto = r["robust_optimum"]["protocol"]
    if d.stages == 1:
        inside = not outside_supported(proto)
        out.append(f"The robust optimum lies {'inside' if inside else '**outside**'} the calibrated conditions (0.5–2 s periods, "
                   "2.5–10 mm): " + ("the data cover it." if inside else "the model extrapolates there; its predictive spread is "
                                     "the posterior's only, not the model's error."))
    return out


def _schedule_diagnosis(study: Study, s: dict) -> str:
    d = study.design
    if study.grid.best is None or not _better(d, s["objective"], s["grid_best_objective"]):
        return ("The schedule does not beat the best constant protocol: starting from it, no feasible step of any stage "
                "improved the objective (history.png), so within these bounds and limits the constant optimum is also "
                "optimal stage by stage.")
    gain = (s["objective"] - s["grid_best_objective"]) / abs(s["grid_best_objective"])
    return f"The schedule beats the best constant protocol of the grid by {100 * gain:+.2f} % (schedule.png shows its stages)."


def write(study: Study, folder) -> None:
    """summary.json, params.toml, report.md and the figures into `folder`."""
    folder = pathlib.Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    io.write_json(folder / "summary.json", summary(study))
    io.write_params_toml(study.design.params, folder / "params.toml")
    io.atomic_write_text(folder / "report.md", report(study))
    d, g, o = study.design, study.grid, study.optimum
    objective = OBJECTIVES[d.objective]
    plots.protocol_landscape(g.periods_s, g.displacements_mm, g.objective, g.feasible, o.path, o.best, g.best, BASELINE,
                             f"{objective.label} ({objective.unit})", folder / "landscape.png")
    plots.optimisation_history(o.objective, o.feasible, g.best_objective if g.best is not None else None, study.baseline_objective,
                               objective.label, objective.unit, folder / "history.png")
    if d.stages > 1 and o.best is not None:
        plots.schedule(o.best, d.stage_length_s, g.best, folder / "schedule.png")


# ---------------------------------------------------------------------------------------
# Problem files
# ---------------------------------------------------------------------------------------

_TOP = {"name", "objective", "parameters", "protocol", "bounds", "constraints", "model", "optimizer", "t_end_s", "uncertainty"}
_PROTOCOL = {"stages", "stage_length_s", "hold_fraction", "lumping"}


def read_design(path, overrides: dict | None = None) -> Design:
    """A `Design` from a TOML file (see `optimize/max_collagen.toml`); every mistake is
    an `InputError` naming the file and the key. `overrides` replace [optimizer] keys."""
    path = pathlib.Path(path)
    doc, _ = read_toml(path, "optimisation problem", _TOP)
    where = str(path)
    objective = doc.get("objective")
    if not isinstance(objective, str):
        raise InputError(f"{where}: objective = \"NAME\" is required; allowed: {', '.join(OBJECTIVES)}")
    if objective not in OBJECTIVES:
        raise InputError(f"{where}: objective = {objective!r}; {suggest(objective, OBJECTIVES)}")

    parameters = doc.get("parameters", {})
    if isinstance(parameters, str):
        try:
            params = read_params_toml(path.parent / parameters)
        except InputError as err:
            raise InputError(f"{where}: parameters = {parameters!r}: {err}") from None
    elif isinstance(parameters, dict):
        params = params_from_table(parameters, f"{where} [parameters]")
    else:
        raise InputError(f"{where}: parameters must be a file name (\"FILE.toml\", relative to the problem file) or a table")

    protocol = table(doc, "protocol", where, _PROTOCOL)
    stages = protocol.get("stages", 1)
    if isinstance(stages, bool) or not isinstance(stages, int) or stages < 1:
        raise InputError(f"{where}: [protocol] stages = {stages!r} must be a positive integer")
    lumping = protocol.get("lumping", "dispersive")
    if lumping not in LUMPING_RULES:
        raise InputError(f"{where}: [protocol] lumping = {lumping!r}; allowed: {', '.join(map(repr, LUMPING_RULES))}")
    hold = number(protocol.get("hold_fraction", 0.05), f"{where}: [protocol] hold_fraction")

    box = {name: bounds(value, f"{where}: [bounds] {name}") for name, value in table(doc, "bounds", where, set(VARIABLES)).items()}
    constraints = {n: number(v, f"{where}: [constraints] {n}", positive=True) for n, v in table(doc, "constraints", where, set(CONSTRAINTS)).items()}

    optimizer = dict(table(doc, "optimizer", where))
    optimizer.update(overrides or {})
    for k, v in optimizer.items():
        if k == "margin" and isinstance(v, (int, float)) and not 0 <= v < 0.5:
            raise InputError(f"{where}: [optimizer] margin = {v!r} must be in [0, 0.5)")
    try:
        return Design(
            objective=objective, params=params, bounds={**DEFAULT_BOUNDS, **box}, constraints=constraints,
            stages=stages, stage_length_s=number(protocol.get("stage_length_s", 604800.0), f"{where}: [protocol] stage_length_s", positive=True),
            t_end_s=number(doc.get("t_end_s", THREE_WEEKS_S), f"{where}: t_end_s", positive=True), hold_fraction=hold, lumping=lumping,
            model=settings(ModelSettings, {"coupling_interval_s": DESIGN_MODEL.coupling_interval_s, **table(doc, "model", where)}, where, "model"),
            settings=settings(OptimizerSettings, optimizer, where, "optimizer"), name=str(doc.get("name", path.stem)),
            uncertainty=read_uncertainty(doc["uncertainty"], where, path.parent) if "uncertainty" in doc else None,
        )
    except InputError as err:
        if str(err).startswith(where):
            raise
        raise InputError(f"{where}: {err}") from None
