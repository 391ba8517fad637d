"""The large-deformation poroelastic beam and one loading cycle (docs/model.md §4).

**Kinematics.** A geometrically exact (elastica) beam along the arc length
s ∈ [0, L], discretised into `n_segments` straight segments of angle θ_k; the curvature
lives on the interior nodes, κ_i = (θ_i − θ_{i−1})/ds. The centre line stretches
under tension by P/EA (it bounds the tension when the strip is pulled back straight
while its pores still drain). Both posts are pins on
one line; the moving post shortens the chord by u_M(t) (A.22).

**Equilibrium.** With compressive post force P along the chord, the moment at node i is
M_i = −P (y_i + e): e = 0 for pins at the centroid line (default), e = h/2 for pins at
the bottom corners (as the paper's model, to first order in the end rotation).

**Section.** Across the thickness at each interior node, on the growth grid's ny cells:
the fibre strain ε = −(κ − κ₀) y, the effective stress of a neo-Hookean fibre
σ' = (E'/3)(λ − λ⁻²), λ = 1 + ε (slope E' = E/(1 − ν²) at ε = 0; or `"linear"`), and
the pore pressure p of a consolidation problem with drained faces (p = 0 relative to
p_ext at y = ±h/2) and, beam-like, no flow along x:

    ∂p/∂t = M ∂/∂y (K ∂p/∂y) − 2μ ∂ε/∂t,    K = k/γ_w,  M = λ + 2μ,

which follows from Darcy's law, incompressible constituents and σ_yy = 0 (so that the
volumetric strain is (2μ/M) ε + p/M). The total axial stress σ' − (2μ/M) p gives the
section moment M = −d ∫ σ y dy. Material: E(m) = E_s + Ē_m0 ρ_m, ν(m), k(m), φ(m)
(docs/model.md §3, §4). The seepage velocity is v_f = −(K/φ) ∇p.

**Time.** Quasi-static over one cycle from rest (p = 0), implicit Euler in time (the
pressure is eliminated linearly, section by section), and at each step a Newton solve
(structured Jacobian, implicit differentiation) for the segment angles and P.

Units inside this module are SI (m, Pa, N, s).

A tiny stress-free imperfection (mid-span rise `imperfection` × L, a half sine) selects
the upward buckling mode and keeps the response smooth from u = 0.
"""

from __future__ import annotations

import functools
import math

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jax.ad_checkpoint import checkpoint_name

from .numerics import nested_checkpoint_scan, thomas_factor, thomas_solve
from .params import SIParams

GAMMA_W_PA_PER_M = 1000.0 * 9.81  # ρ_f g of the culture medium (docs/model.md §4)


def waveform(t, period_s, u_max, hold_fraction):
    """Post displacement u_M(t) of eq. A.22: hold at rest, sinusoidal ramp up, hold at
    full flexure, ramp down, hold; period T, amplitude u_max, hold γ = hold_fraction T."""
    T = period_s
    g = hold_fraction * T
    t = jnp.mod(t, T)
    w = 2 * jnp.pi / (T - 4 * g)
    up = 0.5 * u_max * (1 + jnp.sin(w * (t - g) - 0.5 * jnp.pi))
    down = 0.5 * u_max * (1 + jnp.sin(w * (t - 0.5 * T - g) + 0.5 * jnp.pi))
    return jnp.where(
        t < g, 0.0,
        jnp.where(t < 0.5 * T - g, up, jnp.where(t < 0.5 * T + g, u_max, jnp.where(t < T - g, down, 0.0))),
    )


class BeamGrid(eqx.Module):
    """Resolution of the beam: segments along s and implicit-Euler steps per cycle
    (the thickness uses the growth grid's ny cells)."""

    n_segments: int = eqx.field(static=True, default=50)
    steps_per_cycle: int = eqx.field(static=True, default=200)

    def __check_init__(self):
        if not isinstance(self.n_segments, int) or self.n_segments < 4 or self.n_segments % 2:
            raise ValueError(f"beam n_segments = {self.n_segments!r} must be an even integer >= 4")
        if not isinstance(self.steps_per_cycle, int) or self.steps_per_cycle < 8:
            raise ValueError(f"beam steps_per_cycle = {self.steps_per_cycle!r} must be an integer >= 8")


