"""Culture protocols, the time loop and its `Result` (MODEL.md §2, §3, §5)."""

from __future__ import annotations

import math

import diffrax
import equinox as eqx
import jax
import jax.numpy as jnp
import jax.tree_util as jtu
import numpy as np

from . import observables as obs
from .grid import Grid
from .growth import GrowthModel, State
from .params import Params, concrete_value, nondimensionalise
from .beam import BeamGrid, loading_cycle
from .coupling import RULES, beam_from_ecm, lumped_transport
from .solver import ROS34PW2

THREE_WEEKS_S = 1.8144e6
"""The experiments' assay time, 21 days (MODEL.md §6)."""


class Protocol(eqx.Module):
    """A culture protocol (MODEL.md §1, §4, §5).

    `Protocol.static()`: no motion. `Protocol.flex(...)`: cyclic flexure with post
    displacement u_M(t) of eq. A.22; `period_s`, `post_displacement_mm` and
    `hold_fraction` are differentiable. `lumping` is the coupling rule (`coupling.RULES`),
    `pins` where the posts hold the strip ("centroid" or "bottom" corners).
    """

    regime: str = eqx.field(static=True, default="static")
    period_s: float = 1.0
    post_displacement_mm: float = 5.0
    hold_fraction: float = 0.05
    lumping: str = eqx.field(static=True, default="dispersive")
    pins: str = eqx.field(static=True, default="centroid")

    def __check_init__(self):
        if self.regime not in ("static", "flex"):
            raise ValueError(f"regime = {self.regime!r}; allowed: 'static', 'flex'")
        if self.lumping not in RULES:
            raise ValueError(f"lumping = {self.lumping!r}; allowed: {', '.join(map(repr, RULES))}")
        if self.pins not in ("centroid", "bottom"):
            raise ValueError(f"pins = {self.pins!r}; allowed: 'centroid', 'bottom'")
        checks = (
            ("period_s", lambda v: v > 0, "> 0 s"),
            ("post_displacement_mm", lambda v: 0 <= v < 25.0, "in [0, 25) mm (below the strip length)"),
            ("hold_fraction", lambda v: 0 <= v < 0.25, "in [0, 0.25)"),
        )
        for name, ok, allowed in checks:
            value = concrete_value(getattr(self, name))
            if value is not None and not (np.all(np.isfinite(value)) and np.all(ok(value))):
                raise ValueError(f"protocol {name} = {np.ravel(value)[0]:g} must be {allowed}")

    @classmethod
    def static(cls) -> "Protocol":
        return cls(regime="static")

    @classmethod
    def flex(cls, period_s=1.0, post_displacement_mm=5.0, hold_fraction=0.05, lumping="dispersive", pins="centroid") -> "Protocol":
        return cls("flex", period_s, post_displacement_mm, hold_fraction, lumping, pins)


class SolverOptions(eqx.Module):
    """Tolerances and limits of the growth solve (all static)."""

    rtol: float = eqx.field(static=True, default=1e-5)
    atol: float = eqx.field(static=True, default=1e-8)
    dt0_s: float = eqx.field(static=True, default=10.0)
    dtmax_s: float = eqx.field(static=True, default=2.0e5)
    max_steps: int = eqx.field(static=True, default=4096)
    checkpoints: int = eqx.field(static=True, default=16)
    """Checkpoints of the reverse pass through one growth solve (memory ∝ this)."""
    fixed_steps: int | None = eqx.field(static=True, default=None)
    """If set: no step control, this many steps growing geometrically from `dt0_s`
    (the same discrete map for every parameter value: for finite-difference checks)."""
    autodiff: str = eqx.field(static=True, default="reverse")
    """"reverse" (`jax.grad`; checkpointed) or "forward" (`jax.jvp`/`jacfwd`, e.g. for
    Jacobians of a few parameters in least-squares fits)."""

    def __check_init__(self):
        for name in ("rtol", "atol", "dt0_s", "dtmax_s"):
            value = getattr(self, name)
            if not (isinstance(value, (int, float)) and math.isfinite(value) and value > 0):
                raise ValueError(f"solver option {name} = {value!r} must be a positive number")
        for name in ("max_steps", "fixed_steps", "checkpoints"):
            value = getattr(self, name)
            if value is not None and (not isinstance(value, int) or value < 1):
                raise ValueError(f"solver option {name} = {value!r} must be a positive integer")
        if self.autodiff not in ("reverse", "forward"):
            raise ValueError(f"solver option autodiff = {self.autodiff!r}; allowed: 'reverse', 'forward'")

    def adjoint(self):
        if self.autodiff == "forward":
            return diffrax.ForwardMode()
        return diffrax.RecursiveCheckpointAdjoint(checkpoints=self.checkpoints)

    def controller(self, t0, t1):
        """diffrax step-size controller over [t0, t1]."""
        if self.fixed_steps is None:
            return diffrax.PIDController(rtol=self.rtol, atol=self.atol, dtmax=self.dtmax_s)
        span = t1 - t0
        frac = jnp.geomspace(self.dt0_s / span, 1.0, self.fixed_steps)
        return diffrax.StepTo(ts=t0 + span * jnp.concatenate([jnp.zeros(1), frac]))


