"""Protocol optimisation: schedules, objectives, the augmented Lagrangian's gradient,
the optimum against a brute-force grid, problem files and the CLI."""

import dataclasses
import json
import pathlib
import types

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jaxtissue as jt
from jaxtissue import cache
from jaxtissue import optimization as opt
from jaxtissue.studies import objectives
from jaxtissue.studies.calibration import ModelSettings
from jaxtissue.cli import main
from jaxtissue.io import read_params_toml
from jaxtissue.protocol import interval_bounds

from helpers import TINY_MODEL

ROOT = pathlib.Path(__file__).resolve().parents[1]
WEEK = 604800.0
TINY = ModelSettings(ny=8, flex_nx=2, beam_segments=8, beam_steps_per_cycle=24, coupling_interval_s=WEEK, rtol=1e-8, atol=1e-11)
TINY_TOML = "\n" + TINY_MODEL


def tiny_run(protocol):
    return jt.simulate(jt.paper_parameters(), protocol, 3 * WEEK, TINY.grid("flex"), coupling_interval_s=WEEK,
                       beam=TINY.beam(), options=jt.SolverOptions(rtol=1e-8, atol=1e-11))


def test_schedule_stages_act_in_their_own_weeks():
    constant = tiny_run(jt.Protocol.schedule([1.0, 1.0, 1.0], [5.0, 5.0, 5.0]))
    later = tiny_run(jt.Protocol.schedule([1.0, 1.0, 0.5], [5.0, 5.0, 8.0]))  # only week 3 differs
    np.testing.assert_array_equal(later.collagen_mg_per_g[:3], constant.collagen_mg_per_g[:3])
    assert later.collagen_mg_per_g[3] > constant.collagen_mg_per_g[3]  # faster, larger flexure in week 3
    assert later.surface_strain_max[3] > constant.surface_strain_max[3]
    q = jt.Protocol.schedule([1.0, 2.0, 3.0], [4.0, 5.0, 6.0])
    assert [float(q.at(t).period_s) for t in (0.0, WEEK - 1, WEEK, 2.5 * WEEK, 9 * WEEK)] == [1.0, 1.0, 2.0, 3.0, 3.0]
    with pytest.raises(ValueError, match="same length"):
        jt.Protocol.schedule([1.0, 2.0], [5.0])
    with pytest.raises(ValueError, match="period_s = -1"):
        jt.Protocol.schedule([1.0, -1.0], [5.0, 5.0])


def fake_result(m, h_cm=0.1):
    ny = len(m)
    y = (np.arange(ny) + 0.5) * h_cm / ny - h_cm / 2
    return types.SimpleNamespace(y_cm=jnp.asarray(y), profile_m=jnp.asarray([m]), params=jt.paper_parameters())


def test_core_objectives_against_hand_computed_thirds():
    # six cells: the middle third is exactly cells 2 and 3
    r = fake_result([0.1, 0.2, 0.5, 0.5, 0.2, 0.1])
    assert np.isclose(objectives.core_collagen(r, 0.0), 108.3 * 0.5)
    assert np.isclose(objectives.core_homogeneity(r, 0.0), 0.5 / 0.15)
    # four cells: cells 1 and 2 each lie 2/3 inside |y| < h/6 (cell [−h/4, 0] ∩ [−h/6, h/6])
    m = np.array([0.1, 0.3, 0.5, 0.2])
    r = fake_result(m)
    w = np.array([0.0, 2 / 3, 2 / 3, 0.0])
    core, periphery = np.sum(w * m) / np.sum(w), np.sum((1 - w) * m) / np.sum(1 - w)
    assert np.isclose(objectives.core_collagen(r, 0.0), 108.3 * core)
    assert np.isclose(objectives.core_homogeneity(r, 0.0), core / periphery)


