"""Static versus flexed culture through the staggered beam–growth loop (docs/model.md §5)."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jaxtissue as jt
from jaxtissue.beam import BeamGrid

# coarse but complete: every piece of the coupled model, in seconds
COARSE = dict(grid=jt.Grid(nx=8, ny=16), beam=BeamGrid(n_segments=10, steps_per_cycle=60), coupling_interval_s=1.0e5)
P = jt.paper_parameters()


def run(protocol, params=P, t_end_s=jt.THREE_WEEKS_S):
    return jt.simulate(params, protocol, t_end_s=t_end_s, **COARSE)


@pytest.fixture(scope="module")
def cases():
    protocols = {
        "static": jt.Protocol.static(),
        "flex": jt.Protocol.flex(),
        "0.5Hz": jt.Protocol.flex(period_s=2.0),
        "2Hz": jt.Protocol.flex(period_s=0.5),
        "2.5mm": jt.Protocol.flex(post_displacement_mm=2.5),
        "10mm": jt.Protocol.flex(post_displacement_mm=10.0),
    }
    return {name: run(p) for name, p in protocols.items()}


def final(r, key):
    return float(getattr(r, key)[-1])


def test_flex_gives_more_collagen_and_dna_than_static(cases):
    assert not any(bool(r.failed) for r in cases.values())
    for key in ("collagen_mg_per_g", "dna_ug_per_g"):
        assert final(cases["flex"], key) > final(cases["static"], key)


def test_collagen_increases_with_frequency_and_amplitude(cases):
    c = {k: final(r, "collagen_mg_per_g") for k, r in cases.items()}
    assert c["0.5Hz"] < c["flex"] < c["2Hz"]
    assert c["2.5mm"] < c["flex"] < c["10mm"]


def test_rigidity_and_post_force_rise_with_time(cases):
    for name in ("flex", "2Hz", "10mm"):
        r = cases[name]
        assert np.all(np.diff(np.asarray(r.EI_N_m2)) > 0)
        force = np.asarray(r.post_force_max_N)
        assert force[-1] > 1.5 * force[0] and np.all(np.diff(force) > -1e-9 * force.max())
    assert np.all(np.asarray(cases["static"].post_force_max_N) == 0)


def test_the_last_post_force_is_the_cycle_at_the_end_state(cases):
    """The loop's extra step (a loading cycle only, at the end state) reports what a
    separate cycle at the final state gives."""
    import sys

    sim = sys.modules["jaxtissue.simulate"]
    r = cases["10mm"]
    p = jax.tree_util.tree_map(jnp.asarray, P)
    _, cycle = sim.flex_cycle(r.final, p, jt.Protocol.flex(post_displacement_mm=10.0), COARSE["grid"], COARSE["beam"])
    np.testing.assert_allclose(float(r.post_force_max_N[-1]), float(cycle.post_force_max_N), rtol=1e-12)
    np.testing.assert_allclose(float(r.surface_strain_max[-1]), float(jnp.max(cycle.surface_strain)), rtol=1e-12)
    assert float(r.post_force_max_N[-1]) > float(r.post_force_max_N[-2])


def test_flex_adds_ecm_deep_in_the_construct_and_ends_evolve_alike(cases):
    """Fig. 7/8: flex raises the core; near the posts, where the strip barely bends,
    the two regimes stay close."""
    s, f = np.asarray(cases["static"].final.m), np.asarray(cases["flex"].final.m)
    mid = s.shape[0] // 2
    core = s.shape[1] // 2
    assert f[mid, core] > 1.2 * s[mid, core]
    assert abs(f[0, core] - s[0, core]) < 0.5 * abs(f[mid, core] - s[mid, core])


def test_paper_rule_gives_a_symmetric_signed_flow(cases):
    """The paper's literal rule runs; its lumped velocity across the thickness is
    symmetric about the mid-plane (docs/model.md §5's note), hence not divergence-free."""
    import sys

    from jaxtissue.coupling import lumped_transport

    sim = sys.modules["jaxtissue.simulate"]
    p = jax.tree_util.tree_map(jnp.asarray, P.replace(lumping_C=70.0))
    protocol = jt.Protocol.flex(lumping="paper")
    _, cycle = sim.flex_cycle(cases["static"].final, p, protocol, COARSE["grid"], COARSE["beam"])
    v = np.asarray(lumped_transport(cycle, p, COARSE["grid"], COARSE["beam"], "paper", "centroid").vy)
    assert np.abs(v).max() > 0
    np.testing.assert_allclose(v, v[:, ::-1], atol=1e-6 * np.abs(v).max())
    assert np.abs(np.diff(v, axis=1)).max() > 0.1 * np.abs(v).max()
    r = run(protocol, params=P.replace(lumping_C=70.0), t_end_s=4.0e5)
    assert not bool(r.failed) and np.isfinite(final(r, "collagen_mg_per_g"))



@pytest.mark.parametrize("pins", ["centroid", "bottom"])
def test_the_two_grids_exchange_values_by_linear_interpolation_along_the_strip(pins):
    """Growth cells → beam nodes (the ECM the sections carry) and beam nodes → growth
    cells (the cycle's lumped flow): linear interpolation in x on a strip of any length,
    against np.interp at the points' positions in cm (constant beyond the end points)."""
    from types import SimpleNamespace

    from jaxtissue.beam import Material
    from jaxtissue.coupling import beam_from_ecm, lumped_transport
    from jaxtissue.state import State

    rng = np.random.default_rng(3)
    grid, beam = jt.Grid(nx=7, ny=5), BeamGrid(n_segments=10, steps_per_cycle=40)
    p = P.replace(length_mm=31.0)
    L = 3.1  # cm
    x_cells = (np.arange(7) + 0.5) * L / 7 - L / 2
    x_nodes = np.linspace(-L / 2, L / 2, 11)
    interp = lambda x, xp, v: np.stack([np.interp(x, xp, col) for col in v.T], axis=1)  # noqa: E731

    m = rng.random((7, 5))
    y = State(o=jnp.zeros((7, 5)), c=jnp.zeros((7, 5)), m=jnp.asarray(m))
    E = beam_from_ecm(y, p, grid, beam, pins, "neo-hookean").material.E
    np.testing.assert_allclose(E, Material.from_ecm(interp(x_nodes[1:-1], x_cells, m), p.si()).E, rtol=1e-13)

    sections = rng.random((9, 5))  # the cycle's mean |v_y| at the interior nodes, m/s
    cycle = SimpleNamespace(mean_abs_vy=jnp.asarray(sections))
    nodes = np.concatenate([np.zeros((1, 5)), sections, np.zeros((1, 5))]) if pins == "centroid" else \
        np.concatenate([sections[:1], sections, sections[-1:]])
    D = lumped_transport(cycle, p, grid, beam, "dispersive", pins).dispersion
    h_cm = 0.1
    np.testing.assert_allclose(D, p.lumping_C * h_cm * interp(x_cells, x_nodes, nodes * 100.0), rtol=1e-13)


# ---- gradients through the whole staggered run

OPTIONS = jt.SolverOptions(fixed_steps=10, dt0_s=5.0)
GRAD = dict(grid=jt.Grid(nx=4, ny=10), beam=BeamGrid(n_segments=8, steps_per_cycle=40), coupling_interval_s=2.0e5, options=OPTIONS)


def collagen(params, protocol):
    return jt.simulate(params, protocol, t_end_s=jt.THREE_WEEKS_S, **GRAD).collagen_mg_per_g[-1]


@pytest.fixture(scope="module")
def gradients():
    p = jax.tree_util.tree_map(jnp.asarray, P)
    q = jax.tree_util.tree_map(jnp.asarray, jt.Protocol.flex())
    return jax.jit(jax.grad(collagen, argnums=(0, 1)))(p, q)


@pytest.mark.parametrize("name", ["lumping_C", "k_m0", "k_c_max", "period_s", "post_displacement_mm"])
def test_gradient_through_the_staggered_run(gradients, name):
    on_protocol = name in ("period_s", "post_displacement_mm")
    params, protocol = P, jt.Protocol.flex()
    value = getattr(protocol if on_protocol else params, name)
    h = 1e-4 * value

    def at(v):
        if on_protocol:
            return float(collagen(params, jt.Protocol.flex(**{name: v})))
        return float(collagen(params.replace(**{name: v}), protocol))

    fd = (at(value + h) - at(value - h)) / (2 * h)
    ad = float(getattr(gradients[1] if on_protocol else gradients[0], name))
    assert ad == pytest.approx(fd, rel=1e-3), (name, ad, fd)


@pytest.mark.slow  # `replayed_scan`'s exactness and its float32 storage: tests/test_remat.py
def test_nested_interval_checkpoints_give_the_same_gradient(gradients):
    """`SolverOptions(nest_intervals=True)` keeps ~√n interval states in the reverse
    pass: the same arithmetic, so the same gradient to round-off."""
    nested = dict(GRAD, options=jt.SolverOptions(fixed_steps=10, dt0_s=5.0, nest_intervals=True))
    p = jax.tree_util.tree_map(jnp.asarray, P)
    q = jax.tree_util.tree_map(jnp.asarray, jt.Protocol.flex())
    g = jax.jit(jax.grad(lambda p, q: jt.simulate(p, q, t_end_s=jt.THREE_WEEKS_S, **nested).collagen_mg_per_g[-1], argnums=(0, 1)))(p, q)
    # as elasticities ∂collagen/∂ln(value), on one scale (some derivatives are ~0)
    values = jax.tree_util.tree_leaves((p, q))
    flat, nest = (np.array([float(gi * v) for gi, v in zip(jax.tree_util.tree_leaves(x), values)]) for x in (gradients, g))
    np.testing.assert_allclose(nest, flat, rtol=1e-9, atol=1e-12 * np.abs(flat).max())
    with pytest.raises(ValueError, match=r"nest_intervals = 1 must be True or False"):
        jt.SolverOptions(nest_intervals=1)


@pytest.mark.slow  # as the float64 one above; `replayed_scan` in float32 storage: tests/test_remat.py
def test_nested_gradient_with_float32_storage(gradients):
    """`store_float32=True` keeps the nested reverse pass's states and transports in
    float32: the forward values are unchanged, the gradient within ~1e-6 of float64's
    (and not equal to it: the replay did start from rounded values)."""
    options = jt.SolverOptions(fixed_steps=10, dt0_s=5.0, nest_intervals=True, store_float32=True)
    p = jax.tree_util.tree_map(jnp.asarray, P)
    q = jax.tree_util.tree_map(jnp.asarray, jt.Protocol.flex())
    collagen = lambda p, q: jt.simulate(p, q, t_end_s=jt.THREE_WEEKS_S, **dict(GRAD, options=options)).collagen_mg_per_g[-1]  # noqa: E731
    value, g = jax.jit(jax.value_and_grad(collagen, argnums=(0, 1)))(p, q)
    plain = jt.simulate(P, jt.Protocol.flex(), t_end_s=jt.THREE_WEEKS_S, **GRAD).collagen_mg_per_g[-1]
    assert float(value) == pytest.approx(float(plain), rel=1e-12)
    values = jax.tree_util.tree_leaves((p, q))
    flat, f32 = (np.array([float(gi * v) for gi, v in zip(jax.tree_util.tree_leaves(x), values)]) for x in (gradients, g))
    error = np.abs(f32 - flat).max() / np.abs(flat).max()
    assert 0 < error < 1e-6, error
    with pytest.raises(ValueError, match=r"store_float32 = True needs nest_intervals = True"):
        jt.SolverOptions(store_float32=True)
    with pytest.raises(ValueError, match=r"nest_intervals = 1 must be True or False"):
        jt.SolverOptions(nest_intervals=1)


def test_coupling_intervals_are_split_at_three_weeks():
    """The interval holding 3 weeks ends there (its state is an interval's end state,
    no dense output needed) and the next starts there; every other is T_g long."""
    from jaxtissue.protocol import interval_bounds, save_times

    bounds = interval_bounds(2.0e6, 2.0e4)
    assert len(bounds) == 102 and bounds[0] == 0.0 and bounds[-1] == 2.0e6 and jt.THREE_WEEKS_S in bounds
    steps = np.diff(bounds)
    assert np.all(steps > 0) and np.sum(~np.isclose(steps, 2.0e4)) == 2  # the split interval's two parts
    np.testing.assert_array_equal(save_times(2.0e6, 2.0e4), bounds)
    assert jt.THREE_WEEKS_S not in interval_bounds(1.0e6, 2.0e4)
    np.testing.assert_array_equal(interval_bounds(2.0e6, 2.0e4, jt.THREE_WEEKS_S), bounds[bounds >= jt.THREE_WEEKS_S])
