"""PEtab v2 problems: the shipped problem passes the petab linter and equals the TOML
problem, broken copies fail with the linter's messages, every problem-file feature
round-trips through the export, and the residuals of both noise models match the petab
library's own calculation."""

import dataclasses
import json
import math
import pathlib
import shutil

import equinox as eqx
import jax.numpy as jnp
import numpy as np
import pandas as pd
import pytest
from petab.v2.calculate import calculate_chi2, calculate_residuals

from jaxtissue.cli import main
from jaxtissue.studies import calibration as cal
from jaxtissue.studies import petab_problems

from helpers import TINY_MODEL

ROOT = pathlib.Path(__file__).resolve().parents[1]
SHIPPED = ROOT / "calibrate" / "engelmayr2005" / "problem.yaml"
WEEK = 604800.0


def same_problem(a: cal.Problem, b: cal.Problem):
    """Equal field by field; a log-normal prior's median to rounding (PEtab stores its log)."""
    for field in dataclasses.fields(cal.Problem):
        if field.name == "conditions":
            assert eqx.tree_equal(a.conditions, b.conditions), field.name
        elif field.name != "free":
            assert getattr(a, field.name) == getattr(b, field.name), field.name
    for f, g in zip(a.free, b.free, strict=True):
        assert f._replace(prior=None) == g._replace(prior=None)
        assert (f.prior is None) == (g.prior is None)
        if f.prior is not None:
            assert f.prior.kind == g.prior.kind
            assert f.prior.scale == pytest.approx(g.prior.scale, rel=0, nan_ok=True)
            assert f.prior.location == pytest.approx(g.prior.location, rel=1e-14, nan_ok=True)


def test_shipped_problem_passes_the_linter_and_is_the_toml_problem(capsys):
    for path in (SHIPPED, SHIPPED.parent):  # the YAML file or its folder
        assert main(["lint", str(path)]) == 0
        out = capsys.readouterr().out
        assert out.count("\n") == 1 and "valid PEtab v2 problem for jaxtissue (8 measurements, 2 experiments, 5 estimated" in out
    same_problem(petab_problems.read(SHIPPED), cal.read_problem(ROOT / "calibrate" / "engelmayr2005.toml"))


def _set(column, row, value):
    def edit(df):
        df.loc[row, column] = value
        return df
    return edit


BROKEN = {  # table, edit, the linter's message
    "unknown observable": ("measurements.tsv", _set("observableId", 1, "obs_dna"),
                           "ERROR: Observable(s) {'obs_dna'} are used in the measurement table but are not defined in the observable table."),
    "negative noise": ("measurements.tsv", _set("noiseParameters", 1, "-23"),
                       "ERROR: measurement of obs_dna_ug_per_g in experiment static at time 1.8144e+06 s: noise SD = -23 must be > 0"),
    "missing column": ("measurements.tsv", lambda df: df.drop(columns="measurement"), "ERROR: Measurement row: measurement: Field required"),
    "condition target not in the model": ("conditions.tsv", _set("targetId", 0, "o_ext"),
                                          "ERROR: Condition table contains invalid targets: {'o_ext'}"),
    "parameter not in the model": ("parameters.tsv", _set("parameterId", 0, "k_foo"),
                                   "ERROR: Extraneous parameter(s) in parameter table: {'k_foo'}"),
    "observable formula not an output": ("observables.tsv", _set("observableFormula", 0, "2*dna_ug_per_g"),
                                         "ERROR: observable obs_dna_ug_per_g: observableFormula = 2.0*dna_ug_per_g must be one model output"),
}


@pytest.mark.parametrize("case", BROKEN)
def test_broken_copies_fail_the_linter_with_its_message(tmp_path, capsys, case):
    table, edit, message = BROKEN[case]
    copy = tmp_path / "problem"
    shutil.copytree(SHIPPED.parent, copy)
    df = pd.read_csv(copy / table, sep="\t", dtype=str, keep_default_na=False)
    edit(df).to_csv(copy / table, sep="\t", index=False)
    yaml = str(copy / "problem.yaml")
    assert main(["lint", yaml]) == 2
    lines = capsys.readouterr().out.splitlines()
    assert lines and all(line.startswith(f"{yaml}: ") for line in lines)
    assert any(message in line for line in lines), lines
    assert main(["calibrate", yaml, "--out", str(tmp_path / "fit")]) == 2  # refused before any compile, nothing written
    err = capsys.readouterr().err
    assert message.removeprefix("ERROR: ") in err and not (tmp_path / "fit").exists()


