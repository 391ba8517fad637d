"""The Rosenbrock integrators (ROS34PW2, Rodas4P2): their order conditions, observed
temporal order and agreement with diffrax's Kvaerno5; the structured linear algebra
against dense solves."""

import diffrax
import equinox as eqx
import jax
import jax.flatten_util
import jax.numpy as jnp
import numpy as np
import pytest
from helpers import observed_orders

import jaxtissue as jt
from jaxtissue.growth import GrowthModel
from jaxtissue.growth_jacobian import GrowthJacobian
from jaxtissue.limits import ExtrapolationWarning
from jaxtissue.numerics import (
    ROS34PW2,
    SOLVERS,
    AbstractStructuredField,
    FivePoint,
    Rescaled,
    Stacked,
    line_sweeps,
    stack,
    thomas_factor,
    thomas_solve,
)
from jaxtissue.params import nondimensionalise
from jaxtissue.simulate import METHODS, default_o2_sweeps
from jaxtissue.state import State

GRID = jt.Grid(ny=12)
COEFFS = nondimensionalise(jt.paper_parameters())
MODEL = GrowthModel(COEFFS, GRID)
T = 4.0e5


REFERENCE = diffrax.PIDController(rtol=1e-12, atol=1e-14)
"""Kvaerno5's tolerances for the references: one program for both below."""


def _smooth_start():
    """The state after the initial O2 transient (so the solution is smooth in time)."""
    r = jt.simulate(jt.paper_parameters(), t_end_s=2.0e4, grid=GRID, options=jt.SolverOptions(rtol=1e-10, atol=1e-13))
    return r.final


def _flat(y: State | jax.Array):
    return jnp.concatenate([y.o.ravel(), y.c.ravel(), y.m.ravel()]) if isinstance(y, State) else y


def _solve(solver, y0, controller, dt0=None, field=MODEL, t1=T):
    sol = diffrax.diffeqsolve(
        diffrax.ODETerm(field), solver, 0.0, t1, dt0, y0,
        stepsize_controller=controller, max_steps=100000,
    )
    return _flat(jax.tree_util.tree_map(lambda x: x[-1], sol.ys))


def test_third_order_in_time():
    y0 = _smooth_start()
    reference = _solve(diffrax.Kvaerno5(), y0, REFERENCE, dt0=1.0)
    ns = [4, 8, 16, 32]
    errors = [float(jnp.max(jnp.abs(_solve(ROS34PW2(), y0, diffrax.ConstantStepSize(), jnp.asarray(T / n)) - reference))) for n in ns]
    orders = observed_orders([T / n for n in ns], errors)
    assert np.all(orders[1:] > 2.7), (errors, orders)


@pytest.fixture(scope="module")
def kvaerno5_reference():
    y0 = State.initial(COEFFS, GRID)
    return y0, _solve(diffrax.Kvaerno5(), y0, REFERENCE, dt0=1.0)


@pytest.mark.parametrize("method", METHODS)
def test_adaptive_solution_matches_kvaerno5(method, kvaerno5_reference):
    y0, reference = kvaerno5_reference
    field = MODEL if method == "ros34pw2" else GrowthModel(COEFFS, GRID, cell_transport=False, exact_jacobian=True)  # as `simulate` has it
    ours = _solve(SOLVERS[method](), y0, diffrax.PIDController(rtol=1e-8, atol=1e-11), dt0=1.0, field=field)
    assert float(jnp.max(jnp.abs(ours - reference))) < 1e-6


def _standard_form(method):
    """(α, Γ, b, b̂) of a method given in the transformed variables (a, c, m, m̂)."""
    gamma_matrix = np.linalg.inv(np.eye(len(method.m)) / method.gamma - method.c)
    return method.a @ gamma_matrix, gamma_matrix, method.m @ gamma_matrix, method.m_embedded @ gamma_matrix


def _order_defects(alpha, gamma_matrix, b):
    """Each order's Rosenbrock order conditions, autonomous (Hairer & Wanner IV.7,
    Table 7.1), as the largest defect: {order: defect} to order 4."""
    g = gamma_matrix[0, 0]
    beta = np.tril(alpha + gamma_matrix, -1)
    a, bb = alpha.sum(1), beta.sum(1)
    conditions = {
        1: [b.sum() - 1],
        2: [b @ bb - (0.5 - g)],
        3: [b @ a**2 - 1 / 3, b @ beta @ bb - (1 / 6 - g + g * g)],
        4: [b @ a**3 - 1 / 4, b @ (a * (alpha @ bb)) - (1 / 8 - g / 3), b @ beta @ a**2 - (1 / 12 - g / 3),
            b @ beta @ beta @ bb - (1 / 24 - g / 2 + 1.5 * g * g - g**3)],
    }
    return {order: max(abs(d) for d in defects) for order, defects in conditions.items()}


