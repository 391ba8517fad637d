"""The `jaxtissue` command.

    jaxtissue params                         the parameter table (units, ranges, sources)
    jaxtissue simulate --regime static|flex … one culture, to a folder of files and figures
    jaxtissue cycle …                        one loading cycle of the poroelastic beam
    jaxtissue reproduce --out DIR            the paper's study: six cases, figures, report
    jaxtissue calibrate PROBLEM --out DIR    fit parameters to measurements (TOML or PEtab v2; --posterior: and sample)
    jaxtissue lint PROBLEM.yaml              check a PEtab v2 problem (the petab linter with jaxtissue's model)
    jaxtissue predict --posterior DIR --out DIR  posterior predictive bands of a protocol
    jaxtissue sweep SWEEP.toml --out DIR     a batch of simulations
    jaxtissue sensitivity --out DIR          d ln(output)/d ln(parameter)
    jaxtissue optimize PROBLEM.toml --out DIR    the best conditioning protocol

A mistake in the input gives one line on stderr and exit code 2; a failed solve gives
one line and exit code 1. Output folders appear complete or not at all.
"""

from __future__ import annotations

import argparse
import contextvars
import dataclasses
import math
import os
import re
import sys
import threading
import warnings

import numpy as np

from .cache import collect_less, enable_compilation_cache, saved_executables, use_fast_compilation
from .grid import DEFAULT_SHAPES
from .io import InputError, RunError, ending
from .limits import MAX_STEPS
from .protocol import COUPLING_INTERVAL_S, T_END_S, THREE_WEEKS_S
from .simulate import METHODS

LONG_RUN_S = 10.0
"""`simulate` shows its progress bar on a terminal for runs expected to take longer
than this (`limits.expected_seconds`), after compilation."""

FLAGS = {
    "period_s": "--period",
    "post_displacement_mm": "--post-displacement",
    "hold_fraction": "--hold-fraction",
    "max_steps": "--max-steps",
    "rtol": "--rtol",
    "method": "--method",
    "grid": "--grid",
    "steps_per_cycle": "--steps",
    "t_end_s": "--t-end",
    "out": "--out",
    "export_petab": "--export-petab",
    "overwrite": "--overwrite",
    "resume": "--resume",
    "posterior": "--posterior",
    "draws": "--draws",
    "hold_out": "--hold-out",
    "save": "--save",
    "nest_intervals": "--nest-intervals",
    "dask": "--dask",
    "num_processes": "--num-processes",
    "process_id": "--process-id",
}
"""The library's argument names and the flags that set them: messages from the library
name arguments in backticks, and the command line shows the flag instead."""


def as_flags(message: str) -> str:
    """`message` with each backticked argument name that has a flag (`FLAGS`) replaced
    by the flag, the other backticks dropped."""
    return re.sub(r"`(\w+)`", lambda m: FLAGS.get(m.group(1), m.group(1)), message)


class _Parser(argparse.ArgumentParser):
    def error(self, message):  # one line, no usage dump
        self.exit(2, f"jaxtissue: error: {message}\n")


def _positive_float(text: str) -> float:
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r} is not a number") from None
    if not (math.isfinite(value) and value > 0):
        raise argparse.ArgumentTypeError(f"{text} must be a positive number")
    return value


def _tolerance(text: str) -> float:
    value = _positive_float(text)
    if value >= 1:
        raise argparse.ArgumentTypeError(f"{text} must be below 1 (a relative tolerance)")
    return value


def _grid_size(text: str) -> int:
    try:
        value = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r} is not an integer") from None
    if value < 1:
        raise argparse.ArgumentTypeError(f"{text} must be a positive integer")
    return value


def _max_steps(text: str) -> int:
    value = _grid_size(text)
    if value > MAX_STEPS:
        raise argparse.ArgumentTypeError(f"{text} must be at most {MAX_STEPS}")
    return value


