"""jax.grad through the whole static run against central finite differences."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jaxtissue as jt

# the same discrete map for every parameter value (no adaptive-step noise in the FD)
OPTIONS = jt.SolverOptions(fixed_steps=300, dt0_s=1.0)
GRID = jt.Grid(ny=20)
NAMES = ["k_c_max", "k_a", "k_m0", "o_m", "D_o0"]


def three_week(p):
    r = jt.simulate(p, t_end_s=jt.THREE_WEEKS_S, grid=GRID, options=OPTIONS)
    return jnp.stack([r.collagen_mg_per_g[-1], r.dna_ug_per_g[-1]])


@pytest.fixture(scope="module")
def jacobian():
    p = jax.tree_util.tree_map(jnp.asarray, jt.paper_parameters())
    return jax.jit(jax.jacrev(three_week))(p)


@pytest.mark.parametrize("name", NAMES)
def test_gradient_matches_central_differences(jacobian, name):
    p = jt.paper_parameters()
    value = getattr(p, name)
    eps = 1e-4 * abs(value)
    fd = (three_week(p.replace(**{name: value + eps})) - three_week(p.replace(**{name: value - eps}))) / (2 * eps)
    ad = np.asarray(getattr(jacobian, name))
    rel = np.abs(ad - np.asarray(fd)) / np.abs(np.asarray(fd))
    assert np.all(rel < 1e-4), (name, ad, fd, rel)


ADAPTIVE = jt.SolverOptions(rtol=1e-9, atol=1e-12)


def test_fixed_steps_are_accurate():
    """The fixed geometric steps used above reproduce the adaptive solution closely."""
    p = jt.paper_parameters()
    adaptive = jt.simulate(p, t_end_s=jt.THREE_WEEKS_S, grid=GRID, options=ADAPTIVE)
    fixed = three_week(p)
    np.testing.assert_allclose(np.asarray(fixed), [adaptive.collagen_mg_per_g[-1], adaptive.dna_ug_per_g[-1]], rtol=1e-5)


@pytest.mark.slow  # vmapped forward runs: tests/test_simulate.py::test_jit_and_vmap_over_parameters
def test_vmapped_gradients_equal_one_at_a_time():
    # adaptive steps: in a batch, a finished trajectory is stepped with h = 0 (discarded);
    # that must not turn the batch's gradients into NaN
    def collagen(k_m0):
        r = jt.simulate(jt.paper_parameters(k_m0=k_m0), t_end_s=2.0e5, grid=jt.Grid(ny=8))
        return r.collagen_mg_per_g[-1]

    ks = jnp.array([2.0e-7, 4.0e-7])
    batched = jax.jit(jax.vmap(jax.grad(collagen)))(ks)
    single = jnp.stack([jax.jit(jax.grad(collagen))(k) for k in ks])
    assert np.all(np.isfinite(batched))
    np.testing.assert_allclose(batched, single, rtol=1e-8)


def test_adaptive_gradient_with_a_saved_series_matches_central_differences():
    """Adaptive steps and the series saved, as users run: the checkpointed adjoint
    recomputes the steps from a few stored states, and must retrace the forward pass's
    time grid (`numerics.ReproducibleSteps`; ~1550 steps here)."""
    paper = jt.paper_parameters()

    def collagen(p):  # D_c = χ = 0 held untraced, as in a fit of the kinetic parameters
        r = jt.simulate(p.replace(D_c=paper.D_c, chi=paper.chi), t_end_s=jt.THREE_WEEKS_S, grid=GRID, options=ADAPTIVE)
        return r.collagen_mg_per_g[-1]

    p = jax.tree_util.tree_map(jnp.asarray, paper)
    value_and_grad = jax.jit(jax.value_and_grad(collagen))  # one program for both
    eps = 1e-4 * paper.k_m0
    fd = (float(value_and_grad(p.replace(k_m0=p.k_m0 + eps))[0]) - float(value_and_grad(p.replace(k_m0=p.k_m0 - eps))[0])) / (2 * eps)
    ad = float(value_and_grad(p)[1].k_m0)
    assert abs(ad - fd) < 2e-5 * abs(fd), (ad, fd)


@pytest.mark.slow  # cheaper: test_simulate.py's series by intervals; its gradient in test_posterior_study.py's log likelihood
def test_static_series_by_intervals_agrees_and_differentiates():
    """`SolverOptions(static_series="intervals")` (one solve per coupling interval, no
    host callback): the dense run's series to the tolerance, and its gradient against
    central differences."""
    paper = jt.paper_parameters()
    week = jt.THREE_WEEKS_S / 3
    keys = ("dna_ug_per_g", "collagen_mg_per_g", "E_eff_kPa")

    def run(p, series):
        options = jt.SolverOptions(rtol=1e-9, atol=1e-12, static_series=series)
        return jt.simulate(p.replace(D_c=paper.D_c, chi=paper.chi), t_end_s=jt.THREE_WEEKS_S, grid=jt.Grid(ny=8),
                           coupling_interval_s=week, options=options)

    def collagen(p):  # and the series, from the same program
        r = run(p, "intervals")
        return r.collagen_mg_per_g[-1], {k: getattr(r, k) for k in keys}

    value_and_grad = jax.jit(jax.value_and_grad(collagen, has_aux=True))
    p = jax.tree_util.tree_map(jnp.asarray, paper)
    (_, series), grad = value_and_grad(p)
    dense = run(paper, "dense")
    for key in keys:
        np.testing.assert_allclose(np.asarray(series[key]), np.asarray(getattr(dense, key)), rtol=1e-7, err_msg=key)
    eps = 1e-4 * paper.k_m0
    fd = (float(value_and_grad(p.replace(k_m0=p.k_m0 + eps))[0][0]) - float(value_and_grad(p.replace(k_m0=p.k_m0 - eps))[0][0])) / (2 * eps)
    assert float(grad.k_m0) == pytest.approx(fd, rel=2e-5)


@pytest.mark.slow  # adaptive steps, cheaper: test_adaptive_gradient_with_a_saved_series_matches_central_differences
def test_adaptive_checkpointed_gradient_matches_central_differences():
    """Adaptive steps and the default checkpointed adjoint, whose reverse pass recomputes
    steps from a few stored states: at a tight tolerance the gradient must match central
    differences (a recomputation that strays from the forward steps breaks this, and so
    did stage 0 fed with the primal output of the probe's `jax.linearize`: 5e-3 off)."""
    options = jt.SolverOptions(rtol=1e-10, atol=1e-13)

    def collagen(k):
        r = jt.simulate(jt.paper_parameters().replace(k_c_max=k), t_end_s=jt.THREE_WEEKS_S, grid=jt.Grid(ny=60), options=options, save="end")
        return r.collagen_mg_per_g[-1]

    k = jnp.asarray(1.24e-5)
    eps = 1e-4 * 1.24e-5
    f = jax.jit(collagen)
    fd = (f(k + eps) - f(k - eps)) / (2 * eps)
    ad = jax.jit(jax.grad(collagen))(k)
    assert abs(float(ad) - float(fd)) < 1e-4 * abs(float(fd)), (float(ad), float(fd))


def test_rodas4p2_derivative_matches_central_differences():
    """The order-4 stepper (`SolverOptions(method="rodas4p2")`, its J̃ differentiated
    with the step), forward mode: the derivative of 3-week collagen w.r.t. k_m0 against
    central differences (reverse mode: the slow test below)."""
    paper = jt.paper_parameters()
    options = jt.SolverOptions(rtol=1e-8, atol=1e-11, method="rodas4p2", autodiff="forward")

    def collagen(k):
        return jt.simulate(paper.replace(k_m0=k), t_end_s=jt.THREE_WEEKS_S, grid=jt.Grid(ny=8), options=options, save="end").collagen_mg_per_g[-1]

    value_and_tangent = jax.jit(lambda k: jax.jvp(collagen, (k,), (jnp.ones_like(k),)))
    k, eps = jnp.asarray(paper.k_m0), 1e-4 * paper.k_m0
    fd = (float(value_and_tangent(k + eps)[0]) - float(value_and_tangent(k - eps)[0])) / (2 * eps)
    assert float(value_and_tangent(k)[1]) == pytest.approx(fd, rel=2e-5)


@pytest.mark.slow  # reverse mode's compile (~12 s); forward mode: test_rodas4p2_derivative_matches_central_differences
def test_rodas4p2_gradient_matches_central_differences():
    """The order-4 stepper (`SolverOptions(method="rodas4p2")`, its J̃ differentiated
    with the step): adaptive steps, the checkpointed adjoint, the gradient of 3-week
    collagen against central differences."""
    paper = jt.paper_parameters()
    options = jt.SolverOptions(rtol=1e-8, atol=1e-11, method="rodas4p2")

    def collagen(p):
        r = jt.simulate(p.replace(D_c=paper.D_c, chi=paper.chi), t_end_s=jt.THREE_WEEKS_S, grid=jt.Grid(ny=8), options=options, save="end")
        return r.collagen_mg_per_g[-1]

    value_and_grad = jax.jit(jax.value_and_grad(collagen))
    p = jax.tree_util.tree_map(jnp.asarray, paper)
    eps = 1e-4 * paper.k_m0
    fd = (float(value_and_grad(p.replace(k_m0=p.k_m0 + eps))[0]) - float(value_and_grad(p.replace(k_m0=p.k_m0 - eps))[0])) / (2 * eps)
    assert float(value_and_grad(p)[1].k_m0) == pytest.approx(fd, rel=2e-5)