@pytest.mark.parametrize("method", METHODS)
def test_tableaus_satisfy_their_order_conditions(method):
    """Each method's coefficients: order p (its error estimate's one less and not p),
    one γ on the diagonal, L-stable (R(∞) = 1 − bᵀ(α + Γ)⁻¹1 = 0)."""
    solver = SOLVERS[method]
    alpha, gamma_matrix, b, b_hat = _standard_form(solver)
    p = solver.method_order
    np.testing.assert_allclose(np.diag(gamma_matrix), solver.gamma, rtol=1e-14)
    defects, embedded = _order_defects(alpha, gamma_matrix, b), _order_defects(alpha, gamma_matrix, b_hat)
    assert all(defects[k] < 1e-13 for k in range(1, p + 1)), defects
    assert all(embedded[k] < 1e-13 for k in range(1, p)) and embedded[p] > 1e-3, embedded
    ones = np.ones(len(b))
    assert abs(1 - b @ np.linalg.solve(alpha + gamma_matrix, ones)) < 1e-13
    assert set(SOLVERS) == set(METHODS)


class _DenseField(AbstractStructuredField):
    """A small nonlinear ODE (a damped oscillator with cubic terms) factoring its exact
    Jacobian densely: where each method shows its classical order."""

    def __call__(self, t, y, args):
        return jnp.stack([y[1] + 0.5 * y[0] * (1 - y[0] ** 2), -y[0] - 0.3 * y[1] ** 3])

    def shifted_factor(self, t, y, args, a):
        return _DenseFactor(a * jnp.eye(y.size) - jax.jacfwd(lambda z: self(t, z, args))(y))


class _DenseFactor(eqx.Module):
    matrix: jax.Array

    def solve(self, r):
        return jnp.linalg.solve(self.matrix, r)


@pytest.mark.parametrize("method", METHODS)
def test_each_method_has_its_order_with_an_exact_jacobian(method):
    y0, t1 = jnp.array([1.0, 0.5]), 4.0
    reference = _solve(diffrax.Kvaerno5(), y0, diffrax.PIDController(rtol=1e-13, atol=1e-15), dt0=0.01, field=_DenseField(), t1=t1)
    ns = [32, 64, 128, 256]
    solve = jax.jit(lambda dt: _solve(SOLVERS[method](), y0, diffrax.ConstantStepSize(), dt, field=_DenseField(), t1=t1))
    errors = [float(jnp.max(jnp.abs(solve(jnp.asarray(t1 / n)) - reference))) for n in ns]
    orders = observed_orders([t1 / n for n in ns], errors)
    p = SOLVERS[method].method_order
    assert np.all(orders > p - 0.15) and abs(orders[-1] - p) < 0.25, (errors, orders)  # approached from above


@pytest.mark.parametrize("method", METHODS)
def test_each_methods_dense_output_converges(method):
    """Values inside steps (`SaveAt(ts=...)`): ROS34PW2's cubic Hermite interpolant and
    Rodas4P2's own from its stages, on the ODE above, converge at third order or better
    (local error O(h⁴) of an order-3 interpolant)."""
    y0, t1 = jnp.array([1.0, 0.5]), 4.0
    ts = t1 * jnp.array([0.3, 0.55, 0.8])  # inside steps for every n below

    def solve(solver, controller, dt0):
        return diffrax.diffeqsolve(diffrax.ODETerm(_DenseField()), solver, 0.0, t1, dt0, y0, stepsize_controller=controller,
                                   saveat=diffrax.SaveAt(ts=ts), max_steps=100000).ys

    reference = solve(diffrax.Kvaerno5(), diffrax.PIDController(rtol=1e-13, atol=1e-15), 0.01)
    ns = [16, 32, 64, 128]
    run = jax.jit(lambda dt: solve(SOLVERS[method](), diffrax.ConstantStepSize(), dt))
    errors = [float(jnp.max(jnp.abs(run(jnp.asarray(t1 / n)) - reference))) for n in ns]
    # a line through log error against log step: the points' θ within their steps
    # change with n, and with them the interpolant's error constant
    order = np.polyfit(np.log(t1 / np.asarray(ns)), np.log(errors), 1)[0]
    assert order > 2.8 and np.all(np.diff(errors) < 0), (errors, order)