def build_parser() -> argparse.ArgumentParser:
    from . import __version__

    parser = _Parser(prog="jaxtissue", description="Differentiable simulator of engineered-tissue formation.")
    parser.add_argument("--version", action="version", version=f"jaxtissue {__version__}")
    sub = parser.add_subparsers(dest="command", required=True, parser_class=_Parser)
    parser.commands = sub.choices  # name -> its parser, for hints on unknown flags

    p = sub.add_parser("params", help="print the parameter table (defaults, units, ranges, sources)")
    p.set_defaults(func=cmd_params)

    s = sub.add_parser("simulate", help="simulate one culture into a folder of files and figures")
    s.add_argument("--regime", choices=["static", "flex"], default="static", help="culture regime (default: static)")
    s.add_argument("--t-end", type=_positive_float, default=T_END_S, metavar="S", help=f"end of culture in seconds (default {T_END_S:g})")
    s.add_argument("--grid", type=_grid_size, nargs=2, default=None, metavar=("NX", "NY"), help=f"growth grid cells along x and across y (default {_default_grids()})")
    _flex_arguments(s)
    s.add_argument("--lumping", choices=["dispersive", "paper"], default="dispersive", help="cycle-to-growth coupling rule (default dispersive)")
    _parameter_arguments(s)
    s.add_argument("--rtol", type=_tolerance, default=1e-5, help="relative tolerance of the growth solve (default 1e-5)")
    s.add_argument("--max-steps", type=_max_steps, default=4096, metavar="N", help=f"step limit of each growth solve (default 4096, at most {MAX_STEPS})")
    s.add_argument("--method", choices=METHODS, default="ros34pw2",
                   help="time stepper of the growth solve: ros34pw2 (order 3, any run; the default) or rodas4p2 (order 4, "
                        "for static runs on 1-D grids: fewer steps at tight --rtol; docs/numerics.md)")
    s.add_argument("--save", choices=["intervals", "end"], default="intervals", help="the series at every coupling interval (default) or only at --t-end")
    _output_arguments(s, required=False)
    s.add_argument("--checkpoint-every", type=_grid_size, default=None, metavar="N",
                   help="save the state every N coupling intervals in DIR.checkpoint/ (a killed run continues with --resume DIR)")
    s.add_argument("--resume", type=_folder, metavar="DIR", help="continue the interrupted --checkpoint-every run whose --out was DIR (its settings are reused)")
    s.add_argument("--progress", action=argparse.BooleanOptionalAction, default=None, help=f"progress bar over the run, with its remaining time (its program is then not cached; default: on a terminal, for runs expected to last over {LONG_RUN_S:g} s)")
    s.set_defaults(func=cmd_simulate)

    c = sub.add_parser("cycle", help="one loading cycle of the poroelastic beam, with figures")
    _flex_arguments(c)
    c.add_argument("--ecm", type=float, default=0.0, metavar="VALUE", help="uniform ECM m in [0, 1] of the strip (default 0: bare scaffold)")
    c.add_argument("--ny", type=_grid_size, default=40, help="cells across the thickness (default 40)")
    c.add_argument("--segments", type=_grid_size, default=50, help="beam segments along the strip (default 50)")
    c.add_argument("--steps", type=_grid_size, default=200, help="time steps per cycle (default 200)")
    _parameter_arguments(c)
    _output_arguments(c)
    c.set_defaults(func=cmd_cycle)

    r = sub.add_parser("reproduce", help="the paper's static and flex study into figures and a report")
    r.add_argument("--t-end", type=_positive_float, default=T_END_S, metavar="S", help=f"end of culture in seconds (default {T_END_S:g})")
    _parameter_arguments(r)
    _output_arguments(r)
    r.add_argument("--progress", action=argparse.BooleanOptionalAction, default=None, help=f"progress bars over the runs (their programs are then not cached; default: on a terminal, for flex runs expected to last over {LONG_RUN_S:g} s)")
    r.set_defaults(func=cmd_reproduce)

    k = sub.add_parser("calibrate", help="fit parameters to measurements (multi-start LM, standard errors, profiles)")
    k.add_argument("problem", metavar="PROBLEM", help="problem file: TOML (calibrate/engelmayr2005.toml) or PEtab v2 YAML "
                   "(calibrate/engelmayr2005/problem.yaml)")
    k.add_argument("--export-petab", type=_folder, metavar="DIR", help="write the TOML problem as PEtab v2 files into DIR instead of fitting")
    k.add_argument("--starts", type=_grid_size, default=None, metavar="N", help="number of starts (default: the problem's [fit] starts)")
    k.add_argument("--no-profiles", action="store_true", help="skip the profile likelihoods (identifiability then from standard errors)")
    k.add_argument("--posterior", action="store_true", help="then sample the posterior with NUTS: posterior.nc, pairs.png, traces.png")
    k.add_argument("--chains", type=_grid_size, default=4, metavar="N", help="with --posterior: chains, batched (default 4)")
    k.add_argument("--warmup", type=_grid_size, default=300, metavar="N", help="with --posterior: warmup draws per chain (default 300)")
    k.add_argument("--samples", type=_grid_size, default=800, metavar="N", help="with --posterior: kept draws per chain (default 800)")
    k.add_argument("--seed", type=int, default=0, metavar="S", help="with --posterior: random seed (default 0)")
    k.add_argument("--hold-out", metavar="CONDITION", help="with --posterior: calibrate without that condition's data, then predict them")
    _output_arguments(k, required=False)
    k.add_argument("--progress", action=argparse.BooleanOptionalAction, default=None, help="progress bars (default: on a terminal)")
    k.set_defaults(func=cmd_calibrate)

    t = sub.add_parser("lint", help="check a PEtab v2 calibration problem with the petab linter and jaxtissue's checks")
    t.add_argument("problem", metavar="PROBLEM.yaml", help="PEtab v2 problem file, e.g. calibrate/engelmayr2005/problem.yaml")
    t.set_defaults(func=cmd_lint)

    d = sub.add_parser("predict", help="posterior predictive bands of a protocol from a calibrated posterior")
    d.add_argument("--posterior", required=True, type=_folder, metavar="DIR", help="a `jaxtissue calibrate --posterior` output folder")
    d.add_argument("--regime", choices=["static", "flex"], default="flex", help="culture regime (default: flex)")
    _flex_arguments(d)
    d.add_argument("--t-end", type=_positive_float, default=THREE_WEEKS_S, metavar="S", help="end of culture in s (default 3 weeks)")
    d.add_argument("--draws", type=_grid_size, default=100, metavar="N", help="posterior draws to simulate (default 100)")
    d.add_argument("--seed", type=int, default=0, metavar="S", help="which draws (default 0)")
    _output_arguments(d)
    d.add_argument("--progress", action=argparse.BooleanOptionalAction, default=None, help="progress bar (default: on a terminal)")
    d.set_defaults(func=cmd_predict)

    w = sub.add_parser("sweep", help="a batch of simulations over a grid or design of parameter sets")
    w.add_argument("sweep", metavar="SWEEP.toml", help="sweep definition (see README)")
    w.add_argument("--out", required=True, type=_folder, metavar="DIR", help="output folder: chunks/, sweep.nc, summary.json")
    w.add_argument("--resume", action="store_true", help="continue an interrupted sweep in DIR, skipping finished chunks")
    w.add_argument("--overwrite", action="store_true", help="start afresh in a non-empty DIR")
    w.add_argument("--progress", action=argparse.BooleanOptionalAction, default=None, help="progress bar (default: on a terminal)")
    w.add_argument("--dask", metavar="CLUSTER", help="run the chunks as tasks on a Dask cluster: local:N (N worker processes "
                   "here) or a scheduler address (tcp://host:8786); results into DIR/sweep.zarr as they finish")
    w.add_argument("--distributed", nargs="?", const="", metavar="HOST:PORT",
                   help="one of several processes sharing the sweep (jax.distributed; the coordinator's address, or detected "
                        "from SLURM, Open MPI, ... or $JAX_COORDINATOR_ADDRESS); process 0 writes DIR")
    w.add_argument("--num-processes", type=_grid_size, default=None, metavar="N", help="with --distributed: the number of processes")
    w.add_argument("--process-id", type=int, default=None, metavar="I", help="with --distributed: this process, 0 to N-1")
    w.set_defaults(func=cmd_sweep)

    n = sub.add_parser("sensitivity", help="normalised sensitivities d ln(output)/d ln(parameter) at 3 weeks")
    n.add_argument("--regime", choices=["static", "flex"], default="static", help="culture regime (default: static)")
    n.add_argument("--t-end", type=_positive_float, default=THREE_WEEKS_S, metavar="S", help="time of the outputs in s (default 3 weeks)")
    n.add_argument("--grid", type=_grid_size, nargs=2, default=None, metavar=("NX", "NY"), help=f"growth grid (default {_default_grids()})")
    n.add_argument("--nest-intervals", action="store_true",
                   help="flex: the reverse pass keeps ~sqrt(n) of the n growth intervals' states, for one more forward pass (less memory)")
    n.add_argument("--store-float32", action="store_true",
                   help="with --nest-intervals: those states and transports kept in float32 (half their memory; gradients within ~1e-7)")
    _flex_arguments(n)
    _parameter_arguments(n)
    _output_arguments(n)
    n.set_defaults(func=cmd_sensitivity)

    o = sub.add_parser("optimize", help="gradient-based design of a conditioning protocol, checked against a brute-force grid")
    o.add_argument("problem", metavar="PROBLEM.toml", help="optimisation problem (see optimize/*.toml)")
    o.add_argument("--starts", type=_grid_size, default=None, help="number of starts (overrides the problem file)")
    o.add_argument("--steps", type=_grid_size, default=None, help="Adam steps per start (overrides the problem file)")
    o.add_argument("--grid-points", type=_grid_size, default=None, metavar="N", help="brute-force grid points per axis (overrides the problem file)")
    _output_arguments(o)
    o.add_argument("--progress", action=argparse.BooleanOptionalAction, default=None, help="progress bars (default: on a terminal)")
    o.set_defaults(func=cmd_optimize)
    return parser


