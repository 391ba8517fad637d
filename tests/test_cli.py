"""The `jaxtissue` command: outputs, files that load back, and one-line errors."""

import json
import os
import re
import subprocess
import sys

import numpy as np
import pytest
import xarray as xr

import jaxtissue as jt
from helpers import SMALL_FLEX
from jaxtissue.cli import main
from jaxtissue.io import read_params_toml


def run_cli(*args):
    """Run the real console entry point in a subprocess: (exit code, stdout, stderr)."""
    proc = subprocess.run(
        [sys.executable, "-m", "jaxtissue.cli", *args], capture_output=True, text=True, timeout=600
    )
    return proc.returncode, proc.stdout, proc.stderr


@pytest.fixture(scope="module")
def static_run(tmp_path_factory):
    out = tmp_path_factory.mktemp("runs") / "static"
    code, stdout, stderr = run_cli(
        "simulate", "--regime", "static", "--t-end", "1.9e6", "--grid", "1", "20", "--set", "k_m0=2e-7", "--out", str(out)
    )
    assert code == 0, stderr
    assert f"wrote {out}/" in stdout  # printed and flushed before the process ends without teardown
    return out


def test_simulate_writes_every_file(static_run):
    names = {p.name for p in static_run.iterdir()}
    assert {"result.nc", "summary.json", "params.toml", "profiles.png", "time_series.png"} <= names
    summary = json.loads((static_run / "summary.json").read_text())
    for key in ("times_s", "dna_ug_per_g", "collagen_mg_per_g", "E_eff_kPa", "EI_N_m2", "params"):
        assert key in summary
    assert jt.THREE_WEEKS_S in summary["times_s"]
    assert summary["params"]["k_m0"] == 2e-7
    assert summary["solver"] == {"method": "ros34pw2", "rtol": 1e-5, "atol": 1e-8}
    ds = xr.open_dataset(static_run / "result.nc", engine="h5netcdf")
    assert ds["E_eff_kPa"].attrs["units"] == "kPa"
    assert float(ds["collagen_mg_per_g"][-1]) == pytest.approx(summary["collagen_mg_per_g"][-1])


def test_params_file_round_trips(static_run, tmp_path):
    p = read_params_toml(static_run / "params.toml")
    assert p.k_m0 == 2e-7 and p.k_c_max == 1.24e-5
    code = main(["simulate", "--params", str(static_run / "params.toml"), "--t-end", "2e4", "--grid", "1", "8", "--out", str(tmp_path / "again")])
    assert code == 0


def test_console_ends_the_process_without_teardown_unless_in_a_process_group(monkeypatch):
    """`jaxtissue` (`cli.console`): `main`'s exit code through `os._exit`, or through
    `sys.exit` in a `jax.distributed` group (whose exit handlers shut it down)."""
    from jaxtissue import cli

    class Ended(Exception):
        pass

    def os_exit(code):
        raise Ended(code)

    monkeypatch.setattr(cli, "main", lambda: 3)
    monkeypatch.setattr(cli.os, "_exit", os_exit)
    with pytest.raises(Ended, match="3"):
        cli.console()
    import jax

    monkeypatch.setattr(jax.distributed, "is_initialized", lambda: True)
    with pytest.raises(SystemExit) as stop:
        cli.console()
    assert stop.value.code == 3


def exit_code(argv):
    """`main(argv)`'s exit code, whether it returns it or argparse exits with it."""
    try:
        return main(argv)
    except SystemExit as stop:
        return stop.code


@pytest.mark.parametrize(
    "args, words",
    [
        (["--set", "k_cmax=1e-5"], ["k_cmax", "did you mean 'k_c_max'"]),
        (["--set", "o_m=1.5"], ["o_m", "1.5", "(0, 1)"]),
        (["--set", "k_a=fast"], ["k_a", "not a number"]),
        (["--set", "k_a"], ["NAME=VALUE"]),
        (["--set", "k_m0=1e-7", "--set", "k_m0=2e-7"], ["--set k_m0 is given twice (1e-07 and 2e-07)"]),
        (["--t-end", "0"], ["--t-end", "positive"]),
        (["--t-end", "-5"], ["--t-end", "positive"]),
        (["--rtol", "2"], ["--rtol", "below 1"]),
        (["--grid", "1", "2"], ["NY", "at least 3"]),
        (["--params", "/nonexistent/p.toml"], ["no such parameter file"]),
        (["--params", sys.executable], ["not a TOML parameter file", "not UTF-8"]),
        (["--regime", "dynamic"], ["--regime", "invalid choice"]),
        (["--method", "rk4"], ["--method", "invalid choice"]),
        (["--regime", "flex", "--method", "rodas4p2"], ["method = 'rodas4p2'", "1-D grid", "flex run", "'ros34pw2'"]),
    ],
)
def test_bad_input_gives_one_line_and_exit_2(tmp_path, capsys, args, words):
    out = tmp_path / "never"
    code = exit_code(["simulate", *args, "--out", str(out)])
    err = capsys.readouterr().err
    assert code == 2
    assert err.count("\n") == 1 and err.startswith("jaxtissue: error:"), err
    for word in words:
        assert word in err
    assert not out.exists()