def test_a_solve_in_unit_time_and_stacked_is_the_same_discrete_map():
    """What `growth_solve` integrates: `Rescaled` (n steps of 1/n in s = t/T take the
    steps of T/n in t) of `Stacked` (o, c, m stacked in one array), to round-off."""
    y0 = State.initial(COEFFS, GRID)
    in_t = _solve(ROS34PW2(), y0, diffrax.ConstantStepSize(), jnp.asarray(T / 8))
    field = Rescaled(Stacked(MODEL, jax.tree_util.tree_structure(y0)), T)
    sol = diffrax.diffeqsolve(diffrax.ODETerm(field), ROS34PW2(), 0.0, 1.0, jnp.asarray(1 / 8), stack(y0),
                              stepsize_controller=diffrax.ConstantStepSize())
    np.testing.assert_allclose(sol.ys[-1].ravel(), in_t, rtol=1e-12, atol=1e-14)
    assert float(jnp.max(jnp.abs(in_t - _flat(y0)))) > 1e-2  # the state moved


def _dense_five_point(op: FivePoint) -> np.ndarray:
    """The operator as a dense matrix (columns: its action on unit vectors)."""
    nx, ny = op.diag.shape
    eye = np.eye(nx * ny).reshape(nx * ny, nx, ny)
    return np.stack([np.asarray(op(jnp.asarray(e))).ravel() for e in eye], axis=1)


def test_structured_solves_equal_dense_solves():
    rng = np.random.default_rng(1)
    # Thomas: batched systems along the last axis, under vmap, and its transpose (grad)
    n = 9
    sub, sup = -rng.random((2, 3, n)), -rng.random((2, 3, n))
    diag = 2.5 + rng.random((2, 3, n))
    r = rng.random((2, 3, n))
    x = np.asarray(thomas_solve(thomas_factor(*map(jnp.asarray, (sub, diag, sup))), jnp.asarray(r)))
    for i in range(2):
        for j in range(3):
            A = np.diag(diag[i, j]) + np.diag(sub[i, j, 1:], -1) + np.diag(sup[i, j, :-1], 1)
            np.testing.assert_allclose(x[i, j], np.linalg.solve(A, r[i, j]), rtol=1e-12)
    A = np.diag(diag[0, 0]) + np.diag(sub[0, 0, 1:], -1) + np.diag(sup[0, 0, :-1], 1)
    w = rng.random(n)
    g = jax.grad(lambda b: jnp.dot(w, thomas_solve(thomas_factor(*map(jnp.asarray, (sub[0, 0], diag[0, 0], sup[0, 0]))), b)))(jnp.asarray(r[0, 0]))
    np.testing.assert_allclose(g, np.linalg.solve(A.T, w), rtol=1e-12)
    batched = jax.vmap(lambda d, b: thomas_solve(thomas_factor(jnp.asarray(sub[0]), d, jnp.asarray(sup[0])), b))(jnp.asarray(diag), jnp.asarray(r))
    np.testing.assert_allclose(batched[1], [np.linalg.solve(np.diag(diag[1, j]) + np.diag(sub[0, j, 1:], -1) + np.diag(sup[0, j, :-1], 1), r[1, j]) for j in range(3)], rtol=1e-12)
    # the growth Jacobian's shifted solve, 1-D (Thomas) and 2-D (multigrid, cycled to
    # convergence), against the dense (a I - J~) of the same probed blocks
    # (and in 1-D with m's 5-point coupling into o, `om`: Rodas4P2's exact Jacobian)
    for shape, with_om in (((1, 7), False), ((4, 5), False), ((1, 7), True)):
        f = lambda k: jnp.asarray(rng.random(shape) * k)  # noqa: E731
        x_on = shape[0] > 1
        om = FivePoint(-f(0.2), f(0.1), f(0.1), f(0.1) * x_on, f(0.1) * x_on) if with_om else None
        jac = GrowthJacobian(oo_diag=-2 - f(1), oo_south=f(0.5), oo_north=f(0.5), oo_west=f(0.4) * x_on,
                             oo_east=f(0.4) * x_on, oc=-f(0.3), co=f(0.2), cc=-f(0.5), mo=f(0.1), mc=f(0.1), mm=-f(0.2), om=om)
        a = jnp.asarray(3.0)
        rhs = State(o=f(1), c=f(1), m=f(1))
        x = jac.factor(a, 0, cycles=40).solve(rhs)
        Z = np.zeros((shape[0] * shape[1],) * 2)
        oo = _dense_five_point(FivePoint(jac.oo_diag, jac.oo_south, jac.oo_north, jac.oo_west, jac.oo_east))
        d = lambda v: np.diag(np.asarray(v).ravel())  # noqa: E731
        J = np.block([[oo, d(jac.oc), _dense_five_point(om) if with_om else Z], [d(jac.co), d(jac.cc), Z], [d(jac.mo), d(jac.mc), d(jac.mm)]])
        dense = np.linalg.solve(a * np.eye(J.shape[0]) - J, np.concatenate([np.asarray(v).ravel() for v in (rhs.o, rhs.c, rhs.m)]))
        np.testing.assert_allclose(np.concatenate([np.asarray(v).ravel() for v in (x.o, x.c, x.m)]), dense, rtol=1e-10)


