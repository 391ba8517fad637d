"""The structured finite-volume grid over the reference strip Ω (docs/model.md §1).

Cells are uniform: `nx` along the length x ∈ (−L/2, L/2), `ny` across the thickness
y ∈ (−h/2, h/2). `nx = 1` is the 1-D transmural problem. Sizes are static; the
spacings follow from the (differentiable) geometry in `Coefficients`.
"""

from __future__ import annotations

import equinox as eqx
import jax.numpy as jnp


DEFAULT_SHAPES = {"static": (1, 40), "flex": (50, 40)}
"""The default growth grid (nx, ny) of each regime: static culture is 1-D across the
thickness (docs/model.md §2); flexure needs x-resolution where the curvature varies."""


class Grid(eqx.Module):
    """Cell counts of the growth grid: `nx` along the length, `ny` across the thickness."""

    nx: int = eqx.field(static=True, default=1)
    ny: int = eqx.field(static=True, default=40)

    def __check_init__(self):
        for name, value, low in (("nx", self.nx, 1), ("ny", self.ny, 3)):
            if not isinstance(value, int) or isinstance(value, bool) or value < low:
                raise ValueError(f"grid {name} = {value!r} must be an integer >= {low}")

    @classmethod
    def default(cls, regime: str) -> "Grid":
        """The default grid of a regime ("static" or "flex", `DEFAULT_SHAPES`)."""
        nx, ny = DEFAULT_SHAPES[regime]
        return cls(nx=nx, ny=ny)

    @property
    def shape(self) -> tuple[int, int]:
        return (self.nx, self.ny)

    def spacing(self, length_cm, thickness_cm):
        """Cell sizes (dx, dy) in cm."""
        return length_cm / self.nx, thickness_cm / self.ny

    def x_centres(self, length_cm):
        """Cell-centre x in cm, −L/2 < x < L/2."""
        return (jnp.arange(self.nx) + 0.5) * (length_cm / self.nx) - 0.5 * length_cm

    def y_centres(self, thickness_cm):
        """Cell-centre y in cm, −h/2 < y < h/2."""
        return (jnp.arange(self.ny) + 0.5) * (thickness_cm / self.ny) - 0.5 * thickness_cm

    def y_faces(self, thickness_cm):
        """The ny + 1 face positions across the thickness, in cm."""
        return jnp.arange(self.ny + 1) * (thickness_cm / self.ny) - 0.5 * thickness_cm

    def mid_weights(self):
        """Weights over x that interpolate a cell field linearly to the mid-section x = 0."""
        w = jnp.zeros(self.nx)
        if self.nx % 2:
            return w.at[self.nx // 2].set(1.0)
        return w.at[self.nx // 2 - 1].set(0.5).at[self.nx // 2].set(0.5)