def test_toml_files_with_a_byte_order_mark_are_read(tmp_path):
    """TOML has no byte-order mark, but some editors write one: the files read as without it."""
    text = "[parameters]\nk_m0 = 1.5e-7\n"
    (tmp_path / "plain.toml").write_text(text)
    (tmp_path / "bom.toml").write_bytes(b"\xef\xbb\xbf" + text.encode())
    assert read_params_toml(tmp_path / "bom.toml") == read_params_toml(tmp_path / "plain.toml")
    assert read_params_toml(tmp_path / "bom.toml").k_m0 == 1.5e-7


def test_a_saved_parameter_that_is_not_a_number_is_one_line():
    """Values read back from a file (a checkpoint's run.json) go through `make_params`:
    a string there is an `InputError` naming the file, not a `TypeError`."""
    from jaxtissue.io import InputError, make_params

    with pytest.raises(InputError, match=r"^run.json: parameter k_m0 = 'abc' must be a number \(1/s\)$"):
        make_params({"k_m0": "abc"}, where="run.json")


def test_method_flag_chooses_the_solvers_method(tmp_path, monkeypatch):
    """`simulate --method` reaches the run's `SolverOptions` (the run itself stopped
    before it compiles; the stepper's own tests: tests/test_solver.py)."""
    import sys

    from jaxtissue.io import InputError
    from jaxtissue.numerics import SOLVERS
    from jaxtissue.simulate import METHODS

    chosen = []

    def stop(*args, options, **kwargs):
        chosen.append(options.method)
        raise InputError("stopped before the run")

    monkeypatch.setattr(sys.modules["jaxtissue.simulate"], "simulate", stop)
    for method in (None, "rodas4p2"):
        assert main(["simulate", "--out", str(tmp_path / "o")] + (["--method", method] if method else [])) == 2
    assert chosen == ["ros34pw2", "rodas4p2"] and set(METHODS) == set(SOLVERS)
    assert not (tmp_path / "o").exists()
    from jaxtissue.cli import build_parser

    for method in METHODS:  # the flag offers every method
        assert build_parser().parse_args(["simulate", "--method", method, "--out", "o"]).method == method


def test_malformed_and_unknown_params_files(tmp_path, capsys):
    bad = tmp_path / "bad.toml"
    bad.write_text("k_a = = 3\n")
    assert main(["simulate", "--params", str(bad), "--out", str(tmp_path / "x")]) == 2
    assert "not valid TOML" in capsys.readouterr().err
    bad.write_text("[parameters]\nkm0 = 1e-7\n")
    assert main(["simulate", "--params", str(bad), "--out", str(tmp_path / "x")]) == 2
    assert "did you mean 'k_m0'" in capsys.readouterr().err
    bad.write_text("[parameters]\nk_m0 = 'fast'\n")
    assert main(["simulate", "--params", str(bad), "--out", str(tmp_path / "x")]) == 2
    assert "must be a number" in capsys.readouterr().err


def test_existing_output_is_never_clobbered(static_run, capsys):
    before = (static_run / "summary.json").read_text()
    assert main(["simulate", "--t-end", "2e4", "--grid", "1", "8", "--out", str(static_run)]) == 2
    assert "--overwrite" in capsys.readouterr().err
    assert (static_run / "summary.json").read_text() == before


@pytest.mark.skipif(os.geteuid() == 0, reason="root can write anywhere")
def test_unwritable_output(tmp_path, capsys):
    locked = tmp_path / "locked"
    locked.mkdir()
    locked.chmod(0o500)
    assert main(["simulate", "--t-end", "2e4", "--out", str(locked / "out")]) == 2
    assert "cannot write" in capsys.readouterr().err