def test_an_exact_jacobian_is_the_growth_models_jacobian():
    """`GrowthModel(exact_jacobian=True)` on a 1-D grid without cell flux (Rodas4P2's
    runs): the factored a I − J̃ solves with the model's own Jacobian (dense, jacfwd)."""
    model = GrowthModel(COEFFS, GRID, cell_transport=False, exact_jacobian=True)
    y0 = State.initial(COEFFS, GRID)
    rng = np.random.default_rng(3)
    y = State(o=y0.o * (0.3 + 0.6 * rng.random(y0.o.shape)), c=y0.c * (1 + rng.random(y0.c.shape)), m=jnp.asarray(0.2 * rng.random(y0.m.shape)))
    flat, unflatten = jax.flatten_util.ravel_pytree(y)
    J = np.asarray(jax.jit(jax.jacfwd(lambda z: jax.flatten_util.ravel_pytree(model(0.0, unflatten(z)))[0]))(flat))
    assert np.abs(J[: GRID.ny, -GRID.ny :]).max() > 0  # o depends on m (through D_o): a coupling J̃ keeps
    a = jnp.asarray(10.0 / np.abs(J).max())
    r = jnp.asarray(rng.random(flat.shape))
    solve = jax.jit(lambda m, y, r: jax.flatten_util.ravel_pytree(m.shifted_factor(0.0, y, None, a).solve(unflatten(r)))[0])
    dense = np.linalg.solve(a * np.eye(J.shape[0]) - J, np.asarray(r))
    np.testing.assert_allclose(solve(model, y, r), dense, rtol=1e-10, atol=1e-12 * np.abs(dense).max())
    inexact = solve(GrowthModel(COEFFS, GRID, cell_transport=False), y, r)  # the default J̃ drops D_o(m)
    assert np.abs(inexact - dense).max() > 1e-6 * np.abs(dense).max()


@pytest.mark.slow  # memory of one step's reverse pass; a 2-D step's: test_a_2d_solve_probes_one_colour_at_a_time
def test_a_steps_reverse_pass_keeps_few_residuals():
    """The reverse pass of one step stores its stage states and the O2 solves' line
    factors, not the right-hand side's intermediates (which are recomputed; storing them
    took ~560 fields of the grid): this bounds the gradient's memory (benchmarks/flex.py)."""
    grid = jt.Grid(nx=24, ny=20)
    transport = jt.Transport(vx=jnp.full(grid.shape, 1e-4), vy=jnp.zeros(grid.shape), dispersion=jnp.full(grid.shape, 1e-6))
    y0 = State.initial(COEFFS, grid)
    y0 = State(o=y0.o * 0.8, c=y0.c * 1.1, m=y0.m + 0.1)

    def step(y, coeffs):
        term = diffrax.ODETerm(GrowthModel(coeffs, grid, transport))
        y1, err = ROS34PW2().step(term, 0.0, 100.0, y, None, None, False)[:2]
        return jnp.sum(y1.m) + jnp.sum(err.o)

    _, pullback = jax.vjp(step, y0, COEFFS)  # a pytree holding the residuals
    leaves = jax.tree_util.tree_leaves(pullback)
    cells = np.prod(grid.shape)
    fine = sum(x.size for x in leaves if x.shape[-2:] == grid.shape) / cells
    assert fine < 60, fine  # 4 stages x (3 states + 3 right-hand sides) + the few fields of the step itself
    total = sum(x.size for x in leaves) / cells
    assert total < 200, total  # and the multigrid levels of the O2 solves (measured: 47 + 108)


