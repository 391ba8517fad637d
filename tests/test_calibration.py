"""Calibration: measurement tables, problem files, synthetic recovery, Jacobians, CLI."""

import dataclasses
import json
import pathlib
import re

import equinox as eqx
import jax.numpy as jnp
import numpy as np
import pytest

import jaxtissue as jt
from jaxtissue import cache
from jaxtissue import calibration as cal
from jaxtissue.cli import main
from jaxtissue.data import ENGELMAYR, DataError, read_measurements
from jaxtissue.io import InputError, read_params_toml

from helpers import TINY_MODEL

ROOT = pathlib.Path(__file__).resolve().parents[1]
WEEK = 604800.0
HEADER = "observableId,simulationConditionId,time,measurement,noiseParameters,unit,source\n"

TRUTH = dict(lumping_C=0.3, k_c_max=1.3e-5, k_a=0.9e-5, k_m0=2.0e-7, E_m0_kPa_per_ug_g=1.2)
BOUNDS = dict(lumping_C=(0.05, 2.0), k_c_max=(0.6e-5, 2.5e-5), k_a=(0.3e-5, 2.0e-5), k_m0=(5e-8, 1e-6), E_m0_kPa_per_ug_g=(0.2, 5.0))
STARTS = dict(lumping_C=0.4, k_c_max=1.15e-5, k_a=1.05e-5, k_m0=1.7e-7, E_m0_kPa_per_ug_g=1.0)  # 10-30 % off

MODEL = "\n" + TINY_MODEL + "rtol = 1e-8\natol = 1e-11\n"


def problem_toml(folder, csv_name, free, regimes=("static", "flex"), fit="starts = 1\nmax_steps = 40\nprofile_points = 2"):
    lines = [f'measurements = "{csv_name}"', "[parameters.free]"]
    for name in free:
        lo, hi = BOUNDS[name]
        lines.append(f'{name} = {{ bounds = [{lo!r}, {hi!r}], transform = "log", start = {STARTS[name]!r} }}')
    for regime in regimes:
        lines.append(f'[conditions.{regime}]\nregime = "{regime}"')
    path = folder / "problem.toml"
    path.write_text("\n".join(lines) + "\n" + MODEL + "[fit]\n" + fit + "\n")
    return path


def synthetic(folder, free, regimes=("static", "flex"), noise=0.0, seed=0):
    """Measurements of DNA, collagen and E at 1, 2, 3 weeks from the model at TRUTH."""
    (folder / "m.csv").write_text(HEADER + "".join(
        f"{q},{r},{w * WEEK},1.0,1.0,{u},\n" for q, u in (("dna_ug_per_g", "ug/g"), ("collagen_mg_per_g", "mg/g"), ("E_eff_kPa", "kPa"))
        for r in regimes for w in (1, 2, 3)))
    problem = cal.read_problem(problem_toml(folder, "m.csv", free, regimes))
    truth_t = problem.t_from_values([TRUTH[n] for n in problem.names])
    values = np.asarray(problem.model_values(truth_t))
    sd = 0.02 * np.abs(values)
    noisy = values + noise * sd * np.random.default_rng(seed).standard_normal(values.shape)
    obs = tuple(o._replace(mean=float(v), sd=float(s)) for o, v, s in zip(problem.observations, noisy, sd))
    return dataclasses.replace(problem, observations=obs), truth_t


# ---- measurement tables


def test_engelmayr_table_matches_the_model_spec():
    rows = read_measurements(ROOT / "calibrate" / "data" / "engelmayr2005.csv")
    assert [r[:6] for r in rows] == [o[:6] for o in ENGELMAYR]


@pytest.mark.parametrize("row, message", [
    ("collagen_mg_per_gg,static,0,1,1,mg/g,", "row 2: unknown observableId 'collagen_mg_per_gg'; did you mean 'collagen_mg_per_g'?"),
    ("dna_ug_per_g,static,0,300,-5,ug/g,", "row 2: noiseParameters (SD) = -5 must be > 0"),
    ("dna_ug_per_g,static,soon,300,5,ug/g,", "row 2: time = 'soon' is not a number"),
    ("dna_ug_per_g,static,0,300,5,mg/g,", "row 2: unit 'mg/g' of dna_ug_per_g must be 'ug/g'"),
])
def test_bad_measurement_rows_name_the_row(tmp_path, row, message):
    path = tmp_path / "m.csv"
    path.write_text(HEADER + row + "\n")
    with pytest.raises(DataError) as err:
        read_measurements(path)
    assert str(err.value) == f"{path}, {message}"