def _default_grids() -> str:
    return ", ".join(f"{nx} {ny} {regime}" for regime, (nx, ny) in DEFAULT_SHAPES.items())


def _parameter_arguments(parser):
    parser.add_argument("--set", action="append", default=[], metavar="NAME=VALUE", help="change one parameter (repeatable, once per parameter)")
    parser.add_argument("--params", metavar="FILE.toml", help="parameters from a TOML file")


def _folder(text: str) -> str:
    """A folder argument as one path (`DIR/` is `DIR`): what `DIR.checkpoint` and the
    "wrote DIR/" lines are made from; an empty one is refused (it would be ".")."""
    import pathlib

    if not text.strip():
        raise argparse.ArgumentTypeError(f"{text!r} names no folder")
    return str(pathlib.Path(text))


def _output_arguments(parser, required=True):
    parser.add_argument("--out", required=required, type=_folder, metavar="DIR", help="output folder (must be new or empty)")
    parser.add_argument("--overwrite", action="store_true", help="replace a non-empty output folder")


def _flex_arguments(parser):
    parser.add_argument("--period", type=_positive_float, default=1.0, metavar="S", help="flexure period T in s (default 1)")
    parser.add_argument("--post-displacement", type=float, default=5.0, metavar="MM", help="post displacement amplitude in mm (default 5)")
    parser.add_argument("--hold-fraction", type=float, default=0.05, metavar="F", help="hold at rest and at full flexure, fraction of T in [0, 0.25) (default 0.05)")
    parser.add_argument("--pins", choices=["centroid", "bottom"], default="centroid", help="where the posts pin the strip (default centroid)")


def _flex_protocol(args):
    from .protocol import Protocol, ProtocolValueError

    try:
        return Protocol.flex(args.period, args.post_displacement, args.hold_fraction, getattr(args, "lumping", "dispersive"), args.pins)
    except ProtocolValueError as err:
        raise InputError(f"{FLAGS[err.field]} = {err.value:g} must be {err.allowed}") from None
    except ValueError as err:
        raise InputError(str(err)) from None


def cmd_params(args) -> int:
    from .params import FIELDS, Params

    defaults = Params().as_dict()
    print(f"{'name':<22} {'default':>12}  {'unit':<12} {'allowed':<14} meaning")
    for name, info in FIELDS.items():
        print(f"{name:<22} {defaults[name]:>12.6g}  {info.unit:<12} {info.range_text():<14} {info.doc}")
    return 0


def parse_assignment(text: str) -> tuple[str, float]:
    """`NAME=VALUE` of `--set`."""
    from .params import FIELDS, suggest

    name, sep, value = text.partition("=")
    name = name.strip()
    if not sep or not name:
        raise InputError(f"--set {text!r}: expected NAME=VALUE")
    if name not in FIELDS:
        raise InputError(f"--set {name}: unknown parameter; {suggest(name, FIELDS)}")
    try:
        number = float(value)
    except ValueError:
        raise InputError(f"--set {name}={value}: {value!r} is not a number{FIELDS[name].unit_text}") from None
    return name, number


def load_params(args):
    from .io import make_params, read_params_toml

    base = read_params_toml(args.params) if args.params else None
    changes = {}
    for name, value in map(parse_assignment, args.set):
        if name in changes and changes[name] != value:
            raise InputError(f"--set {name} is given twice ({changes[name]:g} and {value:g}); give it once")
        changes[name] = value
    params = make_params(changes, base, where="--set")
    u = getattr(args, "post_displacement", None)
    if u is not None and getattr(args, "regime", "flex") == "flex" and u >= params.length_mm:
        raise InputError(f"--post-displacement = {u:g} must be below the strip length length_mm = {params.length_mm:g} mm")
    return params


_RUN_KEYS = ("regime", "t_end", "grid", "period", "post_displacement", "hold_fraction", "pins", "lumping", "rtol", "max_steps",
             "method", "checkpoint_every", "out", "overwrite")


