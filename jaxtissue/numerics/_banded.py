"""Banded linear algebra on a structured grid: tridiagonal (Thomas) solves along the
last axis, 5-point operators solved by line relaxation or multigrid, and the
colouring that probes a 5-point Jacobian with a few JVPs (docs/numerics.md). Every
solve costs O(cells).

* `thomas_factor` / `thomas_solve`: the Thomas algorithm for many systems at once, a
  `lax.scan` over the rows (under `vmap` each row is one vector operation over the
  batch, 3× faster than batched LAPACK `gtsv`), differentiated as a linear solve.
* `FivePoint.factor(sweeps)`: along y the Thomas factors; in 2-D either `sweeps` of
  line relaxation (the x-coupling lagged, `line_sweeps` chooses how many) or, with
  `sweeps = 0`, V-cycles of a multigrid that coarsens along x only (columns in pairs
  down to one column, where Thomas is exact), with zebra line relaxation along y:
  robust for any cell aspect ratio, as line relaxation alone is not.
* `colouring`: 3 colours in 1-D, 5 in 2-D, so that no two cells of a 5-point stencil
  share one.

A fixed number of sweeps or cycles from zero is a fixed linear map M: a W-method that
uses it runs with J̃' = a I − M⁻¹, which keeps its order as h → 0; `line_sweeps` keeps
the error the sweeps leave ≤ 1 %, and 3 V-cycles leave ≤ 2 % for any aspect ratio
(`tests/test_solver.py`), so that neither costs order at stiff step sizes.
"""

from __future__ import annotations

import math

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from .._custom_types import Field

# the 5-point stencil, (di, dj) offsets in (x, y)
_OFFSETS = {"south": (0, -1), "north": (0, 1), "west": (-1, 0), "east": (1, 0)}


def colouring(nx: int, ny: int) -> np.ndarray:
    """A colour per cell such that the cells of any 5-point stencil differ in colour."""
    i, j = np.meshgrid(np.arange(nx), np.arange(ny), indexing="ij")
    return (j % 3) if nx == 1 else (i + 2 * j) % 5


def neighbour_colours(col: np.ndarray):
    """For each stencil offset: the neighbour's colour (0 where outside) and a mask."""
    nx, ny = col.shape
    out = {}
    for name, (di, dj) in _OFFSETS.items():
        padded = np.full((nx + 2, ny + 2), -1)
        padded[1:-1, 1:-1] = col
        shifted = padded[1 + di : 1 + di + nx, 1 + dj : 1 + dj + ny]
        out[name] = (np.maximum(shifted, 0), shifted >= 0)
    return out


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

    def times_diagonal(self, w: Field) -> "FivePoint":
        """The operator A diag(w): each coupling scaled by w at the cell it reaches."""
        z, zx = jnp.zeros_like(w[:, :1]), jnp.zeros_like(w[:1])
        return FivePoint(
            self.diag * w,
            self.south * jnp.concatenate([z, w[:, :-1]], axis=1),
            self.north * jnp.concatenate([w[:, 1:], z], axis=1),
            self.west * jnp.concatenate([zx, w[:-1]], axis=0),
            self.east * jnp.concatenate([w[1:], zx], axis=0),
        )

    def minus(self, other: "FivePoint") -> "FivePoint":
        """A − B, entry by entry."""
        return jax.tree_util.tree_map(jnp.subtract, self, other)

    def x_coupling(self, u: Field) -> Field:
        """The west/east terms of the operator alone."""
        zx = jnp.zeros_like(u[:1])
        return self.west * jnp.concatenate([zx, u[:-1]], axis=0) + self.east * jnp.concatenate([u[1:], zx], axis=0)

    def factor(self, sweeps: int = 0, cycles: int = 3) -> "FivePointFactor":
        """Thomas factors along y (exact in 1-D); in 2-D with `sweeps` > 0 they serve
        line relaxation, with 0 `cycles` V-cycles of multigrid (`FivePointFactor.solve`)."""
        nx = self.diag.shape[0]
        thomas = thomas_factor(self.south, self.diag, self.north)
        if nx == 1 or sweeps > 0:
            return FivePointFactor(op=self, thomas=thomas, sweeps=1 if nx == 1 else sweeps)
        levels, op = [(self, thomas)], self
        while op.diag.shape[0] > 1:
            op = op.coarsened(_aggregates(op.diag.shape[0]))
            levels.append((op, thomas_factor(op.south, op.diag, op.north)))
        return FivePointFactor(op=self, thomas=thomas, sweeps=0, levels=tuple(levels), cycles=cycles)

    def coarsened(self, sizes: tuple) -> "FivePoint":
        """The operator on columns aggregated in groups of `sizes` along x: equations
        summed, couplings along y summed, the x-coupling across each aggregate's faces
        scaled by the ratio of cell widths (Δx over the distance of the aggregates'
        centres, as a diffusion operator rediscretised on the coarse cells)."""
        sizes_np = np.asarray(sizes)
        ends = np.cumsum(sizes_np)
        starts = ends - sizes_np
        width = 0.5 * (sizes_np[1:] + sizes_np[:-1])  # centre distance, in fine cells
        west = self.west[starts].at[1:].multiply(1.0 / width[:, None]).at[0].multiply(0.0)
        east = self.east[ends - 1].at[:-1].multiply(1.0 / width[:, None]).at[-1].multiply(0.0)
        rest = self.diag + self.west + self.east  # diag less the x-coupling's share (zero row sums)
        return FivePoint(
            diag=_restrict(rest, sizes) - west - east,
            south=_restrict(self.south, sizes),
            north=_restrict(self.north, sizes),
            west=west,
            east=east,
        )


