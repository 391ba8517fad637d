"""What a run may ask of the model and of the machine (docs/model.md §10).

Two kinds of limit, checked before anything is compiled:

* **Supported ranges** (`SUPPORTED`): where the model was calibrated and its data lie.
  A value outside is allowed (its hard physical range, `params.FIELDS` and `Protocol`,
  is what errors) but extrapolates: `extrapolation` names each one, `simulate` warns
  (`ExtrapolationWarning`) and the command line writes them to `summary.json`.
* **Resources** (`check_run`): a run's coupling intervals, saves and memory. A run that
  cannot fit the machine, or asks for an absurd number of intervals, is a
  `ResourceError` (an `InputError`: one line, exit code 2) saying what it needs, what is
  available and how to ask for less.
"""

from __future__ import annotations

import math
import os
import warnings
from typing import NamedTuple

import numpy as np

from .io import InputError
from .params import concrete_value

MAX_INTERVALS = 100_000
"""Most coupling intervals (and saves) one run may have: 63 years of culture at the
default T_g (docs/model.md §5); beyond it a run is a mistake, not a long run."""
MAX_STEPS = 1_000_000
"""Largest step limit of a growth solve (`SolverOptions.max_steps`)."""
MAX_SWEEP_POINTS = 10_000_000
"""Most parameter sets one sweep file may define (a sweep over more is split in files)."""


def check_count(name: str, n: int) -> None:
    """A `ValueError` where a study's count `name` = `n` (its starts, profile points)
    exceeds `MAX_SWEEP_POINTS`."""
    if n > MAX_SWEEP_POINTS:
        raise ValueError(f"{name} = {n} must be at most {MAX_SWEEP_POINTS}")


class Supported(NamedTuple):
    low: float
    high: float
    unit: str
    why: str


SUPPORTED: dict[str, Supported] = {
    "period_s": Supported(0.5, 2.0, "s", "the flexure data and the frequency study span 0.5-2 Hz (docs/model.md §5, §6)"),
    "post_displacement_mm": Supported(2.5, 10.0, "mm", "the amplitude study spans 2.5-10 mm on the 25 mm strip (docs/model.md §5)"),
    "t_end_s": Supported(0.0, 2.0e6, "s", "the data end at 3 weeks and the paper's runs at 2.0e6 s (docs/model.md §6)"),
    "length_mm": Supported(12.5, 50.0, "mm", "the data's strips are 25 mm long (docs/model.md §1)"),
    "thickness_mm": Supported(0.5, 2.0, "mm", "the data's strips are 1 mm thick (docs/model.md §1)"),
    "o_ext": Supported(0.05, 0.2, "1", "the data were taken at 20 % O2; below 5 % the kinetics are untested (docs/model.md §2)"),
}
"""The ranges the model and its data support, by `Params`, `Protocol` or run field."""


class ExtrapolationWarning(UserWarning):
    """A value outside the range the model and its data support (`SUPPORTED`)."""


class ResourceError(InputError):
    """A run that needs more than the machine has, or an absurd number of intervals."""


def extrapolation(params=None, protocol=None, t_end_s=None) -> list[str]:
    """One line for each concrete value outside its supported range (`SUPPORTED`);
    traced values are not checked."""
    values = {}
    if params is not None:
        values.update({k: getattr(params, k) for k in ("length_mm", "thickness_mm", "o_ext")})
    if protocol is not None and protocol.regime == "flex":
        values.update(period_s=protocol.period_s, post_displacement_mm=protocol.post_displacement_mm)
    if t_end_s is not None:
        values["t_end_s"] = t_end_s
    lines = []
    for name, value in values.items():
        value = concrete_value(value)
        if value is None:
            continue
        s = SUPPORTED[name]
        outside = np.ravel(value)[(np.ravel(value) < s.low) | (np.ravel(value) > s.high)]
        if outside.size:
            unit = "" if s.unit == "1" else f" {s.unit}"  # a fraction: no unit to name
            lines.append(f"{name} = {outside[0]:g}{unit} is outside the supported range {s.low:g}-{s.high:g}{unit} "
                         f"({s.why}): the result extrapolates")
    return lines


def warn_extrapolation(params=None, protocol=None, t_end_s=None) -> list[str]:
    """`extrapolation`, each line also issued as an `ExtrapolationWarning`."""
    lines = extrapolation(params, protocol, t_end_s)
    for line in lines:
        warnings.warn(line, ExtrapolationWarning, stacklevel=3)
    return lines


