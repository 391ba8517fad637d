"""The ROS34PW2 integrator: observed temporal order and agreement with diffrax's Kvaerno5."""

import diffrax
import jax.numpy as jnp
import numpy as np
from helpers import observed_orders

import jaxtissue as jt
from jaxtissue.growth import GrowthModel, State
from jaxtissue.params import nondimensionalise
from jaxtissue.solver import ROS34PW2

GRID = jt.Grid(ny=12)
COEFFS = nondimensionalise(jt.paper_parameters())
MODEL = GrowthModel(COEFFS, GRID)
T = 4.0e5


def _smooth_start():
    """The state after the initial O2 transient (so the solution is smooth in time)."""
    r = jt.simulate(jt.paper_parameters(), t_end_s=2.0e4, grid=GRID, options=jt.SolverOptions(rtol=1e-10, atol=1e-13))
    return r.final


def _solve(solver, y0, controller, dt0=None):
    sol = diffrax.diffeqsolve(
        diffrax.ODETerm(MODEL), solver, 0.0, T, dt0, y0,
        stepsize_controller=controller, max_steps=100000,
    )
    return jnp.concatenate([sol.ys.o[-1].ravel(), sol.ys.c[-1].ravel(), sol.ys.m[-1].ravel()])


def test_third_order_in_time():
    y0 = _smooth_start()
    reference = _solve(diffrax.Kvaerno5(), y0, diffrax.PIDController(rtol=1e-12, atol=1e-14), dt0=1.0)
    ns = [4, 8, 16, 32]
    errors = [float(jnp.max(jnp.abs(_solve(ROS34PW2(), y0, diffrax.ConstantStepSize(), T / n) - reference))) for n in ns]
    orders = observed_orders([T / n for n in ns], errors)
    assert np.all(orders[1:] > 2.7), (errors, orders)


def test_adaptive_solution_matches_kvaerno5():
    y0 = State.initial(COEFFS, GRID)
    reference = _solve(diffrax.Kvaerno5(), y0, diffrax.PIDController(rtol=1e-11, atol=1e-14), dt0=1.0)
    ours = _solve(ROS34PW2(), y0, diffrax.PIDController(rtol=1e-8, atol=1e-11), dt0=1.0)
    assert float(jnp.max(jnp.abs(ours - reference))) < 1e-6