def test_missing_column_is_named(tmp_path):
    path = tmp_path / "m.csv"
    path.write_text("observableId,simulationConditionId,time,measurement\ndna_ug_per_g,static,0,300\n")
    with pytest.raises(DataError, match="missing column 'noiseParameters'"):
        read_measurements(path)


# ---- problem files


def test_engelmayr_problem_reads():
    problem = cal.read_problem(ROOT / "calibrate" / "engelmayr2005.toml")
    assert {"lumping_C", "k_c_max", "k_a", "k_m0", "E_m0_kPa_per_ug_g"} <= set(problem.names)
    assert set(problem.conditions) == {"static", "flex"}
    assert len(problem.observations) == 8


@pytest.mark.parametrize("edit, message", [
    (("transform = \"log\", start = 0.4", "transfrom = \"log\""), "unknown key 'transfrom' in [parameters.free] lumping_C; did you mean 'transform'?"),
    (("[0.05, 2.0]", "[2.0, 0.05]"), "[parameters.free] lumping_C bounds = [2, 0.05] must have low < high"),
    (("lumping_C =", "lumping_K ="), "unknown parameter 'lumping_K' in [parameters.free]; did you mean 'lumping_C'?"),
    (('regime = "flex"', 'regime = "flexx"'), "[conditions.flex] regime = 'flexx'; allowed: 'static', 'flex'"),
    (('regime = "flex"', 'regime = "flex"\nperiod_s = -1.0'), ": [conditions.flex] period_s = -1 must be > 0 s"),
    (('regime = "flex"', 'regime = "flex"\nperiod_s = [1.0, 2.0]'), ": [conditions.flex] period_s = [1.0, 2.0] must be a number"),
    (("starts = 1", "starts = 0"), "[fit] starts = 0 must be a positive integer"),
    (("profile_points = 2", "profile_points = 1000000000"), "[fit] profile_points = 1000000000 must be at most 10000000"),
])
def test_bad_problem_files_give_one_clear_line(tmp_path, edit, message):
    (tmp_path / "m.csv").write_text(HEADER + "dna_ug_per_g,flex,1814400,300,5,ug/g,\n")
    path = problem_toml(tmp_path, "m.csv", ["lumping_C"])
    path.write_text(path.read_text().replace(*edit))
    with pytest.raises(InputError) as err:
        cal.read_problem(path)
    assert message in str(err.value)
    assert "\n" not in str(err.value)


def test_a_batch_larger_than_the_starts_solves_them_all_at_once():
    assert cal.FitSettings(starts=8, batch=100).simultaneous == 8  # not padded to 100 (memory)
    assert cal.FitSettings(starts=8, batch=3).simultaneous == 3


def test_observation_between_save_times_is_refused(tmp_path):
    (tmp_path / "m.csv").write_text(HEADER + "dna_ug_per_g,static,100000,300,5,ug/g,\ndna_ug_per_g,static,1814400,300,5,ug/g,\n")
    with pytest.raises(InputError, match="at time 100000 s: not a save time"):
        cal.read_problem(problem_toml(tmp_path, "m.csv", ["k_a"], regimes=("static",)))


def test_an_observation_beyond_the_longest_run_is_one_line(tmp_path):
    """A time past the longest run the limits allow (`limits.MAX_INTERVALS`) names the
    problem file, the condition and the time, not a command-line flag."""
    (tmp_path / "m.csv").write_text(HEADER + "dna_ug_per_g,static,1e12,300,5,ug/g,\n")
    path = problem_toml(tmp_path, "m.csv", ["k_a"], regimes=("static",))
    with pytest.raises(InputError, match=rf"^{re.escape(str(path))}: the last observation of condition 'static': `time` = 1e\+12 s is"):
        cal.read_problem(path)


