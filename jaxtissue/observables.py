"""What is compared with experiment (MODEL.md §3): bulk assays, mid-section profiles and
the flexural rigidity, from a growth `State`."""

from __future__ import annotations

import jax.numpy as jnp

from .grid import Grid
from .growth import State
from .params import Params


def dna_ug_per_g(y: State, p: Params):
    """DNA assay, µg/g wet weight: 536 × mean(c) (A.24, §3)."""
    return p.dna_ug_g_per_c * jnp.mean(y.c, axis=(-2, -1))


def collagen_mg_per_g(y: State, p: Params):
    """Collagen assay, mg/g wet weight: 108.3 × mean(m) (A.24, §3)."""
    return p.rho_m_max_mg_g * jnp.mean(y.m, axis=(-2, -1))


def mid_profile(field, grid: Grid):
    """A field's transmural profile at the mid-section x = 0 (linear in x)."""
    return jnp.einsum("i,...ij->...j", grid.mid_weights(), field)


def flexural_rigidity_N_m2(y: State, p: Params, grid: Grid):
    """EI at the mid-section, N·m² (A.25, no strain stiffening):
    EI = E_s h³ d/12 + Ē_m0 d ∫ y² ρ_m(0, y) dy, ρ_m = 108.3e3 m µg/g,
    integrating y² exactly over each cell of the piecewise-constant field."""
    h = p.thickness_mm * 1e-3
    d = p.depth_mm * 1e-3
    faces = grid.y_faces(h)  # metres
    y2_cell = (faces[1:] ** 3 - faces[:-1] ** 3) / 3.0
    rho_m = p.rho_m_max_mg_g * 1e3 * mid_profile(y.m, grid)  # µg/g ww
    scaffold = p.E_s_kPa * 1e3 * h**3 * d / 12.0
    ecm = p.E_m0_kPa_per_ug_g * 1e3 * d * jnp.sum(y2_cell * rho_m, axis=-1)
    return scaffold + ecm


def effective_modulus_kPa(EI_N_m2, p: Params):
    """E_eff = 12 EI/(h³ d), kPa: the homogeneous beam's modulus (§3, §6)."""
    h = p.thickness_mm * 1e-3
    d = p.depth_mm * 1e-3
    return 12.0 * EI_N_m2 / (h**3 * d) / 1e3