@pytest.mark.skipif(not os.path.isdir("/proc/self"), reason="needs Linux's /proc")
def test_an_output_where_the_file_system_refuses_files(capsys):
    """/proc takes no new files, even from root (for whom `os.access` says yes)."""
    assert main(["simulate", "--t-end", "2e4", "--out", "/proc/jaxtissue-out"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("jaxtissue: error: --out /proc/jaxtissue-out: cannot write in /proc")


def test_a_full_disk_is_one_line_and_leaves_nothing(tmp_path, capsys, monkeypatch):
    """The file system refusing a write mid-command (here: no space left) is one line
    and exit code 1, not an internal error; no output folder, partial or lock remains."""
    import errno
    import tempfile

    def full(*args, **kwargs):
        raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC), kwargs.get("dir"))

    monkeypatch.setattr(tempfile, "mkstemp", full)
    assert main(["simulate", "--t-end", "2e4", "--grid", "1", "8", "--out", str(tmp_path / "run")]) == 1
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1, err
    assert re.fullmatch(rf"jaxtissue: error: No space left on device \({re.escape(str(tmp_path))}/\.run\.partial-\w+\); no output was written", err[0]), err
    assert list(tmp_path.iterdir()) == []


def test_output_parents_are_created_but_not_through_a_file(tmp_path, capsys):
    assert main(["simulate", "--t-end", "2e4", "--grid", "1", "8", "--out", f"{tmp_path / 'a' / 'b'}/"]) == 0
    assert (tmp_path / "a" / "b" / "summary.json").exists()
    assert capsys.readouterr().out.strip().splitlines()[-1].startswith(f"wrote {tmp_path / 'a' / 'b'}/ (result.nc")
    (tmp_path / "file").write_text("x")
    assert main(["simulate", "--t-end", "2e4", "--out", str(tmp_path / "file" / "b")]) == 2
    assert "cannot create folder" in capsys.readouterr().err


