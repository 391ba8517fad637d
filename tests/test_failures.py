"""Failing solves are detected inside the jitted run (`Result.status`), reported with the
simulated time reached and a hint, and nothing is written as if they had succeeded."""

import numpy as np
import pytest

import jaxtissue as jt
from helpers import SMALL_FLEX
from jaxtissue.beam import BeamGrid
from jaxtissue.cli import main
from jaxtissue.limits import ExtrapolationWarning


def one_error_line(capsys):
    """The one error line on stderr (after any `jaxtissue: warning:` lines)."""
    lines = [line for line in capsys.readouterr().err.splitlines() if not line.startswith("jaxtissue: warning: ")]
    assert len(lines) == 1 and lines[0].startswith("jaxtissue: error: "), lines
    return lines[0]


def test_step_limit_reports_time_reached_and_hint(tmp_path, capsys):
    out = tmp_path / "o"
    assert main(["simulate", "--t-end", "2e5", "--grid", "1", "8", "--max-steps", "12", "--no-progress", "--out", str(out)]) == 1
    err = one_error_line(capsys)
    assert "reached its step limit; the run is valid up to t = " in err and "s of 200000 s" in err and "raise --max-steps" in err
    assert "Nothing was written" in err and not out.exists()


def test_step_limit_time_reached_is_the_last_valid_save():
    r = jt.simulate(jt.paper_parameters(), t_end_s=2e5, grid=jt.Grid(1, 8), options=jt.SolverOptions(max_steps=40))
    assert r.status == jt.RESULTS.max_steps_reached and bool(r.failed)
    k = r.ts.index(float(r.t_reached_s))
    assert np.all(np.isfinite(r.collagen_mg_per_g[: k + 1])) and not np.all(np.isfinite(r.collagen_mg_per_g))
    end = jt.simulate(jt.paper_parameters(), t_end_s=2e5, grid=jt.Grid(1, 8), options=jt.SolverOptions(max_steps=40), save="end")
    assert end.status == jt.RESULTS.max_steps_reached and float(end.t_reached_s) == 0.0  # nothing saved before the end: valid only at the start


def test_beam_non_convergence_is_reported(tmp_path, capsys):
    with pytest.warns(ExtrapolationWarning, match="post_displacement_mm = 24 mm is outside the supported range"):
        r = jt.simulate(jt.paper_parameters(), jt.Protocol.flex(post_displacement_mm=24.0), 1e5, jt.Grid(2, 8), beam=BeamGrid(8, 8))
    assert r.status == jt.RESULTS.beam_failed and float(r.t_reached_s) == 0.0
    # the run stops at its first failure: the growth steps are the first interval's alone
    with pytest.warns(ExtrapolationWarning):
        first = jt.simulate(jt.paper_parameters(), jt.Protocol.flex(post_displacement_mm=24.0), 2e4, jt.Grid(2, 8), beam=BeamGrid(8, 8))
    assert first.status == jt.RESULTS.beam_failed and int(r.num_steps) == int(first.num_steps) > 0
    assert r.failure_message().startswith("the beam's Newton solve did not converge in a loading cycle; the run is valid up to t = 0 s")
    out = tmp_path / "c"
    assert main(["cycle", "--post-displacement", "24", "--steps", "8", "--segments", "8", "--ny", "8", "--out", str(out)]) == 1
    err = capsys.readouterr().err.splitlines()
    assert len(err) == 2 and "post_displacement_mm = 24 mm is outside the supported range" in err[0]  # extrapolation: said
    assert err[1].startswith("jaxtissue: error: ") and "did not converge" in err[1] and not out.exists()


