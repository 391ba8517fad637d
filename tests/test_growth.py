"""The growth model's spatial discretisation against independent references."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from helpers import frozen_cells, observed_orders

import jaxtissue as jt
from jaxtissue.growth import GrowthModel, has_cell_transport, o2_consumption, o2_diffusivity
from jaxtissue.state import State, Transport
from jaxtissue.params import nondimensionalise
from jaxtissue.simulate import SolverOptions, growth_solve

STEADY = SolverOptions(rtol=1e-10, atol=1e-13)


def steady_o2(params, grid, t_end_s=2.0e4, initial_state=None):
    r = jt.simulate(params, t_end_s=t_end_s, grid=grid, options=STEADY, initial_state=initial_state)
    return r.final, r


def test_diffusivity_limits_of_the_unit_cell():
    k = nondimensionalise(jt.paper_parameters())
    assert float(o2_diffusivity(0.0, k)) == pytest.approx(1.5e-5)
    assert float(o2_diffusivity(1.0, k)) == pytest.approx(1.5e-5 * 3 * 0.43 / (3 + 0.43 * 23.07))


def test_zero_order_steady_o2_is_the_analytic_parabola():
    """o_h → 0: D o'' = Q c, o(±h/2) = o_ext ⇒ o = o_ext − Q/(2D)(h²/4 − y²)."""
    p = frozen_cells(o_h=1e-12)
    ny = 50
    final, r = steady_o2(p, jt.Grid(ny=ny))
    y = np.asarray(r.y_cm)
    exact = 0.2 - 8.393e-4 / (2 * 1.5e-5) * (0.05**2 - y**2)
    # the half-cell Dirichlet closure is exact for a parabola up to O(dy²)
    np.testing.assert_allclose(np.asarray(final.o[0]), exact, atol=3 * (0.1 / ny) ** 2 * 28)
    assert exact.min() == pytest.approx(0.2 - 0.0699, abs=1e-3)  # docs/model.md §8


def test_first_order_steady_o2_converges_at_second_order():
    """o ≪ o_h: D o'' = (Q/o_h) o ⇒ o = o_ext cosh(y/λ)/cosh(h/2λ)."""
    p = frozen_cells(o_h=1e6, Q_o=3e4)
    lam = np.sqrt(1.5e-5 * 1e6 / 3e4)
    errors, hs = [], []
    for ny in (10, 20, 40, 80):
        final, r = steady_o2(p, jt.Grid(ny=ny), t_end_s=4000.0)
        y = np.asarray(r.y_cm)
        exact = 0.2 * np.cosh(y / lam) / np.cosh(0.05 / lam)
        errors.append(np.max(np.abs(np.asarray(final.o[0]) - exact)))
        hs.append(0.1 / ny)
    orders = observed_orders(hs, errors)
    assert orders[-1] > 1.9 and np.all(orders > 1.7), orders  # approaches 2


def _restrict(u):
    """Average 2 × 2 fine cells onto the coarse cell they tile."""
    return 0.25 * (u[0::2, 0::2] + u[1::2, 0::2] + u[0::2, 1::2] + u[1::2, 1::2])


def _steady_2d(nx, ny, limited=True):
    """Steady O2 on a 2-D grid with an ECM field and a lumped flow varying in x and y."""
    p = frozen_cells()
    k = nondimensionalise(p)
    grid = jt.Grid(nx=nx, ny=ny)
    x = np.asarray(grid.x_centres(2.5))[:, None]
    y = np.asarray(grid.y_centres(0.1))[None, :]
    m = 0.4 * (1 + np.cos(np.pi * x / 2.5)) * (1 - 4 * y**2 / 0.01) + 0.0 * y
    vy = -2e-3 * np.sin(np.pi * y / 0.1) * np.cos(np.pi * x / 5.0)
    vx = 1e-3 * np.sin(np.pi * x / 2.5) * np.cos(np.pi * y / 0.1)
    transport = Transport(vx=jnp.asarray(vx), vy=jnp.asarray(vy), dispersion=jnp.zeros(grid.shape))
    model = GrowthModel(k, grid, transport, advection="limited" if limited else "upwind")
    y0 = State(o=0.2 * jnp.ones(grid.shape), c=jnp.ones(grid.shape), m=jnp.asarray(m * np.ones(grid.shape)))
    ts = jnp.array([0.0, 3.0e5])
    sol = growth_solve(model, y0, 0.0, 3.0e5, ts, STEADY, (p, grid))
    return np.asarray(sol.ys.o[-1])


@pytest.mark.slow  # 2-D refinement with flow; 1-D second order: test_first_order_steady_o2_converges_at_second_order
def test_2d_steady_o2_with_flow_converges_at_second_order():
    """Grid refinement (Richardson) in 2-D: varying D_o(m), limited advection, ends."""
    sols = [_steady_2d(8 * 2**k, 8 * 2**k) for k in range(3)]
    diffs = [np.mean(np.abs(_restrict(sols[k + 1]) - sols[k])) for k in range(2)]
    order = np.log2(diffs[0] / diffs[1])
    # second order, approached from below: van Leer's limiter clips the smooth extrema
    assert order > 1.7, (diffs, order)


@pytest.mark.slow
def test_first_order_upwind_is_first_order():
    """The same study with plain upwinding: the limiter is what buys the second order."""
    sols = [_steady_2d(8 * 2**k, 8 * 2**k, limited=False) for k in range(3)]
    diffs = [np.mean(np.abs(_restrict(sols[k + 1]) - sols[k])) for k in range(2)]
    order = np.log2(diffs[0] / diffs[1])
    assert 0.7 < order < 1.5, (diffs, order)


def _random_state(grid, seed=0):
    key = jax.random.split(jax.random.PRNGKey(seed), 3)
    return State(
        o=0.2 * jax.random.uniform(key[0], grid.shape),
        c=0.5 + jax.random.uniform(key[1], grid.shape),
        m=0.3 * jax.random.uniform(key[2], grid.shape),
    )


def test_o2_budget_is_exact():
    """d/dt ∫o = surface influx − consumption, to round-off, for any state (2-D)."""
    grid = jt.Grid(nx=6, ny=9)
    k = nondimensionalise(jt.paper_parameters())
    model = GrowthModel(k, grid)
    y = _random_state(grid)
    dx, dy = model.spacing
    dodt = float(jnp.sum(model(0.0, y).o) * dx * dy)
    consumption = float(jnp.sum(o2_consumption(y.o, y.c, k)) * dx * dy)
    influx = float(model.o2_boundary_influx(y))
    assert dodt == pytest.approx(influx - consumption, rel=1e-12)


def test_steady_state_influx_balances_consumption():
    p = jt.paper_parameters()
    final, _ = steady_o2(frozen_cells(), jt.Grid(ny=40))
    k = nondimensionalise(p)
    model = GrowthModel(k, jt.Grid(ny=40))
    dx, dy = model.spacing
    consumption = float(jnp.sum(o2_consumption(final.o, final.c, k)) * dx * dy)
    assert float(model.o2_boundary_influx(final)) == pytest.approx(consumption, rel=1e-6)


def test_no_cell_flux_through_any_face():
    """With motility and chemotaxis, the transport terms only move cells around."""
    grid = jt.Grid(nx=5, ny=7)
    k = nondimensionalise(jt.paper_parameters(D_c=1e-6, chi=3e-6))
    model = GrowthModel(k, grid)
    y = _random_state(grid, seed=1)
    div = model.cell_flux_divergence(y.o, y.c)
    assert float(jnp.abs(div).max()) > 1e-6  # it does move cells
    assert abs(float(jnp.sum(div))) < 1e-12 * float(jnp.abs(div).sum())


def test_2d_static_run_equals_1d():
    """Uniform along x, the 2-D discretisation is the 1-D one: with multigrid or line
    relaxation in the O2 solve (a slightly different J̃, so other steps) to the
    solver's tolerance."""
    p = jt.paper_parameters()
    r1 = jt.simulate(p, t_end_s=4.0e5, grid=jt.Grid(nx=1, ny=20))
    m1 = np.broadcast_to(np.asarray(r1.final.m), (6, 20))
    for sweeps in (0, None):  # multigrid; 2 sweeps
        r = jt.simulate(p, t_end_s=4.0e5, grid=jt.Grid(nx=6, ny=20), options=jt.SolverOptions(o2_sweeps=sweeps))
        np.testing.assert_allclose(np.asarray(r.final.m), m1, rtol=0, atol=1e-4 * m1.max())
        np.testing.assert_allclose(np.asarray(r.dna_ug_per_g), np.asarray(r1.dna_ug_per_g), rtol=1e-5)