@pytest.mark.parametrize("out", [".", "..", "", "/", "sub/.."])
def test_an_output_must_be_a_folder_of_its_own(tmp_path, capsys, monkeypatch, out):
    """`--out .` (or `..`, `/`, an empty path) with `--overwrite` would replace the folder
    the user works in: refused in one line, before anything is computed or touched."""
    (tmp_path / "sub").mkdir()
    (tmp_path / "sub" / "keep.txt").write_text("x")
    monkeypatch.chdir(tmp_path / "sub")
    assert exit_code(["simulate", "--t-end", "2e4", "--grid", "1", "8", "--out", out, "--overwrite"]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "--out" in err and ("names no folder" in err or "name the output folder itself" in err), err
    assert sorted(p.name for p in tmp_path.rglob("*")) == ["keep.txt", "sub"]


def test_version_is_the_packages(capsys):
    import importlib.metadata

    assert exit_code(["--version"]) == 0
    assert capsys.readouterr().out == f"jaxtissue {jt.__version__}\n"
    assert jt.__version__ == importlib.metadata.version("jaxtissue")  # the installed package's (pyproject.toml)


def test_params_table_lists_every_field(capsys):
    assert main(["params"]) == 0
    out = capsys.readouterr().out
    for name in ("k_c_max", "lumping_C", "E_m0_kPa_per_ug_g", "cm^2/s"):
        assert name in out


def test_cycle_command(tmp_path):
    out = tmp_path / "cycle"
    code = main(["cycle", "--post-displacement", "5", "--period", "1", "--ecm", "0.01", "--segments", "20", "--steps", "80", "--ny", "12", "--out", str(out)])
    assert code == 0
    summary = json.loads((out / "summary.json").read_text())
    assert summary["midspan_deflection_mm_max"] == pytest.approx(6.66, rel=0.02)
    assert summary["post_force_max_N"] > 0 and summary["cycle_mean_velocity_cm_s_max"] > 0
    assert (out / "shape.png").exists() and (out / "flow.png").exists()


@pytest.mark.parametrize(
    "args, words",
    [
        (["--ecm", "2"], ["--ecm", "[0, 1]"]),
        (["--post-displacement", "30"], ["--post-displacement", "30", "below the strip length"]),
        (["--hold-fraction", "0.3"], ["--hold-fraction", "0.3", "[0, 0.25)"]),
        (["--period", "0"], ["--period", "positive"]),
        (["--segments", "5"], ["--segments 5", "an even number >= 4"]),
        (["--ny", "2"], ["--ny 2", "at least 3"]),
        (["--steps", "4"], ["--steps 4", "at least 8"]),
    ],
)
def test_cycle_bad_input(tmp_path, capsys, args, words):
    code = exit_code(["cycle", *args, "--out", str(tmp_path / "never")])
    err = capsys.readouterr().err
    assert code == 2 and err.count("\n") == 1, err
    for word in words:
        assert word in err
    assert not (tmp_path / "never").exists()


def _check_reproduction(rep):
    summary = json.loads((rep / "summary.json").read_text())
    for case in ("static", "flex", "flex_0.5Hz", "flex_2Hz", "flex_2.5mm", "flex_10mm"):
        assert set(summary[case]) >= {"dna_ug_per_g", "collagen_mg_per_g", "E_eff_kPa", "post_force_max_N"}
    for name in ("report.md", "fig5_profiles_static.png", "fig7_profiles_flex.png", "fig8_ecm_maps.png", "fig9_contents.png", "fig10_rigidity_force.png"):
        assert (rep / name).exists()
    report = (rep / "report.md").read_text()
    assert "Engelmayr" in report
    assert "values at t = 40000 s (the run ends before 3 weeks)" in report and "3-week values" not in report
    assert "The paper's literal rule (signed mean velocity over one cycle from rest, C = 70)" in report


def test_reproduction_on_small_grids(tmp_path):
    """The main job's cases, files and report over two growth intervals, on small grids
    (the default grids through the command: the slow test below). The flex cases give
    what `simulate` gives for each (over several devices they run as one program:
    `sweep.map_over_devices`, tests/test_optimization.py and benchmarks/flex_cases.py)."""
    p = jt.paper_parameters()
    grid = jt.Grid(*SMALL_FLEX["grid_shape"])
    results = jt.reproduce.run_cases(p, t_end_s=SMALL_FLEX["t_end_s"], log=lambda _: None, flex_grid=grid)
    for name in ("flex", "flex_2Hz", "flex_10mm"):
        alone = jt.simulate(p, jt.reproduce.CASES[name], SMALL_FLEX["t_end_s"], grid)  # the suite's shared program
        assert results[name].ts == alone.ts and bool(results[name].failed) is False
        for k in ("dna_ug_per_g", "collagen_mg_per_g", "E_eff_kPa", "post_force_max_N"):
            np.testing.assert_allclose(getattr(results[name], k), getattr(alone, k), rtol=1e-12, err_msg=f"{name}: {k}")
    rep = tmp_path / "reproduce"
    rep.mkdir()
    jt.reproduce.write(results, p, rep)
    _check_reproduction(rep)
    assert json.loads((rep / "summary.json").read_text())["warnings"] == [] and "## Warnings" not in (rep / "report.md").read_text()


def test_reproduction_records_what_extrapolates():
    """summary.json's and the report's warnings: one line per value outside its supported range."""
    import types

    results = {"static": types.SimpleNamespace(ts=(0.0, 1.0e6)), "flex": types.SimpleNamespace(ts=(0.0, 2.5e6))}
    lines = jt.reproduce.extrapolations(results, jt.paper_parameters().replace(thickness_mm=3.0))
    assert len(lines) == 2 and lines[0].startswith("thickness_mm = 3 mm is outside") and lines[1].startswith("t_end_s = 2.5e+06 s")
    assert jt.reproduce.extrapolations(results | {"flex": types.SimpleNamespace(ts=(0.0, 2.0e6))}, jt.paper_parameters()) == []


@pytest.mark.slow
def test_simulate_flex_and_reproduce_commands(tmp_path):
    """The flex regime and the main job through the command, over two growth intervals."""
    out = tmp_path / "flex"
    assert main(["simulate", "--regime", "flex", "--t-end", "4e4", "--grid", "6", "10", "--period", "2", "--out", str(out)]) == 0
    summary = json.loads((out / "summary.json").read_text())
    assert summary["regime"] == "flex" and summary["post_force_max_N"][-1] > 0
    rep = tmp_path / "reproduce"
    assert main(["reproduce", "--t-end", "4e4", "--out", str(rep)]) == 0
    _check_reproduction(rep)