class Material(eqx.Module):
    """Section properties at the interior nodes × thickness cells (SI units)."""

    E: jax.Array  # Young's modulus, Pa
    nu: jax.Array
    K: jax.Array  # k/γ_w, m²/(Pa s)
    phi: jax.Array  # porosity

    @classmethod
    def from_ecm(cls, m, si: SIParams) -> "Material":
        """E = E_s + Ē_m0 ρ_m (A.25), ν, k, φ linear in m (2.7, 2.8, 2.13); `si` from
        `Params.si()`."""
        E = si.E_s_Pa + si.E_m0_Pa_per_ug_g * si.rho_m_max_ug_g * m
        nu = si.nu_s + (si.nu_t - si.nu_s) * m
        k = si.k_hyd_s_m_s + (si.k_hyd_t_m_s - si.k_hyd_s_m_s) * m  # m/s
        K = k / GAMMA_W_PA_PER_M
        phi = si.phi_s + (si.phi_t - si.phi_s) * m
        return cls(E=E, nu=nu, K=K, phi=phi)

    @property
    def mu(self):
        return self.E / (2 * (1 + self.nu))

    @property
    def lam(self):
        return self.E * self.nu / ((1 + self.nu) * (1 - 2 * self.nu))

    @property
    def M(self):
        return self.lam + 2 * self.mu

    @property
    def E_plane(self):
        return self.E / (1 - self.nu**2)


class Geometry(eqx.Module):
    length: jax.Array  # m
    thickness: jax.Array  # m
    depth: jax.Array  # m
    pin_offset: jax.Array  # m, e of the moment arm

    @classmethod
    def from_params(cls, si: SIParams, pins: str = "centroid") -> "Geometry":
        """The strip of `si` (`Params.si()`), pinned at the centroid line or the bottom
        corners."""
        h = si.thickness_m
        offset = {"centroid": 0.0, "bottom": 0.5}[pins] * h
        return cls(length=si.length_m, thickness=h, depth=si.depth_m, pin_offset=offset)

    def y_cells(self, ny):
        return (jnp.arange(ny) + 0.5) * (self.thickness / ny) - 0.5 * self.thickness


def consolidation_operator(mat: Material, dy, dt):
    """Tridiagonal (sub, diag, sup) of I − dt M ∂_y(K ∂_y ·), p = 0 half a cell out."""
    K = mat.K
    inner = 2 * K[:, 1:] * K[:, :-1] / (K[:, 1:] + K[:, :-1])
    lower = jnp.concatenate([2 * K[:, :1], inner], axis=1)  # face j−1/2 (surface: K_j, dy/2)
    upper = jnp.concatenate([inner, 2 * K[:, -1:]], axis=1)  # face j+1/2
    c = dt * mat.M / dy**2
    sub = jnp.where(jnp.arange(K.shape[1]) == 0, 0.0, -c * lower)
    sup = jnp.where(jnp.arange(K.shape[1]) == K.shape[1] - 1, 0.0, -c * upper)
    return sub, 1 + c * (lower + upper), sup


_GAUSS = (0.5 - 0.5 / 3**0.5, 0.5 + 0.5 / 3**0.5)


class Section(eqx.Module):
    """What the residual needs of a beam's geometry and material, computed once per
    configuration (`Beam.prepared`) rather than in every Newton iteration: a loading
    cycle's reverse pass then accumulates cotangents of these few arrays step by step,
    and carries them back to the material once."""

    E_plane: jax.Array  # (n_segments − 1, ny), Pa
    y_gauss: jax.Array  # (2, ny) Gauss points across the thickness, m
    moment_weights: jax.Array  # (2, ny): d · ½dy · y at each Gauss point, m³
    pore_weights: jax.Array  # (n_segments − 1, ny): d (2μ/M) y dy, m³
    euler_load: jax.Array  # N
    axial_stiffness: jax.Array  # N
    natural_angles: jax.Array  # (n_segments,)
    natural_curvature: jax.Array  # (n_segments − 1,), 1/m
    chord0: jax.Array  # m

    @classmethod
    def of(cls, geo: Geometry, mat: Material, grid: BeamGrid, imperfection: float) -> "Section":
        N, L = grid.n_segments, geo.length
        ny = mat.E.shape[1]
        dy = geo.thickness / ny
        y = geo.y_cells(ny)
        y_gauss = jnp.stack([y - 0.5 * dy + g * dy for g in _GAUSS])
        E_plane = mat.E_plane
        mid = N // 2 - 1
        EI = geo.depth * jnp.sum(E_plane[mid] * (y**2 + dy**2 / 12) * dy)
        s_mid = (jnp.arange(N) + 0.5) * L / N
        angles = jnp.arctan(imperfection * jnp.pi * jnp.cos(jnp.pi * s_mid / L))
        ds = L / N
        return cls(
            E_plane=E_plane,
            y_gauss=y_gauss,
            moment_weights=geo.depth * 0.5 * dy * y_gauss,
            pore_weights=geo.depth * (2 * mat.mu / mat.M) * y * dy,
            euler_load=jnp.pi**2 * EI / L**2,
            axial_stiffness=geo.depth * jnp.mean(jnp.sum(E_plane, axis=1)) * dy,
            natural_angles=angles,
            natural_curvature=(angles[1:] - angles[:-1]) / ds,
            chord0=jnp.sum(ds * jnp.cos(angles)),
        )


