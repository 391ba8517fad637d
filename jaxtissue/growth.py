"""The triphasic growth model (docs/model.md §2): O2 o, cells c, ECM m on the growth grid.

`GrowthModel` is the right-hand side `(t, y, args) -> dy` of

    ∂o/∂t = ∇·((D_o(m) + D_disp) ∇o) − v̂·∇o − Q_o c o/(o_h + o)        (2.1, A.1)
    ∂c/∂t = ∇·(D_c ∇c − χ c (c_max − c) ∇o) + k_c(o) c (c_max − c)      (2.3, A.2)
    ∂m/∂t = k_m(o) c (1 − m)                                             (2.5, A.3)

with o = o_ext on the two surfaces, no flux of c anywhere and no flux of o through the
posts (docs/model.md §2). The lumped transport of the conditioning cycle (velocity v̂ and
dispersivity D_disp, docs/model.md §5) enters through `Transport`; static culture has none.
"""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from . import operators as ops
from ._custom_types import Field
from .grid import Grid
from .growth_jacobian import GrowthJacobian, ShiftedFactor
from .numerics import AbstractStructuredField
from .params import Coefficients, moser_aiba
from .state import State, Transport


def o2_diffusivity(m, coeffs: Coefficients):
    """D_o(m) of the Chang unit cell (A.4, as reconstructed in docs/model.md §2), cm²/s."""
    k, psi = coeffs.kappa, coeffs.psi
    num = 9 * k * m - 6 * m * (1 - m) * (k - 1) + 2 * (1 - m) * k * psi
    den = 9 * m + 3 * m * (1 - m) * (k - 1) + (2 + m) * k * psi
    return coeffs.D_o0 * num / den


def o2_consumption(o, c, coeffs: Coefficients):
    """Michaelis–Menten consumption Q_o c o/(o_h + o) (2.2), with o clipped at 0."""
    o = jnp.maximum(o, 0.0)
    return coeffs.Q_o * c * o / (coeffs.o_h + o)


def proliferation_rate(o, coeffs: Coefficients):
    """k_c(o) = k_p g(o) − k_a, g the Moser–Aiba factor (A.6), 1/s."""
    return coeffs.k_p * moser_aiba(o, coeffs.n_moser, coeffs.o_c, coeffs.k_i) - coeffs.k_a


def ecm_synthesis_rate(o, coeffs: Coefficients):
    """k_m(o) = k_m0 (o − o_m) above the threshold o_m, else 0 (2.6), 1/s."""
    return coeffs.k_m0 * jnp.maximum(o - coeffs.o_m, 0.0)


def has_cell_transport(p) -> bool:
    """False only if `p.D_c` and `p.chi` (of `Params` or `Coefficients`) are both
    concrete (untraced) zeros: the cell flux of (2.3) is then identically zero, whatever
    is being differentiated."""

    def zero(x):
        return not isinstance(x, jax.core.Tracer) and bool(np.all(np.asarray(x) == 0.0))

    return not (zero(p.D_c) and zero(p.chi))


