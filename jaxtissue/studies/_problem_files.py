"""What every problem file shares (calibration, optimisation and sweep files): tables,
settings tables read into dataclasses, the `[model]` table, bounds, grid axes and
space-filling designs. Each mistake is an `InputError` naming the file and the key."""

from __future__ import annotations

import dataclasses
import math

import numpy as np

from ..beam import BeamGrid
from ..grid import Grid
from ..io import InputError, number
from ..limits import MAX_SWEEP_POINTS
from ..params import suggest
from ..simulate import SolverOptions


def bounds(value, where: str) -> tuple[float, float]:
    """`[low, high]`: two finite numbers (their order and range are the caller's to check)."""
    if not (isinstance(value, list) and len(value) == 2):
        raise InputError(f"{where} = {value!r} must be [low, high]")
    low, high = (number(v, where) for v in value)
    return low, high


@dataclasses.dataclass(frozen=True)
class ModelSettings:
    """The `[model]` table of calibration and optimisation problems: the resolution
    and tolerances of the model inside a fit or an optimisation (coarser than
    `simulate`'s defaults, for speed)."""

    ny: int = 16
    flex_nx: int = 6
    beam_segments: int = 16
    beam_steps_per_cycle: int = 80
    coupling_interval_s: float = 1.8144e5  # 3 weeks / 10: 3-week values within 0.05 % of T_g = 2e4 s
    rtol: float = 1e-6
    atol: float = 1e-9
    nest_intervals: bool = False  # reverse-mode gradients (protocol optimisation): SolverOptions.nest_intervals
    store_float32: bool = False  # with nest_intervals: SolverOptions.store_float32

    def __post_init__(self):  # the grids' and the solver options' own checks
        self.grid("flex"), self.beam(), self.options()

    def grid(self, regime: str) -> Grid:
        return Grid(nx=1 if regime == "static" else self.flex_nx, ny=self.ny)

    def beam(self) -> BeamGrid:
        return BeamGrid(n_segments=self.beam_segments, steps_per_cycle=self.beam_steps_per_cycle)

    def options(self) -> SolverOptions:
        return self.solver_options("forward")

    def solver_options(self, autodiff: str) -> SolverOptions:
        """A static series interval by interval: programs the compilation cache keeps."""
        return SolverOptions(rtol=self.rtol, atol=self.atol, autodiff=autodiff, nest_intervals=self.nest_intervals,
                             store_float32=self.store_float32, static_series="intervals")


def table(doc, key, where, allowed=None):
    """`doc[key]` as a table ({} if absent); keys outside `allowed` are an `InputError`."""
    value = doc.get(key, {})
    if not isinstance(value, dict):
        raise InputError(f"{where}: [{key}] must be a table")
    if allowed is not None:
        for k in value:
            if k not in allowed:
                raise InputError(f"{where}: unknown key {k!r} in [{key}]; {suggest(k, sorted(allowed))}")
    return value


def settings(cls, table, where, section):
    """A settings dataclass `cls` from the TOML table of `[section]`: unknown keys and
    values of the wrong kind (by each field's default) are an `InputError`."""
    fields = {f.name: f for f in dataclasses.fields(cls)}
    kwargs = {}
    for k, v in table.items():
        if k not in fields:
            raise InputError(f"{where}: unknown key {k!r} in [{section}]; {suggest(k, fields)}")
        default = fields[k].default
        if isinstance(default, bool):
            if not isinstance(v, bool):
                raise InputError(f"{where}: [{section}] {k} = {v!r} must be true or false")
        elif isinstance(default, int):
            ok = isinstance(v, int) and not isinstance(v, bool) and v >= (0 if k == "seed" else 1)
            need = "an integer >= 0" if k == "seed" else "a positive integer"
            if not ok:
                raise InputError(f"{where}: [{section}] {k} = {v!r} must be {need}")
        else:
            v = number(v, f"{where}: [{section}] {k}", positive=True)
        kwargs[k] = type(default)(v)
    try:  # the settings' own checks (`__post_init__`)
        return cls(**kwargs)
    except ValueError as err:
        raise InputError(f"{where}: [{section}] {err}") from None


def grid_axis(name, spec, where):
    """Grid values of one name: {linspace|logspace = [a, b], n} or {values = [...]}."""
    if not isinstance(spec, dict):
        raise InputError(f"{where}: {name} must be {{ linspace = [a, b], n = N }}, {{ logspace = [a, b], n = N }} or {{ values = [...] }}")
    keys = set(spec) - {"n"}
    if len(keys) != 1 or next(iter(keys)) not in ("linspace", "logspace", "values"):
        raise InputError(f"{where}: {name} needs exactly one of linspace, logspace, values (got {sorted(spec)})")
    kind = next(iter(keys))
    if kind == "values":
        values = spec["values"]
        if not isinstance(values, list) or not values:
            raise InputError(f"{where}: {name} values must be a non-empty list")
        return np.array([number(v, f"{where}: {name} value") for v in values])
    ends, n = spec[kind], spec.get("n")
    if not (isinstance(ends, list) and len(ends) == 2):
        raise InputError(f"{where}: {name} {kind} = {ends!r} must be [first, last]")
    a, b = (number(v, f"{where}: {name} {kind} end") for v in ends)
    if isinstance(n, bool) or not isinstance(n, int) or not 1 <= n <= MAX_SWEEP_POINTS:
        raise InputError(f"{where}: {name} n = {n!r} must be an integer in [1, {MAX_SWEEP_POINTS}]")
    if kind == "logspace":
        if a <= 0 or b <= 0:
            raise InputError(f"{where}: {name} logspace = [{a:g}, {b:g}] needs positive values (they are the values, not exponents)")
        return np.geomspace(a, b, n)
    return np.linspace(a, b, n)


def unit_latin_hypercube(n: int, d: int, rng) -> np.ndarray:
    """n points in [0, 1)^d, one in each of n strata along every axis."""
    return (rng.permuted(np.tile(np.arange(n), (d, 1)), axis=1).T + rng.random((n, d))) / max(n, 1)


def space_filling(names, specs, design, samples, seed, where):
    """`samples` points of a Latin hypercube (`design = "lhs"`) or a scrambled Sobol
    sequence (`"sobol"`) over each name's {range = [low, high], transform}."""
    lo, hi, logs = [], [], []
    for name in names:
        spec = specs[name]
        if not isinstance(spec, dict) or set(spec) - {"range", "transform"} or "range" not in spec:
            raise InputError(f"{where}: with design = {design!r}, {name} must be {{ range = [low, high], transform = \"log\" | \"linear\" }}")
        a, b = (number(v, f"{where}: {name} range end") for v in spec["range"])
        transform = spec.get("transform", "linear")
        if transform not in ("log", "linear"):
            raise InputError(f"{where}: {name} transform = {transform!r}; allowed: 'log', 'linear'")
        if not a < b or (transform == "log" and a <= 0):
            raise InputError(f"{where}: {name} range = [{a:g}, {b:g}] must have low < high (and low > 0 for log)")
        lo.append(math.log(a) if transform == "log" else a)
        hi.append(math.log(b) if transform == "log" else b)
        logs.append(transform == "log")
    k = len(names)
    if design == "lhs":
        u = unit_latin_hypercube(samples, k, np.random.default_rng(seed))
    else:
        from scipy.stats import qmc

        u = qmc.Sobol(k, scramble=True, seed=seed).random(samples)
    x = np.asarray(lo) + (np.asarray(hi) - np.asarray(lo)) * u
    return np.where(logs, np.exp(x), x)
