"""The bounded Levenberg–Marquardt solver (`jaxtissue.numerics.LevenbergMarquardt`) on
problems with known solutions: an optimum on a bound, bounded linear least squares
against SciPy, stalls, step caps, vmapped batches and failed model evaluations."""

import jax
import jax.numpy as jnp
import numpy as np
import optimistix as optx
import pytest

from jaxtissue.numerics import LevenbergMarquardt


def rosenbrock(t, args=None):
    return jnp.stack([10 * (t[1] - t[0] ** 2), 1 - t[0]])


def test_levenberg_marquardt_reaches_an_optimum_on_a_bound_and_stops():
    """Rosenbrock residuals (10(t₁ − t₀²), 1 − t₀) in the box t₀ ≤ 0.5: the optimum is
    on the bound, (0.5, 0.25), where χ² = 0.25 stays > 0. The solve reaches it and stops
    by itself, with far fewer Jacobians than steps (Broyden updates between them), and
    returns the exact Jacobian at its end."""
    lo, hi = jnp.array([-2.0, -1.0]), jnp.array([0.5, 3.0])
    seen = []

    def residual(t, args):  # NaN outside the box: every evaluated point must lie inside
        jax.debug.callback(lambda v: seen.append(np.asarray(v)), t)
        return jnp.where(jnp.all((t >= lo) & (t <= hi)), rosenbrock(t), jnp.nan)

    solver = LevenbergMarquardt(rtol=1e-8, atol=1e-8, ftol=1e-10, lower=lo, upper=hi)
    sol = optx.least_squares(residual, solver, jnp.array([-1.2, 1.0]), max_steps=100, throw=False)
    assert sol.result == optx.RESULTS.successful
    np.testing.assert_allclose(sol.value, [0.5, 0.25], atol=1e-6)
    assert float(jnp.sum(sol.state.residual**2)) == pytest.approx(0.25, rel=1e-8)
    steps, jacobians = int(sol.stats["num_steps"]), int(sol.stats["jacobian_evaluations"])
    assert steps < 40 and jacobians <= steps // 3, (steps, jacobians)  # measured: 18 steps, 3 Jacobians
    assert int(sol.stats["residual_evaluations"]) == steps
    assert bool(sol.state.exact)
    np.testing.assert_allclose(sol.state.jac, jax.jacfwd(rosenbrock)(sol.value), rtol=1e-12)
    seen = np.array(seen)
    assert len(seen) > steps and np.all((seen >= np.asarray(lo)) & (seen <= np.asarray(hi)))


def test_levenberg_marquardt_in_a_box_solves_bounded_linear_least_squares_as_scipy():
    """r = A t − b with the unconstrained minimum outside the box: the active set ends
    on the constrained minimum, which SciPy's `lsq_linear` computes independently."""
    from scipy.optimize import lsq_linear

    rng = np.random.default_rng(1)
    A, b = rng.standard_normal((8, 4)), rng.standard_normal(8) * 3
    lo, hi = np.full(4, -0.2), np.full(4, 0.2)
    expected = lsq_linear(A, b, bounds=(lo, hi), tol=1e-14).x
    assert np.sum(np.isclose(np.abs(expected), 0.2)) >= 2  # several bounds are active
    solver = LevenbergMarquardt(rtol=1e-10, atol=1e-10, ftol=1e-14, lower=lo, upper=hi)
    sol = optx.least_squares(lambda t, _: jnp.asarray(A) @ t - jnp.asarray(b), solver, jnp.zeros(4), max_steps=100)
    np.testing.assert_allclose(sol.value, expected, atol=1e-8)


def test_levenberg_marquardt_stops_when_every_step_is_uphill():
    """r(u) = 1 + |u| with a Jacobian that sees only 1 + u/2 (as round-off in an adaptive
    model can hide a kink from its derivative): from u = 0 every step is uphill and
    rejected; the solve stops once the damped step is below the tolerance in u, at the
    minimum, instead of raising λ until `max_steps`."""

    def residual(u, args):
        return 1 + 0.5 * u + jax.lax.stop_gradient(jnp.abs(u) - 0.5 * u)

    solver = LevenbergMarquardt(rtol=1e-5, atol=1e-5, ftol=1e-5)
    sol = optx.least_squares(residual, solver, jnp.zeros(1), max_steps=60, throw=False)
    assert int(sol.stats["jacobian_evaluations"]) == 1
    assert sol.result == optx.RESULTS.successful
    assert int(sol.stats["num_steps"]) < 15
    np.testing.assert_allclose(sol.value, 0.0, atol=1e-12)


def test_levenberg_marquardt_step_cap_is_an_argument():
    """One compiled solve serves fits and profile points with different step limits:
    with `cap_steps`, the last of `args` caps the steps (reported as not converged)."""
    solver = LevenbergMarquardt(rtol=1e-8, atol=1e-8, ftol=1e-10, cap_steps=True)

    def residual(u, args):
        return jnp.stack([10 * (u[1] - u[0] ** 2), 1 - u[0]])

    @jax.jit
    def solve(cap):
        sol = optx.least_squares(residual, solver, jnp.array([-1.2, 1.0]), (cap,), max_steps=100, throw=False)
        return sol.value, sol.stats["num_steps"], sol.result == optx.RESULTS.successful

    _, steps, ok = solve(np.asarray(5, np.int64))
    assert int(steps) == 5 and not bool(ok)
    value, steps, ok = solve(np.asarray(100, np.int64))
    assert bool(ok) and int(steps) < 100
    np.testing.assert_allclose(value, [1.0, 1.0], atol=1e-6)


def test_levenberg_marquardt_under_vmap_equals_single_solves():
    """A vmapped batch of starts (`[fit] batch > 1`) takes the same steps as each start
    alone (there the Jacobian refresh's `cond` runs both branches and selects)."""
    solver = LevenbergMarquardt(rtol=1e-8, atol=1e-8, ftol=1e-10, lower=jnp.array([-2.0, -1.0]), upper=jnp.array([0.5, 3.0]))

    def solve(t0):
        sol = optx.least_squares(rosenbrock, solver, t0, max_steps=100, throw=False)
        return sol.value, sol.stats["num_steps"], sol.stats["jacobian_evaluations"]

    starts = jnp.array([[-1.2, 1.0], [0.4, -0.5], [-0.3, 2.5]])
    batched = jax.jit(jax.vmap(solve))(starts)
    for k, t0 in enumerate(starts):
        value, steps, jacobians = jax.jit(solve)(t0)
        np.testing.assert_allclose(batched[0][k], value, rtol=1e-12, atol=1e-14)
        assert int(batched[1][k]) == int(steps) and int(batched[2][k]) == int(jacobians)


def test_levenberg_marquardt_steps_back_from_points_where_the_model_fails():
    """Rosenbrock residuals that are NaN below t₁ = −0.2 (as a failed solve's): trial
    points there are rejected, only raising λ, and the solve still reaches (1, 1)."""
    seen = []

    def residual(t, args):
        return jnp.where(t[1] < -0.2, jnp.nan, 1.0) * rosenbrock(t)

    solver = LevenbergMarquardt(rtol=1e-8, atol=1e-8, ftol=1e-10, record=lambda c: seen.append(float(c)))
    sol = optx.least_squares(residual, solver, jnp.array([-1.2, 1.0]), max_steps=100, throw=False)
    assert sol.result == optx.RESULTS.successful
    np.testing.assert_allclose(sol.value, [1.0, 1.0], atol=1e-6)
    assert np.sum(np.isnan(seen)) >= 1 and np.all(np.isfinite(np.asarray(sol.state.jac)))