def test_a_spreadsheets_byte_order_mark_is_read(tmp_path):
    """A measurement table saved as a spreadsheet's "CSV UTF-8" (starting with a UTF-8
    byte-order mark) reads as the same table without it."""
    rows = HEADER + "dna_ug_per_g,static,1814400,300,5,ug/g,\n"
    (tmp_path / "plain.csv").write_text(rows)
    (tmp_path / "bom.csv").write_bytes(b"\xef\xbb\xbf" + rows.encode())
    assert read_measurements(tmp_path / "bom.csv") == read_measurements(tmp_path / "plain.csv")


def test_a_static_condition_seen_once_keeps_only_its_end_state(tmp_path):
    """A static condition observed at one time after seeding (as in the Engelmayr data)
    runs with its end state only: the same model values and Jacobian as from its
    series (solved interval by interval), to the tolerance; seeded values from the
    seeded state; NaN where its solve fails; and, as for the series, a program with no
    host callback, which the compilation cache keeps."""
    import jax

    rows = "".join(f"{q},{r},{t},{v},5,{u},\n" for q, u, v in (("dna_ug_per_g", "ug/g", 500), ("E_eff_kPa", "kPa", 10))
                   for r, t in (("seeded", 0), ("static", 3 * WEEK)))
    (tmp_path / "once.csv").write_text(HEADER + rows)
    (tmp_path / "twice.csv").write_text(HEADER + rows + f"collagen_mg_per_g,static,{WEEK},0.1,0.05,mg/g,\n")
    once = cal.read_problem(problem_toml(tmp_path, "once.csv", ["k_a", "k_m0"], regimes=("static",)))
    twice = cal.read_problem(problem_toml(tmp_path, "twice.csv", ["k_a", "k_m0"], regimes=("static",)))  # a series
    t = once.t_from_values([1.0e-5, 2.0e-7])
    saved = [jax.eval_shape(lambda t: problem.simulate(problem.params(t))["static"].collagen_mg_per_g, t).shape for problem in (once, twice)]
    assert saved[0] == (1,) and saved[1][0] > 1

    def values_and_jacobian(problem):  # one program each
        program = jax.jit(jax.jacfwd(lambda t: (problem.model_values(t),) * 2, has_aux=True))
        j, v = program(t)
        assert "callback" not in program.lower(t).as_text()  # (traced once: the call's)
        return np.asarray(v)[:4], np.asarray(j)[:4]

    (v_once, j_once), (v_twice, j_twice) = values_and_jacobian(once), values_and_jacobian(twice)
    np.testing.assert_allclose(v_once, v_twice, rtol=once.model.rtol)
    assert np.max(np.abs(j_once - j_twice)) < 1e-6 * np.max(np.abs(j_once))

    class FewSteps(type(once.model)):
        def options(self):
            return dataclasses.replace(super().options(), max_steps=2)

    failing = dataclasses.replace(once, model=FewSteps(**dataclasses.asdict(once.model)))
    values = np.asarray(failing.model_values(t))
    assert np.all(np.isfinite(values[[0, 2]])) and np.all(np.isnan(values[[1, 3]]))  # seeded rows, static rows


# ---- fitting


@pytest.fixture(scope="module")
def recovered(tmp_path_factory):
    problem, truth_t = synthetic(tmp_path_factory.mktemp("synthetic"), list(TRUTH))
    return problem, truth_t, cal.fit(problem)


@pytest.mark.slow  # five parameters, static and flex; two, static: test_calibrate_command_recovers_and_writes_its_files
def test_noise_free_synthetic_data_recover_every_parameter_within_1_percent(recovered):
    problem, truth_t, best = recovered
    truth = np.asarray(problem.values_from_t(truth_t))
    start = np.asarray([STARTS[n] for n in problem.names])
    assert np.all(np.abs(start / truth - 1) > 0.09)  # the start really is perturbed
    np.testing.assert_allclose(best.values, truth, rtol=1e-2)
    assert best.chi2 < 1e-6


