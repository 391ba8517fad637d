"""The structured approximation J̃ of the growth Jacobian and the factor of a I − J̃
that each Rosenbrock-W step solves with (docs/numerics.md).

The growth right-hand side (docs/model.md §2) couples o to its four neighbours
(diffusion, advection) and the three species only pointwise, so:

1. **Probe** J with a few coloured JVPs (`numerics.colouring`: 3 colours in 1-D, 5 in
   2-D) instead of one JVP per unknown; c's columns with one JVP where c couples only
   pointwise (no cell flux: D_c = χ = 0).
2. **Eliminate** c and m pointwise (a Schur complement): what is left is a 5-point
   operator on o alone.
3. **Solve** it with `numerics.FivePoint` (Thomas in 1-D; line relaxation or
   multigrid in 2-D, O(cells)), factored once per step and reused by every stage.

J̃ drops the O2 diffusivity's dependence on m and the neighbour couplings of c (cell
motility, chemotaxis): weak or, with the paper's D_c = χ = 0, absent. A W-method's
order does not depend on J̃ being exact. With `exact_m` the m columns are probed by
colours too, and m's 5-point coupling into o (D_o(m)) is kept: still eliminated pointwise
(m and c at a cell depend on o at that cell only), the O2 operator stays 5-point, and
without a cell flux J̃ = J (the exact Jacobian a Rosenbrock method that is not a
W-method needs, `numerics.Rodas4P2`).
"""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
import jax.tree_util as jtu
import numpy as np

from ._custom_types import Field
from .numerics import FivePoint, FivePointFactor, colouring, neighbour_colours
from .state import State


def _pick(responses, colours: np.ndarray):
    """responses[colours[i, j], i, j] (a masked sum: constant masks, no gather indices
    held as buffers)."""
    return sum(jnp.where(colours == k, responses[k], 0.0) for k in range(responses.shape[0]))


class GrowthJacobian(eqx.Module):
    """The blocks of J̃ (see module docstring), every one a field on the grid."""

    oo_diag: Field
    oo_south: Field
    oo_north: Field
    oo_west: Field
    oo_east: Field
    oc: Field
    co: Field
    cc: Field
    mo: Field
    mc: Field
    mm: Field
    om: FivePoint | None = None
    """∂(do/dt)/∂m on the 5-point stencil (through D_o(m)); None where J̃ drops it."""

    @classmethod
    def probe(cls, jvp, shape, pointwise_c: bool = False, exact_m: bool = False) -> "GrowthJacobian":
        """Build J̃ from `jvp(State) -> State` with 2K + 1 JVPs (K colours), or K + 2
        with `pointwise_c` (the caller's promise that c's columns have no entries off
        the diagonal blocks, as without a cell flux: one JVP finds them exactly);
        `exact_m`: m's columns by colours too (K − 1 more JVPs), `om` kept."""
        nx, ny = shape
        col = colouring(nx, ny)
        ncol = int(col.max()) + 1
        masks = jnp.asarray(col[None] == np.arange(ncol)[:, None, None], dtype=float)
        zeros = jnp.zeros_like(masks)
        # 2-D: one colour at a time; batched, the JVPs' intermediates (fluxes on the
        # faces, per colour) are a growth step's largest buffers, forward and reverse
        # (default flex run: forward 2.5 → 1.8 MiB) and the batch is no faster. 1-D:
        # batched, faster on a column of cells.
        batched = jax.vmap(jvp) if nx == 1 else (lambda t: jax.lax.map(jvp, t))
        r_o = batched(State(o=masks, c=zeros, m=zeros))  # columns of J for o
        ones, zero = jnp.ones(shape), zeros[0]
        if pointwise_c:  # all of c's columns at once: their sum is the blocks
            r_c = jvp(State(o=zero, c=ones, m=zero))
        else:  # c's columns, one colour each
            r_c = jtu.tree_map(lambda x: _pick(x, col), batched(State(o=zeros, c=masks, m=zeros)))
        nbr = neighbour_colours(col)

        def stencil(responses):  # the 5-point entries of a block probed by colours
            return {name: jnp.where(mask, _pick(responses, colours), 0.0) for name, (colours, mask) in nbr.items()}

        if exact_m:
            r_m = batched(State(o=zeros, c=zeros, m=masks))
            om = FivePoint(_pick(r_m.o, col), **stencil(r_m.o))
            mm = _pick(r_m.m, col)
        else:
            om, mm = None, jvp(State(o=zero, c=zero, m=ones)).m  # m is pointwise
        oo = stencil(r_o.o)
        return cls(
            oo_diag=_pick(r_o.o, col),
            oo_south=oo["south"],
            oo_north=oo["north"],
            oo_west=oo["west"],
            oo_east=oo["east"],
            oc=r_c.o,
            co=_pick(r_o.c, col),
            cc=r_c.c,
            mo=_pick(r_o.m, col),
            mc=r_c.m,
            mm=mm,
            om=om,
        )

    def factor(self, a, sweeps: int = 0, cycles: int = 3) -> "ShiftedFactor":
        """Factor `a I − J̃` once; the result solves it for many right-hand sides
        (2-D: `sweeps` of line relaxation, 0 = `cycles` V-cycles of multigrid; see
        `FivePoint.factor`)."""
        inv_cc = 1.0 / (a - self.cc)
        diag = a - self.oo_diag - self.oc * self.co * inv_cc
        o_op = FivePoint(diag, -self.oo_south, -self.oo_north, -self.oo_west, -self.oo_east)
        if self.om is not None:  # − om · (m's response to o): m = (r_m + mo o + mc c)/(a − mm)
            o_op = o_op.minus(self.om.times_diagonal((self.mo + self.mc * inv_cc * self.co) / (a - self.mm)))
        return ShiftedFactor(jac=self, a=a, inv_cc=inv_cc, o_factor=o_op.factor(sweeps, cycles))


class ShiftedFactor(eqx.Module):
    """`a I − J̃`, factored: `solve` eliminates c and m pointwise around the O2 solve."""

    jac: GrowthJacobian
    a: jax.Array
    inv_cc: Field
    o_factor: FivePointFactor

    def solve(self, r):
        j = self.jac
        r_o = r.o + j.oc * self.inv_cc * r.c
        if j.om is not None:
            r_o = r_o + j.om((r.m + j.mc * self.inv_cc * r.c) / (self.a - j.mm))
        o = self.o_factor.solve(r_o)
        c = self.inv_cc * (r.c + j.co * o)
        m = (r.m + j.mo * o + j.mc * c) / (self.a - j.mm)
        return State(o=o, c=c, m=m)