def _aggregates(n: int) -> tuple:
    """Sizes of the coarse cells over n columns: pairs, the last a triple if n is odd."""
    sizes = [2] * (n // 2)
    if n % 2:
        sizes[-1] = 3
    return tuple(sizes)


def _restrict(x, sizes: tuple):
    """Sums of x over the aggregates (`_aggregates`) along the first axis."""
    n = len(sizes)
    pairs = x[: 2 * (n - 1)].reshape((n - 1, 2) + x.shape[1:]).sum(axis=1)
    return jnp.concatenate([pairs, x[2 * (n - 1):].sum(axis=0, keepdims=True)])


def _prolong(u, sizes: tuple):
    """The aggregates' values interpolated linearly along x (between the aggregates'
    centres; constant beyond the outermost) onto the fine columns."""
    if len(sizes) == 1:
        return jnp.broadcast_to(u, (sizes[0],) + u.shape[1:])
    sizes_np = np.asarray(sizes, dtype=float)
    centres = np.cumsum(sizes_np) - 0.5 * sizes_np
    fine = np.arange(int(sizes_np.sum())) + 0.5
    right = np.clip(np.searchsorted(centres, fine), 1, len(sizes) - 1)
    left = right - 1
    w = np.clip((fine - centres[left]) / (centres[right] - centres[left]), 0.0, 1.0)[:, None]
    return (1.0 - w) * u[left] + w * u[right]


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


def _columns(factor: "Thomas", parity: int) -> "Thomas":
    """The Thomas factors of every other column (x index ≡ parity mod 2)."""
    return Thomas(*(x[:, parity::2] for x in (factor.sub, factor.diag, factor.sup, factor.inv, factor.c)))


def _zebra(op: FivePoint, factor: "Thomas", u, r, order=(0, 1)):
    """One sweep of zebra line relaxation: the even columns solved exactly along y with
    their x-neighbours' current values, then the odd ones (or the reverse `order`)."""
    for parity in order:
        rhs = (r - op.x_coupling(u))[parity::2]
        u = u.at[parity::2].set(thomas_solve(_columns(factor, parity), rhs))
    return u


def _v_cycle(levels, r, level=0):
    """One V-cycle from zero: zebra pre-smoothing, the residual summed onto the coarse
    columns, the coarse correction interpolated back linearly, reversed zebra
    post-smoothing (a fixed linear map)."""
    op, factor = levels[level]
    if level == len(levels) - 1:  # one column: Thomas is exact
        return thomas_solve(factor, r)
    sizes = _aggregates(op.diag.shape[0])
    u = _zebra(op, factor, jnp.zeros_like(r), r)
    u = u + _prolong(_v_cycle(levels, _restrict(r - op(u), sizes), level + 1), sizes)
    return _zebra(op, factor, u, r, order=(1, 0))


class FivePointFactor(eqx.Module):
    """A factored `FivePoint` operator: Thomas factors along y (1-D, or 2-D line
    relaxation), or, with `sweeps` = 0 in 2-D, the operators and Thomas factors of every
    level of a multigrid that coarsens along x only (`levels`, finest first)."""

    op: FivePoint
    thomas: Thomas
    sweeps: int = eqx.field(static=True, default=1)
    levels: tuple | None = None
    cycles: int = eqx.field(static=True, default=3)

    def solve(self, r: Field) -> Field:
        op = self.op
        if self.levels is None and self.sweeps == 1:  # one sweep from zero (in 1-D exact)
            return thomas_solve(self.thomas, r)
        # the repeats as loops from u = 0, the first sweep or cycle included: one copy of
        # each in the program (the first's products with u = 0 are exact zeros)
        u = jnp.zeros_like(r)
        if self.levels is None:  # line Jacobi: u ← Y⁻¹ (r − X u), `sweeps` times
            return jax.lax.fori_loop(0, self.sweeps, lambda _, u: thomas_solve(self.thomas, r - op.x_coupling(u)), u)
        # multigrid: u ← u + V(r − A u), `cycles` times (a fixed linear map)
        return jax.lax.fori_loop(0, self.cycles, lambda _, u: u + _v_cycle(self.levels, r - op(u)), u)


def line_sweeps(nx: int, thickness_over_cell_length: float, target: float = 0.01, most: int = 8) -> int:
    """Sweeps of line relaxation for the 2-D O2 solve, or 0 for multigrid.

    Line Jacobi (Thomas solves across the thickness, the x-coupling lagged) contracts
    the error by at most ρ = 2r²/(2r² + π²), r = h/Δx: the mode that alternates
    between columns and is smoothest across the thickness, where the lagged coupling
    2D/Δx² meets the smallest transverse rate π²D/h². k sweeps leave ρᵏ. Returns the
    least even k with ρᵏ ≤ `target`, or 0 if that is more than `most` (cells too short
    for the sweeps to pay: 3 V-cycles cost about 12 sweeps). Even k: the residual
    error has no negative eigenvalues (symmetric operator), so the effective J̃ errs on
    the stiff side.
    """
    if nx == 1:
        return 0
    r = thickness_over_cell_length
    rho = 2 * r**2 / (2 * r**2 + np.pi**2)
    k = 2 * max(1, math.ceil(math.log(target) / math.log(rho) / 2))
    return k if k <= most else 0