class Result(eqx.Module):
    """The outputs of `simulate` (MODEL.md §3), at the save times `ts` (s; static, so
    `result.index(t)` works inside `jit` and `grad`).

    Series have a leading time axis; `profile_*` are mid-section profiles across the
    thickness (axis `y_cm`); `final` holds the last 2-D fields. `post_force_max_N` is the
    peak post force of a loading cycle with the ECM of that time (0 in static culture).
    `failed` is True when a solve stopped early (the values are then not valid).
    """

    ts: tuple = eqx.field(static=True)
    dna_ug_per_g: jax.Array
    collagen_mg_per_g: jax.Array
    E_eff_kPa: jax.Array
    EI_N_m2: jax.Array
    post_force_max_N: jax.Array
    profile_o: jax.Array
    profile_c: jax.Array
    profile_m: jax.Array
    final: State
    x_cm: jax.Array
    y_cm: jax.Array
    num_steps: jax.Array
    failed: jax.Array
    params: Params

    def index(self, t_s: float) -> int:
        """The index of the save time closest to `t_s`."""
        return int(np.argmin(np.abs(np.asarray(self.ts) - t_s)))

    def to_xarray(self):
        """An `xarray.Dataset` with units in each variable's attributes."""
        from .io import result_to_xarray

        return result_to_xarray(self)


def interval_bounds(t_end_s: float, coupling_interval_s: float) -> np.ndarray:
    """0, every coupling interval T_g below `t_end_s`, and `t_end_s`."""
    n = int(math.floor(t_end_s / coupling_interval_s + 1e-9))
    ts = set(np.round(np.arange(n + 1) * coupling_interval_s, 9).tolist()) | {t_end_s}
    return np.array(sorted(ts))


def save_times(t_end_s: float, coupling_interval_s: float) -> np.ndarray:
    """The interval bounds, and exactly 3 weeks if reached."""
    ts = set(interval_bounds(t_end_s, coupling_interval_s).tolist())
    if t_end_s >= THREE_WEEKS_S:
        ts.add(THREE_WEEKS_S)
    return np.array(sorted(ts))


def _observe(t, y: State, args):
    p, grid = args
    EI = obs.flexural_rigidity_N_m2(y, p, grid)
    return dict(
        dna_ug_per_g=obs.dna_ug_per_g(y, p),
        collagen_mg_per_g=obs.collagen_mg_per_g(y, p),
        EI_N_m2=EI,
        E_eff_kPa=obs.effective_modulus_kPa(EI, p),
        profile_o=obs.mid_profile(y.o, grid),
        profile_c=obs.mid_profile(y.c, grid),
        profile_m=obs.mid_profile(y.m, grid),
    )


