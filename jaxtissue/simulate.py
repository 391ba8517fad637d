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
from .params import Params, nondimensionalise
from .solver import ROS34PW2

THREE_WEEKS_S = 1.8144e6
"""The experiments' assay time, 21 days (MODEL.md §6)."""


class Protocol(eqx.Module):
    """A culture protocol. `Protocol.static()`: no motion (MODEL.md §1)."""

    regime: str = eqx.field(static=True, default="static")

    def __check_init__(self):
        if self.regime not in ("static",):
            raise ValueError(f"regime = {self.regime!r}; allowed: 'static'")

    @classmethod
    def static(cls) -> "Protocol":
        return cls(regime="static")


class SolverOptions(eqx.Module):
    """Tolerances and limits of the growth solve (all static)."""

    rtol: float = eqx.field(static=True, default=1e-5)
    atol: float = eqx.field(static=True, default=1e-8)
    dt0_s: float = eqx.field(static=True, default=10.0)
    dtmax_s: float = eqx.field(static=True, default=2.0e5)
    max_steps: int = eqx.field(static=True, default=4096)
    fixed_steps: int | None = eqx.field(static=True, default=None)
    """If set: no step control, this many steps growing geometrically from `dt0_s`
    (the same discrete map for every parameter value: for finite-difference checks)."""

    def __check_init__(self):
        for name in ("rtol", "atol", "dt0_s", "dtmax_s"):
            value = getattr(self, name)
            if not (isinstance(value, (int, float)) and math.isfinite(value) and value > 0):
                raise ValueError(f"solver option {name} = {value!r} must be a positive number")
        for name in ("max_steps", "fixed_steps"):
            value = getattr(self, name)
            if value is not None and (not isinstance(value, int) or value < 1):
                raise ValueError(f"solver option {name} = {value!r} must be a positive integer")

    def controller(self, t0, t1):
        """diffrax step-size controller over [t0, t1]."""
        if self.fixed_steps is None:
            return diffrax.PIDController(rtol=self.rtol, atol=self.atol, dtmax=self.dtmax_s)
        span = t1 - t0
        frac = jnp.geomspace(self.dt0_s / span, 1.0, self.fixed_steps)
        return diffrax.StepTo(ts=t0 + span * jnp.concatenate([jnp.zeros(1), frac]))


class Result(eqx.Module):
    """The outputs of `simulate` (MODEL.md §3), at the save times `ts` (s).

    Series have a leading time axis; `profile_*` are mid-section profiles across the
    thickness (axis `y_cm`); `final` holds the last 2-D fields. `failed` is True when
    the solver stopped early (then the values after that time are not valid).
    """

    ts: jax.Array
    dna_ug_per_g: jax.Array
    collagen_mg_per_g: jax.Array
    E_eff_kPa: jax.Array
    EI_N_m2: jax.Array
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


def save_times(t_end_s: float, coupling_interval_s: float) -> np.ndarray:
    """0, every coupling interval up to `t_end_s`, `t_end_s`, and 3 weeks if reached."""
    n = int(math.floor(t_end_s / coupling_interval_s + 1e-9))
    ts = set(np.round(np.arange(n + 1) * coupling_interval_s, 9).tolist()) | {t_end_s}
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
    """Integrate the growth system over [t0, t1] (diffrax, `ROS34PW2`), observing at `ts`."""
    saveat = diffrax.SaveAt(
        subs=[diffrax.SubSaveAt(ts=ts, fn=_observe), diffrax.SubSaveAt(t1=True)]
    )
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
        progress_meter=diffrax.TqdmProgressMeter() if progress else diffrax.NoProgressMeter(),
        throw=False,
    )


@eqx.filter_jit
def _simulate(params: Params, protocol: Protocol, grid: Grid, ts, options, initial_state, progress):
    coeffs = nondimensionalise(params)
    model = GrowthModel(coeffs=coeffs, grid=grid)
    y0 = State.initial(coeffs, grid) if initial_state is None else initial_state
    sol = growth_solve(model, y0, ts[0], ts[-1], ts, options, (params, grid), progress)
    series, final = sol.ys
    final = jtu.tree_map(lambda x: x[-1], final)
    return Result(
        ts=ts,
        **series,
        final=final,
        x_cm=grid.x_centres(coeffs.length_cm),
        y_cm=grid.y_centres(coeffs.thickness_cm),
        num_steps=sol.stats["num_steps"],
        failed=sol.result != diffrax.RESULTS.successful,
        params=params,
    )


def simulate(
    params: Params,
    protocol: Protocol | None = None,
    t_end_s: float = 2.0e6,
    grid: Grid = Grid(),
    *,
    coupling_interval_s: float = 2.0e4,
    options: SolverOptions = SolverOptions(),
    initial_state: State | None = None,
    progress: bool = False,
) -> Result:
    """Simulate tissue formation from seeding (t = 0) to `t_end_s` seconds.

    **Arguments:**

    - `params`: a `Params` (e.g. `jt.paper_parameters()`); every float field is
      differentiable.
    - `protocol`: `Protocol.static()` (default).
    - `t_end_s`: end of culture, s (default 2.0e6 s ≈ 3.3 weeks, as the paper).
    - `grid`: the growth grid; `Grid(nx=1, ny=…)` is the 1-D transmural problem.
    - `coupling_interval_s`: the growth interval T_g (MODEL.md §5); results are saved
      every T_g, at `t_end_s`, and at exactly 3 weeks when reached.
    - `options`: tolerances and step limits (`SolverOptions`).
    - `initial_state`: start from this `State` instead of MODEL.md §2's ICs.
    - `progress`: show a progress bar.

    **Returns:** a `Result`. Jit-able (close over the static arguments) and
    differentiable with `jax.grad` / `jax.vmap` over `params`.
    """
    protocol = Protocol.static() if protocol is None else protocol
    if not isinstance(params, Params):
        raise TypeError(f"params must be a jaxtissue Params, got {type(params).__name__}")
    for name, value in (("t_end_s", t_end_s), ("coupling_interval_s", coupling_interval_s)):
        if not (isinstance(value, (int, float)) and math.isfinite(value) and value > 0):
            raise ValueError(f"{name} = {value!r} must be a positive number of seconds")
    ts = jnp.asarray(save_times(float(t_end_s), float(coupling_interval_s)))
    params = jtu.tree_map(lambda x: jnp.asarray(x, dtype=float), params)
    return _simulate(params, protocol, grid, ts, options, initial_state, progress)
