"""What is compared with experiment (docs/model.md §3): bulk assays, mid-section
profiles and the flexural rigidity, each a function `(state, params, grid)` of a growth
`State` (the output registry, `result.OUTPUTS`, lists them with their units)."""

from __future__ import annotations

import jax.numpy as jnp

from .grid import Grid
from .params import Params
from .state import State


def dna_ug_per_g(y: State, p: Params, grid: Grid):
    """DNA assay, µg/g wet weight: 536 × mean(c) (A.24, §3)."""
    return p.dna_ug_g_per_c * jnp.mean(y.c, axis=(-2, -1))


def collagen_mg_per_g(y: State, p: Params, grid: Grid):
    """Collagen assay, mg/g wet weight: 108.3 × mean(m) (A.24, §3)."""
    return p.rho_m_max_mg_g * jnp.mean(y.m, axis=(-2, -1))


def mid_profile(field, grid: Grid):
    """A field's transmural profile at the mid-section x = 0 (linear in x)."""
    return jnp.einsum("i,...ij->...j", grid.mid_weights(), field)


def flexural_rigidity_N_m2(y: State, p: Params, grid: Grid):
    """EI at the mid-section, N·m² (A.25, no strain stiffening):
    EI = E_s h³ d/12 + Ē_m0 d ∫ y² ρ_m(0, y) dy, ρ_m = 108.3e3 m µg/g,
    integrating y² exactly over each cell of the piecewise-constant field."""
    si = p.si()
    h, d = si.thickness_m, si.depth_m
    faces = grid.y_faces(h)  # metres
    y2_cell = (faces[1:] ** 3 - faces[:-1] ** 3) / 3.0
    rho_m = si.rho_m_max_ug_g * mid_profile(y.m, grid)  # µg/g ww
    scaffold = si.E_s_Pa * h**3 * d / 12.0
    ecm = si.E_m0_Pa_per_ug_g * d * jnp.sum(y2_cell * rho_m, axis=-1)
    return scaffold + ecm


def effective_modulus_kPa(y: State, p: Params, grid: Grid):
    """E_eff = 12 EI/(h³ d), kPa: the homogeneous beam's modulus (§3, §6)."""
    si = p.si()
    return 12.0 * flexural_rigidity_N_m2(y, p, grid) / (si.thickness_m**3 * si.depth_m) / 1e3