def test_conditioning_dose_counts_cycles_times_displacement():
    bounds = interval_bounds(3 * WEEK, 2.016e5)
    assert np.isclose(objectives.conditioning_dose(jt.Protocol.flex(0.5, 4.0), bounds), 3 * WEEK / 0.5 * 4.0 / 1e6)
    q = jt.Protocol.schedule([1.0, 2.0, 0.5], [5.0, 2.0, 1.0])
    assert np.isclose(objectives.conditioning_dose(q, bounds), WEEK * (5.0 / 1.0 + 2.0 / 2.0 + 1.0 / 0.5) / 1e6)


def tiny_design(**kw):
    kw.setdefault("objective", "total_collagen")
    return opt.Design(params=jt.paper_parameters(), t_end_s=3 * WEEK, model=TINY, stage_length_s=WEEK, **kw)


def _lagrangian_problem(stages):
    d = tiny_design(constraints={"surface_strain_max": 0.05, "post_force_max_N": 0.02}, stages=stages)
    theta = d.constant(0.8, 5.5) * jnp.linspace(0.9, 1.1, stages)[:, None]
    lam = jnp.array([0.3, 0.0])  # one multiplier active, the strain constraint violated
    return d, d.z_from_theta(theta), lam


def test_lagrangian_directional_derivative_matches_central_differences():
    """The cheap version of the test below: a weekly schedule's Lagrangian, its
    derivative along one direction (one JVP) against a central difference."""
    d, z, lam = _lagrangian_problem(3)
    v = jnp.linspace(-1.0, 1.0, z.size).reshape(z.shape)
    jvp = jax.jit(lambda z: jax.jvp(lambda x: d.lagrangian(x, lam, 0.5), (z,), (v,), has_aux=True))  # value too: one program
    _, slope, aux = jvp(z)
    assert d.violation(aux[2])[0] > 0
    h = 1e-4
    fd = (jvp(z + h * v)[0] - jvp(z - h * v)[0]) / (2 * h)
    np.testing.assert_allclose(float(slope), float(fd), rtol=2e-4)


@pytest.mark.slow  # every component; the directional derivative above is the default run's
@pytest.mark.parametrize("stages", [1, 3])
def test_lagrangian_gradient_matches_central_differences(stages):
    d, z, lam = _lagrangian_problem(stages)
    grad, aux = jax.jit(jax.jacfwd(d.lagrangian, has_aux=True))(z, lam, 0.5)
    assert d.violation(aux[2])[0] > 0
    f = jax.jit(lambda z: d.lagrangian(z, lam, 0.5)[0])
    h = 1e-4
    fd = np.zeros(z.shape)
    for idx in np.ndindex(*z.shape):
        e = jnp.zeros(z.shape).at[idx].set(h)
        fd[idx] = (f(z + e) - f(z - e)) / (2 * h)
    np.testing.assert_allclose(np.asarray(grad), fd, rtol=2e-4, atol=1e-6 * np.max(np.abs(fd)))


def write_problem(folder, body, name="p.toml"):
    path = pathlib.Path(folder) / name
    path.write_text(body)
    return path


PROBLEM = """
objective = "total_collagen"
t_end_s = 1814400.0
[constraints]
surface_strain_max = 0.05
[optimizer]
starts = 2
steps = 16
learning_rate = 0.3
inner_steps = 4
grid_points = 5
""" + TINY_TOML