def growth_solve(model: GrowthModel, y0: State, t0, t1, ts, options: SolverOptions, args, progress=False):
    """Integrate the growth system over [t0, t1] (diffrax, `ROS34PW2`); `sol.ys` is
    (observables at `ts`, state at `ts`)."""
    saveat = diffrax.SaveAt(subs=[diffrax.SubSaveAt(ts=ts, fn=_observe), diffrax.SubSaveAt(ts=ts)])
    return diffrax.diffeqsolve(
        diffrax.ODETerm(model),
        ROS34PW2(),
        t0=t0,
        t1=t1,
        dt0=options.dt0_s if options.fixed_steps is None else None,
        y0=y0,
        args=args,
        saveat=saveat,
        stepsize_controller=options.controller(t0, t1),
        max_steps=options.max_steps,
        adjoint=options.adjoint(),
        progress_meter=diffrax.TqdmProgressMeter() if progress else diffrax.NoProgressMeter(),
        throw=False,
    )


class _Progress:
    """A tqdm bar over growth intervals, fed from inside jitted code."""

    bar = None

    @classmethod
    def tick(cls, _):
        if cls.bar is not None:
            cls.bar.update(1)


def flex_cycle(y: State, params: Params, protocol: Protocol, grid: Grid, beam_grid: BeamGrid, keep_fields=False):
    """One loading cycle from rest with the ECM of `y` (MODEL.md §5, step 1)."""
    beam = beam_from_ecm(y, params, grid, beam_grid, protocol.pins, "neo-hookean")
    u_max = protocol.post_displacement_mm * 1e-3
    return beam, loading_cycle(beam, protocol.period_s, u_max, protocol.hold_fraction, keep_fields)


@eqx.filter_jit
def _simulate(params: Params, protocol: Protocol, grid: Grid, beam_grid: BeamGrid, schedule: tuple, options, initial_state, progress):
    times, coupling_interval_s = schedule
    coeffs = nondimensionalise(params)
    args = (params, grid)
    y0 = State.initial(coeffs, grid) if initial_state is None else initial_state
    bounds = interval_bounds(times[-1], coupling_interval_s)
    extra = THREE_WEEKS_S in times and THREE_WEEKS_S not in bounds
    if protocol.regime == "static":
        model = GrowthModel(coeffs=coeffs, grid=grid)
        ts = jnp.asarray(times)
        sol = growth_solve(model, y0, ts[0], ts[-1], ts, options, args, progress)
        series, states = sol.ys
        series["post_force_max_N"] = jnp.zeros(len(times))
        final = jtu.tree_map(lambda x: x[-1], states)
        num_steps, failed = sol.stats["num_steps"], sol.result != diffrax.RESULTS.successful
    else:
        t0s, t1s = jnp.asarray(bounds[:-1]), jnp.asarray(bounds[1:])
        tes = jnp.clip(THREE_WEEKS_S, t0s, t1s)

        def interval(y, k):
            t0, t1, te = t0s[k], t1s[k], tes[k]
            _, cycle = flex_cycle(y, params, protocol, grid, beam_grid)
            transport = lumped_transport(cycle, params, grid, beam_grid, protocol.lumping, protocol.pins)
            model = GrowthModel(coeffs=coeffs, grid=grid, transport=transport)
            sol = growth_solve(model, y, t0, t1, jnp.stack([te, t1]), options, args)
            series, states = sol.ys
            if progress:
                jax.debug.callback(_Progress.tick, t1)
            y1 = jtu.tree_map(lambda x: x[-1], states)
            out = dict(
                series=series, extra_state=jtu.tree_map(lambda x: x[0], states),
                post_force=cycle.post_force_max_N, steps=sol.stats["num_steps"],
                failed=cycle.failed | (sol.result != diffrax.RESULTS.successful),
            )
            return y1, out

        # each interval is rematerialised in the backward pass: memory holds one
        # state per interval plus one interval's working set (beam.py nests further)
        final, out = jax.lax.scan(jax.checkpoint(interval), y0, jnp.arange(len(bounds) - 1))
        start = _observe(0.0, y0, args)
        series = {k: jnp.concatenate([start[k][None], v[:, 1]]) for k, v in out["series"].items()}
        _, last_cycle = flex_cycle(final, params, protocol, grid, beam_grid)
        series["post_force_max_N"] = jnp.concatenate([out["post_force"], last_cycle.post_force_max_N[None]])
        failed = jnp.any(out["failed"]) | last_cycle.failed
        if extra:
            k3 = int(np.searchsorted(bounds, THREE_WEEKS_S)) - 1
            y3 = jtu.tree_map(lambda x: x[k3], out["extra_state"])
            _, cycle3 = flex_cycle(y3, params, protocol, grid, beam_grid)
            at3 = {k: v[k3, 0] for k, v in out["series"].items()}
            at3["post_force_max_N"] = cycle3.post_force_max_N
            series = {k: jnp.concatenate([v[: k3 + 1], at3[k][None], v[k3 + 1 :]]) for k, v in series.items()}
            failed = failed | cycle3.failed
        num_steps = jnp.sum(out["steps"])
    return Result(
        ts=tuple(times),
        **series,
        final=final,
        x_cm=grid.x_centres(coeffs.length_cm),
        y_cm=grid.y_centres(coeffs.thickness_cm),
        num_steps=num_steps,
        failed=failed,
        params=params,
    )