def test_a_2d_solve_probes_one_colour_at_a_time():
    """In 2-D the coloured JVPs that build J̃ run one colour at a time: a growth solve's
    buffers hold ~120 fields of the grid, where the batch of five colours (with its
    per-colour face fluxes) needed ~170."""
    grid = jt.Grid(nx=20, ny=16)
    params = jax.tree_util.tree_map(jnp.asarray, jt.paper_parameters())
    solve = jax.jit(lambda p: jt.simulate(p, jt.Protocol.static(), t_end_s=1e5, grid=grid).final.m)
    analysis = solve.lower(params).compile().memory_analysis()
    assert analysis.temp_size_in_bytes < 140 * grid.nx * grid.ny * 8


def test_step_sizes_are_rounded_so_round_off_cannot_move_the_time_grid():
    """`ReproducibleSteps` rounds each step down to 12 bits: a round-off difference in
    the error estimate (forward pass vs its recomputation in the reverse pass) leaves
    the step unchanged; the step changes by less than 2^-11 relative."""
    from jaxtissue.numerics import quantise

    dt = jnp.asarray(np.random.default_rng(1).uniform(1.0, 1e5, 1000))
    q = quantise(dt)
    assert bool(jnp.all(q <= dt)) and bool(jnp.all((dt - q) / dt < 2.0**-11))
    assert float(jnp.mean(quantise(dt * (1 + 1e-9)) == q)) > 0.99


def _strip_operator(nx, ny, aspect, seed=0):
    """a I − (diffusion) on an nx × ny grid whose cells are `aspect` times longer than
    thick (a varying diffusivity), as FivePoint."""
    rng = np.random.default_rng(seed)
    D = 1.0 + rng.random((nx, ny))
    cy, cx = D, D / aspect**2
    south = -cy * (np.arange(ny) > 0)
    north = -cy * (np.arange(ny) < ny - 1)
    west = -cx * (np.arange(nx) > 0)[:, None]
    east = -cx * (np.arange(nx) < nx - 1)[:, None]
    diag = 1e-3 + 2 * cy - west - east  # surfaces drained (2 cy on the faces), ends no-flux
    return FivePoint(*map(jnp.asarray, (diag, south, north, west, east)))


def _dense_solve(op, rhs):
    return jnp.asarray(np.linalg.solve(_dense_five_point(op), np.asarray(rhs).ravel()).reshape(rhs.shape))


def test_line_relaxation_contracts_as_line_sweeps_predicts():
    """k sweeps leave an error ≤ ρᵏ of the exact solve (ρ of `line_sweeps`), and are a
    fixed linear map (what makes them a valid J̃ for the W-method)."""
    nx, ny = 20, 10
    for r in (0.5, 1.5):  # h/Δx
        op = _strip_operator(nx, ny, aspect=ny / r)
        rhs = jnp.asarray(np.random.default_rng(1).random((nx, ny)))
        exact = _dense_solve(op, rhs)
        rho = 2 * r**2 / (2 * r**2 + np.pi**2)
        for k in (2, 4):
            err = float(jnp.max(jnp.abs(op.factor(k).solve(rhs) - exact)) / jnp.max(jnp.abs(exact)))
            assert err <= 2 * rho**k, (r, k, err, rho**k)
            assert err > 1e-3 * rho**k  # really approximate: the test sees the sweeps
        twice = op.factor(2).solve(2 * rhs) - 2 * op.factor(2).solve(rhs)
        assert float(jnp.max(jnp.abs(twice))) < 1e-12
    assert line_sweeps(1, 0.0) == 0
    assert line_sweeps(50, 2.0) == 6  # the default flex grid: ρ = 0.45, ρ⁶ = 0.008
    assert line_sweeps(200, 8.0) == 0  # ρ = 0.93: multigrid