@pytest.mark.slow  # run with -m slow
def test_optimize_command_beats_the_grid_inside_bounds_and_limits(tmp_path):
    problem = write_problem(tmp_path, PROBLEM)
    assert main(["optimize", str(problem), "--out", str(tmp_path / "o"), "--no-progress"]) == 0
    s = json.loads((tmp_path / "o" / "summary.json").read_text())
    for key in ("optimum", "objective", "baseline_objective", "grid_best_objective", "grid_best", "constraints", "t_end_s"):
        assert key in s
    assert s["objective"] >= s["grid_best_objective"]  # at least as good as the dense grid
    assert s["grid_best_objective"] > s["baseline_objective"]
    T, u = s["optimum"]["period_s"], s["optimum"]["post_displacement_mm"]
    assert 0.25 <= T <= 10.0 and 0.0 <= u <= 10.0
    c = s["constraints"]["surface_strain_max"]
    assert c["satisfied"] and c["value"] <= 0.05 and c["value"] > 0.045  # the limit is active
    # the reported optimum is what a plain simulation gives
    d = tiny_design(constraints={"surface_strain_max": 0.05})
    J, values, failed = jax.jit(d.evaluate)(d.constant(T, u))
    assert np.isclose(J, s["objective"], rtol=1e-6) and np.isclose(values[0], c["value"], rtol=1e-6) and not failed
    assert read_params_toml(tmp_path / "o" / "params.toml") == jt.paper_parameters()
    for f in ("report.md", "landscape.png", "history.png"):
        assert (tmp_path / "o" / f).stat().st_size > 0
    assert "better than or equal to the best grid point" in (tmp_path / "o" / "report.md").read_text()
    assert main(["optimize", str(problem), "--out", str(tmp_path / "o")]) == 2  # never silently overwritten


@pytest.mark.slow
def test_schedule_beats_the_best_constant_protocol(tmp_path):
    body = PROBLEM.replace("[constraints]", "[protocol]\nstages = 3\nstage_length_s = 604800.0\n[constraints]\npost_force_max_N = 0.004")
    problem = write_problem(tmp_path, body.replace("steps = 16", "steps = 30"))
    assert main(["optimize", str(problem), "--out", str(tmp_path / "o"), "--no-progress"]) == 0
    s = json.loads((tmp_path / "o" / "summary.json").read_text())
    assert len(s["optimum"]["period_s"]) == 3
    assert s["objective"] > s["grid_best_objective"]
    assert all(c["satisfied"] for c in s["constraints"].values())
    assert (tmp_path / "o" / "schedule.png").exists()


BAD = [
    ("objective = \"total_colagen\"", "did you mean 'total_collagen'"),
    ("", "objective = \"NAME\" is required"),
    ("objective = \"total_collagen\"\n[bounds]\nperiod_s = [2.0, 1.0]", "bounds period_s = [2, 1]"),
    ("objective = \"total_collagen\"\n[bounds]\nperiod_s = [0.0, 1.0]", "bounds period_s = [0, 1]"),
    ("objective = \"total_collagen\"\n[bounds]\npost_displacement_mm = [0.0, 30.0]", "the strip length"),
    ("objective = \"total_collagen\"\n[bounds]\nperiod = [1.0, 2.0]", "did you mean 'period_s'"),
    ("objective = \"total_collagen\"\n[constraints]\nsurface_strain = 0.05", "did you mean 'surface_strain_max'"),
    ("objective = \"total_collagen\"\n[constraints]\nsurface_strain_max = -0.05", "surface_strain_max = -0.05 must be a positive number"),
    ("objective = \"least_conditioning\"", "needs a target"),
    ("objective = \"total_collagen\"\n[protocol]\nstages = 0", "stages = 0 must be a positive integer"),
    ("objective = \"total_collagen\"\n[protocol]\nstages = 4", "the last stage would start after t_end_s"),
    ("objective = \"total_collagen\"\n[optimizer]\nstarts = 0", "starts = 0 must be a positive integer"),
    ("objective = \"total_collagen\"\n[optimizer]\nstarts = 1000000000", "[optimizer] starts = 1000000000 must be at most 10000000"),
    ("objective = \"total_collagen\"\n[optimizer]\ngrid_points = 100000", "[optimizer] grid_points = 100000 is a grid of 1e+10 protocols; at most 10000000 (grid_points <= 3162)"),
    ("objective = \"total_collagen\"\nparameters = \"missing.toml\"", "no such parameter file"),
    ("objective = \"total_collagen\"\n[parameters]\nk_m0 = -1.0", "k_m0"),
    ("objective = \"total_collagen\"\nsteps = 3", "unknown key 'steps'"),
    ("objective = \"total_collagen\"\n[model]\nnest_intervals = \"yes\"", "nest_intervals = 'yes' must be true or false"),
    ("objective = \"total_collagen\"\n[model]\nstore_float32 = true", "[model] solver option store_float32 = True needs nest_intervals = True"),
    ("objective = \"total_collagen\"\n[model]\nrtol = 2.0", "[model] solver option rtol = 2.0 must be below 1"),
]