def check_intervals(t_end_s: float, coupling_interval_s: float, name: str = "t_end_s") -> int:
    """The number of coupling intervals of a run, or a `ResourceError` above `MAX_INTERVALS`."""
    n = math.ceil(t_end_s / coupling_interval_s - 1e-9)
    if n > MAX_INTERVALS:
        raise ResourceError(f"`{name}` = {t_end_s:g} s is {n:.3g} coupling intervals of {coupling_interval_s:g} s; "
                            f"a run may have at most {MAX_INTERVALS} (a shorter `{name}` or a longer coupling interval)")
    return n


# Bytes per growth-grid cell, from the peak resident memory of runs on growing grids
# (float64; static 1 x 1e5 -> 1 x 4e5: 770 B, flex 100 x 80 -> 400 x 320: 1.9 kB): a run's
# working set, a saved state, and a state kept for the reverse pass.
_SOLVE_BYTES_PER_CELL = {"static": 1000, "flex": 2000}
_STATE_BYTES_PER_CELL = 3 * 8
_REVERSE_CHECKPOINTS = 8
_BASE_BYTES = 1.0e9  # the interpreter, JAX, XLA's compiler

_SECONDS_PER_CELL_STEP = 5e-6  # benchmarks/scaling.py: 4.7-5.3 us per cell and growth step on 2 cores
_STEPS_PER_INTERVAL = {"static": 1.0, "flex": 7.0}  # the default runs: ~90 steps in all, ~7 per interval


def expected_seconds(cells: int, intervals: int, regime: str) -> float:
    """A rough duration of a run after its compilation (order of magnitude)."""
    return _SECONDS_PER_CELL_STEP * cells * max(_STEPS_PER_INTERVAL[regime] * intervals, 90)


class Estimate(NamedTuple):
    bytes: float
    intervals: int
    saves: int


def estimate(cells: int, t_end_s: float, coupling_interval_s: float, *, save_series: bool = True, reverse: bool = False,
             batch: int = 1, regime: str = "static") -> Estimate:
    """Memory (bytes) a run needs: the solve's working set per run of the batch, the
    saved series (a state per save for a static run that saves every interval) and, for
    a gradient, the states its reverse pass keeps (one per interval, and its
    checkpoints)."""
    n = check_intervals(t_end_s, coupling_interval_s)
    saves = n + 2 if save_series else 1
    per_run = cells * _SOLVE_BYTES_PER_CELL[regime]
    if save_series and regime == "static":
        per_run += saves * cells * _STATE_BYTES_PER_CELL
    if reverse:
        per_run += (n + _REVERSE_CHECKPOINTS) * cells * _STATE_BYTES_PER_CELL * (2 if regime == "flex" else 1)
    return Estimate(_BASE_BYTES + batch * per_run, n, saves)


def available_bytes() -> float:
    """Memory this process may still use: the machine's available memory, or the
    cgroup's limit when it is lower."""
    available = math.inf
    try:
        with open("/proc/meminfo") as f:
            for line in f:
                if line.startswith("MemAvailable:"):
                    available = int(line.split()[1]) * 1024
    except OSError:
        try:
            available = os.sysconf("SC_AVPHYS_PAGES") * os.sysconf("SC_PAGE_SIZE")
        except (ValueError, OSError):
            pass
    for path in ("/sys/fs/cgroup/memory.max", "/sys/fs/cgroup/memory/memory.limit_in_bytes"):
        try:
            text = open(path).read().strip()
        except OSError:
            continue
        if text.isdigit():
            available = min(available, float(text))
    return float(available)


def check_memory(need: Estimate, what: str, hints: str) -> None:
    """A `ResourceError` if `need` exceeds the memory available (`available_bytes`)."""
    have = available_bytes()
    if need.bytes > have:
        raise ResourceError(f"{what} needs about {need.bytes / 2**30:.3g} GiB of memory, {have / 2**30:.3g} GiB are available; "
                            f"{hints}")


def check_study(what: str, grid, t_end_s: float, coupling_interval_s: float, batch: int, reverse: bool) -> None:
    """`check_memory` for a study of `batch` simultaneous runs on `grid` (flexure),
    with a reverse pass if `reverse`."""
    need = estimate(grid.nx * grid.ny, t_end_s, coupling_interval_s, save_series=False, reverse=reverse, batch=batch,
                    regime="flex")
    check_memory(need, f"{what} ({batch} simultaneous runs on the {grid.nx} x {grid.ny} grid)",
                 "a coarser grid in [model], or fewer draws, starts or chains")