def test_post_displacement_is_bounded_by_the_strip_in_the_parameters():
    """A protocol knows no strip: its displacement is checked against `length_mm`."""
    protocol = jt.Protocol.flex(post_displacement_mm=30.0)
    with pytest.raises(ValueError, match=r"post_displacement_mm = 30 must be below the strip length 25 mm"):
        jt.simulate(jt.paper_parameters(), protocol, 2e4, jt.Grid(2, 8), beam=BeamGrid(8, 16))
    with pytest.raises(ValueError, match=r"post_displacement_mm = -1 must be >= 0 mm"):
        jt.Protocol.flex(post_displacement_mm=-1.0)
    with pytest.warns(ExtrapolationWarning, match="post_displacement_mm = 30 mm is outside the supported range"):  # valid, not studied
        long = jt.simulate(jt.paper_parameters().replace(length_mm=40.0), protocol, SMALL_FLEX["t_end_s"], jt.Grid(*SMALL_FLEX["grid_shape"]))
    assert float(long.post_force_max_N[-1]) > 0


def test_a_continued_run_starts_at_an_interval_bound():
    """`t_start_s` must be a coupling-interval bound: a multiple of T_g or 3 weeks (where
    the interval holding it is split); a run from 3 weeks continues on the same bounds."""
    p, grid = jt.paper_parameters(), jt.Grid(1, 8)
    y = jt.simulate(p, None, jt.THREE_WEEKS_S, grid).final
    with pytest.raises(ValueError, match=r"t_start_s = 15000 must be a multiple of coupling_interval_s = 20000 or 3 weeks"):
        jt.simulate(p, None, 1.9e6, grid, initial_state=y, t_start_s=1.5e4)
    r = jt.simulate(p, None, 1.9e6, grid, initial_state=y, t_start_s=jt.THREE_WEEKS_S)
    assert r.ts[0] == jt.THREE_WEEKS_S and r.ts[1] == 1.82e6 and r.ts[-1] == 1.9e6


def test_concentrations_out_of_bounds_are_reported(tmp_path, capsys):
    # three huge fixed steps: the scheme overshoots (o < 0, c > c_max)
    r = jt.simulate(jt.paper_parameters(), t_end_s=2e6, grid=jt.Grid(1, 8), options=jt.SolverOptions(fixed_steps=3, dt0_s=1e5))
    assert r.status == jt.RESULTS.out_of_bounds and bool(r.failed)
    assert "concentrations left their physical bounds" in r.failure_message() and "finer `grid`" in r.failure_message()
    out = tmp_path / "o"
    # 120 × the paper's O2 uptake at --rtol 0.5: the first interval's steps drive o below 0
    assert main(["simulate", "--set", "Q_o=0.1", "--rtol", "0.5", "--grid", "1", "8", "--no-progress", "--out", str(out)]) == 1
    assert "concentrations left their physical bounds" in one_error_line(capsys) and not out.exists()
    ok = jt.simulate(jt.paper_parameters(), t_end_s=2e6, grid=jt.Grid(1, 8))
    assert ok.status == jt.RESULTS.successful and ok.failure_message() == "" and float(ok.t_reached_s) == 2e6


def test_input_mistakes_name_the_field_and_exit_2(tmp_path, capsys):
    out = str(tmp_path / "o")
    cases = [
        (["simulate", "--regime", "flex", "--set", "length_mm=10", "--post-displacement", "12", "--out", out], "below the strip length length_mm = 10 mm"),
        (["cycle", "--set", "length_mm=3", "--post-displacement", "5", "--out", out], "--post-displacement = 5"),
        (["simulate", "--sett", "o_m=0.5", "--out", out], "did you mean '--set'?"),
        (["simulate", "--set", "o_mm=0.5", "--out", out], "did you mean 'o_m'?"),
        (["simulate", "--set", "o_m=1.5", "--out", out], "o_m = 1.5 is outside its allowed range (0, 1)"),
        (["simulate", "--regime", "flex", "--hold-fraction", "0.3", "--out", out], "--hold-fraction = 0.3 must be in [0, 0.25)"),
        (["simulate", "--regime", "flex", "--post-displacement", "-1", "--out", out], "--post-displacement = -1 must be >= 0 mm"),
        (["simulate", "--resume", out], "no interrupted run there"),
        (["sensitivity", "--regime", "flex", "--store-float32", "--out", out], "--store-float32 needs --nest-intervals"),
    ]
    for argv, message in cases:
        assert main(argv) == 2
        assert message in one_error_line(capsys)
    assert not (tmp_path / "o").exists()