@pytest.mark.parametrize("body, message", BAD)
def test_bad_problem_files_give_one_line_and_exit_2(tmp_path, capsys, body, message):
    problem = write_problem(tmp_path, body)
    assert main(["optimize", str(problem), "--out", str(tmp_path / "o")]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and message in err and str(problem) in err
    assert not (tmp_path / "o").exists()


def test_the_memory_check_sizes_all_starts_at_once(tmp_path):
    """The starts' gradients run at once (vmapped): the memory check counts them all."""
    from jaxtissue.limits import ResourceError

    design = opt.read_design(write_problem(tmp_path, PROBLEM.replace("starts = 2", "starts = 10000000")))
    with pytest.raises(ResourceError, match=r"^the optimisation \(10000000 simultaneous runs on the 2 x 8 grid\) needs about"):
        opt.run(design)


def test_model_table_can_nest_the_interval_checkpoints(tmp_path):
    design = opt.read_design(write_problem(tmp_path, PROBLEM.replace("[model]", "[model]\nnest_intervals = true\nstore_float32 = true")))
    assert design.model.nest_intervals is True
    options = design.model.solver_options("reverse")
    assert options.nest_intervals and options.store_float32
    assert opt.read_design(write_problem(tmp_path, PROBLEM, "q.toml")).model.nest_intervals is False


def test_shipped_problem_files_are_valid():
    files = sorted((ROOT / "optimize").glob("*.toml"))
    names = {f.stem for f in files} - {"calibrated_parameters"}
    assert {"max_collagen", "max_collagen_schedule", "least_conditioning"} <= names
    objectives = {opt.read_design(ROOT / "optimize" / f"{n}.toml").objective for n in names}
    assert objectives == set(opt.OBJECTIVES)


@eqx.filter_jit
def _stages_times(design, x):
    return x * design.stages


def test_a_design_read_from_its_file_names_its_saved_programs(tmp_path, monkeypatch):
    """The optimisation's programs take the design as a static argument (`cache.prepared`):
    one read from its file is named by its values (a robust design's posterior draws
    too), so that a second `jaxtissue optimize` loads them (the cheap version of the next
    test)."""
    monkeypatch.delenv("JAXTISSUE_NO_SAVED_PROGRAMS", raising=False)
    x = jnp.arange(3.0)
    for n, name in enumerate(("max_collagen_schedule.toml", "max_collagen_robust.toml"), start=1):
        path = ROOT / "optimize" / name
        with cache.saved_executables(tmp_path):
            cache.call(_stages_times, opt.read_design(path), x)
            assert len(list(tmp_path.glob("*.jtx"))) == n
            monkeypatch.setattr(cache, "_loaded", {})
            with monkeypatch.context() as m:
                m.setattr(cache, "_compile", lambda *a: pytest.fail("compiled again"))
                again = opt.read_design(path)  # as a new process reads it
                np.testing.assert_array_equal(cache.prepared(_stages_times, again, x)(again, x + 1.0), (x + 1.0) * again.stages)


@pytest.mark.slow  # compiles the optimisation's programs; the test above is its cheap version
def test_a_second_optimisation_loads_its_programs(tmp_path, monkeypatch):
    monkeypatch.delenv("JAXTISSUE_NO_SAVED_PROGRAMS", raising=False)
    design = opt.read_design(write_problem(tmp_path, PROBLEM.replace("steps = 16", "steps = 3").replace("grid_points = 5", "grid_points = 2")))
    with cache.saved_executables(tmp_path / "programs"):
        first = opt.run(design)
        assert len(list((tmp_path / "programs").glob("*.jtx"))) == 3  # the baseline, the grid's batch, the Adam step
        monkeypatch.setattr(cache, "_loaded", {})  # as in a new process: neither traced nor compiled again
        for where, name in ((opt.Design, "evaluate_with"), (cache, "_compile")):
            monkeypatch.setattr(where, name, lambda *a, name=name: pytest.fail(f"{name} again"))
        second = opt.run(dataclasses.replace(design))
    np.testing.assert_array_equal(second.optimum.path, first.optimum.path)
    np.testing.assert_array_equal(second.grid.objective, first.grid.objective)


@pytest.mark.slow  # compiles the grid search; the limits' messages: test_bad_problem_files_...
def test_unreachable_limit_is_an_error_naming_it(tmp_path, capsys):
    body = PROBLEM.replace('objective = "total_collagen"', 'objective = "least_conditioning"').replace(
        "surface_strain_max = 0.05", "EI_min_N_m2 = 1e-5").replace("grid_points = 5", "grid_points = 2")
    problem = write_problem(tmp_path, body)
    assert main(["optimize", str(problem), "--out", str(tmp_path / "o"), "--no-progress"]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "EI_min_N_m2 <=" in err and "(limit 1e-05)" in err and "relax a limit" in err
    assert not (tmp_path / "o").exists()


_OVER_DEVICES = """
from jaxtissue.studies import sweep
assert sweep.use_all_cores()  # as `jaxtissue optimize` does
import jax, jax.numpy as jnp, numpy as np
jax.config.update("jax_enable_x64", True)
from jaxtissue.studies.sweep import map_over_devices, vmap_over_devices
def step(z, state, lam):  # a start's step: arrays and a pytree in, a pytree out
    return z * state["m"] + lam.sum(), {"m": state["m"] + 1.0, "n": state["n"] * 2}, (jnp.sin(z).sum(), lam)
n = 2 * len(jax.devices())
z, lam = jnp.arange(n * 3.0).reshape(n, 3), jnp.ones((n, 2))
state = {"m": jnp.linspace(0, 1, n)[:, None] * jnp.ones((n, 3)), "n": jnp.arange(n)}
plain = jax.jit(jax.vmap(step))(z, state, lam)
split = jax.jit(vmap_over_devices(step, n))(z, state, lam)
assert len(jax.devices()) > 1 and len(split[0].sharding.device_set) == len(jax.devices())
mapped = jax.jit(map_over_devices(lambda a: step(*a), n))((z, state, lam))  # rows one after another on each device
assert len(mapped[0].sharding.device_set) == len(jax.devices())
for a, b, c in zip(jax.tree.leaves(plain), jax.tree.leaves(split), jax.tree.leaves(mapped)):
    np.testing.assert_array_equal(np.asarray(a), np.asarray(b))
    np.testing.assert_allclose(np.asarray(c), np.asarray(a), rtol=1e-15)
print("ok", len(jax.devices()))
"""


def test_batches_split_over_the_cores_compute_the_same():
    """`sweep.vmap_over_devices` (the starts and grid batches of `jaxtissue optimize`, over
    one CPU device per core, in a process of its own) and `sweep.map_over_devices`
    (reproduce's flex cases) give what one device gives."""
    import os
    import subprocess
    import sys

    if (os.cpu_count() or 1) < 2:
        pytest.skip("one core: nothing to split")
    env = {k: v for k, v in os.environ.items() if k != "XLA_FLAGS"}
    out = subprocess.run([sys.executable, "-c", _OVER_DEVICES], env=env, capture_output=True, text=True, timeout=300)
    assert out.returncode == 0, out.stderr[-2000:]
    assert out.stdout.split()[0] == "ok"
