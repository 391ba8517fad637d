"""What a run returns: `Result`, the registry of its outputs (`OUTPUTS`: name, unit,
description, how each is computed) and its failure statuses (`RESULTS`).

Files, figures, sweeps, the reproduction study, the data reader and the command line
all take names and units from `OUTPUTS`.
"""

from __future__ import annotations

from typing import Callable, NamedTuple

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from . import observables as obs
from .grid import Grid
from .params import CM_PER_M, Params
from .state import State


class Output(NamedTuple):
    unit: str
    description: str
    dims: tuple[str, ...]
    """Of the saved array: ("time_s",) a value per save time, ("time_s", "y_cm") a
    mid-section profile per save time, ("x_cm", "y_cm") a final 2-D field."""
    compute: Callable | None = None
    """(State, Params, Grid) -> value at one state; None: from the loading cycle (the
    series) or `Result.final` (the fields)."""
    measurable: bool = False
    """Compared with experiment (docs/model.md §6): a measurement table may name it."""
    label: str = ""
    """A figure's axis label, unit included."""


OUTPUTS: dict[str, Output] = {
    "dna_ug_per_g": Output("ug/g", "DNA content per wet weight (A.24)", ("time_s",), obs.dna_ug_per_g, True, "DNA (µg/g ww)"),
    "collagen_mg_per_g": Output("mg/g", "collagen content per wet weight (A.24)", ("time_s",), obs.collagen_mg_per_g, True, "collagen (mg/g ww)"),
    "E_eff_kPa": Output("kPa", "effective flexural modulus 12 EI/(h^3 d) (A.25)", ("time_s",), obs.effective_modulus_kPa, True, "effective modulus E (kPa)"),
    "EI_N_m2": Output("N m^2", "flexural rigidity at the mid-section (A.25)", ("time_s",), obs.flexural_rigidity_N_m2),
    "post_force_max_N": Output("N", "peak post force of a loading cycle with the ECM of that time (0: static)", ("time_s",), None, True),
    "surface_strain_max": Output("1", "peak surface fibre strain of that loading cycle (0: static)", ("time_s",)),
    "profile_o": Output("1", "O2 o = rho_o/(5 rho_o,ext) at the mid-section", ("time_s", "y_cm"), lambda y, p, g: obs.mid_profile(y.o, g)),
    "profile_c": Output("1", "cell density c = rho_c/rho_c,seed at the mid-section", ("time_s", "y_cm"), lambda y, p, g: obs.mid_profile(y.c, g)),
    "profile_m": Output("1", "ECM m = rho_m/rho_m,max at the mid-section", ("time_s", "y_cm"), lambda y, p, g: obs.mid_profile(y.m, g)),
    "o": Output("1", "final O2 field", ("x_cm", "y_cm")),
    "c": Output("1", "final cell-density field", ("x_cm", "y_cm")),
    "m": Output("1", "final ECM field", ("x_cm", "y_cm")),
}
"""Every output of a run, in the order files list them."""

SERIES = tuple(k for k, o in OUTPUTS.items() if o.dims[0] == "time_s")
"""The `Result` fields with a leading time axis (scalars per time, then profiles)."""
SCALARS = tuple(k for k, o in OUTPUTS.items() if o.dims == ("time_s",))
"""The series with one value per save time."""
MEASURABLE = tuple(k for k, o in OUTPUTS.items() if o.measurable)
"""The outputs that data can be compared with."""


class RESULTS(eqx.Enumeration):
    """How a run ended (`Result.status`). Messages name the arguments that help, in
    backticks (the command line shows its own flags for them)."""

    successful = ""
    max_steps_reached = "the growth solve reached its step limit; raise `max_steps` or loosen `rtol`"
    beam_failed = ("the beam's Newton solve did not converge in a loading cycle; try a smaller `post_displacement_mm` "
                   "or more `steps_per_cycle`")
    out_of_bounds = ("concentrations left their physical bounds (NaN, o/c/m < 0, m > 1 or c > c_max); "
                     "try a tighter `rtol` or a finer `grid`")
    growth_failed = "the growth solve failed; try a tighter `rtol` or a finer `grid`"


STATUS_ORDER = (RESULTS.successful, RESULTS.max_steps_reached, RESULTS.beam_failed, RESULTS.out_of_bounds,
                RESULTS.growth_failed)
"""`RESULTS` by the integer code a run computes them as (0 = successful)."""


def status_from_code(code) -> RESULTS:
    """The `RESULTS` item of an integer code (`STATUS_ORDER`; traced codes allowed)."""
    status = RESULTS.successful
    for k in range(len(STATUS_ORDER) - 1, 0, -1):
        status = RESULTS.where(code == k, STATUS_ORDER[k], status)
    return status


def coordinates_cm(params: Params, grid: Grid):
    """Cell-centre x and y of the growth grid, cm."""
    si = params.si()
    return grid.x_centres(CM_PER_M * si.length_m), grid.y_centres(CM_PER_M * si.thickness_m)