def simulate(
    params: Params,
    protocol: Protocol | None = None,
    t_end_s: float = 2.0e6,
    grid: Grid | None = None,
    *,
    coupling_interval_s: float = 2.0e4,
    beam: BeamGrid = BeamGrid(),
    options: SolverOptions = SolverOptions(),
    initial_state: State | None = None,
    progress: bool = False,
) -> Result:
    """Simulate tissue formation from seeding (t = 0) to `t_end_s` seconds.

    **Arguments:**

    - `params`: a `Params` (e.g. `jt.paper_parameters()`); every float field is
      differentiable.
    - `protocol`: `Protocol.static()` (default) or `Protocol.flex(...)`.
    - `t_end_s`: end of culture, s (default 2.0e6 s ≈ 3.3 weeks, as the paper).
    - `grid`: the growth grid; default `Grid(1, 40)` (the 1-D transmural problem) for
      static culture and `Grid(50, 40)` for flex.
    - `coupling_interval_s`: the growth interval T_g (MODEL.md §5); results are saved
      every T_g, at `t_end_s`, and at exactly 3 weeks when reached. In flex culture one
      loading cycle is solved per interval.
    - `beam`: the beam's resolution (`BeamGrid`).
    - `options`: tolerances and step limits of the growth solves (`SolverOptions`).
    - `initial_state`: start from this `State` instead of MODEL.md §2's ICs.
    - `progress`: show a progress bar.

    **Returns:** a `Result`. Jit-able (close over the static arguments) and
    differentiable with `jax.grad` / `jax.vmap` over `params` and the protocol's floats.
    """
    protocol = Protocol.static() if protocol is None else protocol
    if not isinstance(params, Params):
        raise TypeError(f"params must be a jaxtissue Params, got {type(params).__name__}")
    if grid is None:
        grid = Grid(nx=1, ny=40) if protocol.regime == "static" else Grid(nx=50, ny=40)
    for name, value in (("t_end_s", t_end_s), ("coupling_interval_s", coupling_interval_s)):
        if not (isinstance(value, (int, float)) and math.isfinite(value) and value > 0):
            raise ValueError(f"{name} = {value!r} must be a positive number of seconds")
    u, length = concrete_value(protocol.post_displacement_mm), concrete_value(params.length_mm)
    if protocol.regime == "flex" and u is not None and length is not None and np.any(u >= length):
        raise ValueError(f"protocol post_displacement_mm = {np.ravel(u)[0]:g} must be below the strip length {np.ravel(length)[0]:g} mm")
    times = tuple(save_times(float(t_end_s), float(coupling_interval_s)).tolist())
    params = jtu.tree_map(lambda x: jnp.asarray(x, dtype=float), params)
    protocol = jtu.tree_map(lambda x: jnp.asarray(x, dtype=float), protocol)
    if progress and protocol.regime == "flex":
        from tqdm.auto import tqdm

        _Progress.bar = tqdm(total=len(interval_bounds(float(t_end_s), float(coupling_interval_s))) - 1, unit="interval", desc="flex culture")
    try:
        return _simulate(params, protocol, grid, beam, (times, float(coupling_interval_s)), options, initial_state, progress)
    finally:
        if _Progress.bar is not None:
            _Progress.bar.close()
            _Progress.bar = None