class Beam(eqx.Module):
    """One beam configuration: geometry, section material and resolution. `prepared()`
    adds its `Section` constants (else each method computes what it needs)."""

    geometry: Geometry
    material: Material  # (n_segments − 1, ny)
    grid: BeamGrid
    fibre_law: str = eqx.field(static=True, default="neo-hookean")
    imperfection: float = eqx.field(static=True, default=1e-2)
    section: Section | None = None

    def prepared(self) -> "Beam":
        """This beam with its `Section` constants computed once, from its material now
        (change the material of the unprepared beam, then prepare it again)."""
        return eqx.tree_at(lambda beam: beam.section, self, self._section, is_leaf=lambda x: x is None)

    @property
    def _section(self) -> Section:
        if self.section is not None:
            return self.section
        return Section.of(self.geometry, self.material, self.grid, self.imperfection)

    @property
    def ds(self):
        return self.geometry.length / self.grid.n_segments

    @property
    def ny(self):
        return self.material.E.shape[1]

    def natural_angles(self):
        """Segment angles of the stress-free half-sine imperfection."""
        return self._section.natural_angles

    def curvature(self, theta):
        return (theta[1:] - theta[:-1]) / self.ds

    def elastic_moment(self, dkappa):
        """−d ∫ σ'(ε) y dy with ε = −Δκ y, two Gauss points per cell (exact if linear)."""
        sec = self._section
        eps = -dkappa[:, None, None] * sec.y_gauss  # (sections, Gauss point, cell)
        if self.fibre_law == "linear":
            sigma = eps
        else:
            stretch = 1 + eps
            sigma = (stretch - stretch**-2) / 3
        return -jnp.sum(sec.E_plane * jnp.sum(sigma * sec.moment_weights, axis=1), axis=1)

    def pore_moment_weights(self):
        """d (2μ/M) y dy: the section moment of the pore pressure is Σ_j w_j p_j."""
        return self._section.pore_weights

    def euler_load(self):
        """π² EI/L² of the drained section at mid-span, N (scales the post force)."""
        return self._section.euler_load

    def _scale(self):
        """Moment scale EI_mid/L of the residual's moment rows, N m."""
        return self.euler_load() * self.geometry.length / jnp.pi**2

    def section_moment(self, kappa, a, b):
        """Section moments at the interior nodes for curvature κ and pore pressure
        p = a + κ b: elastic plus pore part (local in κ)."""
        dkappa = kappa - self._section.natural_curvature
        return self.elastic_moment(dkappa) + jnp.sum(self.pore_moment_weights() * (a + kappa[:, None] * b), axis=1)

    def _geometric_residual(self, z, u):
        """The residual's terms in the node positions: P (y_i + e) on the moment rows,
        pins on one line, chord = c₀ − u."""
        geo = self.geometry
        theta, P = z[:-1], z[-1] * self.euler_load()
        ds = self.segment_length(P)
        y_nodes = jnp.concatenate([jnp.zeros(1), jnp.cumsum(ds * jnp.sin(theta))])
        r_moment = P * (y_nodes[1:-1] + geo.pin_offset) / self._scale()
        chord0 = self._section.chord0
        r_close = jnp.sum(ds * jnp.sin(theta)) / geo.length
        r_chord = (jnp.sum(ds * jnp.cos(theta)) - (chord0 - u)) / geo.length
        return jnp.concatenate([r_moment, r_close[None], r_chord[None]])

    def residual(self, z, args):
        """Moment balance at the interior nodes, pins on one line, chord = c₀ − u
        (unknowns z = (θ, P/P_E); args = (u, a, b))."""
        u, a, b = args
        moment = self.section_moment(self.curvature(z[:-1]), a, b) / self._scale()
        return self._geometric_residual(z, u) + jnp.pad(moment, (0, 2))

    def linearise(self, z, args):
        """The residual and its Jacobian (as a `NewtonMatrix`) in closed form, sharing
        the section moments. A section's moment depends on its own κ only, so its
        tangent stiffness is one JVP (a diagonal) times κ = Dθ; the post force's moment
        P y_i has ∂/∂θ_k = P ds cos θ_k for k < i (lower triangular)."""
        u, a, b = args
        geo = self.geometry
        theta, P_E = z[:-1], self.euler_load()
        P, S, L = z[-1] * P_E, self._scale(), geo.length
        kappa = self.curvature(theta)
        moment, stiffness = jax.jvp(lambda k: self.section_moment(k, a, b), (kappa,), (jnp.ones_like(kappa),))
        residual = self._geometric_residual(z, u) + jnp.pad(moment / S, (0, 2))
        ds, dds_dP = jax.value_and_grad(self.segment_length)(P)
        sin, cos = jnp.sin(theta), jnp.cos(theta)
        y_inner = jnp.cumsum(ds * sin)[:-1]  # y at the interior nodes
        matrix = NewtonMatrix(
            ds=self.ds,
            bending=stiffness / S,
            lever=P * ds * cos / S,
            moment_P=P_E * (y_inner + geo.pin_offset + P * y_inner * dds_dP / ds) / S,
            close=ds * cos / L,
            close_P=P_E * dds_dP * jnp.sum(sin) / L,
            chord=-ds * sin / L,
            chord_P=P_E * dds_dP * jnp.sum(cos) / L,
        )
        return residual, matrix

    def jacobian(self, z, args):
        """∂residual/∂z as a dense matrix (for checks; the solver uses `linearise`)."""
        return self.linearise(z, args)[1].dense()

    def axial_stiffness(self):
        """EA of the drained section, averaged along the strip, N."""
        return self._section.axial_stiffness

    def segment_length(self, P):
        """Segment length under the post force P (compression positive): the centre
        line stretches under tension, P/EA, so that pulling the strip straight meets
        its axial stiffness rather than a constraint; in compression it is
        inextensible (else a compressed unbuckled branch competes with buckling).
        The switch is smoothed over |P| ~ 1e-3 P_Euler."""
        P0 = 1e-3 * self.euler_load()
        tension = 0.5 * (jnp.sqrt(P**2 + P0**2) - P0 - P)
        return self.ds * (1 + tension / self.axial_stiffness())

    def rest_state(self):
        return jnp.concatenate([self.natural_angles(), jnp.zeros(1)])

    def equilibrium(self, u, z0, a=None, b=None, tol=1e-10, max_steps=20):
        """(θ, P/P_E) at end shortening u (m), from the guess z0; a, b: pore pressure
        p = a + κ b (zero: drained). Returns (z, converged).

        Newton's method with the structured Jacobian (`linearise`, `NewtonMatrix`)
        until the step is below √tol: Newton converges quadratically, so the error
        left is ~tol. Derivatives are the implicit-function theorem's,
        ż = −J⁻¹ ṙ with ṙ the residual's derivative at the root (`_newton_jvp`): the
        iterations themselves are never differentiated."""
        if a is None:
            a = jnp.zeros_like(self.material.E)
            b = jnp.zeros_like(self.material.E)
        return _newton(self, (u, a, b), jax.lax.stop_gradient(z0), tol, max_steps)

    def shape(self, z):
        """Node coordinates (x, y) in m of the state z."""
        theta = z[:-1]
        ds = self.segment_length(z[-1] * self.euler_load())
        zero = jnp.zeros(1)
        x = jnp.concatenate([zero, jnp.cumsum(ds * jnp.cos(theta))])
        y = jnp.concatenate([zero, jnp.cumsum(ds * jnp.sin(theta))])
        return x, y