def test_unreadable_problems_are_one_line(tmp_path, capsys):
    (tmp_path / "bad.yaml").write_text("format_version: 2.0.0\nmodel_files: {m: {location: x.xml, language: sbml}}\n")
    shutil.copytree(SHIPPED.parent, tmp_path / "p")
    text = SHIPPED.read_text()
    (tmp_path / "p" / "no_version.yaml").write_text(text.replace("format_version: 2.0.0\n", ""))
    (tmp_path / "p" / "no_table.yaml").write_text(text.replace("[parameters.tsv]", "[nothere.tsv]"))
    for path, message in ((tmp_path / "none.yaml", "no such PEtab problem file"),
                          (tmp_path / "bad.yaml", "must have location: FILE.toml and language: jaxtissue"),
                          (ROOT / "calibrate" / "engelmayr2005.toml", "a TOML file, not a PEtab YAML problem; `jaxtissue calibrate"),
                          (tmp_path, "a folder without problem.yaml"),
                          (tmp_path / "p" / "no_version.yaml", "ERROR: 'format_version' is a required property"),
                          (tmp_path / "p" / "no_table.yaml", "No such file or directory")):
        assert main(["lint", str(path)]) == 2
        out = capsys.readouterr().out
        assert out.count("\n") == 1 and message in out


ROUND_TRIP_CSV = """observableId,simulationConditionId,time,measurement,noiseParameters,unit,source,noiseDistribution
dna_ug_per_g,seeded,0,536,38,ug/g,seeding,normal
collagen_mg_per_g,static,1209600,0.4,0.25,mg/g,,log-normal
E_eff_kPa,static,1209600,600,0.2,kPa,,log-normal
dna_ug_per_g,flex,1209600,340,20,ug/g,,
E_eff_kPa,stages,1209600,800,150,kPa,,normal
"""

ROUND_TRIP = f"""name = "round_trip"
measurements = "m.csv"
[parameters.free]
k_m0 = {{ bounds = [5e-8, 1e-6], transform = "log", prior = {{ log-normal = [2e-7, 0.5] }} }}
E_m0_kPa_per_ug_g = {{ bounds = [0.2, 5.0], transform = "linear", prior = {{ normal = [1.0, 0.5] }}, start = 1.2 }}
k_c_max = {{ bounds = [1e-6, 2.5e-5], prior = "uniform" }}
k_a = {{ bounds = [2e-6, 2e-5], transform = "linear" }}
[parameters.fixed]
o_ext = 0.15
D_c = 1e-9
[conditions.static]
regime = "static"
[conditions.flex]
regime = "flex"
period_s = 2.0
post_displacement_mm = 7.5
hold_fraction = 0.1
[conditions.stages]
regime = "flex"
period_s = [1.0, 0.5]
post_displacement_mm = [5.0, 2.5]
stage_length_s = 604800.0
{TINY_MODEL}
[fit]
starts = 3
seed = 7
max_steps = 20
"""


@pytest.fixture
def round_trip(tmp_path):
    """A TOML problem with every feature a PEtab file can hold, and its export."""
    (tmp_path / "m.csv").write_text(ROUND_TRIP_CSV)
    (tmp_path / "problem.toml").write_text(ROUND_TRIP)
    assert main(["calibrate", str(tmp_path / "problem.toml"), "--export-petab", str(tmp_path / "petab")]) == 0
    return cal.read_problem(tmp_path / "problem.toml"), tmp_path / "petab" / "problem.yaml"


def test_every_problem_feature_round_trips_through_petab(round_trip, capsys):
    toml, yaml = round_trip
    assert main(["lint", str(yaml)]) == 0
    assert "ERROR" not in capsys.readouterr().out
    petab = petab_problems.read(yaml)
    same_problem(petab, toml)
    assert [f.transform for f in petab.free] == ["log", "linear", "log", "linear"]
    assert petab.free[0].prior.location == pytest.approx(2e-7, rel=1e-12)  # PEtab's log-normal: [ln median, SD of ln]
    assert petab.conditions["stages"].stages == 2 and petab.base.o_ext == 0.15
    assert list(petab.log_normal()) == [False, True, True, False, False]


def test_residuals_of_both_noise_models_match_petabs_calculation(round_trip):
    _, yaml = round_trip
    problem, files = petab_problems.read(yaml), petab_problems.load(yaml)
    model = problem.data()[0] * np.linspace(0.7, 1.4, len(problem.observations))  # any positive model values
    simulation = files.measurement_df.rename(columns={"measurement": "simulation"})
    simulation["simulation"] = model
    args = (files.measurement_df, simulation, files.observable_df, files.parameter_df)
    (theirs,) = calculate_residuals(*args)
    ours = np.asarray(problem.residuals_of(jnp.asarray(model)))
    np.testing.assert_allclose(ours, -theirs["residual"].to_numpy(), rtol=1e-12)  # theirs: data − model
    assert float(np.sum(ours**2)) == pytest.approx(calculate_chi2(*args), rel=1e-12)
    np.testing.assert_allclose(problem.model_from_residuals(ours), model, rtol=1e-12)