# the default run: 2 and 13 cells along x; 40 (the deepest hierarchy) with `-m slow`
@pytest.mark.parametrize("nx", [2, 13, pytest.param(40, marks=pytest.mark.slow)])
def test_multigrid_contracts_for_any_cell_aspect_ratio(nx):
    """3 V-cycles (the default) leave ≤ 2 % of the error for cells from 0.3 to 100
    times shorter than the strip is thick — line relaxation alone needs ever more sweeps
    there — and are a fixed linear map; more cycles converge to the dense solve."""
    ny = 10
    solve = jax.jit(lambda op, b, cycles: op.factor(0, cycles=cycles).solve(b), static_argnums=2)
    for r in (0.3, 2.0, 8.0, 30.0, 100.0):  # h/Δx
        op = _strip_operator(nx, ny, aspect=ny / r, seed=nx)
        rhs = jnp.asarray(np.random.default_rng(nx).random((nx, ny)))
        exact = _dense_solve(op, rhs)
        errors = [float(jnp.max(jnp.abs(solve(op, rhs, k) - exact)) / jnp.max(jnp.abs(exact))) for k in (3, 12)]
        assert errors[0] <= 0.02, (nx, r, errors)
        assert errors[1] <= max(1e-2 * errors[0], 1e-12), (nx, r, errors)
        twice = solve(op, 2 * rhs, 3) - 2 * solve(op, rhs, 3)
        assert float(jnp.max(jnp.abs(twice))) < 1e-12


@pytest.mark.slow  # 2-D order with line relaxation; the contraction it rests on: test_line_relaxation_contracts_as_line_sweeps_predicts
def test_order_in_time_with_line_relaxation():
    """A 2-D strip (6 × 6 cells) whose solution is uniform along x — the mode that line
    relaxation converges slowest. With the sweeps `line_sweeps` chooses (4 for a 6 mm
    strip, ρ⁴ = 8e-4) ROS34PW2 keeps its third order at these stiff step sizes; with 2
    sweeps on a 2 mm strip (ρ² = 0.42) the error of J̃ shows: order 1. On a 1 mm strip
    (cells 6 times shorter than thick, where line relaxation stalls) multigrid keeps it."""
    for length_mm, sweeps, lowest, highest in ((6.0, None, 2.7, np.inf), (2.0, 2, 0.0, 1.5), (1.0, 0, 2.7, np.inf)):
        params = jt.paper_parameters().replace(length_mm=length_mm)
        grid = jt.Grid(nx=6, ny=6)
        if sweeps is None:
            sweeps = line_sweeps(grid.nx, 1.0 * grid.nx / length_mm)
            assert sweeps == 4
        model = GrowthModel(nondimensionalise(params), grid, cell_transport=False, o2_sweeps=sweeps)
        with pytest.warns(ExtrapolationWarning, match=f"length_mm = {length_mm:g} mm is outside"):  # short strips on purpose
            y0 = jt.simulate(params, t_end_s=2.0e4, grid=grid, options=jt.SolverOptions(rtol=1e-10, atol=1e-13, o2_sweeps=0)).final

        def solve(solver, controller, dt0, model=model):
            sol = diffrax.diffeqsolve(diffrax.ODETerm(model), solver, 0.0, T, dt0, y0, stepsize_controller=controller, max_steps=100000)
            return jnp.concatenate([sol.ys.o[-1].ravel(), sol.ys.c[-1].ravel(), sol.ys.m[-1].ravel()])

        reference = solve(diffrax.Kvaerno5(), diffrax.PIDController(rtol=1e-12, atol=1e-14), 1.0)
        ns = [4, 8, 16, 32]
        errors = [float(jnp.max(jnp.abs(solve(ROS34PW2(), diffrax.ConstantStepSize(), jnp.asarray(T / n)) - reference))) for n in ns]
        orders = observed_orders([T / n for n in ns], errors)
        assert np.all((orders[1:] > lowest) & (orders[1:] < highest)), (length_mm, errors, orders)


