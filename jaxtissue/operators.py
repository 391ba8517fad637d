"""Small pure finite-volume operators on the growth grid (axis 0 = x, axis 1 = y).

Fluxes live on faces; a boundary condition is a value: `None` means no flux through
the boundary faces, a number (or array) is a Dirichlet value imposed at the face,
half a cell from the centre. All operators are second order in space.
"""

from __future__ import annotations

import jax.numpy as jnp

from jaxtyping import Array, Float

from ._custom_types import FaceFieldX, FaceFieldY, Field


def safe_div(num, den):
    """num/den with 0 where den = 0 (finite gradients on both branches)."""
    zero = den == 0
    return jnp.where(zero, 0.0, num / jnp.where(zero, 1.0, den))


def harmonic_mean(a, b):
    """2ab/(a+b): the face coefficient of two cells in series."""
    return safe_div(2.0 * a * b, a + b)


def face_coefficient_x(coef: Field) -> FaceFieldX:
    """Diffusion coefficient on the x-faces; the two ends carry no flux (value 0)."""
    inner = harmonic_mean(coef[:-1], coef[1:])
    zero = jnp.zeros_like(coef[:1])
    return jnp.concatenate([zero, inner, zero], axis=0)


def face_coefficient_y(coef: Field) -> FaceFieldY:
    """Diffusion coefficient on the y-faces; a surface face takes its cell's value."""
    inner = harmonic_mean(coef[:, :-1], coef[:, 1:])
    return jnp.concatenate([coef[:, :1], inner, coef[:, -1:]], axis=1)


def gradient_x(u: Field, dx) -> FaceFieldX:
    """∂u/∂x on the x-faces; 0 on the two ends (no-flux posts)."""
    inner = (u[1:] - u[:-1]) / dx
    zero = jnp.zeros_like(u[:1])
    return jnp.concatenate([zero, inner, zero], axis=0)


def gradient_y(u: Field, dy, boundary) -> FaceFieldY:
    """∂u/∂y on the y-faces. `boundary=None`: 0 on the surfaces; a value: the one-sided
    half-cell difference to that Dirichlet value."""
    inner = (u[:, 1:] - u[:, :-1]) / dy
    if boundary is None:
        bottom = top = jnp.zeros_like(u[:, :1])
    else:
        bottom = (u[:, :1] - boundary) / (0.5 * dy)
        top = (boundary - u[:, -1:]) / (0.5 * dy)
    return jnp.concatenate([bottom, inner, top], axis=1)


def divergence(flux_x: Float[Array, "*batch nx_faces ny"], flux_y: Float[Array, "*batch nx ny_faces"], dx, dy) -> Field:
    """Cell-average divergence of a face flux."""
    return (flux_x[1:] - flux_x[:-1]) / dx + (flux_y[:, 1:] - flux_y[:, :-1]) / dy


def diffusion(u: Field, coef: Field, dx, dy, boundary) -> Field:
    """∇·(D ∇u) with harmonic-mean face coefficients, no flux at the ends and
    `boundary` (None or Dirichlet value) on the two surfaces."""
    fx = face_coefficient_x(coef) * gradient_x(u, dx)
    fy = face_coefficient_y(coef) * gradient_y(u, dy, boundary)
    return divergence(fx, fy, dx, dy)


def face_average_x(u: Field) -> FaceFieldX:
    """Arithmetic mean on the x-faces (the ends take their cell's value)."""
    return jnp.concatenate([u[:1], 0.5 * (u[:-1] + u[1:]), u[-1:]], axis=0)


def face_average_y(u: Field) -> FaceFieldY:
    """Arithmetic mean on the y-faces (the surfaces take their cell's value)."""
    return jnp.concatenate([u[:, :1], 0.5 * (u[:, :-1] + u[:, 1:]), u[:, -1:]], axis=1)


def van_leer(a, b):
    """Van Leer's limited slope from the two one-sided differences a, b."""
    return jnp.where(a * b > 0, safe_div(2.0 * a * b, a + b), 0.0)


def _face_states(u, ghost_lo, ghost_hi, axis, limited):
    """Left and right states on the interior faces along `axis` (MUSCL)."""
    padded = jnp.concatenate([ghost_lo, u, ghost_hi], axis=axis)
    n = u.shape[axis]
    take = lambda start, stop: jnp.take(padded, jnp.arange(start, stop), axis=axis)  # noqa: E731
    if limited:
        slope = van_leer(take(1, n + 1) - take(0, n), take(2, n + 2) - take(1, n + 1))
    else:
        slope = jnp.zeros_like(u)
    left = u + 0.5 * slope  # state on each cell's high face
    right = u - 0.5 * slope  # state on each cell's low face
    idx_l = jnp.arange(0, n - 1)
    idx_r = jnp.arange(1, n)
    return jnp.take(left, idx_l, axis=axis), jnp.take(right, idx_r, axis=axis)


def advection(u: Field, vx: Field, vy: Field, dx, dy, boundary, limited: bool = True) -> Field:
    """v·∇u for a given cell-centred velocity, in the non-conservative form
    ∇·(v u) − u ∇·v, with upwind face states (`limited`: MUSCL with van Leer's
    limiter, second order; otherwise first-order upwind).

    Pipeline: 1. velocity to faces (mean of neighbours; zero at the impervious ends,
    the surface cell's value on the surfaces); 2. scalar to faces (upwind state; the
    Dirichlet `boundary` value on the surfaces); 3. flux u·v on faces; 4. divergence
    minus u times the divergence of v.
    """
    # 1. velocity on faces
    ux = face_average_x(vx).at[0].set(0.0).at[-1].set(0.0)
    uy = face_average_y(vy)
    # 2. scalar on interior faces, upwinded
    gx_lo, gx_hi = u[:1], u[-1:]
    gy_lo = 2.0 * boundary - u[:, :1]
    gy_hi = 2.0 * boundary - u[:, -1:]
    lx, rx = _face_states(u, gx_lo, gx_hi, 0, limited)
    ly, ry = _face_states(u, gy_lo, gy_hi, 1, limited)
    sx = jnp.where(ux[1:-1] > 0, lx, rx)
    sy = jnp.where(uy[:, 1:-1] > 0, ly, ry)
    b = jnp.broadcast_to(boundary, u[:, :1].shape)
    sx = jnp.concatenate([u[:1], sx, u[-1:]], axis=0)
    sy = jnp.concatenate([b, sy, b], axis=1)
    # 3. fluxes, 4. divergence minus u div v
    div_flux = divergence(ux * sx, uy * sy, dx, dy)
    div_v = divergence(ux, uy, dx, dy)
    return div_flux - u * div_v