def test_a_log_normal_fit_converges_and_its_chi2_is_petabs(tmp_path):
    """Static data with log-normal noise on collagen and E, fitted from the PEtab file:
    the fit lowers χ² from its start, converges, and its χ² is the petab library's χ² of
    the fitted model values."""
    (tmp_path / "m.csv").write_text(
        "observableId,simulationConditionId,time,measurement,noiseParameters,noiseDistribution\n"
        "collagen_mg_per_g,static,1209600,0.35,0.2,log-normal\nE_eff_kPa,static,1209600,520,0.15,log-normal\n"
        "E_eff_kPa,seeded,0,174,22,normal\n")
    (tmp_path / "problem.toml").write_text(
        'measurements = "m.csv"\n[parameters.free]\nk_m0 = { bounds = [5e-8, 1e-6] }\nE_m0_kPa_per_ug_g = { bounds = [0.1, 10.0] }\n'
        '[conditions.static]\nregime = "static"\n' + TINY_MODEL + "[fit]\nstarts = 1\nmax_steps = 30\n")
    assert main(["calibrate", str(tmp_path / "problem.toml"), "--export-petab", str(tmp_path / "petab")]) == 0
    yaml = tmp_path / "petab" / "problem.yaml"
    problem = petab_problems.read(yaml)
    best = cal.fit(problem)
    start_chi2 = float(np.sum(np.asarray(problem.residuals(jnp.asarray(best.starts_t[0]))) ** 2))
    assert bool(best.converged_all[0]) and best.chi2 < 0.01 * start_chi2
    model = problem.model_from_residuals(np.asarray(problem.residuals(jnp.asarray(best.t))))
    files = petab_problems.load(yaml)
    simulation = files.measurement_df.rename(columns={"measurement": "simulation"})
    simulation["simulation"] = model
    assert best.chi2 == pytest.approx(calculate_chi2(files.measurement_df, simulation, files.observable_df, files.parameter_df), rel=1e-9)


def test_export_refuses_what_petab_cannot_hold(tmp_path, capsys):
    (tmp_path / "m.csv").write_text("observableId,simulationConditionId,time,measurement,noiseParameters\n"
                                    "E_eff_kPa,flex,1814400,900,200\n")
    (tmp_path / "p.toml").write_text('measurements = "m.csv"\n[parameters.free]\nk_m0 = { bounds = [5e-8, 1e-6] }\n'
                                     '[conditions.flex]\nregime = "flex"\nlumping = "paper"\n')
    assert main(["calibrate", str(tmp_path / "p.toml"), "--export-petab", str(tmp_path / "out")]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "lumping = 'paper'" in err and not (tmp_path / "out").exists()
    assert main(["calibrate", str(SHIPPED), "--export-petab", str(tmp_path / "out")]) == 2
    assert "is a PEtab problem already" in capsys.readouterr().err
    assert main(["calibrate", str(tmp_path / "p.toml")]) == 2
    assert "calibrate needs --out DIR" in capsys.readouterr().err


@pytest.mark.slow  # two full fits of the shipped problem (~2 × 100 s)
def test_petab_and_toml_problems_reach_the_same_chi2(tmp_path, capsys):
    chi2 = {}
    for name, path in (("toml", ROOT / "calibrate" / "engelmayr2005.toml"), ("petab", SHIPPED)):
        assert main(["calibrate", str(path), "--no-profiles", "--out", str(tmp_path / name)]) == 0
        chi2[name] = json.loads((tmp_path / name / "summary.json").read_text())["chi2"]
    assert math.isfinite(chi2["toml"]) and chi2["petab"] == pytest.approx(chi2["toml"], rel=1e-6)


def test_normal_noise_values_never_pass_through_exp():
    """Large residuals of normal-noise data (a poor posterior draw) give no overflow
    warning from the log-normal branch."""
    problem = cal.read_problem(ROOT / "calibrate" / "engelmayr2005.toml")
    r = np.full(len(problem.observations), 50.0)
    with np.errstate(over="raise", invalid="raise"):
        model = problem.model_from_residuals(r)
        noisy = problem.with_noise(model, r)
    mean, sd = problem.data()
    np.testing.assert_allclose(model, mean + 50 * sd)
    np.testing.assert_allclose(noisy, model + 50 * sd)
