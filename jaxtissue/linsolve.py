"""The structured linear algebra of the growth system's implicit steps (MODEL.md §9).

A linearly implicit step solves `(a I − J) u = r` with `a = 1/(γ h)`. The growth
Jacobian couples o to its four neighbours (diffusion, advection) and the three species
only pointwise, so:

1. **Probe** `J` with a few coloured JVPs (3 colours in 1-D, 5 in 2-D: no two cells of
   a 5-point stencil share one) instead of one JVP per unknown.
2. **Eliminate** c and m pointwise (a Schur complement): what is left is a 5-point
   operator on o alone.
3. **Solve** it: in 1-D (`nx = 1`) the Thomas algorithm, factored once per step and
   reused by every stage (a `lax.scan` along y: under `vmap` each row is one vector
   operation over the batch, 3× faster than batched LAPACK `gtsv`). In 2-D either a
   block-tridiagonal (block Thomas) elimination along x with ny × ny blocks, or — on
   the strip's grids, whose cells are far longer than thick — a few sweeps of line
   relaxation: Thomas solves across the thickness with the weak x-coupling lagged
   (`line_sweeps`), about 2× cheaper per step than the block elimination.

A fixed number of sweeps from zero is a fixed linear map M, used by every stage: the
W-method then runs with J̃' = a I − M⁻¹. It keeps its order as h → 0 for any J̃, but at
stiff step sizes the error left by the sweeps (≤ ρᵏ, `line_sweeps`) enters the local
error, which the step control sees; `line_sweeps` keeps it ≤ 1 % (the default flex
run takes the same 679 steps as with block elimination, its 3-week values agree to
1e-8; `tests/test_solver.py` shows the order lost with too few sweeps).

The approximation `J̃` kept here drops the O2-diffusivity's dependence on m and the
neighbour couplings of c (cell motility/chemotaxis) — weak or, with the paper's
D_c = χ = 0, absent. The integrator is a Rosenbrock-W method, whose order (as h → 0)
does not depend on the Jacobian being exact (see `solver.py`).
"""

from __future__ import annotations

import math

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from ._types import Field
from .growth import State

# the 5-point stencil, (di, dj) offsets in (x, y)
_OFFSETS = {"south": (0, -1), "north": (0, 1), "west": (-1, 0), "east": (1, 0)}


def colouring(nx: int, ny: int) -> np.ndarray:
    """A colour per cell such that the cells of any 5-point stencil differ in colour."""
    i, j = np.meshgrid(np.arange(nx), np.arange(ny), indexing="ij")
    return (j % 3) if nx == 1 else (i + 2 * j) % 5


def _neighbour_colours(col: np.ndarray):
    """For each stencil offset: the neighbour's colour (0 where outside) and a mask."""
    nx, ny = col.shape
    out = {}
    for name, (di, dj) in _OFFSETS.items():
        padded = np.full((nx + 2, ny + 2), -1)
        padded[1:-1, 1:-1] = col
        shifted = padded[1 + di : 1 + di + nx, 1 + dj : 1 + dj + ny]
        out[name] = (np.maximum(shifted, 0), shifted >= 0)
    return out


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

    @classmethod
    def probe(cls, jvp, shape) -> "GrowthJacobian":
        """Build J̃ from `jvp(State) -> State` with 2K + 1 JVPs (K colours)."""
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
        r_c = batched(State(o=zeros, c=masks, m=zeros))  # columns of J for c
        r_m = jvp(State(o=zeros[0], c=zeros[0], m=jnp.ones(shape)))  # m is pointwise
        nbr = _neighbour_colours(col)
        oo = {
            name: jnp.where(mask, _pick(r_o.o, colours), 0.0)
            for name, (colours, mask) in nbr.items()
        }
        return cls(
            oo_diag=_pick(r_o.o, col),
            oo_south=oo["south"],
            oo_north=oo["north"],
            oo_west=oo["west"],
            oo_east=oo["east"],
            oc=_pick(r_c.o, col),
            co=_pick(r_o.c, col),
            cc=_pick(r_c.c, col),
            mo=_pick(r_o.m, col),
            mc=_pick(r_c.m, col),
            mm=r_m.m,
        )

    def factor(self, a, sweeps: int = 0) -> "ShiftedFactor":
        """Factor `a I − J̃` once; the result solves it for many right-hand sides
        (2-D: `sweeps` of line relaxation, 0 = block elimination; see `FivePoint.factor`)."""
        inv_cc = 1.0 / (a - self.cc)
        diag = a - self.oo_diag - self.oc * self.co * inv_cc
        o_op = FivePoint(diag, -self.oo_south, -self.oo_north, -self.oo_west, -self.oo_east)
        return ShiftedFactor(jac=self, a=a, inv_cc=inv_cc, o_factor=o_op.factor(sweeps))


