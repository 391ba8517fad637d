"""The poroelastic beam against closed forms and its own refinement."""

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest
from helpers import observed_orders

import jaxtissue as jt
from jaxtissue.numerics import thomas_factor, thomas_solve
from jaxtissue.beam import (
    Beam, BeamGrid, Geometry, Material, consolidation_operator, loading_cycle, waveform,
)

P = jt.paper_parameters()


def uniform_beam(n_segments=40, ny=16, law="linear", steps=200, scale_E=1.0, scale_k=1.0):
    p = P.replace(E_s_kPa=174.0 * scale_E, k_hyd_s_cm_s=3.66e-6 * scale_k)
    mat = Material.from_ecm(jnp.zeros((n_segments - 1, ny)), p.si())
    return Beam(Geometry.from_params(p.si()), mat, BeamGrid(n_segments=n_segments, steps_per_cycle=steps), fibre_law=law)


def static_elastica(beam, u_m, increments=100):
    """Drained equilibrium at end shortening u: continuation along a ramp that starts
    gently, as the loading waveform does (the straight beam is a bifurcation point)."""
    ramp = u_m * (1 - np.cos(0.5 * np.pi * np.arange(1, increments + 1) / increments))
    z, converged = _ramped_equilibria(beam, jnp.asarray(ramp))
    assert bool(jnp.all(converged))
    return z


@eqx.filter_jit
def _ramped_equilibria(beam, ramp):
    def step(z, u):
        return beam.equilibrium(u, z)

    return jax.lax.scan(step, beam.rest_state(), ramp)


@pytest.mark.parametrize("u_mm, deflection_mm", [(2.5, 4.87), (5.0, 6.66), (10.0, 8.72)])
def test_elastica_midspan_deflection_matches_closed_form(u_mm, deflection_mm):
    beam = uniform_beam(n_segments=60)
    z = static_elastica(beam, u_mm * 1e-3)
    _, y = beam.shape(z)
    assert float(y[30]) * 1e3 == pytest.approx(deflection_mm, rel=1e-2)