@functools.partial(jax.custom_jvp, nondiff_argnums=(3, 4))
def _newton(beam: Beam, args, z0, tol, max_steps):
    """Newton iterations for `Beam.equilibrium`: (z, converged)."""

    def body(carry):
        k, z, _ = carry
        r, J = beam.linearise(z, args)
        dz = J.solve(r)
        return k + 1, z - dz, jnp.max(jnp.abs(dz))

    def cond(carry):
        k, _, step = carry
        return (k < max_steps) & (step > tol**0.5)

    _, z, step = jax.lax.while_loop(cond, body, (0, z0, jnp.asarray(jnp.inf, z0.dtype)))
    return z, step <= tol**0.5


@_newton.defjvp
def _newton_jvp(tol, max_steps, primals, tangents):
    """The implicit-function theorem at the root: ż = −J⁻¹ (∂r/∂(beam, args)) · tangents.
    The root is named "beam_newton" so that rematerialisation keeps it rather than
    solving again (`nested_checkpoint_scan`)."""
    beam, args, z0 = primals
    d_beam, d_args, _ = tangents
    z, converged = checkpoint_name(_newton(beam, args, z0, tol, max_steps), "beam_newton")
    _, dr = jax.jvp(lambda bm, ar: bm.residual(z, ar), (beam, args), (d_beam, d_args))
    _, J = beam.linearise(z, args)
    return (z, converged), (-J.solve(dr), np.zeros((), jax.dtypes.float0))


