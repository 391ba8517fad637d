"""The staggered time loop of a culture (docs/model.md §2, §5): growth solves, and in
flexure one loading cycle per coupling interval, into a `Result`."""

from __future__ import annotations

import dataclasses
import math

import equinox as eqx
import jax
import jax.numpy as jnp
import jax.tree_util as jtu
import numpy as np

from . import cache, limits
from .beam import BeamGrid, loading_cycle
from .coupling import beam_from_ecm, lumped_transport, with_rule_constant
from .grid import Grid
from .growth import GrowthModel, has_cell_transport
from .numerics import Rescaled, Stacked, line_sweeps, replayed_scan, stack
from .params import FIELDS, Params, concrete_value, nondimensionalise
from .protocol import COUPLING_INTERVAL_S, PROTOCOL_FIELDS, T_END_S, THREE_WEEKS_S, Protocol, interval_bounds, save_times
from .result import Result, coordinates_cm, observe, out_of_bounds, status_from_code
from .state import State

METHODS = ("ros34pw2", "rodas4p2")
"""`SolverOptions.method`'s values (`numerics.SOLVERS`' keys; named here, where no
diffrax is imported)."""


class SolverOptions(eqx.Module):
    """Tolerances and limits of the growth solve (all static)."""

    rtol: float = eqx.field(static=True, default=1e-5)
    atol: float = eqx.field(static=True, default=1e-8)
    dt0_s: float = eqx.field(static=True, default=10.0)
    dtmax_s: float = eqx.field(static=True, default=2.0e5)
    max_steps: int = eqx.field(static=True, default=4096)
    checkpoints: int | None = eqx.field(static=True, default=None)
    """Checkpoints of the reverse pass through one growth solve (memory ∝ this). None:
    16 for a static run's one solve, 8 for each flex coupling interval (~7 steps each
    in the default flex run, 683 in 101: each step is then stored once)."""
    fixed_steps: int | None = eqx.field(static=True, default=None)
    """If set: no step control, this many steps growing geometrically from `dt0_s`
    (the same discrete map for every parameter value: for finite-difference checks)."""
    o2_sweeps: int | None = eqx.field(static=True, default=None)
    """2-D grids: sweeps of line relaxation in each step's O2 solve, 0 for multigrid
    (3 V-cycles), None to choose from the grid and the strip's thickness/length
    (`numerics.line_sweeps`: 6 on the default 50 × 40 grid, 0 for cells shorter than
    h/3). Fewer sweeps approximate the step's Jacobian more coarsely (see
    `growth_jacobian`): cheaper steps, possibly more of them."""
    nest_intervals: bool = eqx.field(static=True, default=False)
    """Flex runs, reverse mode: the reverse pass keeps ~√n of the n coupling intervals'
    states instead of all n and each interval's lumped transport (a third of a state),
    for one more pass of the growth solves (no loading cycle; `numerics.replayed_scan`):
    for long runs or large grids where memory binds."""
    store_float32: bool = eqx.field(static=True, default=False)
    """With `nest_intervals`: those kept states and transports are stored in float32
    (half their memory). The solves stay float64; the reverse pass replays from values
    rounded to 6e-8 relative, so the gradient differs from the float64 one at about
    that level (`tests/test_coupling.py`)."""
    method: str = eqx.field(static=True, default="ros34pw2")
    """The time stepper (docs/numerics.md, "Time"): "ros34pw2", the Rosenbrock-W method
    of order 3 (4 stages; of full order for any J̃: every run), or "rodas4p2", the
    Rosenbrock method of order 4 (6 stages, with the exact Jacobian: static runs on 1-D
    grids without cell flux only; fewer steps at tight tolerances)."""
    autodiff: str = eqx.field(static=True, default="reverse")
    """"reverse" (`jax.grad`; checkpointed) or "forward" (`jax.jvp`/`jacfwd`, e.g. for
    Jacobians of a few parameters in least-squares fits)."""
    static_series: str = eqx.field(static=True, default="dense")
    """How a static run saves its series: "dense", one growth solve saved at the save
    times by its dense output (fewest steps), or "intervals", one solve per coupling
    interval, each ending at a save time and starting with the step the last one ended
    with (at least one step per interval): diffrax checks "dense"'s save times with a
    host callback, so only "intervals" can be kept as a saved or cached program (the
    command line's choice; docs/numerics.md, "Compilation")."""

    def __check_init__(self):
        for name in ("rtol", "atol", "dt0_s", "dtmax_s"):
            value = getattr(self, name)
            if not (isinstance(value, (int, float)) and math.isfinite(value) and value > 0):
                raise ValueError(f"solver option {name} = {value!r} must be a positive number")
        if self.rtol >= 1:  # a relative error of 100 % or more controls nothing
            raise ValueError(f"solver option rtol = {self.rtol!r} must be below 1")
        for name in ("max_steps", "fixed_steps", "checkpoints"):
            value = getattr(self, name)
            if value is not None and (not isinstance(value, int) or not 1 <= value <= limits.MAX_STEPS):
                raise ValueError(f"solver option {name} = {value!r} must be an integer in [1, {limits.MAX_STEPS}]")
        if self.o2_sweeps is not None and (not isinstance(self.o2_sweeps, int) or self.o2_sweeps < 0):
            raise ValueError(f"solver option o2_sweeps = {self.o2_sweeps!r} must be None or an integer >= 0")
        for name in ("nest_intervals", "store_float32"):
            if not isinstance(getattr(self, name), bool):
                raise ValueError(f"solver option {name} = {getattr(self, name)!r} must be True or False")
        if self.store_float32 and not self.nest_intervals:
            raise ValueError("solver option store_float32 = True needs nest_intervals = True")
        if self.method not in METHODS:
            raise ValueError(f"solver option method = {self.method!r}; allowed: " + ", ".join(map(repr, METHODS)))
        if self.autodiff not in ("reverse", "forward"):
            raise ValueError(f"solver option autodiff = {self.autodiff!r}; allowed: 'reverse', 'forward'")
        if self.static_series not in ("dense", "intervals"):
            raise ValueError(f"solver option static_series = {self.static_series!r}; allowed: 'dense', 'intervals'")

    def adjoint(self, checkpoints: int):
        """diffrax adjoint; `checkpoints` unless set in these options."""
        import diffrax  # here and below, where a run is traced: a saved program runs without it

        if self.autodiff == "forward":
            return diffrax.ForwardMode()
        return diffrax.RecursiveCheckpointAdjoint(checkpoints=self.checkpoints or checkpoints)

    def controller(self, span_s, dt0_s=None):
        """diffrax step-size controller over an interval of `span_s` seconds, in the unit
        time s = (t − t0) / span_s that `growth_solve` integrates in; its first step
        `dt0_s` (may be traced; default `self.dt0_s`)."""
        import diffrax

        from .numerics import ReproducibleSteps

        if self.fixed_steps is None:
            pid = diffrax.PIDController(rtol=self.rtol, atol=self.atol, dtmax=self.dtmax_s / span_s)
            return ReproducibleSteps(pid, dt0=(self.dt0_s if dt0_s is None else dt0_s) / span_s)
        frac = jnp.geomspace(self.dt0_s / span_s, 1.0, self.fixed_steps)
        return diffrax.StepTo(ts=jnp.concatenate([jnp.zeros(1), frac]))


