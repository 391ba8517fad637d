"""Batch sweeps over parameters and protocol fields.

A `Sweep` (from TOML, `read_sweep`) is a design of parameter sets: a full grid
(`linspace`, `logspace`, `values` per name) or a space-filling design (`design = "lhs"`
or `"sobol"`, `samples = N`, a `range` and `transform` per name). `run` evaluates it in
chunks: one jitted, `vmap`ped simulation per chunk, its batch axis sharded over every
device of `jax.devices()` (`jax.sharding`; on several hosts after
`jax.distributed.initialize()`, the same call spans them all; `jaxtissue sweep` first
splits a CPU into one device per core, `use_all_cores`). Each finished chunk is
written atomically to `DIR/chunks/`; `resume=True` skips those already there, so an
interrupted sweep resumes and ends with the same `DIR/sweep.nc`.
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
import math
import pathlib

import equinox as eqx
import jax
import numpy as np

from .. import cache, limits
from ..beam import BeamGrid
from ..cache import add_xla_flag
from ..grid import Grid
from ..growth import has_cell_transport
from ..io import InputError, atomic_write, atomic_write_text, number, params_from_table, read_arrays, read_toml, write_netcdf
from ..params import FIELDS, Params, suggest
from ..protocol import COUPLING_INTERVAL_S, PROTOCOL_FIELDS, THREE_WEEKS_S, Protocol, in_table, save_times
from ..result import OUTPUTS, SCALARS
from ..simulate import SolverOptions, method_problem, simulate
from ._problem_files import grid_axis, space_filling


@dataclasses.dataclass(frozen=True)
class Sweep:
    names: tuple  # swept parameter / protocol field names
    points: np.ndarray  # (N, k) parameter sets, in store order
    axes: dict | None  # grid: {name: values} (points are their product, C order); else None
    protocol: Protocol
    base: Params = Params()
    t_end_s: float = THREE_WEEKS_S
    outputs: str = "final"  # "final": values at t_end_s; "series": every save time
    chunk: int = 64
    grid: Grid | None = None
    beam: BeamGrid = BeamGrid()
    coupling_interval_s: float = COUPLING_INTERVAL_S
    rtol: float = 1e-5
    max_steps: int = 4096  # per growth solve; a set that needs more is marked failed
    method: str = "ros34pw2"  # the time stepper (SolverOptions.method)
    source: str = ""  # the sweep file's text (a resumed sweep must match it)

    def __post_init__(self):
        if self.grid is None:
            object.__setattr__(self, "grid", Grid.default(self.protocol.regime))

    @property
    def size(self) -> int:
        return self.points.shape[0]

    def model(self, values):
        """(Params, Protocol) of one parameter set (traced values allowed)."""
        params = {n: values[i] for i, n in enumerate(self.names) if n in FIELDS}
        protocol = self.protocol
        for i, n in enumerate(self.names):
            if n in PROTOCOL_FIELDS:
                protocol = eqx.tree_at(lambda q, n=n: getattr(q, n), protocol, values[i])
        return self.base.replace(**params), protocol

    def run_one(self, values) -> dict:
        params, protocol = self.model(values)
        r = simulate(params, protocol, self.t_end_s, self.grid, coupling_interval_s=self.coupling_interval_s,
                     beam=self.beam, options=SolverOptions(rtol=self.rtol, atol=self.rtol * 1e-3, max_steps=self.max_steps, method=self.method),
                     save="end" if self.outputs == "final" else "intervals")
        pick = (lambda v: v[-1]) if self.outputs == "final" else (lambda v: v)
        out = {k: pick(getattr(r, k)) for k in SCALARS}
        out["failed"] = r.failed
        return out

    def times(self) -> np.ndarray:
        return save_times(self.t_end_s, self.coupling_interval_s)

    def model_only(self) -> "Sweep":
        """The sweep without its points (and file text): what decides its chunks' program,
        and what names it among saved programs (`jaxtissue.cache.call`)."""
        return dataclasses.replace(self, points=None, axes=None, source="")


# ---------------------------------------------------------------------------------------
# Sweep files
# ---------------------------------------------------------------------------------------

_TOP = {"regime", "t_end_s", "design", "samples", "seed", "outputs", "chunk", "parameters", "protocol", "fixed", "model"}


def _check_value(name, value, where):
    """A swept value inside its allowed range (the protocol's own checks for its fields)."""
    if name in FIELDS:
        if not FIELDS[name].contains(value):
            raise InputError(f"{where}: {name} = {value:g} must be in {FIELDS[name].range_text()} {FIELDS[name].unit}")
        return
    try:
        Protocol.flex(**{name: value})
    except (TypeError, ValueError) as err:
        raise InputError(f"{where}: {err}") from None


def read_sweep(path) -> Sweep:
    """A `Sweep` from a TOML file; any mistake is an `InputError` naming file and key."""
    path = pathlib.Path(path)
    doc, text = read_toml(path, "sweep", _TOP)
    where = str(path)
    regime = doc.get("regime", "static")
    if regime not in ("static", "flex"):
        raise InputError(f"{where}: regime = {regime!r}; allowed: 'static', 'flex'")
    t_end = number(doc.get("t_end_s", THREE_WEEKS_S), f"{where}: t_end_s", positive=True)
    outputs = doc.get("outputs", "final")
    if outputs not in ("final", "series"):
        raise InputError(f"{where}: outputs = {outputs!r}; allowed: 'final', 'series'")
    chunk = doc.get("chunk", 64)
    if isinstance(chunk, bool) or not isinstance(chunk, int) or chunk < 1:
        raise InputError(f"{where}: chunk = {chunk!r} must be a positive integer")

    protocol_table = doc.get("protocol", {})
    for key in protocol_table:
        if key not in set(PROTOCOL_FIELDS) | {"lumping", "pins"}:
            raise InputError(f"{where}: unknown key {key!r} in [protocol]; {suggest(key, sorted(set(PROTOCOL_FIELDS) | {'lumping', 'pins'}))}")
    try:
        protocol = Protocol(regime=regime, **protocol_table)
    except (TypeError, ValueError) as err:
        raise InputError(f"{where}: [protocol] {in_table(err)}") from None

    fixed = doc.get("fixed", {})
    if not isinstance(fixed, dict):
        raise InputError(f"{where}: [fixed] must be a table of name = value")
    base = params_from_table(fixed, f"{where} [fixed]")

    specs = doc.get("parameters", {})
    if not isinstance(specs, dict) or not specs:
        raise InputError(f"{where}: [parameters] must name at least one parameter to sweep")
    valid = list(FIELDS) + (list(PROTOCOL_FIELDS) if regime == "flex" else [])
    for name in specs:
        if name not in valid:
            hint = " (protocol fields are swept only with regime = \"flex\")" if name in PROTOCOL_FIELDS else ""
            raise InputError(f"{where}: unknown parameter {name!r} in [parameters]{hint}; {suggest(name, valid)}")
    names = tuple(specs)
    design = doc.get("design", "grid")
    if design == "grid":
        axes = {n: grid_axis(n, specs[n], f"{where}: [parameters]") for n in names}
        size = math.prod(len(a) for a in axes.values())
        if size > limits.MAX_SWEEP_POINTS:
            raise InputError(f"{where}: the grid of [parameters] has {size:.3g} points; a sweep may have at most {limits.MAX_SWEEP_POINTS}")
        mesh = np.meshgrid(*axes.values(), indexing="ij")
        points = np.stack([m.ravel() for m in mesh], axis=1)
    elif design in ("lhs", "sobol"):
        samples = doc.get("samples")
        if isinstance(samples, bool) or not isinstance(samples, int) or not 1 <= samples <= limits.MAX_SWEEP_POINTS:
            raise InputError(f"{where}: samples = {samples!r} must be an integer in [1, {limits.MAX_SWEEP_POINTS}] with design = {design!r}")
        seed = doc.get("seed", 0)
        axes = None
        points = space_filling(names, specs, design, samples, seed, f"{where}: [parameters]")
    else:
        raise InputError(f"{where}: design = {design!r}; allowed: 'grid', 'lhs', 'sobol'")
    for name, column in zip(names, points.T):
        for value in np.unique(column):
            _check_value(name, value, f"{where}: [parameters]")

    model = doc.get("model", {})
    allowed = {"nx", "ny", "beam_segments", "beam_steps_per_cycle", "coupling_interval_s", "rtol", "max_steps", "method"}
    for key in model:
        if key not in allowed:
            raise InputError(f"{where}: unknown key {key!r} in [model]; {suggest(key, sorted(allowed))}")
    try:
        grid = None
        if "nx" in model or "ny" in model:
            default = Grid.default(regime)
            grid = Grid(nx=model.get("nx", default.nx), ny=model.get("ny", default.ny))
        beam = BeamGrid(n_segments=model.get("beam_segments", BeamGrid.n_segments),
                        steps_per_cycle=model.get("beam_steps_per_cycle", BeamGrid.steps_per_cycle))
    except (TypeError, ValueError) as err:
        raise InputError(f"{where}: [model] {err}") from None
    interval = number(model.get("coupling_interval_s", COUPLING_INTERVAL_S), f"{where}: [model] coupling_interval_s")
    rtol = number(model.get("rtol", 1e-5), f"{where}: [model] rtol")
    max_steps = model.get("max_steps", 4096)
    if interval <= 0 or not 0 < rtol < 1 or isinstance(max_steps, bool) or not isinstance(max_steps, int) or max_steps < 1:
        raise InputError(f"{where}: [model] needs coupling_interval_s > 0, rtol in (0, 1), max_steps a positive integer")
    method = model.get("method", "ros34pw2")
    try:
        options = SolverOptions(method=method)
    except ValueError as err:
        raise InputError(f"{where}: [model] {err}") from None
    cell_flux = has_cell_transport(base) or bool({"D_c", "chi"} & set(names))  # swept: nonzero somewhere
    if (problem := method_problem(options, regime, grid or Grid.default(regime), cell_flux)) is not None:
        raise InputError(f"{where}: [model] {problem}")
    return Sweep(names, points, axes, protocol, base, t_end, outputs, chunk, grid, beam, interval, rtol, max_steps, method, text)


# ---------------------------------------------------------------------------------------
# Execution
# ---------------------------------------------------------------------------------------


def use_all_cores() -> bool:
    """Give JAX one CPU device per core (`use_cpu_devices`), so that a sweep's batch is
    sharded over every core of a CPU-only machine."""
    import os

    return use_cpu_devices(os.cpu_count() or 1)


def use_cpu_devices(n: int) -> bool:
    """Split the CPU into `n` JAX devices (`--xla_force_host_platform_device_count`).
    Works only before JAX starts its backends and leaves an explicit device count in
    `XLA_FLAGS` alone (`cache.add_xla_flag`); accelerators are unaffected. Returns
    whether the setting was made."""
    return n >= 2 and add_xla_flag(f"--xla_force_host_platform_device_count={n}")


def vmap_over_devices(fn, n: int, in_axes=0):
    """`jax.vmap(fn, in_axes)` for a batch of n (in_axes 0 or None per argument; every
    result batched), sharded over `jax.devices()` where their count divides n (e.g. one
    per CPU core, `use_all_cores`); else the plain vmap."""
    return _split(jax.vmap(fn, in_axes=in_axes), n, in_axes)


def map_over_devices(fn, n: int):
    """`jax.lax.map(fn, xs)` for a batch of n, its rows split over `jax.devices()` as
    `vmap_over_devices` splits them: each device runs its rows one after another with
    `fn`'s own program. For runs that vmap makes dearer per row (its while loops run
    to the slowest row, its conds take both branches), such as full flex runs."""
    return _split(lambda xs: jax.lax.map(fn, xs), n, 0)


def _split(batched, n: int, in_axes):
    """`batched` sharded along its batch axis over `jax.devices()` where their count divides n."""
    devices = jax.devices()
    if len(devices) < 2 or n % len(devices):
        return batched
    b, r = jax.sharding.PartitionSpec("batch"), jax.sharding.PartitionSpec()
    in_specs = b if in_axes == 0 else tuple(r if axis is None else b for axis in in_axes)
    return jax.shard_map(batched, mesh=jax.sharding.Mesh(np.array(devices), ("batch",)), in_specs=in_specs, out_specs=b,
                         check_vma=False)


def even_batches(n: int, most: int) -> int:
    """The batch size that runs n rows in the fewest batches of at most `most` rows,
    as equal as can be and each a multiple of the device count (`vmap_over_devices`
    then splits every batch over all devices; the last batch is padded)."""
    devices = len(jax.devices())
    count = math.ceil(n / max(most, 1))
    return devices * math.ceil(n / (count * devices))


def join_processes(coordinator: str | None = None, num_processes: int | None = None, process_id: int | None = None) -> None:
    """Join a sweep shared by several processes (`jax.distributed.initialize`; CPU
    collectives over gloo): every process runs every chunk on its share of the devices,
    process 0 writes the files. Arguments left None are detected from the cluster
    (SLURM, Open MPI, ...) or `$JAX_COORDINATOR_ADDRESS`; a mistake is an `InputError`."""
    if num_processes is not None and process_id is not None and not 0 <= process_id < num_processes:
        raise InputError(f"`process_id` = {process_id} must be in [0, {num_processes - 1}]")
    try:
        jax.distributed.initialize(coordinator, num_processes, process_id)
    except (ValueError, RuntimeError) as err:
        raise InputError(f"jax.distributed: {str(err).splitlines()[0]}") from None


def is_writer() -> bool:
    """Whether this process writes a sweep's files (the only one, or process 0)."""
    return jax.process_index() == 0


_BATCHED: dict = {}  # the model of a sweep -> its compiled chunk function (repeated runs compile once)


def batched(sweep: Sweep):
    """A jitted, vmapped run of a chunk of parameter sets; the chunk's batch axis is
    sharded over `jax.devices()`. Returns (function, devices); the chunk length must be
    a multiple of the device count. Sweeps of the same model share one function."""
    model = sweep.model_only()
    key = repr((model, jax.devices()))
    if key not in _BATCHED:
        _BATCHED[key] = _batched(model)
    return _BATCHED[key]


def _chunk(model: Sweep, values):
    """`model.run_one` of each row of `values`."""
    return jax.vmap(model.run_one)(values)


def _batched(model: Sweep):
    """`batched` for a sweep's model (`Sweep.model_only`), which also names its program
    where the command line saves its programs: a later sweep of the same model loads it."""
    devices = jax.devices()
    mesh = jax.sharding.Mesh(np.array(devices), ("batch",))
    sharding = jax.sharding.NamedSharding(mesh, jax.sharding.PartitionSpec("batch"))
    fn = eqx.filter_jit(_chunk)  # the batch axis split as the values are (`sharding`)

    def run(values: np.ndarray) -> dict:
        x = jax.make_array_from_callback(values.shape, sharding, lambda index: values[index])
        if jax.process_count() > 1:  # one program over several processes: compiled by each
            from jax.experimental import multihost_utils

            out = multihost_utils.process_allgather(fn(model, x), tiled=True)
        else:
            out = cache.call(fn, model, x)
        return jax.tree_util.tree_map(np.asarray, out)

    return run, len(devices)


def run_chunk(sweep: Sweep, start: int) -> dict:
    """The outputs of the chunk starting at point `start`: `batched`'s function on its
    points, the batch padded with copies of the last point (one compiled batch shape)."""
    fn, n_dev = batched(sweep)
    values = sweep.points[start : start + sweep.chunk]
    batch = -(-sweep.chunk // n_dev) * n_dev
    result = fn(np.concatenate([values, np.repeat(values[-1:], batch - len(values), axis=0)]))
    return {k: v[: len(values)] for k, v in result.items()}


def fingerprint(sweep: Sweep) -> str:
    """A short hash of the sweep file and its points (what a resumed sweep must match)."""
    return hashlib.sha256((sweep.source + repr(sweep.points.tolist())).encode()).hexdigest()[:16]


def run(sweep: Sweep, out, resume: bool = False, progress: bool = False):
    """Run every chunk not already in `out/chunks/` and assemble `out/sweep.nc`.
    Returns the `xarray.Dataset`."""
    from tqdm.auto import tqdm

    _, n_dev = batched(sweep)
    batch = -(-sweep.chunk // n_dev) * n_dev  # the chunk padded to a multiple of the device count (`run_chunk`)
    need = limits.estimate(sweep.grid.nx * sweep.grid.ny, sweep.t_end_s, sweep.coupling_interval_s,
                           save_series=sweep.outputs != "final", batch=batch, regime=sweep.protocol.regime)
    limits.check_memory(need, f"a chunk of {batch} runs on the {sweep.grid.nx} x {sweep.grid.ny} grid",
                        "a smaller `chunk` in the sweep file, `outputs = \"final\"` or a coarser grid")
    out = pathlib.Path(out)
    chunks = out / "chunks"
    manifest = chunks / "sweep.json"
    stamp = {"fingerprint": fingerprint(sweep), "size": sweep.size, "chunk": sweep.chunk}
    writer = is_writer()
    if writer:
        chunks.mkdir(parents=True, exist_ok=True)
        if manifest.exists():
            try:
                held = json.loads(manifest.read_text())
            except (ValueError, UnicodeDecodeError) as err:
                raise InputError(f"`resume` {out}: {manifest} is damaged ({type(err).__name__}: {err}); "
                                 f"remove {chunks} to start the sweep again") from None
            if held != stamp:
                raise InputError(f"`resume` {out}: the folder holds a different sweep (its file or chunk size changed)")
        else:
            atomic_write_text(manifest, json.dumps(stamp))
    starts = range(0, sweep.size, sweep.chunk)
    done = np.array([resume and (chunks / f"{s:08d}.npz").exists() for s in starts])
    if jax.process_count() > 1:  # every process runs the same chunks: process 0's view of the folder
        from jax.experimental import multihost_utils

        done = np.asarray(multihost_utils.broadcast_one_to_all(done))
    todo = [s for s, d in zip(starts, done) if not d]
    # finished chunks read first: a damaged one is found before any chunk is computed
    by_start = {s: read_arrays(chunks / f"{s:08d}.npz", ("failed",), "compute that chunk again", min(sweep.chunk, sweep.size - s))
                for s, d in zip(starts, done) if d}
    with tqdm(total=len(starts), initial=len(starts) - len(todo), desc="sweep", unit="chunk", disable=not (progress and writer)) as bar:
        for s in todo:
            result = run_chunk(sweep, s)
            if writer:
                atomic_write(chunks / f"{s:08d}.npz", lambda f, result=result: np.savez(f, **result))
            by_start[s] = result
            bar.update(1)
    parts = [by_start[s] for s in starts]
    merged = {k: np.concatenate([p[k] for p in parts]) for k in parts[0]}
    ds = to_dataset(sweep, merged)
    if writer:
        write_netcdf(ds, out / "sweep.nc")
    return ds


def to_dataset(sweep: Sweep, values: dict):
    """The sweep's outputs as an `xarray.Dataset`: one dimension per swept name (grid)
    or a `sample` dimension (space-filling); failed sets are NaN and flagged."""
    import xarray as xr

    failed = values["failed"].astype(bool)
    data = {}
    for k in SCALARS:
        v = np.where(failed.reshape((-1,) + (1,) * (values[k].ndim - 1)), np.nan, values[k])
        data[k] = (v, OUTPUTS[k].unit)
    extra = ("time_s",) if sweep.outputs == "series" else ()
    if sweep.axes is not None:
        dims = tuple(sweep.names)
        shape = tuple(len(a) for a in sweep.axes.values())
        coords = {n: (n, a) for n, a in sweep.axes.items()}
    else:
        dims, shape = ("sample",), (sweep.size,)
        coords = {"sample": np.arange(sweep.size)} | {n: ("sample", sweep.points[:, i]) for i, n in enumerate(sweep.names)}
    if extra:
        coords["time_s"] = sweep.times()
    variables = {k: (dims + extra, v.reshape(shape + v.shape[1:])) for k, (v, _) in data.items()}
    variables["failed"] = (dims, failed.reshape(shape))
    ds = xr.Dataset(variables, coords=coords)
    for k in SCALARS:
        ds[k].attrs.update(units=OUTPUTS[k].unit, long_name=OUTPUTS[k].description)
    for n in sweep.names:
        ds[n].attrs["units"] = FIELDS[n].unit if n in FIELDS else PROTOCOL_FIELDS[n]
    ds.attrs.update({f"param_{k}": v for k, v in sweep.base.as_dict().items()})
    ds.attrs.update(regime=sweep.protocol.regime, t_end_s=sweep.t_end_s, outputs=sweep.outputs, failures=int(failed.sum()))
    return ds