def _volterra_solve(bending, W, ds, rhs):
    """x with A x = rhs (rhs: (n − 1, m)), A = diag(bending) + ds (W_i − W_j)_{j<i}: forward
    substitution in O(n), row i needing only Σ_{j<i} x_j and Σ_{j<i} W_j x_j. Marching
    in a scan, not LAPACK's triangular solve, whose batched CPU kernel can deadlock two
    solves that XLA runs at once on a two-thread pool."""

    def row(sums, inputs):
        b, w, f = inputs
        s0, s1 = sums
        x = (f - ds * (w * s0 - s1)) / b
        return (s0 + x, s1 + w * x), x

    zero = jnp.zeros(rhs.shape[1:], rhs.dtype)
    return jax.lax.scan(row, (zero, zero), (bending, W, rhs))[1]


class NewtonMatrix(eqx.Module):
    """The Jacobian of `Beam.residual` by its structure, and its O(n) solve.

    Rows: n − 1 moment rows, then "close" (pins on one line) and "chord"; columns: the
    n segment angles θ, then P/P_E. The moment rows are

        bending_i (θ_{i+1} − θ_i)/ds + Σ_{k≤i} lever_k θ_k + moment_P_i P̂.

    In the curvatures δκ_i = (δθ_{i+1} − δθ_i)/ds and δθ_0 they are lower triangular
    (a Volterra sum, i.e. marching along the strip): with W_i = Σ_{k≤i} lever_k,
    A δκ = ρ − W δθ_0 − moment_P δP̂, A = diag(bending) + ds (W_i − W_j)_{j<i}. One
    triangular solve with three right-hand sides (`_volterra_solve`, forward substitution
    in O(n)) leaves a 2 × 2 system for (δθ_0, δP̂) from the two constraint rows. Its
    diagonal is the bending stiffness, so no pivoting is needed."""

    ds: jax.Array
    bending: jax.Array  # (n − 1,)
    lever: jax.Array  # (n,)
    moment_P: jax.Array  # (n − 1,)
    close: jax.Array  # (n,)
    close_P: jax.Array
    chord: jax.Array  # (n,)
    chord_P: jax.Array

    def dense(self):
        n = self.lever.shape[0]
        eye = jnp.eye(n - 1, n)
        D = (jnp.roll(eye, 1, axis=1) - eye) / self.ds
        moment = self.bending[:, None] * D + jnp.tril(jnp.ones((n - 1, n))) * self.lever
        return jnp.concatenate([
            jnp.concatenate([moment, self.moment_P[:, None]], axis=1),
            jnp.concatenate([self.close, self.close_P[None]])[None],
            jnp.concatenate([self.chord, self.chord_P[None]])[None],
        ])

    def _angles(self, dkappa):
        """δθ_k − δθ_0 = ds Σ_{j<k} δκ_j."""
        return self.ds * jnp.concatenate([jnp.zeros(1), jnp.cumsum(dkappa)])

    def solve(self, r):
        """δz with J δz = r (linear in r: the matrix's own pieces are solved separately)."""
        W = jnp.cumsum(self.lever)[:-1]
        K_W, K_P = _volterra_solve(self.bending, W, self.ds, jnp.stack([W, self.moment_P], axis=1)).T
        K_r = _volterra_solve(self.bending, W, self.ds, r[:-2, None])[:, 0]  # apart: linear in r, so reverse mode transposes it
        # δθ = δθ_0 + angles(k_r − k_W δθ_0 − k_P δP̂): the constraint rows in (δθ_0, δP̂)
        th_r, th_W, th_P = (self._angles(k) for k in (K_r, K_W, K_P))
        ones = jnp.ones_like(self.lever)
        a11 = self.close @ (ones - th_W)
        a12 = self.close_P - self.close @ th_P
        a21 = self.chord @ (ones - th_W)
        a22 = self.chord_P - self.chord @ th_P
        f1 = r[-2] - self.close @ th_r
        f2 = r[-1] - self.chord @ th_r
        det = a11 * a22 - a12 * a21
        d0 = (a22 / det) * f1 - (a12 / det) * f2
        dP = (a11 / det) * f2 - (a21 / det) * f1
        dkappa = K_r - K_W * d0 - K_P * dP
        return jnp.concatenate([d0 + self._angles(dkappa), dP[None]])