def _resumed_run(args):
    """The settings of the interrupted run whose output folder is `args.resume`."""
    import json
    import pathlib

    if args.out is not None and pathlib.Path(args.out) != pathlib.Path(args.resume):
        raise InputError(f"--resume {args.resume} continues into that folder; drop --out {args.out}")
    run_file = pathlib.Path(f"{args.resume}.checkpoint") / "run.json"
    if not run_file.exists():
        raise InputError(f"--resume {args.resume}: no interrupted run there ({run_file} missing)")
    try:
        saved = json.loads(run_file.read_text())
        saved.setdefault("method", "ros34pw2")  # a run.json from before --method
        resumed = argparse.Namespace(**{k: saved[k] for k in _RUN_KEYS}, resume=args.resume, progress=args.progress)
        resumed.grid = tuple(resumed.grid) if resumed.grid else None
        return resumed, saved["params"]
    except (ValueError, KeyError, TypeError, AttributeError) as err:  # not JSON, or not what a run writes
        raise InputError(f"--resume {args.resume}: {run_file} is damaged ({type(err).__name__}: {err}); "
                         f"remove {run_file.parent} to start the run again") from None


def cmd_simulate(args) -> int:
    import json
    import pathlib
    import shutil

    from . import io, limits
    from .coupling import with_rule_constant
    from .grid import Grid
    from .params import Params
    from .protocol import Protocol
    from .growth import has_cell_transport
    from .simulate import SolverOptions, method_problem, simulate

    if args.checkpoint_every is not None and args.save != "intervals":
        raise InputError("--checkpoint-every saves every interval; drop --save end")
    if args.resume:
        if args.checkpoint_every is not None:
            raise InputError("--resume reuses the interrupted run's --checkpoint-every; drop it")
        args, saved_params = _resumed_run(args)
        params = io.make_params(saved_params, Params(), where=f"{args.resume}.checkpoint/run.json")
    else:
        if args.out is None:
            raise InputError("--out DIR is required (or --resume DIR)")
        params = load_params(args)
    protocol = Protocol.static() if args.regime == "static" else _flex_protocol(args)
    nx, ny = args.grid if args.grid else DEFAULT_SHAPES[args.regime]
    if ny < 3:
        raise InputError(f"--grid NY = {ny} must be at least 3")
    grid = Grid(nx=nx, ny=ny)
    io.check_output_folder(args.out, args.overwrite)
    # a static series interval by interval: a program the cache can keep (as a fitted file's options have it)
    options = SolverOptions(rtol=args.rtol, atol=args.rtol * 1e-3, max_steps=args.max_steps, static_series="intervals",
                            method=args.method)
    resolution = {}
    if getattr(args, "params", None) and not args.grid:  # a fitted file: simulate at the resolution of the fit
        from .studies.calibration import fitted_model

        fitted = fitted_model(args.params)
        if fitted is not None:
            grid = fitted.grid(args.regime)
            options = dataclasses.replace(fitted.options(), max_steps=args.max_steps, method=args.method)
            resolution = {"beam": fitted.beam(), "coupling_interval_s": fitted.coupling_interval_s}
            print(f"model resolution from {args.params} [model]: grid {grid.nx} x {grid.ny}, beam {fitted.beam_segments} x "
                  f"{fitted.beam_steps_per_cycle}, T_g = {fitted.coupling_interval_s:g} s, rtol = {fitted.rtol:g} (--grid overrides)")
    progress = args.progress if args.progress is not None else \
        _long_run(grid.nx * grid.ny, args.t_end, resolution.get("coupling_interval_s", COUPLING_INTERVAL_S), args.regime)
    if (problem := method_problem(options, args.regime, grid, has_cell_transport(params))) is not None:
        raise InputError(f"--method {options.method}: {problem}")
    kept = pathlib.Path(f"{args.out}.checkpoint")
    if kept.exists() and not args.resume:
        raise InputError(f"--out {args.out}: an interrupted run is kept in {kept}; continue it with --resume {args.out} or remove that folder")
    params, lumping_note = with_rule_constant(params, protocol.lumping)
    notes = limits.extrapolation(params, protocol, args.t_end)
    writers = _import_in_background(*_WRITERS)
    if args.checkpoint_every is None:
        result = simulate(params, protocol, t_end_s=args.t_end, grid=grid, options=options, progress=progress, save=args.save,
                          **resolution)
    else:
        if not args.resume:
            kept.mkdir(parents=True)
            run = {k: getattr(args, k) for k in _RUN_KEYS} | {"params": params.as_dict()}
            io.atomic_write_text(kept / "run.json", json.dumps(run, indent=1))
        from tqdm.auto import tqdm

        from .studies.checkpoint import simulate_checkpointed

        with tqdm(desc="segments", unit="segment", disable=not progress) as bar:
            def tick(k, n):
                bar.total = n
                bar.update(1)

            result = simulate_checkpointed(params, protocol, args.t_end, grid, kept, args.checkpoint_every, options=options, progress=tick)
    if bool(result.failed):
        print(f"jaxtissue: error: {as_flags(result.failure_message())}. Nothing was written.", file=sys.stderr)
        return 1
    writers.join()
    from . import plots

    with io.output_folder(args.out, args.overwrite) as tmp:
        io.write_netcdf(result.contents(), tmp / "result.nc")
        solver = {"method": options.method, "rtol": options.rtol, "atol": options.atol}
        io.write_json(tmp / "summary.json", summary(result, args.regime) | {"solver": solver, "warnings": notes} |
                      ({"lumping": {"rule": protocol.lumping, "C": params.lumping_C, "why": lumping_note}} if lumping_note else {}))
        io.write_params_toml(params, tmp / "params.toml", notes=(lumping_note,) if lumping_note else ())
        plots.profiles(result, tmp / "profiles.png", title=f"{args.regime} culture")
        plots.time_series({args.regime: result}, tmp / "time_series.png")
    if args.checkpoint_every is not None:
        shutil.rmtree(kept, ignore_errors=True)
    print(f"wrote {args.out}/ (result.nc, summary.json, params.toml, profiles.png, time_series.png)")
    return 0


_WRITERS = ("jaxtissue.plots", "h5netcdf")
"""The writers' libraries, imported while a command's runs go on (a `Result`'s NetCDF
file is written without xarray: `io.write_netcdf`)."""

_XARRAY = ("xarray", "dask.array", "dask.distributed")
"""xarray, and the parts of dask it imports to look for dask's arrays and, writing
NetCDF, for dask's scheduler."""