def method_problem(options: SolverOptions, regime: str, grid: Grid, cell_flux: bool) -> str | None:
    """Why `options.method` cannot solve this run, or None: "rodas4p2" needs the exact
    Jacobian (`GrowthModel.exact_jacobian`), which only a static run on a 1-D grid
    without cell flux (`cell_flux`: `has_cell_transport` of its parameters) has."""
    if options.method != "rodas4p2" or (regime == "static" and grid.nx == 1 and not cell_flux):
        return None
    return (f"solver option method = 'rodas4p2' needs a static run on a 1-D grid without cell flux (nx = 1, D_c = chi = 0), "
            f"where its Jacobian is exact; this is a {regime} run on {grid.nx} x {grid.ny}{' with cell flux' if cell_flux else ''}: "
            "use 'ros34pw2'")


def _growth_code(sol):
    """Integer status code (`result.STATUS_ORDER`) of a growth solve."""
    import diffrax

    return jnp.where(sol.result == diffrax.RESULTS.successful, 0, jnp.where(sol.result == diffrax.RESULTS.max_steps_reached, 1, 4))


def growth_solve(model: GrowthModel, y0: State, t0, t1, ts, options: SolverOptions, args, progress=False, checkpoints=16,
                 dt0_s=None):
    """Integrate the growth system over [t0, t1] (diffrax, `options.method`); `sol.ys` is the
    state at `ts` (`ts=None`: at t1 only, no dense output). Observables are taken from
    the saved states afterwards (`result.observe`), outside the solver's loop and its
    checkpointed reverse pass (`checkpoints`, unless `options` sets them). `dt0_s`: the
    first step (default `options.dt0_s`), e.g. `next_step_s` of the solve before.

    The solve runs in the unit time s = (t − t0)/(t1 − t0) (`numerics.Rescaled`; `sol.ts`
    is in s): diffrax's time bounds are then constants, also where t0 and t1 are traced.
    o, c and m are integrated stacked in one array (`numerics.Stacked`); `sol.ys` is a
    `State` again."""
    import diffrax

    from .numerics import SOLVERS

    span = t1 - t0
    saveat = diffrax.SaveAt(t1=ts is None, ts=None if ts is None else (ts - t0) / span, controller_state=True)
    field = Stacked(model, jtu.tree_structure(y0))
    sol = diffrax.diffeqsolve(
        diffrax.ODETerm(Rescaled(field, span)),
        SOLVERS[options.method](),
        t0=0.0,
        t1=1.0,
        dt0=None,  # the controller's (`ReproducibleSteps.dt0`)
        y0=stack(y0),
        args=args,
        saveat=saveat,
        stepsize_controller=options.controller(span, dt0_s),
        max_steps=options.max_steps,
        adjoint=options.adjoint(checkpoints),
        progress_meter=diffrax.TqdmProgressMeter() if progress else diffrax.NoProgressMeter(),
        throw=False,
    )
    return eqx.tree_at(lambda sol: sol.ys, sol, jax.vmap(field.unstack)(sol.ys))


