"""Property-based tests (hypothesis). Over the valid parameter space: no NaN,
concentrations within their physical bounds, finite gradients. Over invalid input:
every mistake is one line on stderr and exit code 2, never a traceback.

The default run tries a bounded number of examples (deterministic); set
JAXTISSUE_FUZZ=long for the longer profile."""

import math
import os
import sys
import time

import jax
import jax.numpy as jnp
import numpy as np
from hypothesis import HealthCheck, assume, given, settings
from hypothesis import strategies as st

import jaxtissue as jt
from jaxtissue import limits
from jaxtissue.cli import main
from jaxtissue.params import FIELDS
from jaxtissue.result import BOUNDS_TOL

LONG = os.environ.get("JAXTISSUE_FUZZ") == "long"
settings.register_profile("bounded", max_examples=8, deadline=None, derandomize=True,
                          suppress_health_check=[HealthCheck.function_scoped_fixture, HealthCheck.too_slow])
settings.register_profile("long", max_examples=200, deadline=None,
                          suppress_health_check=[HealthCheck.function_scoped_fixture, HealthCheck.too_slow])
PROFILE = "long" if LONG else "bounded"

# the kinetic and transport parameters, each over a factor of 3 around the paper's value
VARIED = ("D_o0", "Q_o", "k_c_max", "k_a", "k_m0", "o_m", "o_c", "E_m0_kPa_per_ug_g")
GRID = jt.Grid(1, 10)


def _params(factors):
    base = jt.paper_parameters()
    return base.replace(**{n: getattr(base, n) * f for n, f in zip(VARIED, factors)})


factors = st.lists(st.floats(1 / 3, 3.0), min_size=len(VARIED), max_size=len(VARIED))


def _collagen(p):
    r = jt.simulate(p, t_end_s=jt.THREE_WEEKS_S, grid=GRID)
    return r.collagen_mg_per_g[-1], (r.failed, r.final, r.collagen_mg_per_g, r.dna_ug_per_g)


_run_and_grad = jax.jit(jax.value_and_grad(_collagen, has_aux=True))  # the run and its gradient: one program


@settings(settings.get_profile(PROFILE))
@given(factors)
def test_valid_parameters_give_bounded_finite_fields_and_gradients(f):
    assume(f[VARIED.index("o_m")] * 0.16 < 1 and f[VARIED.index("o_c")] * 0.45 < 1)
    p = _params(f)
    p = jax.tree_util.tree_map(jnp.asarray, p)
    (_, (failed, final, collagen, dna)), g = _run_and_grad(p)
    assert not bool(failed)
    o, c, m = (np.asarray(x) for x in (final.o, final.c, final.m))
    assert np.all(np.isfinite(o)) and np.all(np.isfinite(c)) and np.all(np.isfinite(m))
    assert o.min() >= -BOUNDS_TOL and c.min() >= -BOUNDS_TOL and m.min() >= -BOUNDS_TOL
    assert m.max() <= 1 + BOUNDS_TOL and c.max() <= float(p.c_max) * (1 + BOUNDS_TOL)
    assert np.all(np.isfinite(collagen)) and np.all(np.isfinite(dna))
    assert all(np.isfinite(float(getattr(g, n))) for n in VARIED)


def _exit_code(argv):
    try:
        return main(argv)
    except SystemExit as exit:  # argparse's own errors (one line, see cli._Parser)
        return exit.code


def _one_line_exit_2(capsys, argv):
    code = _exit_code(argv)
    err = capsys.readouterr().err
    assert code == 2, err
    assert err.count("\n") == 1 and err.startswith("jaxtissue: error: ") and "Traceback" not in err
    return err


numbers = st.one_of(st.floats(allow_nan=True, allow_infinity=True), st.integers(-10**6, 10**6).map(float))


@settings(settings.get_profile(PROFILE), max_examples=200 if LONG else 40)
@given(name=st.sampled_from(sorted(FIELDS)), value=numbers)
def test_out_of_range_parameters_are_one_line_errors(tmp_path, capsys, name, value):
    assume(not (math.isfinite(value) and FIELDS[name].contains(value)))
    err = _one_line_exit_2(capsys, ["simulate", "--set", f"{name}={value!r}", "--out", str(tmp_path / "o")])
    assert name in err
    assert not (tmp_path / "o").exists()


text = st.text(st.characters(blacklist_categories=("Cs",), blacklist_characters="\x00"), max_size=12)


@settings(settings.get_profile(PROFILE), max_examples=200 if LONG else 40)
@given(flag=st.sampled_from(["--period", "--post-displacement", "--hold-fraction", "--t-end", "--rtol", "--max-steps", "--set", "--grid"]),
       value=st.one_of(text, numbers.map(repr)))
