"""The `jaxtissue` command.

    jaxtissue params                         the parameter table (units, ranges, sources)
    jaxtissue simulate --regime static …     one culture, to a folder of files and figures

A mistake in the input gives one line on stderr and exit code 2; a failed solve gives
one line and exit code 1. Output folders appear complete or not at all.
"""

from __future__ import annotations

import argparse
import math
import os
import sys

from .io import InputError

DEFAULT_GRID = (1, 40)


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


def _grid_size(text: str) -> int:
    try:
        value = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r} is not an integer") from None
    if value < 1:
        raise argparse.ArgumentTypeError(f"{text} must be a positive integer")
    return value


def build_parser() -> argparse.ArgumentParser:
    parser = _Parser(prog="jaxtissue", description="Differentiable simulator of engineered-tissue formation.")
    sub = parser.add_subparsers(dest="command", required=True, parser_class=_Parser)

    p = sub.add_parser("params", help="print the parameter table (defaults, units, ranges, sources)")
    p.set_defaults(func=cmd_params)

    s = sub.add_parser("simulate", help="simulate one culture into a folder of files and figures")
    s.add_argument("--regime", choices=["static"], default="static", help="culture regime (default: static)")
    s.add_argument("--t-end", type=_positive_float, default=2.0e6, metavar="S", help="end of culture in seconds (default 2.0e6)")
    s.add_argument("--grid", type=_grid_size, nargs=2, default=DEFAULT_GRID, metavar=("NX", "NY"), help="growth grid cells along x and across y (default 1 40)")
    s.add_argument("--set", action="append", default=[], metavar="NAME=VALUE", help="change one parameter (repeatable)")
    s.add_argument("--params", metavar="FILE.toml", help="parameters from a TOML file (e.g. a params.toml written here)")
    s.add_argument("--rtol", type=_positive_float, default=1e-5, help="relative tolerance of the growth solve (default 1e-5)")
    s.add_argument("--out", required=True, metavar="DIR", help="output folder (must be new or empty)")
    s.add_argument("--overwrite", action="store_true", help="replace a non-empty output folder")
    s.add_argument("--progress", action=argparse.BooleanOptionalAction, default=None, help="progress bar (default: on a terminal)")
    s.set_defaults(func=cmd_simulate)
    return parser


def cmd_params(args) -> int:
    from .params import FIELDS, Params

    defaults = Params().as_dict()
    print(f"{'name':<22} {'default':>12}  {'unit':<12} {'allowed':<14} meaning")
    for name, info in FIELDS.items():
        print(f"{name:<22} {defaults[name]:>12.6g}  {info.unit:<12} {info.range_text():<14} {info.doc}")
    return 0


def load_params(args):
    from .io import make_params, parse_assignment, read_params_toml

    base = read_params_toml(args.params) if args.params else None
    changes = dict(parse_assignment(text) for text in args.set)
    return make_params(changes, base)


def cmd_simulate(args) -> int:
    from . import io, plots
    from .grid import Grid
    from .simulate import Protocol, SolverOptions, simulate

    params = load_params(args)
    nx, ny = args.grid
    if ny < 3:
        raise InputError(f"--grid NY = {ny} must be at least 3")
    grid = Grid(nx=nx, ny=ny)
    io.check_output_folder(args.out, args.overwrite)
    progress = sys.stderr.isatty() if args.progress is None else args.progress
    result = simulate(
        params, Protocol.static(), t_end_s=args.t_end, grid=grid,
        options=SolverOptions(rtol=args.rtol, atol=args.rtol * 1e-3), progress=progress,
    )
    if bool(result.failed):
        print(
            f"jaxtissue: error: the growth solve failed after {int(result.num_steps)} steps; "
            "try a tighter --rtol or a finer --grid. Nothing was written.",
            file=sys.stderr,
        )
        return 1
    with io.output_folder(args.out, args.overwrite) as tmp:
        io.write_netcdf(result.to_xarray(), tmp / "result.nc")
        io.write_json(tmp / "summary.json", summary(result, args.regime))
        io.write_params_toml(params, tmp / "params.toml")
        plots.profiles(result, tmp / "profiles.png", title=f"{args.regime} culture")
        plots.time_series({args.regime: result}, tmp / "time_series.png")
    print(f"wrote {args.out}/ (result.nc, summary.json, params.toml, profiles.png, time_series.png)")
    return 0


def summary(result, regime: str) -> dict:
    """The `summary.json` of a run: series, 3-week values (when reached) and parameters."""
    from .simulate import THREE_WEEKS_S

    keys = ("dna_ug_per_g", "collagen_mg_per_g", "E_eff_kPa", "EI_N_m2")
    out = {"regime": regime, "times_s": result.ts}
    out.update({k: getattr(result, k) for k in keys})
    if float(result.ts[-1]) >= THREE_WEEKS_S:
        i = result.index(THREE_WEEKS_S)
        out["three_weeks"] = {k: float(getattr(result, k)[i]) for k in keys}
    out["solver_steps"] = int(result.num_steps)
    out["params"] = result.params.as_dict()
    return out


def main(argv=None) -> int:
    args = build_parser().parse_args(argv)
    try:
        return args.func(args)
    except InputError as err:
        print(f"jaxtissue: error: {err}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print("jaxtissue: interrupted; nothing was written", file=sys.stderr)
        return 130
    except BrokenPipeError:  # e.g. `jaxtissue params | head`
        sys.stderr.close()
        return 0
    except Exception as err:  # a bug, not the user's mistake: still one line
        if os.environ.get("JAXTISSUE_DEBUG"):
            raise
        print(f"jaxtissue: internal error: {type(err).__name__}: {err} (set JAXTISSUE_DEBUG=1 for the traceback)", file=sys.stderr)
        return 1


if __name__ == "__main__":
    sys.exit(main())