def next_step_s(sol, t0, t1, options: SolverOptions):
    """The step (s) that `growth_solve`'s solve `sol` over [t0, t1] would have taken
    next (`ReproducibleSteps.next_step`), no longer than `options.dtmax_s`;
    `options.dt0_s` with `fixed_steps` or where the solve failed with no finite step."""
    if options.fixed_steps is not None:
        return jnp.asarray(options.dt0_s)
    from .numerics import ReproducibleSteps

    dt = jax.lax.stop_gradient(ReproducibleSteps.next_step(sol.controller_state) * (t1 - t0))
    return jnp.where(jnp.isfinite(dt) & (dt > 0), jnp.minimum(dt, options.dtmax_s), options.dt0_s)


class _Progress:
    """A tqdm bar over growth intervals, fed from inside jitted code."""

    bar = None

    @classmethod
    def tick(cls, _):
        if cls.bar is not None:
            cls.bar.update(1)


def flex_cycle(y: State, params: Params, protocol: Protocol, grid: Grid, beam_grid: BeamGrid, keep_fields=False):
    """One loading cycle from rest with the ECM of `y` (docs/model.md §5, step 1)."""
    beam = beam_from_ecm(y, params, grid, beam_grid, protocol.pins, "neo-hookean")
    u_max = protocol.post_displacement_mm * 1e-3
    return beam, loading_cycle(beam, protocol.period_s, u_max, protocol.hold_fraction, keep_fields)