class GrowthModel(AbstractStructuredField):
    """The right-hand side of the growth system (module docstring), as a callable pytree.

    `advection` chooses the scheme for v̂·∇o: `"limited"` (MUSCL, van Leer; second
    order) or `"upwind"` (first order). `cell_transport=False` drops the cell flux
    (motility, chemotaxis): for D_c = χ = 0 known before tracing (`has_cell_transport`),
    where it is identically zero. `o2_sweeps`: the O2 solve of `shifted_factor` in 2-D,
    sweeps of line relaxation or 0 for multigrid (`numerics.line_sweeps`).
    `exact_jacobian`: J̃ = J (static runs without cell flux on 1-D grids:
    `growth_jacobian`'s `exact_m`), differentiated with the step: what a Rosenbrock method
    that is not a W-method needs for its order and its gradients (`numerics.Rodas4P2`).
    """

    coeffs: Coefficients
    grid: Grid
    transport: Transport = eqx.field(default_factory=Transport)
    advection: str = eqx.field(static=True, default="limited")
    cell_transport: bool = eqx.field(static=True, default=True)
    o2_sweeps: int = eqx.field(static=True, default=0)
    exact_jacobian: bool = eqx.field(static=True, default=False)

    def __check_init__(self):
        if self.advection not in ("limited", "upwind"):
            raise ValueError(f"advection = {self.advection!r} must be 'limited' or 'upwind'")

    @property
    def spacing(self):
        return self.grid.spacing(self.coeffs.length_cm, self.coeffs.thickness_cm)

    def o2_diffusivity(self, m) -> Field:
        d = o2_diffusivity(m, self.coeffs)
        if self.transport.dispersion is not None:
            d = d + self.transport.dispersion
        return d

    def __call__(self, t, y: State, args=None) -> State:
        k = self.coeffs
        dx, dy = self.spacing
        o, c, m = y.o, y.c, y.m
        # O2 (2.1)
        do = ops.diffusion(o, self.o2_diffusivity(m), dx, dy, k.o_ext) - o2_consumption(o, c, k)
        if self.transport.vx is not None:
            do = do - ops.advection(
                o, self.transport.vx, self.transport.vy, dx, dy, k.o_ext,
                limited=self.advection == "limited",
            )
        # cells (2.3): random motility and chemotaxis, no flux through any face
        dc = proliferation_rate(o, k) * c * (k.c_max - c)
        if self.cell_transport:
            dc = dc + self.cell_flux_divergence(o, c)
        # ECM (2.5, 2.6)
        dm = ecm_synthesis_rate(o, k) * c * (1.0 - m)
        return State(o=do, c=dc, m=dm)

    def for_jacobian(self) -> "GrowthModel":
        """The model whose Jacobian the implicit solver uses: first-order upwind
        advection, so that every coupling stays within the 5-point stencil that
        `linsolve` probes exactly (the limiter's wider stencil would alias)."""
        if self.transport.vx is None or self.advection == "upwind":
            return self
        return GrowthModel(self.coeffs, self.grid, self.transport, "upwind", self.cell_transport, self.o2_sweeps, self.exact_jacobian)

    def shifted_factor(self, t, y: State, args, a) -> ShiftedFactor:
        """`a I − J̃` at y, factored (`growth_jacobian`): J̃ is probed from the JVP of
        `for_jacobian()` and held constant under differentiation (a W-method keeps its
        order for any J̃: no second derivatives), unless `exact_jacobian`."""
        _, jvp = jax.linearize(lambda z: self.for_jacobian()(t, z, args), y)
        jac = GrowthJacobian.probe(jvp, self.grid.shape, pointwise_c=not self.cell_transport, exact_m=self.exact_jacobian)
        return (jac if self.exact_jacobian else jax.lax.stop_gradient(jac)).factor(a, self.o2_sweeps)

    def cell_flux_divergence(self, o, c) -> Field:
        """−∇·J_c with J_c = −D_c ∇c + χ c (c_max − c) ∇o and J_c = 0 on every face."""
        k = self.coeffs
        dx, dy = self.spacing
        sens = c * (k.c_max - c)
        jx = k.D_c * ops.gradient_x(c, dx) - k.chi * ops.face_average_x(sens) * ops.gradient_x(o, dx)
        jy_inner = (
            k.D_c * ops.gradient_y(c, dy, None)
            - k.chi * ops.face_average_y(sens) * ops.gradient_y(o, dy, None)
        )
        jy = jy_inner.at[:, 0].set(0.0).at[:, -1].set(0.0)
        return ops.divergence(jx, jy, dx, dy)

    def o2_boundary_influx(self, y: State):
        """O2 entering through the two surfaces per unit depth, Σ faces D ∂o/∂n dx (cm²/s
        in o-units): the surface term of the O2 budget (used to check conservation)."""
        dx, dy = self.spacing
        g = ops.gradient_y(y.o, dy, self.coeffs.o_ext)
        flux = ops.face_coefficient_y(self.o2_diffusivity(y.m)) * g
        return jnp.sum(flux[:, -1] - flux[:, 0]) * dx