@pytest.mark.slow  # the closed-form deflections above are the default run's
def test_elastica_converges_at_second_order_in_s():
    """Richardson: successive differences of the mid-span deflection shrink 4x."""
    defl = []
    for n in (10, 20, 40, 80):
        beam = uniform_beam(n_segments=n, ny=4)
        _, y = beam.shape(static_elastica(beam, 5e-3))
        defl.append(float(y[n // 2]))
    diffs = np.abs(np.diff(defl))
    orders = np.log2(diffs[:-1] / diffs[1:])
    assert np.all(orders > 1.8), (defl, orders)


def test_post_force_scales_with_EI():
    """Doubling every modulus (and halving k, so c_v stays) doubles the post force."""
    base = loading_cycle(uniform_beam(n_segments=20, ny=8, law="neo-hookean", steps=60), 1.0, 5e-3, 0.05)
    stiff = loading_cycle(uniform_beam(n_segments=20, ny=8, law="neo-hookean", steps=60, scale_E=2.0, scale_k=0.5), 1.0, 5e-3, 0.05)
    assert float(stiff.post_force_max_N) == pytest.approx(2 * float(base.post_force_max_N), rel=1e-6)
    beam = uniform_beam(n_segments=40)
    z = static_elastica(beam, 5e-3)
    # the elastica's force at 5 mm shortening: P/P_Euler from the same closed form
    assert float(z[-1]) == pytest.approx(1.0, abs=0.35)


def terzaghi_degree(T_v, terms=200):
    """Average degree of consolidation of a layer drained on both faces."""
    M = (2 * np.arange(terms) + 1) * np.pi / 2
    return 1 - np.sum(2 / M**2 * np.exp(-(M**2) * T_v))


def test_suddenly_strained_layer_follows_terzaghi():
    ny = 80
    mat = Material.from_ecm(jnp.zeros((1, ny)), P.si())
    h = 1e-3
    c_v = float(mat.K[0, 0] * mat.M[0, 0])
    t_total = 0.3 * (h / 2) ** 2 / c_v  # up to T_v = 0.3
    errors = []
    for n_steps in (50, 100, 200):
        dt = t_total / n_steps
        op = thomas_factor(*consolidation_operator(mat, h / ny, dt))
        p0 = jnp.ones((1, ny))  # the undrained response to a sudden uniform strain
        p = jax.jit(lambda p, op=op, n=n_steps: jax.lax.fori_loop(0, n, lambda _, p: thomas_solve(op, p), p))(p0)
        U = 1 - float(jnp.mean(p))
        errors.append(abs(U - terzaghi_degree(0.3)))
    assert errors[-1] < 5e-3
    assert np.all(observed_orders([1, 0.5, 0.25], errors) > 0.8)  # implicit Euler: first order


def test_linear_symmetric_cycle_in_periodic_state_has_zero_mean_flow():
    beam = uniform_beam(n_segments=20, ny=12, steps=80)
    first = loading_cycle(beam, 1.0, 0.5e-3, 0.0)
    periodic = loading_cycle(beam, 1.0, 0.5e-3, 0.0, cycles=6)
    ratio_first = float(jnp.abs(first.mean_vy).max() / first.mean_abs_vy.max())
    ratio_periodic = float(jnp.abs(periodic.mean_vy).max() / periodic.mean_abs_vy.max())
    assert ratio_periodic < 1e-3 and ratio_first > 10 * ratio_periodic


def test_cycle_means_are_the_means_of_the_step_fields():
    """The cycle accumulates Σp and Σ|∂p/∂y| (v_f is linear in p); its means equal the
    step-by-step seepage fields averaged afterwards (Darcy, NumPy's gradient along x)."""
    beam = uniform_beam(n_segments=20, ny=12, steps=40)
    cycle = loading_cycle(beam, 1.0, 5e-3, 0.05, keep_fields=True)
    vy, p = np.asarray(cycle.fields["vy"][1:]), np.asarray(cycle.fields["p"][1:])
    k_over_phi = np.asarray(beam.material.K / beam.material.phi)
    vx = -k_over_phi * np.gradient(p, float(beam.ds), axis=1)
    np.testing.assert_allclose(cycle.mean_vy, vy.mean(axis=0), rtol=1e-10, atol=1e-12 * np.abs(vy).max())
    np.testing.assert_allclose(cycle.mean_abs_vy, np.abs(vy).mean(axis=0), rtol=1e-10)
    np.testing.assert_allclose(cycle.mean_vx, vx.mean(axis=0), rtol=1e-10, atol=1e-12 * np.abs(vx).max())


def test_cycle_gradient_stores_carries_not_step_intermediates():
    """The reverse pass of a cycle (80 steps: 5 chunks of 16) recomputes each step of
    the chunk it reverses from the step's carry and Newton root: XLA's buffers hold
    under 100 section fields (n − 1) × ny, where keeping every step's Gauss-point
    stresses and Newton matrices took about 180."""
    beam = uniform_beam(n_segments=20, ny=12, law="neo-hookean", steps=80)

    def loss(scale):
        cycle = loading_cycle(eqx.tree_at(lambda b: b.material.E, beam, beam.material.E * scale), 1.0, 5e-3, 0.05)
        return jnp.sum(cycle.mean_abs_vy) + cycle.post_force_max_N

    analysis = jax.jit(jax.grad(loss)).lower(1.0).compile().memory_analysis()
    assert analysis.temp_size_in_bytes < 100 * beam.material.E.nbytes


def test_batched_cycles_call_no_lapack_kernel():
    """A batch of cycles (as posterior draws or sweeps run them) compiles to XLA's own
    operations: the Newton solve marches (`_volterra_solve`), with no LAPACK custom call,
    whose batched CPU kernels can deadlock when XLA runs two of them at once."""
    import re

    beam = uniform_beam(n_segments=20, ny=12, steps=16)

    def force(scale):
        return loading_cycle(eqx.tree_at(lambda b: b.material.E, beam, beam.material.E * scale), 1.0, 5e-3, 0.05).post_force_max_N

    text = jax.jit(jax.vmap(jax.value_and_grad(force))).lower(jnp.array([1.0, 1.5])).compile().as_text()
    assert not [t for t in re.findall(r'custom_call_target="([^"]+)"', text) if "lapack" in t]


def test_cycle_time_stepping_converges_at_first_order():
    values = []
    for steps in (50, 100, 200, 400):
        c = loading_cycle(uniform_beam(n_segments=20, ny=12, steps=steps), 1.0, 5e-3, 0.05)
        values.append(float(c.mean_abs_vy.max()))
    diffs = np.abs(np.diff(values))
    order = np.log2(diffs[:-1] / diffs[1:])
    assert np.all(order > 0.8), (values, order)


def test_waveform_shape_and_derivatives():
    t = jnp.linspace(0, 1, 401)
    u = waveform(t, 1.0, 5.0, 0.05)
    assert float(u[0]) == 0 and float(u.max()) == pytest.approx(5.0) and float(u[200]) == pytest.approx(5.0)
    assert float(waveform(0.03, 1.0, 5.0, 0.05)) == 0.0
    for arg, h in ((1, 1e-6), (2, 1e-6), (3, 1e-7)):
        f = lambda *a: waveform(0.3, *a)  # noqa: E731
        x = [1.0, 5.0, 0.05]
        g = jax.grad(f, argnums=arg - 1)(*x)
        up, dn = list(x), list(x)
        up[arg - 1] += h
        dn[arg - 1] -= h
        assert float(g) == pytest.approx(float(f(*up) - f(*dn)) / (2 * h), rel=1e-5)


@pytest.mark.parametrize("P_over_PE", [0.9, -0.7])  # compression; tension (stretching centre line)
def test_structured_jacobian_equals_forward_mode(P_over_PE):
    beam = uniform_beam(n_segments=20, ny=8, law="neo-hookean")
    key1, key2 = jax.random.split(jax.random.PRNGKey(0))
    z = (beam.rest_state() + 0.1 * jax.random.normal(key1, (21,))).at[-1].set(P_over_PE)
    a = 1e2 * jax.random.normal(key2, beam.material.E.shape)
    args = (1e-3, a, 0.1 * a)
    structured, forward = eqx.filter_jit(lambda b, z, args: (b.jacobian(z, args), jax.jacfwd(b.residual)(z, args)))(beam, z, args)
    np.testing.assert_allclose(structured, forward, rtol=1e-12, atol=1e-12)


@pytest.mark.parametrize("P_over_PE", [0.9, -0.7, 0.0, 3.5])
def test_structured_newton_solve_equals_dense_lu(P_over_PE):
    """NewtonMatrix.solve (triangular sweep + 2 × 2 border) against LU of the dense J."""
    beam = uniform_beam(n_segments=20, ny=8, law="neo-hookean")
    key1, key2, key3 = jax.random.split(jax.random.PRNGKey(1), 3)
    z = (beam.rest_state() + 0.1 * jax.random.normal(key1, (21,))).at[-1].set(P_over_PE)
    a = 1e2 * jax.random.normal(key2, beam.material.E.shape)
    _, J = beam.linearise(z, (1e-3, a, 0.1 * a))
    rhs = jax.random.normal(key3, (21,))
    expected = np.linalg.solve(np.asarray(J.dense()), np.asarray(rhs))
    np.testing.assert_allclose(J.solve(rhs), expected, rtol=1e-11, atol=1e-11 * np.abs(expected).max())


def test_equilibrium_derivative_is_the_implicit_function_theorem():
    """d(post force)/dE of a drained equilibrium against central differences."""
    base = uniform_beam(n_segments=20, ny=8, law="neo-hookean")
    start = static_elastica(base, 2e-3)  # Newton's start, the same for every E

    @jax.jit
    def force(scale):
        beam = eqx.tree_at(lambda b: b.material.E, base, base.material.E * scale)
        z, _ = beam.equilibrium(2e-3, start)
        return z[-1] * beam.euler_load()

    g = jax.jit(jax.grad(force))(1.0)
    h = 1e-4
    fd = (force(1 + h) - force(1 - h)) / (2 * h)
    assert float(g) == pytest.approx(float(fd), rel=1e-6)


@pytest.mark.parametrize("dkappa_per_m", [-150.0, 40.0, 200.0])  # surface strains up to 10 %
def test_neo_hookean_section_moment_converges_to_its_integral(dkappa_per_m):
    """M = −d (E'/3) ∫ [(1 − Δκ y) − (1 − Δκ y)⁻²] y dy over a uniform section, in
    closed form (w = 1 − Δκ y: ∫ y w⁻² dy = [(1/w + ln w)/Δκ²]); two Gauss points per
    cell converge at fourth order in the cell size."""
    k, errors, cells = dkappa_per_m, [], (4, 8, 16)
    for ny in cells:
        beam = uniform_beam(n_segments=10, ny=ny, law="neo-hookean")
        geo = beam.geometry
        h, d, E = float(geo.thickness), float(geo.depth), float(beam.material.E_plane[0, 0])
        G = lambda w: (1 / w + np.log(w)) / k**2  # noqa: E731
        expected = -d * E / 3 * (-k * h**3 / 12 - (G(1 - k * h / 2) - G(1 + k * h / 2)))
        moment = np.asarray(beam.elastic_moment(jnp.full(9, k)))
        assert np.ptp(moment) <= 1e-15 * abs(expected)
        errors.append(abs(moment[0] - expected) / abs(expected))
    assert errors[-1] < 1e-7
    assert np.all(observed_orders(1 / np.asarray(cells), errors) > 3.8), errors


def test_prepared_section_constants_change_nothing():
    """`Beam.prepared()` (the section constants computed once, as a loading cycle
    does) gives the same residual and Jacobian as computing them on each call, on a
    graded section."""
    n, ny = 12, 8
    m = jnp.linspace(0.0, 0.6, (n - 1) * ny).reshape(n - 1, ny) ** 2
    beam = Beam(Geometry.from_params(P.si(), "bottom"), Material.from_ecm(m, P.si()), BeamGrid(n_segments=n, steps_per_cycle=20))
    prepared = beam.prepared()
    assert beam.section is None and prepared.section is not None
    key1, key2 = jax.random.split(jax.random.PRNGKey(2))
    z = (beam.rest_state() + 0.05 * jax.random.normal(key1, (n + 1,))).at[-1].set(0.8)
    a = 1e2 * jax.random.normal(key2, (n - 1, ny))
    args = (1e-3, a, 0.1 * a)
    both = eqx.filter_jit(lambda b, z, args: (b.residual(z, args), b.jacobian(z, args)))
    for got, want in zip(both(prepared, z, args), both(beam, z, args)):
        np.testing.assert_allclose(got, want, rtol=1e-13, atol=1e-15)