@eqx.filter_jit
def _simulate(params: Params, protocol: Protocol, grid: Grid, beam_grid: BeamGrid, schedule: tuple, options, initial_state, progress,
              cell_transport: bool):
    times, coupling_interval_s, end_only = schedule
    out_times = times[-1:] if end_only else times
    coeffs = nondimensionalise(params)
    args = (params, grid)
    y0 = State.initial(coeffs, grid) if initial_state is None else initial_state
    ts = jnp.asarray(out_times)
    sweeps = options.o2_sweeps or 0
    if protocol.regime == "static":
        model = GrowthModel(coeffs=coeffs, grid=grid, cell_transport=cell_transport, o2_sweeps=sweeps,
                            exact_jacobian=options.method == "rodas4p2")
        one_solve = not _by_intervals(protocol.regime, options, end_only)
        if one_solve:
            sol = growth_solve(model, y0, times[0], times[-1], None if end_only else ts, options, args, progress)
            states = sol.ys
            num_steps, code = sol.stats["num_steps"], _growth_code(sol)
        else:  # one solve per interval, ending at its save time (`SolverOptions.static_series`)
            states, num_steps, code, t_fail = _static_by_intervals(model, y0, times, options, args, progress)
        series = jax.vmap(lambda y: observe(y, params, grid))(states)
        series["post_force_max_N"] = jnp.zeros(len(out_times))
        series["surface_strain_max"] = jnp.zeros(len(out_times))
        final = jtu.tree_map(lambda x: x[-1], states)
        if one_solve:
            reached = jnp.isfinite(series["collagen_mg_per_g"])
            if end_only:  # a failed solve still leaves its last state at "t1": not valid there
                reached &= code == 0
            t_fail = jnp.max(jnp.where(reached, ts, times[0]))
    else:
        n_intervals = len(times) - 1

        def loading(theta, y, k):
            """The loading cycle at save time k: its lumped transport and outputs."""
            p, q = theta
            _, cycle = flex_cycle(y, p, q.at(jnp.asarray(times)[k]), grid, beam_grid)
            transport = lumped_transport(cycle, p, grid, beam_grid, q.lumping, q.pins)
            return transport, dict(post_force=cycle.post_force_max_N, strain=jnp.max(cycle.surface_strain), failed=cycle.failed)

        def solve(theta, y, k, transport):
            """Interval k's growth solve with the transport frozen."""
            p = theta[0]
            model = GrowthModel(coeffs=nondimensionalise(p), grid=grid, transport=transport, cell_transport=cell_transport,
                                o2_sweeps=sweeps)
            y1, steps, code, _ = _interval_solve(model, y, None, times, k, options, (p, grid), progress)
            return y1, dict(series=observe(y1, p, grid), steps=steps, code=code)

        def end(theta, y, k, transport):  # its series entry is dropped below (the run ends at the last save time)
            return y, dict(series=observe(y, theta[0], grid), steps=jnp.zeros((), jnp.int32), code=jnp.zeros((), jnp.int32))

        def growth(theta, y, k, transport):
            """Interval k's growth solve; none after the last save time, whose loading
            cycle only reports (one scan step more: the cycle is compiled once)."""
            return jax.lax.cond(k < n_intervals, solve, end, theta, y, k, transport)

        theta = (params, protocol)
        if options.nest_intervals and options.autodiff == "reverse":
            # the reverse pass keeps ~√n states and every interval's lumped transport, and
            # replays a chunk's states with the growth solves alone (no loading cycle)
            store = jnp.float32 if options.store_float32 else None
            final, (cycles, out) = replayed_scan(loading, growth, theta, y0, n_intervals + 1, store_dtype=store)
        else:
            # each interval is rematerialised in the backward pass: memory holds one
            # state per interval plus one interval's working set (beam.py nests further)
            @jax.checkpoint
            def interval(y, k):
                transport, cycle = loading(theta, y, k)
                y1, out = growth(theta, y, k, transport)
                return y1, (cycle, out)

            def skipped(y, k):  # after a failure: the run's status is already decided
                shapes = jax.eval_shape(interval, y, k)[1]
                return y, jtu.tree_map(lambda s: jnp.full(s.shape, True if s.dtype == bool else (0 if jnp.issubdtype(s.dtype, jnp.integer) else jnp.nan), s.dtype), shapes)

            def step(carry, k):
                y, dead = carry
                y1, (cycle, out) = jax.lax.cond(dead, skipped, interval, y, k)
                return (y1, dead | cycle["failed"] | (out["code"] != 0)), (cycle, out)

            # a run stops at its first failure (a loading cycle or growth solve)
            (final, _), (cycles, out) = jax.lax.scan(step, (y0, jnp.asarray(False)), jnp.arange(n_intervals + 1))
        start = observe(y0, params, grid)
        series = {k: jnp.concatenate([start[k][None], v[:-1]]) for k, v in out["series"].items()}
        series["post_force_max_N"] = cycles["post_force"]
        series["surface_strain_max"] = cycles["strain"]
        codes = jnp.where(cycles["failed"], 2, out["code"])
        first = jnp.argmax(codes > 0)
        code, t_fail = codes[first], jnp.asarray(times)[first]
        num_steps = jnp.sum(out["steps"])
        if end_only:
            series = {k: v[-1:] for k, v in series.items()}
    # concentrations out of bounds (where the solves themselves succeeded)
    bad = out_of_bounds(series, params)
    first_bad = jnp.argmax(bad)
    t_bad = jnp.where(first_bad > 0, ts[jnp.maximum(first_bad - 1, 0)], times[0])  # the last good save time
    code, t_fail = jnp.where((code == 0) & jnp.any(bad), 3, code), jnp.where((code == 0) & jnp.any(bad), t_bad, t_fail)
    t_reached = jnp.where(code == 0, ts[-1], t_fail)
    x_cm, y_cm = coordinates_cm(params, grid)
    return Result(
        ts=tuple(out_times),
        **series,
        final=final,
        x_cm=x_cm,
        y_cm=y_cm,
        num_steps=num_steps,
        failed=code != 0,
        status=status_from_code(code),
        t_reached_s=t_reached,
        params=params,
    )


