"""The growth system's unknowns and the lumped transport it is given (docs/model.md §2,
§5): non-dimensional fields on the growth grid."""

from __future__ import annotations

import equinox as eqx
import jax.numpy as jnp

from ._custom_types import Field
from .grid import Grid
from .params import Coefficients


class State(eqx.Module):
    """Non-dimensional fields on the growth grid (docs/model.md §2)."""

    o: Field
    c: Field
    m: Field

    @classmethod
    def initial(cls, coeffs: Coefficients, grid: Grid) -> "State":
        """o = o_ext, c = 1, m = 0 everywhere (docs/model.md §2)."""
        ones = jnp.ones(grid.shape)
        return cls(o=coeffs.o_ext * ones, c=ones, m=0.0 * ones)


class Transport(eqx.Module):
    """Lumped transport of a conditioning cycle, frozen over a growth interval (§5):
    cell-centred velocity (cm/s) and an added O2 dispersivity (cm²/s). A part that is
    None is absent (not computed with zeros): the dispersive rule has no velocity."""

    vx: Field | None = None
    vy: Field | None = None
    dispersion: Field | None = None

    def __check_init__(self):
        if (self.vx is None) != (self.vy is None):
            raise ValueError("Transport needs both velocity components vx and vy, or neither")
