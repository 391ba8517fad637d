"""What protocol optimisation can maximise or minimise, and limit: small functions of a
`Result` (and the conditioning dose), each with its sense, label and unit."""

from __future__ import annotations

from typing import Callable, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from ..protocol import Protocol


def _core_fraction(result):
    """The fraction of each mid-section cell inside the core, the middle third of the
    thickness (|y| < h/6; exact overlap, so independent of the grid's alignment)."""
    y = result.y_cm
    dy = y[1] - y[0]
    sixth = (y[-1] - y[0] + dy) / 6.0
    return jnp.clip(jnp.minimum(y + dy / 2, sixth) - jnp.maximum(y - dy / 2, -sixth), 0.0, None) / dy


def _core_and_periphery_m(result):
    """Mean ECM m in the core and in the rest of the mid-section at the end."""
    w, m = _core_fraction(result), result.profile_m[-1]
    return jnp.sum(w * m) / jnp.sum(w), jnp.sum((1 - w) * m) / jnp.sum(1 - w)


def total_collagen(result, dose):
    """Collagen assay at the end of culture, mg/g ww (docs/model.md §3)."""
    return result.collagen_mg_per_g[-1]


def flexural_rigidity(result, dose):
    """EI at the mid-section at the end of culture, N·m² (A.25)."""
    return result.EI_N_m2[-1]


def core_collagen(result, dose):
    """Collagen in the core (middle third of the thickness at the mid-section) at the
    end of culture, mg/g ww."""
    return result.params.rho_m_max_mg_g * _core_and_periphery_m(result)[0]


def core_homogeneity(result, dose):
    """Core/periphery ratio of ECM at the mid-section at the end of culture (1 =
    uniform; static culture leaves a poor core)."""
    core, periphery = _core_and_periphery_m(result)
    return core / periphery


def least_conditioning(result, dose):
    """The conditioning dose: Σ over coupling intervals of cycles × post displacement,
    10⁶ mm (the paper's 1 Hz / 5 mm for 3 weeks: 9.07). Minimised, with a floor on EI."""
    return dose


class Objective(NamedTuple):
    fn: Callable
    sense: int  # +1: maximise, −1: minimise
    label: str
    unit: str


OBJECTIVES = {
    "total_collagen": Objective(total_collagen, +1, "collagen at the end of culture", "mg/g"),
    "flexural_rigidity": Objective(flexural_rigidity, +1, "EI at the end of culture", "N m^2"),
    "core_collagen": Objective(core_collagen, +1, "core collagen (middle third) at the end of culture", "mg/g"),
    "core_homogeneity": Objective(core_homogeneity, +1, "core/periphery ECM ratio at the end of culture", "1"),
    "least_conditioning": Objective(least_conditioning, -1, "conditioning dose (cycles x post displacement)", "1e6 mm"),
}


class Constraint(NamedTuple):
    value: Callable  # Result -> scalar
    kind: str  # "ceiling" (value <= limit) or "floor" (value >= limit)
    label: str
    unit: str


CONSTRAINTS = {
    "post_force_max_N": Constraint(lambda r: jnp.max(r.post_force_max_N), "ceiling", "peak post force over the culture", "N"),
    "surface_strain_max": Constraint(lambda r: jnp.max(r.surface_strain_max), "ceiling", "peak surface fibre strain over the culture", "1"),
    "EI_min_N_m2": Constraint(lambda r: r.EI_N_m2[-1], "floor", "EI at the end of culture", "N m^2"),
}

def conditioning_dose(protocol: Protocol, bounds_s) -> jax.Array:
    """Σ_k (t_k+1 − t_k)/T_k × u_k over the coupling intervals, in 10⁶ mm."""
    t0 = jnp.asarray(bounds_s[:-1])
    stages = [protocol.at(t) for t in np.asarray(bounds_s[:-1])]
    per = jnp.stack([q.post_displacement_mm / q.period_s for q in stages])
    return jnp.sum((jnp.asarray(bounds_s[1:]) - t0) * per) / 1e6
