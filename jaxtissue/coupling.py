"""The two time scales (docs/model.md §5): ECM → beam properties; one loading cycle → the
lumped transport that the growth model sees, frozen over a growth interval.

Two lumping rules, both a function of the cycle's seepage velocity v_f scaled by the
lumping constant C:

* `"dispersive"` (default): oscillatory pore flow mixes the medium, an added O2
  dispersivity D_disp = C · h · (1/T) ∫₀ᵀ |v_f,y| dt (isotropic, cm²/s). It reproduces
  the experimental fact that flexure enhances nutrient supply.
* `"paper"`: the paper's literal rule (eq. 2.15), an advective velocity
  v̂ = (C/T) ∫₀ᵀ v_f dt, signed, over one cycle from rest. Its mean over a nearly
  periodic cycle nearly cancels, and what is left is symmetric about the mid-plane and
  can *reduce* supply (docs/model.md §5; `jaxtissue reproduce` reports both).

The beam works in SI units (`Params.si()`), the growth grid in cm and cm/s.
"""

from __future__ import annotations

import jax.numpy as jnp
import numpy as np

from .beam import Beam, BeamGrid, Geometry, Material
from .grid import Grid
from .params import CM_PER_M, Params, concrete_value
from .state import State, Transport


PAPER_RULE_C = 70.0
"""The paper's lumping constant, for its literal rule (docs/model.md §5)."""


def with_rule_constant(params: Params, lumping: str) -> tuple[Params, str | None]:
    """`params` with the lumping constant of the rule `lumping`: the paper's rule takes
    the paper's C = 70 unless `lumping_C` was changed from the dispersive default
    (docs/model.md §5). Returns the parameters and, when C was switched, why."""
    default = Params().lumping_C
    C = concrete_value(params.lumping_C)
    if lumping != "paper" or C is None or np.ndim(C) or float(C) != default:
        return params, None
    why = (f"lumping_C = {PAPER_RULE_C:g}: the paper's rule uses the paper's C (docs/model.md §5), not the dispersive "
           f"rule's default {default:g}; set lumping_C to choose another")
    return params.replace(lumping_C=PAPER_RULE_C), why


def _to_x(values, x_from, x_to):
    """Interpolate per-thickness-cell values (n, ny) linearly along the strip from the
    points `x_from` to `x_to` (increasing NumPy arrays of x/L, constant beyond the ends).
    Both sets of points scale with the strip's length, so each point's two neighbours
    and weights are fixed: no search in the program."""
    right = np.clip(np.searchsorted(x_from, x_to), 1, len(x_from) - 1)
    w = np.clip((x_to - x_from[right - 1]) / (x_from[right] - x_from[right - 1]), 0.0, 1.0)[:, None]
    return values[right - 1] * (1.0 - w) + values[right] * w


def _cells(grid: Grid) -> np.ndarray:
    return (np.arange(grid.nx) + 0.5) / grid.nx  # cell centres, x/L


def _nodes(beam_grid: BeamGrid) -> np.ndarray:
    return np.linspace(0.0, 1.0, beam_grid.n_segments + 1)  # the beam's nodes (`BeamGrid.n_segments` equal segments), x/L


def beam_from_ecm(y: State, p: Params, grid: Grid, beam_grid: BeamGrid, pins: str, fibre_law: str) -> Beam:
    """The beam whose sections carry the current ECM (growth cells → interior nodes)."""
    si = p.si()
    x_nodes = _nodes(beam_grid)[1:-1]
    if grid.nx == 1:  # uniform along the strip
        m_sections = jnp.broadcast_to(y.m, (x_nodes.shape[0], grid.ny))
    else:
        m_sections = _to_x(y.m, _cells(grid), x_nodes)
    return Beam(Geometry.from_params(si, pins), Material.from_ecm(m_sections, si), beam_grid, fibre_law=fibre_law)


def lumped_transport(cycle, p: Params, grid: Grid, beam_grid: BeamGrid, rule: str, pins: str) -> Transport:
    """The cycle's lumped transport on the growth grid (module docstring), cm/s, cm²/s."""
    si = p.si()

    def to_growth(sections):  # (n_segments − 1, ny) in m/s → (nx, ny) in cm/s
        ends = jnp.zeros_like(sections[:1]) if pins == "centroid" else None
        first = ends if ends is not None else sections[:1]
        last = ends if ends is not None else sections[-1:]
        nodes = jnp.concatenate([first, sections, last]) * CM_PER_M
        return _to_x(nodes, _nodes(beam_grid), _cells(grid))

    C = p.lumping_C
    if rule == "dispersive":
        h_cm = si.thickness_m * CM_PER_M
        return Transport(dispersion=C * h_cm * to_growth(cycle.mean_abs_vy))
    return Transport(vx=C * to_growth(cycle.mean_vx), vy=C * to_growth(cycle.mean_vy))