def _by_intervals(regime: str, options: SolverOptions, end_only: bool) -> bool:
    """Whether a run is solved one growth interval at a time (its progress counted in
    intervals): a flex run, or a static series with `static_series="intervals"`."""
    return regime == "flex" or (options.static_series == "intervals" and not end_only)


def _bounds(times: tuple, k):
    """(t0, t1) of interval k between the save times, from constants made where they are
    used."""
    return jnp.asarray(times[:-1])[k], jnp.asarray(times[1:])[k]


def _interval_solve(model: GrowthModel, y: State, dt0_s, times: tuple, k, options: SolverOptions, args, progress):
    """Interval k's growth solve, from y over [times[k], times[k+1]] with the first step
    `dt0_s` (None: `options.dt0_s`), its end state only, and the interval bar's tick:
    the end state, the steps, the status code and the step it would have taken next."""
    t0, t1 = _bounds(times, k)
    sol = growth_solve(model, y, t0, t1, None, options, args, checkpoints=8, dt0_s=dt0_s)
    if progress:
        jax.debug.callback(_Progress.tick, t1)
    y1 = jtu.tree_map(lambda x: x[-1], sol.ys)
    return y1, sol.stats["num_steps"].astype(jnp.int32), _growth_code(sol).astype(jnp.int32), next_step_s(sol, t0, t1, options)


def _static_by_intervals(model: GrowthModel, y0: State, times: tuple, options: SolverOptions, args, progress=False):
    """A static run as one growth solve per interval [times[k], times[k+1]], each from
    the last one's end state and with the step it would have taken next (`next_step_s`):
    the states at every save time, the steps, the status code of the first failed solve
    (0 if none) and the save time it started from."""

    def interval(carry, k):
        y1, steps, code, next_step = _interval_solve(model, *carry, times, k, options, args, progress)
        return (y1, next_step), (y1, steps, code)  # no jump at a save time: the step goes on

    first_step = jnp.asarray(options.dt0_s, dtype=float)
    _, (ends, steps, codes) = jax.lax.scan(jax.checkpoint(interval), (y0, first_step), jnp.arange(len(times) - 1))
    states = jtu.tree_map(lambda a, b: jnp.concatenate([a[None], b]), y0, ends)
    first = jnp.argmax(codes > 0)
    return states, jnp.sum(steps), codes[first], jnp.asarray(times)[first]