def test_thomas_derivatives_in_the_bands_equal_the_dense_solve():
    """`thomas_solve` differentiates as a linear solve, ẋ = A⁻¹(ṙ − Ȧx) (never through
    the elimination): reverse and forward mode against jnp.linalg.solve of the same
    bands, batched."""
    rng = np.random.default_rng(5)
    n = 7
    bands = tuple(jnp.asarray(v) for v in (-rng.random((3, n)), 3 + rng.random((3, n)), -rng.random((3, n)), rng.random((3, n))))
    w = jnp.asarray(rng.random((3, n)))

    def dense(sub, diag, sup, r):
        A = jax.vmap(lambda l, d, u: jnp.diag(d) + jnp.diag(l[1:], -1) + jnp.diag(u[:-1], 1))(sub, diag, sup)
        return jnp.sum(w * jnp.linalg.solve(A, r[..., None])[..., 0])

    def thomas(sub, diag, sup, r):
        return jnp.sum(w * thomas_solve(thomas_factor(sub, diag, sup), r))

    expected = jax.grad(dense, argnums=(0, 1, 2, 3))(*bands)
    got = jax.grad(thomas, argnums=(0, 1, 2, 3))(*bands)
    got_fwd = jax.jacfwd(thomas, argnums=(0, 1, 2, 3))(*bands)
    for e, g, f in zip(expected, got, got_fwd):
        np.testing.assert_allclose(g, e, rtol=1e-12, atol=1e-14)
        np.testing.assert_allclose(f, e, rtol=1e-12, atol=1e-14)


def test_o2_sweeps_option_is_checked_and_chosen_from_the_strip():
    with pytest.raises(ValueError, match=r"o2_sweeps = -1 must be None or an integer >= 0"):
        jt.SolverOptions(o2_sweeps=-1)
    assert default_o2_sweeps(jt.Grid(50, 40), jt.paper_parameters()) == 6
    assert default_o2_sweeps(jt.Grid(50, 40), jt.paper_parameters().replace(length_mm=5.0)) == 0  # Δx = h/10
    assert default_o2_sweeps(jt.Grid(1, 40), jt.paper_parameters()) == 0


@pytest.mark.slow  # the 2-D solves at fine grids: test_multigrid_contracts_for_any_cell_aspect_ratio, test_order_in_time_with_line_relaxation
def test_order_and_gradient_on_a_200_by_160_grid():
    """On the 200 × 160 grid (multigrid O2 solves): ROS34PW2 with fixed steps keeps its
    third order (self-convergence: the differences of successive halvings shrink ~8×),
    and the gradient of a short flex run's collagen matches central differences as on
    coarse grids (`test_coupling.test_gradient_through_the_staggered_run`)."""
    from jaxtissue.beam import BeamGrid

    grid, params = jt.Grid(200, 160), jt.paper_parameters()
    assert default_o2_sweeps(grid, params) == 0  # multigrid
    y0 = jt.simulate(params, t_end_s=2.0e4, grid=grid, options=jt.SolverOptions(rtol=1e-8, atol=1e-11)).final
    model = GrowthModel(nondimensionalise(params), grid, cell_transport=False, o2_sweeps=0)
    solve = jax.jit(lambda dt: _solve(ROS34PW2(), y0, diffrax.ConstantStepSize(), dt, field=model))
    ns = [4, 8, 16, 32, 64]
    ys = [solve(jnp.asarray(T / n)) for n in ns]
    differences = [float(jnp.max(jnp.abs(a - b))) for a, b in zip(ys[:-1], ys[1:])]
    orders = observed_orders([T / n for n in ns[:-1]], differences)
    print("200 x 160, fixed steps", ns, "successive differences", differences, "orders", orders)
    assert np.all(orders[1:] > 2.7), (differences, orders)

    kw = dict(t_end_s=6.0e4, grid=grid, beam=BeamGrid(n_segments=8, steps_per_cycle=40), coupling_interval_s=2.0e4,
              options=jt.SolverOptions(fixed_steps=6, dt0_s=5.0))

    def collagen(p):
        return jt.simulate(p, jt.Protocol.flex(), **kw).collagen_mg_per_g[-1]

    def arrays(p):
        return jax.tree_util.tree_map(jnp.asarray, p)

    g = jax.jit(jax.grad(collagen))(arrays(params))
    forward = jax.jit(collagen)
    for name in ("k_m0", "k_c_max"):
        v = getattr(params, name)
        h = 1e-4 * v
        fd = (float(forward(arrays(params.replace(**{name: v + h})))) - float(forward(arrays(params.replace(**{name: v - h}))))) / (2 * h)
        ad = float(getattr(g, name))
        print(f"200 x 160 flex, d collagen / d {name}: reverse mode {ad:.6e}, central differences {fd:.6e}")
        assert ad == pytest.approx(fd, rel=1e-3), (name, ad, fd)  # as on coarse grids (J̃ held constant: docs/numerics.md)