class FivePoint(eqx.Module):
    """A 5-point operator on the grid: (A u)_ij = diag u_ij + south u_i,j−1 + north
    u_i,j+1 + west u_i−1,j + east u_i+1,j (neighbours outside the grid are absent)."""

    diag: Field
    south: Field
    north: Field
    west: Field
    east: Field

    def __call__(self, u: Field) -> Field:
        z = jnp.zeros_like(u[:, :1])
        up = jnp.concatenate([u[:, 1:], z], axis=1)
        down = jnp.concatenate([z, u[:, :-1]], axis=1)
        return self.diag * u + self.south * down + self.north * up + self.x_coupling(u)

    def x_coupling(self, u: Field) -> Field:
        """The west/east terms of the operator alone."""
        zx = jnp.zeros_like(u[:1])
        return self.west * jnp.concatenate([zx, u[:-1]], axis=0) + self.east * jnp.concatenate([u[1:], zx], axis=0)

    def factor(self, sweeps: int = 0) -> "FivePointFactor":
        """Thomas factors along y; in 2-D with `sweeps` > 0 they serve line relaxation
        (`FivePointFactor.solve`), with 0 the block-Thomas inverses along x."""
        nx = self.diag.shape[0]
        if nx == 1 or sweeps > 0:
            return FivePointFactor(op=self, block_inverses=None, thomas=thomas_factor(self.south, self.diag, self.north),
                                   sweeps=1 if nx == 1 else sweeps)
        blocks = jax.vmap(_tridiagonal_matrix)(self.south, self.diag, self.north)

        def eliminate(prev_inv, inputs):
            block, west, east_prev = inputs
            inv = jnp.linalg.inv(block - west[:, None] * prev_inv * east_prev[None, :])
            return inv, inv

        east_prev = jnp.concatenate([jnp.zeros_like(self.east[:1]), self.east[:-1]], axis=0)
        _, invs = jax.lax.scan(eliminate, jnp.zeros_like(blocks[0]), (blocks, self.west, east_prev))
        return FivePointFactor(op=self, block_inverses=invs)


class Thomas(eqx.Module):
    """Tridiagonal systems along the last axis, factored (`thomas_factor`): the bands
    (`sub[..., 0]` and `sup[..., -1]` zero) and the elimination's pivots `inv` and
    multipliers `c`, all stored row-major (the system's axis first)."""

    sub: jax.Array
    diag: jax.Array
    sup: jax.Array
    inv: jax.Array
    c: jax.Array


def _rows(x):
    return jnp.moveaxis(x, -1, 0)


def thomas_factor(sub, diag, sup) -> Thomas:
    """Thomas elimination of tridiagonal systems along the last axis (`sub[..., 0]` and
    `sup[..., -1]` are ignored), for `thomas_solve`: a `lax.scan` over the rows, each
    row one vector operation over the leading axes (no pivoting: for diagonally
    dominant operators). The elimination itself is never differentiated: `thomas_solve`
    carries the derivatives with respect to the bands."""

    def eliminate(c_prev, row):
        lower, d, upper = row
        inv = 1.0 / (d - lower * c_prev)
        return upper * inv, (inv, upper * inv)

    lower = _rows(jnp.asarray(sub).at[..., 0].set(0.0))
    upper = _rows(jnp.asarray(sup).at[..., -1].set(0.0))
    diag = _rows(jnp.asarray(diag))
    _, (inv, c) = jax.lax.scan(eliminate, jnp.zeros_like(diag[0]), jax.lax.stop_gradient((lower, diag, upper)))
    return Thomas(sub=lower, diag=diag, sup=upper, inv=inv, c=c)


def _sweeps(lower, inv, c, r):
    """Forward elimination and back substitution with the factors (row-major)."""

    def forward(z_prev, row):
        ri, li, ii = row
        z = (ri - li * z_prev) * ii
        return z, z

    _, z = jax.lax.scan(forward, jnp.zeros_like(r[0]), (r, lower, inv))

    def backward(x_next, row):
        zi, ci = row
        x = zi - ci * x_next
        return x, x

    _, x = jax.lax.scan(backward, jnp.zeros_like(r[0]), (z, c), reverse=True)
    return x


def _band_product(bands, x):
    """The tridiagonal operator with (row-major) bands (sub, diag, sup) applied to x."""
    sub, diag, sup = bands
    z = jnp.zeros_like(x[:1])
    return diag * x + sub * jnp.concatenate([z, x[:-1]]) + sup * jnp.concatenate([x[1:], z])