def _import_in_background(*modules: str):
    """A started daemon thread importing `modules` while the main thread traces and runs
    the computation (which releases the interpreter while it runs). Join it before the
    main thread imports them; a module that fails here is left to fail there, with the
    command's own error handling."""
    import importlib
    import threading

    def load():
        for name in modules:
            try:
                importlib.import_module(name)
            except Exception:  # noqa: BLE001 (reported where the main thread imports it)
                pass

    thread = threading.Thread(target=load, name="jaxtissue imports", daemon=True)
    thread.start()
    return thread


def summary(result, regime: str) -> dict:
    """The `summary.json` of a run: series, 3-week values (when reached) and parameters."""
    from .result import SCALARS

    keys = SCALARS
    out = {"regime": regime, "times_s": result.ts}
    out.update({k: getattr(result, k) for k in keys})
    if np.min(np.abs(np.asarray(result.ts) - THREE_WEEKS_S)) < 1e-6:
        i = result.index(THREE_WEEKS_S)
        out["three_weeks"] = {k: float(np.asarray(getattr(result, k))[i]) for k in keys}  # indexed on the host: no JAX op to compile
    out["solver_steps"] = int(result.num_steps)
    out["params"] = result.params.as_dict()
    return out


def cmd_cycle(args) -> int:
    import jax
    import jax.numpy as jnp

    from . import cache, io, plots
    from .beam import BeamGrid, uniform_cycle
    from .limits import warn_extrapolation

    params = load_params(args)
    protocol = _flex_protocol(args)
    notes = warn_extrapolation(params, protocol)
    if not 0.0 <= args.ecm <= 1.0:
        raise InputError(f"--ecm {args.ecm:g} must be in [0, 1]")
    for flag, value, ok, allowed in (("--ny", args.ny, args.ny >= 3, "at least 3"),
                                     ("--segments", args.segments, args.segments >= 4 and args.segments % 2 == 0, "an even number >= 4"),
                                     ("--steps", args.steps, args.steps >= 8, "at least 8")):
        if not ok:
            raise InputError(f"{flag} {value} must be {allowed}")
    io.check_output_folder(args.out, args.overwrite)
    grid = BeamGrid(n_segments=args.segments, steps_per_cycle=args.steps)
    si = jax.tree_util.tree_map(jnp.asarray, params.si())  # values, not constants: one program for every parameter set
    beam, cycle = cache.call(uniform_cycle, si, protocol.pins, grid, args.ny,
                             *map(jnp.asarray, (args.ecm, protocol.period_s, protocol.post_displacement_mm * 1e-3, protocol.hold_fraction)))
    if bool(cycle.failed):
        from .result import RESULTS

        print(f"jaxtissue: error: {as_flags(RESULTS[RESULTS.beam_failed])}. Nothing was written.", file=sys.stderr)
        return 1
    c = jax.device_get(cycle)  # on the host: no eager JAX operation (each compiles a program of its own)
    summary = {
        "midspan_deflection_mm_max": 1e3 * float(np.max(c.midspan_deflection_m)),
        "post_force_max_N": float(np.max(c.post_force_N)),
        "cycle_mean_velocity_cm_s_max": 100 * float(np.max(np.abs(c.mean_vy))),
        "cycle_mean_abs_velocity_cm_s_max": 100 * float(np.max(c.mean_abs_vy)),
        "surface_strain_max": float(np.max(c.surface_strain)),
        "period_s": args.period, "post_displacement_mm": args.post_displacement,
        "hold_fraction": args.hold_fraction, "ecm": args.ecm, "params": params.as_dict(),
        "t_s": c.t, "post_displacement_mm_t": 1e3 * c.u, "post_force_N_t": c.post_force_N,
        "midspan_deflection_mm_t": 1e3 * c.midspan_deflection_m, "warnings": notes,
    }
    with io.output_folder(args.out, args.overwrite) as tmp:
        io.write_json(tmp / "summary.json", summary)
        plots.cycle_figures(cycle, beam, tmp / "shape.png", tmp / "flow.png")
    print(f"wrote {args.out}/ (summary.json, shape.png, flow.png)")
    return 0


def _long_run(cells: int, t_end_s: float, coupling_interval_s: float, regime: str) -> bool:
    """Whether a run shows a progress bar by default: on a terminal, where it is expected
    to outlast `LONG_RUN_S` (the bar, fed from inside the run, keeps its program out of
    the compilation cache)."""
    from . import limits

    intervals = limits.check_intervals(t_end_s, coupling_interval_s)
    return sys.stderr.isatty() and limits.expected_seconds(cells, intervals, regime) > LONG_RUN_S


def cmd_reproduce(args) -> int:
    from concurrent.futures import ThreadPoolExecutor

    from . import io
    from .studies import reproduce, sweep

    sweep.use_all_cores()  # the flex cases' batch and the posterior draws split over the cores; before JAX starts

    params = load_params(args)
    io.check_output_folder(args.out, args.overwrite)
    progress = args.progress if args.progress is not None else \
        _long_run(int(np.prod(DEFAULT_SHAPES["flex"])), args.t_end, COUPLING_INTERVAL_S, "flex")
    libraries = _import_in_background(*_WRITERS, *_XARRAY, "arviz")  # and what reads the shipped posterior
    results = reproduce.run_cases(params, t_end_s=args.t_end, progress=progress)
    libraries.join()
    failed = [name for name, r in results.items() if bool(r.failed)]
    if failed:
        print(f"jaxtissue: error: {'; '.join(f'{n}: {as_flags(results[n].failure_message())}' for n in failed)}. Nothing was written.", file=sys.stderr)
        return 1
    with io.output_folder(args.out, args.overwrite) as tmp, ThreadPoolExecutor(1, thread_name_prefix="jaxtissue figures") as pool:
        cases = pool.submit(reproduce.write_cases, results, tmp)  # drawn while the posterior draws run
        print("running the calibrated model's posterior draws ...")
        bands = reproduce.calibrated_bands(args.t_end)
        cases.result()
        reproduce.write_report(results, params, tmp, bands)
    print(f"wrote {args.out}/ (report.md, summary.json, figures fig5–fig10, cases/*.nc)")
    return 0