def test_cell_flux_is_dropped_only_when_known_to_be_zero():
    """With D_c = χ = 0 given as numbers the cell flux of (2.3) is skipped; a traced
    zero (being differentiated) keeps it; both runs agree."""
    p = jt.paper_parameters()
    assert not has_cell_transport(p)
    assert has_cell_transport(p.replace(D_c=1e-9)) and has_cell_transport(p.replace(chi=1e-9))
    seen = []

    def collagen(d_c, options=jt.SolverOptions()):
        seen.append(has_cell_transport(p.replace(D_c=d_c)))
        return jt.simulate(p.replace(D_c=d_c), t_end_s=1.0e5, grid=jt.Grid(ny=8), options=options).collagen_mg_per_g

    traced = jax.jit(collagen)(0.0)
    assert seen == [True]
    plain = jt.simulate(p, t_end_s=1.0e5, grid=jt.Grid(ny=8)).collagen_mg_per_g
    np.testing.assert_allclose(plain, traced, rtol=1e-10)  # round-off through adaptive steps
    # the derivative through the kept flux at D_c = 0 is finite (in forward mode: the same
    # local derivatives that reverse mode transposes, without compiling a reverse pass)
    forward = jt.SolverOptions(autodiff="forward")
    assert np.isfinite(float(jax.jacfwd(lambda d: collagen(d, forward)[-1])(0.0))) and seen == [True, True]