@jax.custom_jvp
def _thomas_solve(bands, factors, r):
    return _sweeps(bands[0], *factors, r)


def _thomas_solve_jvp(primals, tangents):
    """x = A⁻¹ r: ẋ = A⁻¹ (ṙ − Ȧ x), one more solve with the same factors (reverse mode
    transposes it: no derivative of the elimination is ever formed or stored). The
    factors' tangents are ignored: they follow from the bands'."""
    bands, factors, r = primals
    dbands, _, dr = tangents
    x = _sweeps(bands[0], *factors, r)
    zero = lambda t: isinstance(t, jax.custom_derivatives.SymbolicZero)  # noqa: E731
    if zero(dr) and all(map(zero, dbands)):
        return x, jnp.zeros_like(x)
    dA = tuple(jnp.zeros_like(x) if zero(d) else d for d in dbands)
    rhs = (jnp.zeros_like(x) if zero(dr) else dr) - _band_product(dA, x)
    return x, _sweeps(bands[0], *factors, rhs)


_thomas_solve.defjvp(_thomas_solve_jvp, symbolic_zeros=True)


def thomas_solve(factor: Thomas, r):
    """Solve the factored systems for right-hand sides `r` (same shape as `diag`).
    Differentiable in `r` and in the bands the factor was built from."""
    x = _thomas_solve((factor.sub, factor.diag, factor.sup), (factor.inv, factor.c), _rows(r))
    return jnp.moveaxis(x, 0, -1)


def _tridiagonal_matrix(sub, diag, sup):
    n = diag.shape[0]
    return jnp.diag(diag) + jnp.diag(sub[1:], -1) + jnp.diag(sup[:-1], 1)


class FivePointFactor(eqx.Module):
    """A factored `FivePoint` operator: Thomas factors along y (1-D, or 2-D line
    relaxation) or block-Thomas inverses (2-D)."""

    op: FivePoint
    block_inverses: jax.Array | None
    thomas: Thomas | None = None
    sweeps: int = eqx.field(static=True, default=1)

    def solve(self, r: Field) -> Field:
        op = self.op
        if self.thomas is not None:  # line Jacobi from u = 0: u ← Y⁻¹ (r − X u), `sweeps` times
            u = thomas_solve(self.thomas, r)
            for _ in range(self.sweeps - 1):
                u = thomas_solve(self.thomas, r - op.x_coupling(u))
            return u
        invs = self.block_inverses

        def forward(z_prev, inputs):
            inv, west, ri = inputs
            z = inv @ (ri - west * z_prev)
            return z, z

        _, z = jax.lax.scan(forward, jnp.zeros_like(r[0]), (invs, op.west, r))

        def backward(x_next, inputs):
            inv, east, zi = inputs
            x = zi - inv @ (east * x_next)
            return x, x

        _, x = jax.lax.scan(backward, jnp.zeros_like(r[0]), (invs, op.east, z), reverse=True)
        return x


class ShiftedFactor(eqx.Module):
    """`a I − J̃`, factored: `solve` eliminates c and m pointwise around the O2 solve."""

    jac: GrowthJacobian
    a: jax.Array
    inv_cc: Field
    o_factor: FivePointFactor

    def solve(self, r):
        j = self.jac
        o = self.o_factor.solve(r.o + j.oc * self.inv_cc * r.c)
        c = self.inv_cc * (r.c + j.co * o)
        m = (r.m + j.mo * o + j.mc * c) / (self.a - j.mm)
        return State(o=o, c=c, m=m)


def line_sweeps(nx: int, thickness_over_cell_length: float, target: float = 0.01, most: int = 8) -> int:
    """Sweeps of line relaxation for the 2-D O2 solve, or 0 for block elimination.

    Line Jacobi (Thomas solves across the thickness, the x-coupling lagged) contracts
    the error by at most ρ = 2r²/(2r² + π²), r = h/Δx: the mode that alternates
    between columns and is smoothest across the thickness, where the lagged coupling
    2D/Δx² meets the smallest transverse rate π²D/h². k sweeps leave ρᵏ. Returns the
    least even k with ρᵏ ≤ `target`, or 0 if that is more than `most` (cells too short
    for the sweeps to pay). Even k: the residual error has no negative eigenvalues
    (symmetric operator), so the effective J̃ errs on the stiff side.
    """
    if nx == 1:
        return 0
    r = thickness_over_cell_length
    rho = 2 * r**2 / (2 * r**2 + np.pi**2)
    k = 2 * max(1, math.ceil(math.log(target) / math.log(rho) / 2))
    return k if k <= most else 0