class CycleResult(eqx.Module):
    """One loading cycle from rest. Per step (steps + 1, first = rest): time, post
    displacement u (m), post force (N, compression positive), mid-span deflection (m),
    peak surface strain. (As the strip is pulled back straight while its pores still
    drain, it carries a brief tension; the reported post force is the peak
    compression.)
    Cycle means on the sections (interior nodes × ny): signed seepage velocity
    `mean_vy`, `mean_vx` and `mean_abs_vy` (m/s). `fields` (if kept): θ history,
    pore pressure (Pa) and v_y (m/s) histories."""

    t: jax.Array
    u: jax.Array
    post_force_N: jax.Array
    midspan_deflection_m: jax.Array
    surface_strain: jax.Array
    mean_vy: jax.Array
    mean_vx: jax.Array
    mean_abs_vy: jax.Array
    failed: jax.Array
    fields: dict | None

    @property
    def post_force_max_N(self):
        """Peak compressive post force over the cycle, N."""
        return jnp.max(self.post_force_N)


def _pressure_gradient(p, dy, ds):
    """∇p at the cells of each section (∂p/∂x, ∂p/∂y), Pa/m; the seepage velocity is
    v_f = −(K/φ) ∇p (Darcy)."""
    pad = jnp.pad(p, ((0, 0), (1, 1)))  # drained faces: p = 0 half a cell out
    grad_face = (pad[:, 1:] - pad[:, :-1]) / dy
    grad_face = grad_face.at[:, 0].multiply(2.0).at[:, -1].multiply(2.0)
    return jnp.gradient(p, ds, axis=0), 0.5 * (grad_face[:, 1:] + grad_face[:, :-1])