def cmd_calibrate(args) -> int:
    from . import io
    from .studies import calibration

    overrides = {} if args.starts is None else {"starts": args.starts}
    if args.export_petab is not None:
        return _export_petab(args, overrides)
    if args.out is None:
        raise InputError("calibrate needs --out DIR (or --export-petab DIR to convert the problem)")
    if _is_petab(args.problem):
        from .studies import petab_problems

        messages, loaded = petab_problems.check(args.problem)
        messages = petab_problems.errors(messages)
        for m in messages:
            print(f"jaxtissue: error: {args.problem}: {m.split(': ', 1)[1]}", file=sys.stderr)
        if messages:
            return 2
        problem = petab_problems.to_problem(loaded)
        problem = dataclasses.replace(problem, fit=dataclasses.replace(problem.fit, **overrides))
    else:
        problem = calibration.read_problem(args.problem, overrides)
    held_out = None
    if args.hold_out is not None and not args.posterior:
        raise InputError("--hold-out needs --posterior (the held-out data are predicted from the posterior)")
    if args.posterior:
        from .studies import posterior

        if args.hold_out is not None:
            problem, held_out = posterior.hold_out(problem, args.hold_out)
        try:
            settings = posterior.SamplerSettings(chains=args.chains, warmup=args.warmup, samples=args.samples, seed=args.seed)
        except ValueError as err:
            raise InputError(f"--chains, --warmup, --samples: {err}") from None
        posterior.check_size(problem, settings)
        posterior.split_cpu(problem, args.chains)  # before anything starts JAX's backends
    io.check_output_folder(args.out, args.overwrite)
    progress = sys.stderr.isatty() if args.progress is None else args.progress
    cal = calibration.calibrate(problem, with_profiles=not args.no_profiles, progress=progress)
    if not math.isfinite(cal.fit.chi2):
        print("jaxtissue: error: every start failed (non-finite residuals); try narrower bounds or more starts. Nothing was written.", file=sys.stderr)
        return 1
    sampled = None
    if args.posterior:
        sampled = posterior.run(cal, settings, progress=progress, held_out=held_out)
    with io.output_folder(args.out, args.overwrite) as tmp:
        calibration.write(cal, tmp)
        if sampled is not None:
            posterior.write(cal, sampled, tmp)
    print(f"chi2 = {cal.fit.chi2:.4g}; " + ", ".join(f"{n} = {v:.4g}" for n, v in zip(problem.names, cal.fit.values)))
    if sampled is not None:
        s = sampled.summary
        print(f"posterior: {s['draws']} draws, {s['divergences']} divergent; "
              + ", ".join(f"{n} {v['q50']:.3g} [{v['q05']:.3g}, {v['q95']:.3g}] (R-hat {v['r_hat']:.3f}, ESS {v['ess_bulk']:.0f})"
                          for n, v in s["posterior"].items()))
        for c in s.get("held_out", []):
            print(f"held out {c['observation']}: data {c['data']:.4g}, 90 % predictive [{c['lower']:.4g}, {c['upper']:.4g}]"
                  f" -> {'inside' if c['inside'] else 'OUTSIDE'}")
    print(f"wrote {args.out}/ (summary.json, fitted.toml, report.md, waterfall.png, fit.png, profiles.png, correlation.png"
          + (", posterior.nc, pairs.png, traces.png)" if sampled is not None else ")"))
    return 0


def _is_petab(path) -> bool:
    """A PEtab problem: a YAML file, or a folder holding problem.yaml."""
    return str(path).lower().endswith((".yaml", ".yml")) or os.path.isdir(path)


def _export_petab(args, overrides) -> int:
    from . import io
    from .studies import calibration, petab_problems

    if _is_petab(args.problem):
        raise InputError(f"--export-petab: {args.problem} is a PEtab problem already; export takes a TOML problem")
    problem = calibration.read_problem(args.problem, overrides)
    with io.output_folder(args.export_petab, args.overwrite, argument="export_petab") as tmp:
        files = petab_problems.export(problem, tmp)
    print(f"wrote {args.export_petab}/ ({', '.join(files)}); check it with `jaxtissue lint {args.export_petab}/problem.yaml`")
    return 0


def cmd_lint(args) -> int:
    from .studies import petab_problems

    messages, loaded = petab_problems.check(args.problem)
    for m in messages:
        print(f"{args.problem}: {m}")
    if petab_problems.errors(messages):
        return 2
    problem = petab_problems.to_problem(loaded)
    print(f"{args.problem}: valid PEtab v2 problem for jaxtissue ({len(problem.observations)} measurements, "
          f"{len(problem.conditions)} experiments, {len(problem.free)} estimated parameters)")
    return 0


def cmd_predict(args) -> int:
    from tqdm.auto import tqdm

    from . import io, limits, plots
    from .protocol import Protocol
    from .result import SCALARS
    from .studies import posterior, sweep

    sweep.use_all_cores()  # the draws' batches split over the cores; before JAX starts
    saved = posterior.read_saved(args.posterior)
    protocol = Protocol.static() if args.regime == "static" else _flex_protocol(args)
    io.check_output_folder(args.out, args.overwrite)
    progress = sys.stderr.isatty() if args.progress is None else args.progress
    with tqdm(total=min(args.draws, saved.values[..., 0].size), desc="predict", unit="draw", disable=not progress) as bar:
        ds = posterior.predict(saved, protocol, args.t_end, draws=args.draws, seed=args.seed, progress=bar.update)
    shown = [k for k in SCALARS if k != "surface_strain_max" and (args.regime == "flex" or k != "post_force_max_N")]
    bands = {k: tuple(ds[f"{k}_q{q:02d}"].values for q in (5, 50, 95)) for k in shown}
    condition = args.regime
    data = {}
    for quantity, cond, t, mean, sd in saved.observations:
        if cond in (condition, "seeded"):
            data.setdefault(quantity, []).append((t, mean, sd, cond))
    end = {k: {"q05": float(ds[f"{k}_q05"].values[-1]), "q50": float(ds[f"{k}_q50"].values[-1]), "q95": float(ds[f"{k}_q95"].values[-1])}
           for k in shown}
    summary = {"posterior": str(args.posterior), "regime": args.regime, "t_end_s": args.t_end, "draws": int(ds.sizes["draw"]),
               "failed_draws": int(ds["failed"].values.sum()), "at_t_end": end,
               "model": dataclasses.asdict(saved.model), "warnings": limits.extrapolation(None, protocol, args.t_end)}
    title = f"{args.regime}" + (f", T = {args.period:g} s, {args.post_displacement:g} mm" if args.regime == "flex" else "") + \
        f": posterior predictive of {summary['draws']} draws (data: condition '{condition}')"
    with io.output_folder(args.out, args.overwrite) as tmp:
        io.write_netcdf(ds, tmp / "predict.nc")
        io.write_json(tmp / "summary.json", summary)
        plots.predictive_bands(ds["time_s"].values, bands, data, title, tmp / "bands.png")
    for k, v in end.items():
        print(f"{k} at {args.t_end:g} s: median {v['q50']:.4g}, 90 % band [{v['q05']:.4g}, {v['q95']:.4g}]")
    print(f"wrote {args.out}/ (predict.nc, summary.json, bands.png)")
    return 0