class Result(eqx.Module):
    """The outputs of `simulate` (`OUTPUTS`; docs/model.md §3), at the save times `ts`
    (s; static, so `result.index(t)` works inside `jit` and `grad`).

    Series have a leading time axis; `profile_*` are mid-section profiles across the
    thickness (axis `y_cm`); `final` holds the last 2-D fields. `post_force_max_N` and
    `surface_strain_max` are the peak post force and peak surface fibre strain of a
    loading cycle with the ECM of that time (0 in static culture). `failed` is True
    when a solve stopped early or the concentrations left their bounds; `status` says
    why (`RESULTS`) and `t_reached_s` until when the run is valid.
    """

    ts: tuple = eqx.field(static=True)
    dna_ug_per_g: jax.Array
    collagen_mg_per_g: jax.Array
    E_eff_kPa: jax.Array
    EI_N_m2: jax.Array
    post_force_max_N: jax.Array
    surface_strain_max: jax.Array
    profile_o: jax.Array
    profile_c: jax.Array
    profile_m: jax.Array
    final: State
    x_cm: jax.Array
    y_cm: jax.Array
    num_steps: jax.Array
    failed: jax.Array
    status: RESULTS
    t_reached_s: jax.Array
    params: Params

    def failure_message(self) -> str:
        """One line: what failed, the simulated time reached and a hint ('' if none)."""
        if not bool(self.failed):
            return ""
        what, hint = RESULTS[self.status].split("; ", 1)
        return f"{what}; the run is valid up to t = {float(self.t_reached_s):g} s of {self.ts[-1]:g} s; {hint}"

    def index(self, t_s: float) -> int:
        """The index of the save time closest to `t_s`; a `ValueError` for a time before
        the first save time or after the last (no value of this run is from then)."""
        ts = np.asarray(self.ts)
        slack = 1e-9 * max(abs(ts[-1]), 1.0)
        if not ts[0] - slack <= t_s <= ts[-1] + slack:
            raise ValueError(f"t_s = {t_s:g} s is outside this run's save times, {ts[0]:g} to {ts[-1]:g} s")
        return int(np.argmin(np.abs(ts - t_s)))

    def contents(self) -> tuple[dict, dict]:
        """What `to_xarray` and a run's result.nc hold, as NumPy arrays and plain values:
        {name: (dims, values, attrs)} (the coordinates time_s, x_cm and y_cm first), with
        units in each variable's attributes, and the dataset's attributes (the
        parameters, the solver's steps and status)."""
        coords = {
            "time_s": (("time_s",), np.asarray(self.ts), dict(units="s", long_name="time since seeding")),
            "x_cm": (("x_cm",), np.asarray(self.x_cm), dict(units="cm", long_name="position along the strip (cell centre)")),
            "y_cm": (("y_cm",), np.asarray(self.y_cm), dict(units="cm", long_name="position across the thickness (cell centre)")),
        }
        values = {k: np.asarray(getattr(self, k)) for k in SERIES} | {k: np.asarray(getattr(self.final, k)) for k in ("o", "c", "m")}
        variables = {k: (OUTPUTS[k].dims, v, dict(units=OUTPUTS[k].unit, long_name=OUTPUTS[k].description)) for k, v in values.items()}
        attrs = self.params.as_dict() | dict(
            solver_steps=int(np.asarray(self.num_steps)),
            solver_failed=int(bool(np.asarray(self.failed))),
            status=RESULTS[self.status] or "successful",
            t_reached_s=float(np.asarray(self.t_reached_s)),
        )
        return coords | variables, attrs

    def to_xarray(self):
        """An `xarray.Dataset` of `contents`: units in each variable's attributes, the
        parameters in the dataset's."""
        import xarray as xr

        variables, attrs = self.contents()
        return xr.Dataset(variables, attrs=attrs)


def observe(y: State, params: Params, grid: Grid) -> dict:
    """The `Result` series that a growth state determines (`OUTPUTS[...].compute`)."""
    return {k: o.compute(y, params, grid) for k, o in OUTPUTS.items() if o.compute is not None}


BOUNDS_TOL = 1e-4
"""How far concentrations may leave their bounds before a run is marked failed."""


def out_of_bounds(series: dict, params: Params, tol: float = BOUNDS_TOL):
    """Per save time: a profile is non-finite or leaves its bounds by more than `tol`."""
    o, c, m = series["profile_o"], series["profile_c"], series["profile_m"]
    bad = ~(jnp.isfinite(o) & jnp.isfinite(c) & jnp.isfinite(m))
    bad |= (o < -tol) | (c < -tol) | (m < -tol) | (m > 1 + tol) | (c > params.c_max * (1 + tol))
    return jnp.any(bad, axis=-1) | ~jnp.isfinite(series["collagen_mg_per_g"])