def test_garbled_flags_are_one_line_errors(tmp_path, capsys, flag, value):
    assume(not value.startswith("-") or value[1:2].isdigit() or value[1:2] == ".")  # argparse would read a flag
    argv = ["simulate", "--regime", "flex", flag, value] + (["1"] if flag == "--grid" else []) + ["--out", str(tmp_path / "o")]
    try:
        number = float(value)
    except ValueError:
        number = None
    valid = {
        "--period": number is not None and math.isfinite(number) and number > 0,
        "--post-displacement": number is not None and math.isfinite(number) and 0 <= number < 25,
        "--hold-fraction": number is not None and math.isfinite(number) and 0 <= number < 0.25,
        "--t-end": number is not None and math.isfinite(number) and number > 0,
        "--rtol": number is not None and math.isfinite(number) and number > 0,
        "--max-steps": value.strip().lstrip("+").isdigit() and int(value) > 0,
        "--grid": value.strip().lstrip("+").isdigit() and int(value) > 0,
        "--set": False,
    }[flag]
    assume(not valid)
    _one_line_exit_2(capsys, argv)
    assert not (tmp_path / "o").exists()


@settings(settings.get_profile(PROFILE), max_examples=200 if LONG else 30)
@given(kind=st.sampled_from(["sweep", "calibrate", "optimize"]), body=st.text(max_size=200))
def test_garbage_problem_files_are_one_line_errors(tmp_path, capsys, kind, body):
    path = tmp_path / "problem.toml"
    path.write_bytes(body.encode("utf-8", "replace"))
    code = _exit_code([kind, str(path), "--out", str(tmp_path / "o")])
    err = capsys.readouterr().err
    assert code == 2, err
    assert err.count("\n") == 1 and "Traceback" not in err
    assert not (tmp_path / "o").exists()


@settings(settings.get_profile(PROFILE), max_examples=200 if LONG else 30)
@given(body=st.text(max_size=300))
def test_garbage_measurement_tables_are_one_line_errors(tmp_path, capsys, body):
    (tmp_path / "data.csv").write_bytes(body.encode("utf-8", "replace"))
    problem = tmp_path / "problem.toml"
    problem.write_text('measurements = "data.csv"\n[parameters.free]\nk_m0 = { bounds = [1e-7, 1e-6] }\n[conditions.static]\nregime = "static"\n')
    code = _exit_code(["calibrate", str(problem), "--out", str(tmp_path / "o")])
    err = capsys.readouterr().err
    assert code == 2, err
    assert err.count("\n") == 1 and "Traceback" not in err and "data.csv" in err


class _Compiling(Exception):
    """Raised in place of the compiled run: the checks before it have passed."""


def _stub_run(*args, **kwargs):
    raise _Compiling


extreme = st.floats(-15, 15).map(lambda e: 10.0**e)


@settings(settings.get_profile(PROFILE), max_examples=200 if LONG else 30)
@given(regime=st.sampled_from(["static", "flex"]), t_end=extreme, nx=st.integers(0, 9).map(lambda e: 10**e),
       ny=st.integers(0, 9).map(lambda e: 3 * 10**e), period=extreme, displacement=st.floats(0, 24.99))
def test_extreme_but_well_formed_runs_are_refused_in_one_line_or_reach_their_run(tmp_path, capsys, monkeypatch, regime, t_end, nx, ny,
                                                                                 period, displacement):
    """Huge and tiny times, grids, periods, displacements: within seconds, either one
    line and exit code 2 (too many intervals, too much memory) or the checks pass and
    the run starts (stubbed here: the runs themselves are the tests above and in
    test_limits.py)."""
    monkeypatch.setattr(sys.modules["jaxtissue.simulate"], "_simulate", _stub_run)
    argv = ["simulate", "--regime", regime, "--t-end", repr(t_end), "--grid", str(nx), str(ny), "--no-progress",
            "--out", str(tmp_path / "o")]
    if regime == "flex":
        argv += ["--period", repr(period), "--post-displacement", repr(displacement)]
    start = time.perf_counter()
    code = _exit_code(argv)
    err = capsys.readouterr().err
    assert time.perf_counter() - start < 30 and "Traceback" not in err
    errors = [line for line in err.splitlines() if not line.startswith("jaxtissue: warning: ")]
    assert len(errors) == 1, err
    if code == 2:
        assert errors[0].startswith("jaxtissue: error: ") and ("coupling intervals" in err or "GiB of memory" in err), err
    else:
        assert code == 1 and "_Compiling" in errors[0], err
        assert nx * ny * 1000 < limits.available_bytes() and t_end / 2e4 <= limits.MAX_INTERVALS
    assert not (tmp_path / "o").exists()