def cmd_optimize(args) -> int:
    from . import io
    from .studies import optimization, sweep

    sweep.use_all_cores()  # starts and grid batches split over the cores; before anything starts JAX's backends
    overrides = {k: v for k, v in (("starts", args.starts), ("steps", args.steps), ("grid_points", args.grid_points)) if v is not None}
    design = optimization.read_design(args.problem, overrides)
    io.check_output_folder(args.out, args.overwrite)
    progress = sys.stderr.isatty() if args.progress is None else args.progress
    study = optimization.run(design, progress=progress)
    with io.output_folder(args.out, args.overwrite) as tmp:
        optimization.write(study, tmp)
    s = optimization.summary(study)
    print(f"{s['sense']} {design.objective}: optimum {s['objective']:.5g} {s['objective_unit']} at {s['optimum']} "
          f"(paper protocol {s['baseline_objective']:.5g}, best grid point {s['grid_best_objective']:.5g})")
    print(f"wrote {args.out}/ (summary.json, params.toml, report.md, landscape.png, history.png)")
    return 0


def cmd_sweep(args) -> int:
    import pathlib

    from . import io
    from .studies import sweep

    if args.dask is None:
        sweep.use_all_cores()  # before anything starts JAX's backend (Dask: the worker processes share the cores)
    definition = sweep.read_sweep(args.sweep)
    out = pathlib.Path(args.out)
    if args.resume and args.overwrite:
        raise InputError("--resume and --overwrite exclude each other")
    if args.dask is not None and args.distributed is not None:
        raise InputError("--dask and --distributed exclude each other")
    if args.dask is not None:
        from .studies.sweep_dask import check_cluster

        check_cluster(args.dask)
    if args.distributed is None and (args.num_processes is not None or args.process_id is not None):
        raise InputError("--num-processes and --process-id go with --distributed")
    if args.distributed is not None:
        sweep.join_processes(args.distributed or None, args.num_processes, args.process_id)
    if sweep.is_writer():  # (of several processes, process 0 checks and writes the folder)
        if args.resume:
            kept = out / "sweep.zarr" if args.dask else out / "chunks" / "sweep.json"
            if not kept.exists():
                raise InputError(f"--resume {out}: no interrupted {'--dask ' if args.dask else ''}sweep there ({kept.relative_to(out)} missing)")
            io.lock_output(out)
        else:
            io.check_output_folder(out, args.overwrite)
            if out.exists():
                import shutil

                shutil.rmtree(out)
    progress = sys.stderr.isatty() if args.progress is None else args.progress
    if args.dask is not None:
        from .studies import sweep_dask

        ds = sweep_dask.run(definition, out, args.dask, resume=args.resume, progress=progress)
    else:
        ds = sweep.run(definition, out, resume=args.resume, progress=progress)
    failures = int(ds.attrs["failures"])
    if not sweep.is_writer():
        return 0
    io.write_json(out / "summary.json", {
        "size": definition.size, "failures": failures, "names": list(definition.names), "regime": definition.protocol.regime,
        "t_end_s": definition.t_end_s, "failed_points": definition.points[np.asarray(ds["failed"]).ravel()].tolist(),
    })
    print(f"{definition.size} parameter sets, {failures} failed; wrote {out}/sweep.nc and summary.json")
    return 0


def cmd_sensitivity(args) -> int:
    from . import io, plots
    from .grid import Grid
    from .protocol import Protocol
    from .simulate import SolverOptions
    from .studies import sensitivity

    if args.store_float32 and not args.nest_intervals:
        raise InputError("--store-float32 needs --nest-intervals (it stores the nested reverse pass's states)")
    params = load_params(args)
    protocol = _flex_protocol(args) if args.regime == "flex" else Protocol.static()
    io.check_output_folder(args.out, args.overwrite)
    grid = None if args.grid is None else Grid(*args.grid)
    options = SolverOptions(nest_intervals=args.nest_intervals, store_float32=args.store_float32)
    table = sensitivity.sensitivities(params, protocol, args.t_end, grid=grid, options=options)
    names = list(next(iter(table.values())))
    print(f"d ln(output)/d ln(parameter) at t = {args.t_end:g} s, {args.regime} culture")
    print(f"{'parameter':22s}" + "".join(f"{k:>20s}" for k in table))
    for n in names:
        print(f"{n:22s}" + "".join(f"{table[k][n]:20.4g}" for k in table))
    with io.output_folder(args.out, args.overwrite) as tmp:
        io.write_json(tmp / "sensitivity.json", {"regime": args.regime, "t_end_s": args.t_end, "sensitivities": table})
        plots.sensitivities(table, tmp / "sensitivity.png", title=f"{args.regime} culture, t = {args.t_end:g} s")
    print(f"wrote {args.out}/ (sensitivity.json, sensitivity.png)")
    return 0