def default_o2_sweeps(grid: Grid, params: Params) -> int:
    """`SolverOptions.o2_sweeps` chosen from the grid and the strip's h/Δx (the largest
    of a batch; the paper's 1 mm × 25 mm strip where they are traced)."""
    h, length = concrete_value(params.thickness_mm), concrete_value(params.length_mm)
    h = 1.0 if h is None else float(np.max(h))
    length = 25.0 if length is None else float(np.min(length))
    return line_sweeps(grid.nx, h * grid.nx / length)


def _float_array(x):
    """x as a float64 array: JAX's for a JAX array or tracer, NumPy's for a concrete
    number (converted on the host: no JAX operation, which would compile a small program
    of its own, before a run that may be loaded as a saved program)."""
    if isinstance(x, (jax.Array, jax.core.Tracer)):
        return jnp.asarray(x, dtype=float)
    return np.asarray(x, dtype=float)


def _seconds(name: str, value) -> float:
    """A run's time argument as a float: a concrete positive number (a Python or NumPy
    number, or a 0-d array); it fixes the save times and so the program."""
    if isinstance(value, jax.core.Tracer):
        raise TypeError(f"{name} must be a concrete number of seconds, not a traced value: it fixes the save times "
                        "(close over it, or mark it static, in jit)")
    try:
        seconds = math.nan if isinstance(value, (bool, str)) or np.ndim(value) != 0 else float(value)
    except (TypeError, ValueError):
        seconds = math.nan
    if not (math.isfinite(seconds) and seconds > 0):
        raise ValueError(f"{name} = {value!r} must be a positive number of seconds")
    return seconds