@pytest.mark.slow  # the command test checks the Jacobian of its fit against central differences
def test_fit_jacobian_matches_central_differences_at_the_optimum(recovered):
    problem, _, best = recovered
    J = cal.fisher(problem, best.t).jacobian
    # k_m = k_m0 max(o − o_m, 0) switches on where O2 crosses o_m inside the static column:
    # the tangents' right-hand side jumps there, and the step control, which sees only the
    # solution, leaves them accurate to the step at the crossing (docs/numerics.md,
    # "Derivatives across the ECM threshold"): 4e-4 of the largest entry at rtol 1e-8
    assert cal.jacobian_fd_error(problem, best.t, J, h=1e-4) < 2e-3
    # the fit's own (the LM solve's exact Jacobian where it converged) is the same matrix,
    # to the growth solves' tolerance (rtol 1e-8 here): it comes from another compiled
    # program (the LM solve), whose adaptive steps may differ by rounding
    assert np.max(np.abs(best.jacobian - J)) < 1e-7 * np.max(np.abs(J))


@pytest.mark.slow  # the noise-free recovery is the default run's
def test_noisy_synthetic_data_recover_within_three_standard_errors(tmp_path):
    free = ["k_c_max", "k_a", "k_m0", "E_m0_kPa_per_ug_g"]
    problem, truth_t = synthetic(tmp_path, free, regimes=("static",), noise=1.0, seed=3)
    best = cal.fit(problem)
    fi = cal.fisher(problem, best.t)
    z = (best.t - np.asarray(truth_t)) / fi.standard_errors_t
    assert np.all(np.abs(z) < 3), z
    assert best.chi2 < 3 * len(problem.observations)  # a sensible fit: χ² ~ n − k


@pytest.mark.slow
def test_profiles_flag_a_parameter_the_data_cannot_see(tmp_path):
    """lumping_C only acts in flexed culture: with static data only its profile is flat."""
    free = ["lumping_C", "k_m0"]
    problem, _ = synthetic(tmp_path, free, regimes=("static",))
    best = cal.fit(problem)
    fi = cal.fisher(problem, best.t)
    prof = {p.name: p for p in cal.profiles(problem, best, fi.standard_errors_t)}
    assert not prof["lumping_C"].identifiable
    assert np.ptp(prof["lumping_C"].chi2) < 1e-6
    assert prof["k_m0"].identifiable
    lo, hi = prof["k_m0"].interval
    assert lo < TRUTH["k_m0"] < hi


# ---- the command


def test_calibrate_command_recovers_and_writes_its_files(tmp_path, capsys):
    """Noise-free static data from known parameters, fitted through the command from two
    starts: the parameters come back, the fit's Jacobian matches central differences,
    and every file is written (the cheap version of the slow recovery tests above)."""
    free = ["k_m0", "E_m0_kPa_per_ug_g"]
    problem, _ = synthetic(tmp_path, free, regimes=("static",))
    rows = [f"{o.quantity},{o.regime},{o.time_s},{o.mean!r},{o.sd!r},{o.unit},\n" for o in problem.observations]
    (tmp_path / "m.csv").write_text(HEADER + "".join(rows))
    out = tmp_path / "fit"
    assert main(["calibrate", str(tmp_path / "problem.toml"), "--starts", "2", "--out", str(out)]) == 0
    summary = json.loads((out / "summary.json").read_text())
    assert set(summary["parameters"]) == set(free)
    for name in free:
        assert summary["parameters"][name] == pytest.approx(TRUTH[name], rel=1e-2), name
    assert summary["chi2"] < 1e-6 and summary["jacobian_vs_central_differences"] < 1e-4
    for key in ("standard_errors", "chi2", "identifiable", "observations"):
        assert key in summary
    assert {"name", "regime", "time_s", "data_mean", "data_sd", "noise", "model", "residual"} == set(summary["observations"][0])
    fitted = read_params_toml(out / "fitted.toml")
    assert fitted.k_m0 == pytest.approx(summary["parameters"]["k_m0"])
    assert {"report.md", "waterfall.png", "fit.png", "profiles.png", "correlation.png"} <= {p.name for p in out.iterdir()}
    assert len(summary["starts"]["chi2"]) == 2 and min(summary["starts"]["chi2"]) == pytest.approx(summary["chi2"])
    assert main(["calibrate", str(tmp_path / "problem.toml"), "--out", str(out)]) == 2  # never overwrites
    assert "folder exists and is not empty" in capsys.readouterr().err


@eqx.filter_jit
def _scaled(problem, x):
    return x * len(problem.observations)