def main(argv=None) -> int:
    parser = build_parser()
    args, unknown = parser.parse_known_args(argv)
    if unknown:
        from .params import suggest

        flags = sorted(set(re.findall(r"--[a-z][\w-]*", parser.commands[args.command].format_help())) - {"--help"})
        hint = suggest(unknown[0].split("=")[0], flags)
        hint = f" ({hint})" if hint.startswith("did you mean") else f"; see jaxtissue {args.command} --help"
        print(f"jaxtissue: error: unrecognized arguments: {' '.join(unknown)}{hint}", file=sys.stderr)
        return 2
    with warnings.catch_warnings():
        warnings.showwarning = _show_warning
        warnings.simplefilter("always", RuntimeWarning)
        use_fast_compilation()  # before anything starts JAX's backends
        folder = enable_compilation_cache()  # a second run of the same command loads its programs
        warnings.simplefilter("default", RuntimeWarning)
        warnings.filterwarnings("ignore", r"\s*ArviZ is undergoing", FutureWarning)  # its daily notice, also where imported in the background
        try:
            with saved_executables(None if folder is None else folder / "executables"):
                return _interruptible(_run, args)
        finally:
            from .io import release_outputs

            release_outputs()


def _show_warning(message, category, filename, lineno, file=None, line=None):
    print(f"jaxtissue: warning: {message}", file=sys.stderr)


_SAY = threading.Lock()  # the command's last line: its error, or the main thread's word on a signal


def _say(line: str) -> None:
    """Print the command's error line, unless a signal is ending the process (its main
    thread then says so, and an error that the ending caused is not the user's news)."""
    with _SAY:
        if not ending():
            print(line, file=sys.stderr, flush=True)


def _run(args) -> int:
    """The command, its errors as one line and an exit code."""
    try:
        return args.func(args)
    except InputError as err:
        _say(f"jaxtissue: error: {as_flags(str(err))}")
        return 2
    except KeyboardInterrupt:
        _say("jaxtissue: interrupted; nothing was written")
        return 130
    except RunError as err:
        _say(f"jaxtissue: error: {err}. Nothing was written.")
        return 1
    except BrokenPipeError:  # e.g. `jaxtissue params | head`
        sys.stderr.close()
        return 0
    except OSError as err:  # the system's refusal (a full disk, a lost connection), not a bug
        where = f" ({err.filename})" if err.filename else ""
        _say(f"jaxtissue: error: {err.strerror or err}{where}; no output was written{_kept_checkpoint(args)}")
        return 1
    except Exception as err:  # a bug, not the user's mistake: still one line
        if os.environ.get("JAXTISSUE_DEBUG"):
            raise
        _say(f"jaxtissue: internal error: {type(err).__name__}: {err} (set JAXTISSUE_DEBUG=1 for the traceback)")
        return 1


class _Terminated(BaseException):
    pass


def _interruptible(run, args) -> int:
    """`run(args)` in a worker thread while the main thread waits for signals: a compiled
    computation does not return to Python until it ends, so SIGINT (exit code 130) and
    SIGTERM (143) are answered here within a fraction of a second, with one line; the
    unfinished output folders are removed and the process ends at once."""
    import signal

    if threading.current_thread() is not threading.main_thread():
        return run(args)
    outcome = {}

    def work():
        outcome["rc"] = run(args)

    def terminate(signum, frame):
        raise _Terminated

    previous = signal.signal(signal.SIGTERM, terminate)
    # in a copy of this thread's context: the command's `saved_executables` folder with it
    worker = threading.Thread(target=contextvars.copy_context().run, args=(work,), name=f"jaxtissue {args.command}", daemon=True)
    try:
        worker.start()
        while worker.is_alive():
            worker.join(0.05)
    except (KeyboardInterrupt, _Terminated) as err:
        from .io import release_outputs

        name, code = ("SIGINT", 130) if isinstance(err, KeyboardInterrupt) else ("SIGTERM", 143)
        _SAY.acquire()  # held until the process ends: the worker's errors from here on are not printed
        release_outputs(ending=True)
        kept = _kept_checkpoint(args)
        bars = "tqdm" in sys.modules and len(getattr(sys.modules["tqdm"].tqdm, "_instances", ())) > 0
        print(f"{chr(10) if bars else ''}jaxtissue: interrupted by {name}; no output was written{kept}", file=sys.stderr, flush=True)
        sys.stdout.flush()
        os._exit(code)  # the worker is inside a compiled computation: do not wait for it
    finally:
        signal.signal(signal.SIGTERM, previous)
    return outcome.get("rc", 1)


def _kept_checkpoint(args) -> str:
    """What an interrupted command keeps for `--resume`, as the end of its message."""
    import pathlib

    out = getattr(args, "out", None) or getattr(args, "resume", None)
    if not out or args.command not in ("simulate", "sweep"):
        return ""
    if args.command == "sweep" and (pathlib.Path(out) / "sweep.zarr").is_dir():
        return (f"; the finished chunks are kept in {out}/sweep.zarr: continue with "
                f"`jaxtissue sweep {args.sweep} --out {out} --dask {args.dask} --resume`")
    if args.command == "sweep" and (pathlib.Path(out) / "chunks").is_dir():
        return f"; the finished chunks are kept: continue with `jaxtissue sweep {args.sweep} --out {out} --resume`"
    if args.command == "simulate" and pathlib.Path(f"{out}.checkpoint").is_dir():
        return f"; the checkpoint {out}.checkpoint is kept: continue with `jaxtissue simulate --resume {out}`"
    return ""


def console() -> None:
    """The `jaxtissue` command: `main`, then the process ends with its exit code without
    the interpreter's teardown of the loaded libraries (every file is written
    and closed by then). A process of a multi-process sweep (`jax.distributed`) leaves
    through `sys.exit`, whose exit handlers shut the group down."""
    collect_less()  # the libraries imported so far: jax, equinox
    code = main()
    sys.stdout.flush()
    sys.stderr.flush()
    if _joined_a_group():
        sys.exit(code)
    os._exit(code)


def _joined_a_group() -> bool:
    return "jax" in sys.modules and sys.modules["jax"].distributed.is_initialized()


if __name__ == "__main__":
    console()