def simulate(
    params: Params,
    protocol: Protocol | None = None,
    t_end_s: float = T_END_S,
    grid: Grid | None = None,
    *,
    coupling_interval_s: float = COUPLING_INTERVAL_S,
    beam: BeamGrid = BeamGrid(),
    options: SolverOptions = SolverOptions(),
    initial_state: State | None = None,
    t_start_s: float = 0.0,
    save: str = "intervals",
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
    - `coupling_interval_s`: the growth interval T_g (docs/model.md §5); results are saved
      every T_g, at `t_end_s`, and at exactly 3 weeks when reached, where the interval
      holding it is split. In flex culture one loading cycle is solved per interval.
    - `beam`: the beam's resolution (`BeamGrid`).
    - `options`: tolerances and step limits of the growth solves (`SolverOptions`).
    - `initial_state`: start from this `State` instead of docs/model.md §2's ICs.
    - `t_start_s`: the time of `initial_state` (an interval bound: 0, a multiple of
      the coupling interval or 3 weeks), to continue a run from a saved state.
    - `save`: `"intervals"` (default) saves the series at every save time above;
      `"end"` only at `t_end_s` (what a sweep of final values needs: a static run then
      skips the interpolation and observables at the ~90 intermediate times).
    - `progress`: show a progress bar.

    **Returns:** a `Result`. Jit-able (close over the static arguments) and
    differentiable with `jax.grad` / `jax.vmap` over `params` and the protocol's floats.

    The paper's lumping rule takes the paper's C = 70 unless `params.lumping_C` differs
    from the dispersive default (`coupling.with_rule_constant`). Concrete values outside
    the range the model and data support give an `ExtrapolationWarning`; a run of more
    than `limits.MAX_INTERVALS` intervals, or one whose memory exceeds the machine's, is
    a `limits.ResourceError` (docs/model.md §10).
    """
    protocol = Protocol.static() if protocol is None else protocol
    grid = Grid.default(getattr(protocol, "regime", "static")) if grid is None else grid
    for name, value, kind, example in (("params", params, Params, "paper_parameters()"), ("protocol", protocol, Protocol, "Protocol.flex()"),
                                       ("grid", grid, Grid, "Grid(nx=1, ny=40)"), ("beam", beam, BeamGrid, "BeamGrid()"),
                                       ("options", options, SolverOptions, "SolverOptions(rtol=1e-6)")):
        if not isinstance(value, kind):
            raise TypeError(f"{name} must be a jaxtissue {kind.__name__} (e.g. {example}), got {type(value).__name__}")
    stages = (protocol.stages,) if protocol.stage_length_s is not None else ()
    shapes = [(f"params.{n}", getattr(params, n), ()) for n in FIELDS] + \
        [(f"protocol.{n}", getattr(protocol, n), () if n == "hold_fraction" else stages) for n in PROTOCOL_FIELDS]
    for name, value, shape in shapes:  # a batch of parameter sets or protocols is vmapped, not passed whole
        if np.shape(value) != shape:
            raise ValueError(f"{name} has shape {np.shape(value)}; simulate runs one parameter set and protocol (map a batch "
                             "with jax.vmap; jaxtissue.sweep.map_over_devices spreads one over devices; stages: Protocol.schedule)")
    if initial_state is not None:
        if not isinstance(initial_state, State):
            raise TypeError(f"initial_state must be a jaxtissue State (e.g. a Result's final), got {type(initial_state).__name__}")
        for name in ("o", "c", "m"):
            if jnp.shape(getattr(initial_state, name)) != grid.shape:
                raise ValueError(f"initial_state.{name} has shape {jnp.shape(getattr(initial_state, name))}; "
                                 f"the {grid.nx} x {grid.ny} grid needs {grid.shape}")
    t_end_s, coupling_interval_s = _seconds("t_end_s", t_end_s), _seconds("coupling_interval_s", coupling_interval_s)
    u, length = concrete_value(protocol.post_displacement_mm), concrete_value(params.length_mm)
    if protocol.regime == "flex" and u is not None and length is not None and np.any(u >= length):
        raise ValueError(f"protocol post_displacement_mm = {np.ravel(u)[0]:g} must be below the strip length {np.ravel(length)[0]:g} mm")
    if not (isinstance(t_start_s, (int, float)) and 0 <= t_start_s < t_end_s):
        raise ValueError(f"t_start_s = {t_start_s!r} must be in [0, t_end_s)")
    if t_start_s and initial_state is None:
        raise ValueError("t_start_s > 0 needs the initial_state at that time")
    if t_start_s and np.min(np.abs(interval_bounds(t_end_s, coupling_interval_s) - t_start_s)) > 1e-9 * coupling_interval_s:
        raise ValueError(f"t_start_s = {t_start_s:g} must be a multiple of coupling_interval_s = {coupling_interval_s:g} "
                         f"or 3 weeks ({THREE_WEEKS_S:g} s)")
    if save not in ("intervals", "end"):
        raise ValueError(f"save = {save!r}; allowed: 'intervals', 'end'")
    need = limits.estimate(grid.nx * grid.ny, t_end_s - t_start_s, coupling_interval_s, save_series=save == "intervals",
                           regime=protocol.regime)
    limits.check_memory(need, f"a {grid.nx} x {grid.ny} {protocol.regime} run of {need.intervals} intervals",
                        "a coarser `grid`" + (", or `save` end (no series)" if save == "intervals" and protocol.regime == "static" else ""))
    params, _ = with_rule_constant(params, protocol.lumping)
    limits.warn_extrapolation(params, protocol, t_end_s)
    times = tuple(save_times(float(t_end_s), float(coupling_interval_s), float(t_start_s)).tolist())
    cell_transport = has_cell_transport(params)  # known before the floats become traced
    if (problem := method_problem(options, protocol.regime, grid, cell_transport)) is not None:
        raise ValueError(problem)
    if options.o2_sweeps is None:
        options = dataclasses.replace(options, o2_sweeps=default_o2_sweeps(grid, params))
    params, protocol = jtu.tree_map(_float_array, (params, protocol))
    if progress and _by_intervals(protocol.regime, options, save == "end"):
        from tqdm.auto import tqdm

        _Progress.bar = tqdm(total=len(times) - 1, unit="interval", desc=f"{protocol.regime} culture")  # the save times are the interval bounds
    try:
        return cache.call(_simulate, params, protocol, grid, beam, (times, float(coupling_interval_s), save == "end"), options, initial_state, progress, cell_transport)
    finally:
        if _Progress.bar is not None:
            _Progress.bar.close()
            _Progress.bar = None