def test_a_problem_read_from_its_file_names_its_saved_programs(tmp_path, monkeypatch):
    """The fit's programs take the problem as a static argument (`cache.call`): one read
    from its file is named by its values, so that a second `calibrate` loads them; one
    whose parameters hold arrays by theirs too (the cheap version of the next test)."""
    monkeypatch.delenv("JAXTISSUE_NO_SAVED_PROGRAMS", raising=False)
    problem = cal.read_problem(ROOT / "calibrate" / "engelmayr2005.toml")
    x = jnp.arange(3.0)
    with cache.saved_executables(tmp_path):
        cache.call(_scaled, problem, x)
        assert len(list(tmp_path.glob("*.jtx"))) == 1
        monkeypatch.setattr(cache, "_loaded", {})
        with monkeypatch.context() as m:
            m.setattr(cache, "_compile", lambda *a: pytest.fail("compiled again"))
            again = cal.read_problem(ROOT / "calibrate" / "engelmayr2005.toml")  # as a new process reads it
            np.testing.assert_array_equal(cache.call(_scaled, again, x), x * len(again.observations))
        held = [dataclasses.replace(problem, base=problem.base.replace(k_a=jnp.asarray(v))) for v in (1e-5, 1e-5, 1.0000000001e-5)]
        cache.call(_scaled, held[0], x)
        assert len(list(tmp_path.glob("*.jtx"))) == 2
        with monkeypatch.context() as m:
            m.setattr(cache, "_compile", lambda *a: pytest.fail("compiled again"))
            cache.call(_scaled, held[1], x)  # the same values in another array
        cache.call(_scaled, held[2], x)
        assert len(list(tmp_path.glob("*.jtx"))) == 3


@pytest.mark.slow  # compiles the fit's programs; the test above is its cheap version
def test_a_second_calibration_loads_its_programs(tmp_path, monkeypatch):
    monkeypatch.delenv("JAXTISSUE_NO_SAVED_PROGRAMS", raising=False)
    problem, _ = synthetic(tmp_path, ["k_m0", "E_m0_kPa_per_ug_g"], regimes=("static",))
    # seen at 3 weeks only: its static run keeps its end state, with no host callback
    problem = dataclasses.replace(problem, observations=tuple(o for o in problem.observations if o.time_s == 3 * WEEK))
    with cache.saved_executables(tmp_path / "programs"):
        first = cal.calibrate(problem, with_profiles=False)
        assert len(list((tmp_path / "programs").glob("*.jtx"))) == 2  # the fit's solve and the residuals
        monkeypatch.setattr(cache, "_loaded", {})  # as in a new process: neither traced nor compiled again
        for where, name in ((cal, "lm_solve"), (cal.Problem, "model_values"), (cache, "_compile")):
            monkeypatch.setattr(where, name, lambda *a, name=name: pytest.fail(f"{name} again"))
        second = cal.calibrate(dataclasses.replace(problem), with_profiles=False)
    np.testing.assert_array_equal(second.fit.ends_t, first.fit.ends_t)
    np.testing.assert_array_equal(second.model, first.model)


def test_calibrate_command_bad_file_exits_2(tmp_path, capsys):
    assert main(["calibrate", str(tmp_path / "none.toml"), "--out", str(tmp_path / "o")]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "no such problem file" in err


@pytest.mark.slow  # the command test reloads its fitted file
def test_result_values_in_fitted_file_reproduce_the_model(recovered, tmp_path):
    problem, _, best = recovered
    from jaxtissue.io import write_params_toml

    write_params_toml(problem.params(jnp.asarray(best.t)), tmp_path / "p.toml")
    params = read_params_toml(tmp_path / "p.toml")
    static = jt.simulate(params, jt.Protocol.static(), 3 * WEEK, problem.model.grid("static"),
                         coupling_interval_s=problem.model.coupling_interval_s, options=problem.model.options())
    i = [k for k, o in enumerate(problem.observations) if o.quantity == "collagen_mg_per_g" and o.regime == "static"][-1]
    assert float(static.collagen_mg_per_g[-1]) == pytest.approx(float(problem.model_values(jnp.asarray(best.t))[i]), rel=1e-9)