def loading_cycle(beam: Beam, period_s, u_max_m, hold_fraction, keep_fields: bool = False, cycles: int = 1) -> CycleResult:
    """Solve one cycle of A.22 from rest (p = 0): implicit Euler, `steps_per_cycle`
    steps. With `cycles > 1` the loading repeats and the last cycle is reported (its
    means approach the periodic steady state)."""
    n = beam.grid.steps_per_cycle
    dt = period_s / n

    beam = beam.prepared()  # the section's constants once, not in every Newton iteration
    geo, mat = beam.geometry, beam.material
    dy = geo.thickness / beam.ny
    op = thomas_factor(*consolidation_operator(mat, dy, dt))  # once per cycle
    drive = 2 * mat.mu * geo.y_cells(beam.ny)  # p gains drive · Δκ
    b = thomas_solve(op, drive)
    k_over_phi = mat.K / mat.phi
    kappa0 = beam.section.natural_curvature
    mid = beam.grid.n_segments // 2

    last = n * (cycles - 1)  # the reported cycle's first step

    def step(carry, k):
        z, z_prev, z_prev2, p, kappa, sums = carry
        u = waveform((k + 1) * dt, period_s, u_max_m, hold_fraction)
        a = thomas_solve(op, p - kappa[:, None] * drive)
        z_new, converged = beam.equilibrium(u, 3 * (z - z_prev) + z_prev2, a, b)  # Newton from the quadratic extrapolation
        kappa_new = beam.curvature(z_new[:-1])
        p_new = a + kappa_new[:, None] * b
        # cycle means accumulate in the carry, not per step: v_f is linear in p, so
        # its mean is that of the mean p (after the loop); |v_f,y| = (K/φ)|∂p/∂y|
        w = (k >= last) / n
        gy = _pressure_gradient(p_new, dy, beam.ds)[1]
        sums = dict(p=sums["p"] + w * p_new, abs_gy=sums["abs_gy"] + w * jnp.abs(gy))
        _, ys = beam.shape(z_new)
        out = dict(
            u=u,
            post_force_N=z_new[-1] * beam.euler_load(),
            midspan_deflection_m=ys[mid],
            surface_strain=0.5 * geo.thickness * jnp.max(jnp.abs(kappa_new - kappa0)),
            failed=~converged,
        )
        if keep_fields:
            out["theta"], out["p"], out["vy"] = z_new[:-1], p_new, -k_over_phi * gy
        return (z_new, z, z_prev, p_new, kappa_new, sums), out

    z0 = beam.rest_state()
    zeros = jnp.zeros_like(mat.E)
    init = (z0, z0, z0, zeros, kappa0, dict(p=zeros, abs_gy=zeros))
    # A gradient keeps ~√n carries and the converged Newton iterates, not every step's;
    # a chunk's reverse pass recomputes each step from its carry and Newton root, so
    # that it stores one carry per step rather than each step's Gauss-point stresses
    # and Newton matrices (one cycle's gradient on the default grids: 4.8 → 1.6 MiB,
    # about as fast). Chunks of the least divisor of n from ⌊√(2n)⌋ steps (20 of 200),
    # longer than `remat.chunking`'s 10: fewer chunk carries, which stay stored through
    # the reverse pass of the growth solve that follows the cycle.
    step = jax.checkpoint(step, policy=jax.checkpoint_policies.save_only_these_names("beam_newton"), prevent_cse=False)
    steps = n * cycles
    chunk = next(d for d in range(math.isqrt(2 * steps), steps + 1) if steps % d == 0)
    (*_, sums), hist = nested_checkpoint_scan(step, init, steps, keep=("beam_newton",), chunk_length=chunk)
    hist = jax.tree_util.tree_map(lambda h: h[-n:], hist)
    mean_gx, mean_gy = _pressure_gradient(sums["p"], dy, beam.ds)
    zero = jnp.zeros(1)
    _, y_rest = beam.shape(z0)
    fields = None
    if keep_fields:
        fields = dict(theta=jnp.concatenate([z0[None, :-1], hist["theta"]]),
                      p=jnp.concatenate([zeros[None], hist["p"]]),
                      vy=jnp.concatenate([zeros[None], hist["vy"]]))
    return CycleResult(
        t=jnp.arange(n + 1) * dt,
        u=jnp.concatenate([zero, hist["u"]]),
        post_force_N=jnp.concatenate([zero, hist["post_force_N"]]),
        midspan_deflection_m=jnp.concatenate([y_rest[mid][None], hist["midspan_deflection_m"]]),
        surface_strain=jnp.concatenate([zero, hist["surface_strain"]]),
        mean_vy=-k_over_phi * mean_gy,
        mean_vx=-k_over_phi * mean_gx,
        mean_abs_vy=k_over_phi * sums["abs_gy"],
        failed=jnp.any(hist["failed"]),
        fields=fields,
    )


@eqx.filter_jit
def uniform_cycle(si: SIParams, pins: str, grid: BeamGrid, ny: int, ecm, period_s, u_max_m, hold_fraction):
    """The beam of a strip whose every layer holds the ECM fraction `ecm`, and its
    loading cycle with the fields (`loading_cycle(keep_fields=True)`): `jaxtissue
    cycle`'s one program."""
    material = Material.from_ecm(jnp.full((grid.n_segments - 1, ny), ecm), si)
    beam = Beam(Geometry.from_params(si, pins), material, grid)
    return beam, loading_cycle(beam, period_s, u_max_m, hold_fraction, keep_fields=True)
