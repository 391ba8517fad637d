"""Runs at the limits (docs/model.md §10): extrapolation is said, absurd or oversized runs
are input errors before anything compiles, the paper's rule takes the paper's C, and a
command interrupted by a signal, or racing another for its output folder, ends cleanly."""

import json
import os
import re
import signal
import subprocess
import sys
import time

import jax
import jax.numpy as jnp
import pytest

import jaxtissue as jt
from helpers import SMALL_FLEX_ARGS, wait_for
from jaxtissue import limits
from jaxtissue.cli import main
from jaxtissue.coupling import PAPER_RULE_C, with_rule_constant


def one_line(capsys, prefix="jaxtissue: error: "):
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and err.startswith(prefix) and "Traceback" not in err, err
    return err


def test_extrapolation_names_each_value_outside_its_supported_range():
    p = jt.paper_parameters()
    assert limits.extrapolation(p, jt.Protocol.flex(), jt.T_END_S) == []
    assert limits.extrapolation(p, jt.Protocol.flex(period_s=0.5, post_displacement_mm=10.0), jt.THREE_WEEKS_S) == []
    lines = limits.extrapolation(p.replace(thickness_mm=3.0), jt.Protocol.flex(period_s=1e-9, post_displacement_mm=24.9), 4e6)
    assert [line.split(" = ")[0] for line in lines] == ["thickness_mm", "period_s", "post_displacement_mm", "t_end_s"]
    assert "period_s = 1e-09 s is outside the supported range 0.5-2 s" in lines[1]
    [o2] = limits.extrapolation(p.replace(o_ext=0.01), jt.Protocol.static(), jt.T_END_S)  # a fraction: no unit "1"
    assert o2.startswith("o_ext = 0.01 is outside the supported range 0.05-0.2 (")
    schedule = jt.Protocol.schedule([1.0, 4.0], [5.0, 5.0])
    assert [line.split(" = ")[0] for line in limits.extrapolation(None, schedule)] == ["period_s"]
    assert limits.extrapolation(None, jt.Protocol.static(), None) == []  # a static run has no flexure to check

    def traced(T):  # traced values are not checked (an optimiser's iterates)
        return jnp.asarray(len(limits.extrapolation(None, jt.Protocol.flex(period_s=T))))

    assert int(jax.jit(traced)(1e-9)) == 0
    with pytest.warns(limits.ExtrapolationWarning, match="period_s = 0.1 s"):
        limits.warn_extrapolation(None, jt.Protocol.flex(period_s=0.1))


def test_absurd_and_oversized_runs_are_input_errors_before_compiling():
    p = jt.paper_parameters()
    start = time.perf_counter()
    with pytest.raises(limits.ResourceError, match=r"`t_end_s` = 1e\+12 s is 5e\+07 coupling intervals of 20000 s; a run may have at most 100000"):
        jt.simulate(p, t_end_s=1e12)
    with pytest.raises(limits.ResourceError, match=r"a 1 x 100000000 static run of 100 intervals needs about .* GiB of memory, .* GiB are available"):
        jt.simulate(p, grid=jt.Grid(1, 100_000_000))
    with pytest.raises(ValueError, match=r"max_steps = 10000000 must be an integer in \[1, 1000000\]"):
        jt.SolverOptions(max_steps=10**7)
    with pytest.raises(limits.ResourceError, match=r"computing the sensitivities of a 2000 x 2000 flex run needs about .*; a coarser `grid` or `nest_intervals`"):
        jt.sensitivity.sensitivities(p, jt.Protocol.flex(), grid=jt.Grid(2000, 2000))  # a reverse pass per output
    assert time.perf_counter() - start < 5
    assert issubclass(limits.ResourceError, ValueError)


def test_the_memory_estimate_grows_with_each_demand_and_is_checked_against_what_is_available(monkeypatch):
    base = limits.estimate(2000, 2e6, 2e4, regime="flex", save_series=False)
    assert base.intervals == 100 and base.saves == 1
    for bigger in (limits.estimate(8000, 2e6, 2e4, regime="flex", save_series=False),
                   limits.estimate(2000, 2e6, 2e4, regime="flex", save_series=False, reverse=True),
                   limits.estimate(2000, 2e6, 2e4, regime="flex", save_series=False, batch=4)):
        assert bigger.bytes > base.bytes
    static = limits.estimate(40_000, 2e6, 2e4, regime="static")
    assert static.bytes - limits.estimate(40_000, 2e6, 2e4, regime="static", save_series=False).bytes == 102 * 40_000 * 24  # every interval bound and 3 weeks
    assert 0 < limits.available_bytes() < float("inf")
    monkeypatch.setattr(limits, "available_bytes", lambda: 0.99 * base.bytes)
    with pytest.raises(limits.ResourceError, match=r"the run needs about .* GiB of memory, .* GiB are available; fewer"):
        limits.check_memory(base, "the run", "fewer")
    monkeypatch.setattr(limits, "available_bytes", lambda: 1.01 * base.bytes)
    limits.check_memory(base, "the run", "fewer")


@pytest.mark.parametrize("argv, words", [
    (["--regime", "static", "--t-end", "1e12"], "--t-end = 1e+12 s is 5e+07 coupling intervals"),
    (["--regime", "static", "--grid", "1", "100000000"], "GiB of memory"),
    (["--regime", "flex", "--max-steps", "10000000"], "--max-steps: 10000000 must be at most 1000000"),
])
def test_the_extreme_runs_of_the_command_line_end_in_one_line(tmp_path, capsys, argv, words):
    out = tmp_path / "r"
    start = time.perf_counter()
    try:
        code = main(["simulate", *argv, "--out", str(out)])
    except SystemExit as exit:  # argparse's own errors (one line, see cli._Parser)
        code = exit.code
    assert code == 2
    assert words in one_line(capsys) and time.perf_counter() - start < 30
    assert not out.exists() and not list(tmp_path.iterdir())  # no folder, no lock file


def test_huge_sweeps_are_input_errors(tmp_path, capsys):
    for body in ('[parameters]\nk_m0 = { linspace = [1e-7, 2e-7], n = 100000 }\nD_o0 = { linspace = [1e-5, 2e-5], n = 100000 }\n',
                 'design = "lhs"\nsamples = 100000000\n[parameters]\nk_m0 = { range = [1e-7, 2e-7] }\n',
                 '[parameters]\nk_m0 = { linspace = [1e-7, 2e-7], n = 1000000000000 }\n'):
        (tmp_path / "s.toml").write_text(body)
        start = time.perf_counter()
        assert main(["sweep", str(tmp_path / "s.toml"), "--out", str(tmp_path / "o")]) == 2
        assert "10000000" in one_line(capsys) and time.perf_counter() - start < 5
    assert not (tmp_path / "o").exists()


def test_the_paper_rule_takes_the_papers_C_unless_C_was_chosen(tmp_path, capsys, monkeypatch):
    p = jt.paper_parameters()
    switched, why = with_rule_constant(p, "paper")
    assert switched.lumping_C == PAPER_RULE_C == 70.0 and "the paper's rule uses the paper's C" in why
    assert with_rule_constant(p, "dispersive") == (p, None)
    chosen = p.replace(lumping_C=5.0)
    assert with_rule_constant(chosen, "paper") == (chosen, None)

    out = tmp_path / "r"  # through the command: the files say which C and why
    assert main(["simulate", "--regime", "flex", "--lumping", "paper", *SMALL_FLEX_ARGS, "--out", str(out)]) == 0
    summary = json.loads((out / "summary.json").read_text())
    assert summary["lumping"]["C"] == 70.0 and summary["params"]["lumping_C"] == 70.0 and summary["warnings"] == []
    text = (out / "params.toml").read_text()
    assert "lumping_C = 70.0" in text and "# lumping_C = 70: the paper's rule uses the paper's C" in text

    module = sys.modules["jaxtissue.simulate"]  # and through `simulate` (the run itself: `reproduce`'s paper-rule case)
    seen = []
    monkeypatch.setattr(module, "_simulate", lambda params, *args: seen.append(float(params.lumping_C)))
    for q in (p, chosen):
        jt.simulate(q, jt.Protocol.flex(lumping="paper"), 2e4, jt.Grid(2, 6))
    jt.simulate(p, jt.Protocol.flex(), 2e4, jt.Grid(2, 6))
    assert seen == [70.0, 5.0, p.lumping_C]


def test_an_extrapolating_flex_run_warns_and_records_it(tmp_path, capsys):
    """The 1 GHz flexure and the nearly folded strip of a new user: a run, with one
    warning line each and `warnings` in summary.json."""
    out = tmp_path / "r"
    start = time.perf_counter()
    code = main(["simulate", "--regime", "flex", "--period", "1e-9", "--post-displacement", "24.9",
                 *SMALL_FLEX_ARGS, "--out", str(out)])
    err = capsys.readouterr().err
    assert code == 0, err
    assert time.perf_counter() - start < 60
    warned = [line for line in err.splitlines() if line.startswith("jaxtissue: warning: ")]
    assert len(warned) == 2 and "period_s = 1e-09 s" in warned[0] and "post_displacement_mm = 24.9 mm" in warned[1]
    summary = json.loads((out / "summary.json").read_text())
    assert len(summary["warnings"]) == 2 and summary["warnings"][0] in warned[0] and "lumping" not in summary


# start_new_session=True makes subprocess fork the child (not posix_spawn), which JAX warns of; the child execs at once
@pytest.mark.filterwarnings("ignore:os.fork\\(\\) was called:RuntimeWarning")
def test_sigint_ends_a_run_at_once_and_a_second_writer_is_refused(tmp_path, capsys):
    """SIGINT reaches a command inside its compiled run: exit 130 within seconds, one
    line, no output folder, no partial or lock file. While it ran, a second command
    for the same folder was refused."""
    out, log = tmp_path / "r", tmp_path / "stderr.txt"
    # 1000 coupling intervals (~10 s once compiled, beyond the supported duration: a warning line): the run is
    # still going when SIGINT arrives however fast the machine
    cmd = [sys.executable, "-m", "jaxtissue.cli", "simulate", "--regime", "flex", "--grid", "50", "40", "--t-end", "2e7",
           "--save", "end", "--progress", "--out", str(out)]
    with open(log, "w") as stderr:  # SIGINT as a terminal delivers it: a test runner's worker may ignore SIGINT,
        # and a child started from it would inherit that (as a shell's background jobs do)
        proc = subprocess.Popen(cmd, stdout=subprocess.DEVNULL, stderr=stderr, start_new_session=True,
                                preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL))
    try:
        wait_for(lambda: (tmp_path / ".r.lock").exists(), proc, 120, "lock")
        assert main(["simulate", "--out", str(out)]) == 2
        assert "another jaxtissue command (pid" in one_line(capsys)
        wait_for(lambda: re.search(r"\| *[1-9]\d*/\d+ \[", log.read_text()), proc, 300, "an interval done")
        sent = time.perf_counter()
        os.killpg(proc.pid, signal.SIGINT)
        assert proc.wait(timeout=30) == 130
        assert time.perf_counter() - sent < 5
    finally:
        if proc.poll() is None:
            os.killpg(proc.pid, signal.SIGKILL)
    last = log.read_text().strip().splitlines()[-1]
    assert last == "jaxtissue: interrupted by SIGINT; no output was written"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["stderr.txt"]


_LATE_WRITER = """
import os, pathlib, signal, sys, threading, time
from jaxtissue import cli, io

writing = threading.Event()

def work(args):  # a command whose next write comes after the signal has been answered
    os.kill(os.getpid(), signal.SIGTERM)
    while not io.ending():
        time.sleep(0.001)
    writing.set()
    io.atomic_write_text(pathlib.Path(sys.argv[1]) / "late.txt", "late")  # refused: the process is ending
    return 0

release = io.release_outputs
def release_then_wait(ending=False):  # the main thread, ending: time for the worker's error line to appear
    release(ending)
    if ending and writing.wait(30):
        time.sleep(0.5)

io.release_outputs = release_then_wait

build = cli.build_parser
def with_work():
    parser = build()
    parser.commands["params"].set_defaults(func=work)
    return parser

cli.build_parser = with_work
sys.exit(cli.main(["params"]))
"""


def test_a_write_refused_while_a_signal_ends_the_process_prints_nothing(tmp_path):
    """The signal line race, made deterministic: the command's worker writes only after
    the main thread has started ending the process on SIGTERM, and the main thread
    gives it half a second before its own line; the write is refused and its error
    ("interrupted") is not printed, so the signal's line is the only one."""
    proc = subprocess.run([sys.executable, "-c", _LATE_WRITER, str(tmp_path)], capture_output=True, text=True, timeout=120)
    assert proc.returncode == 143, proc.stderr
    assert proc.stderr.splitlines() == ["jaxtissue: interrupted by SIGTERM; no output was written"]
    assert list(tmp_path.iterdir()) == []


def test_long_runs_are_the_ones_that_show_progress_by_default():
    """On a terminal, `simulate` shows a bar with the remaining time for runs expected to
    outlast `LONG_RUN_S` after compiling: not the default grids, the refined ones."""
    from jaxtissue.cli import LONG_RUN_S

    assert limits.expected_seconds(1 * 40, 100, "static") < LONG_RUN_S
    assert limits.expected_seconds(50 * 40, 100, "flex") < LONG_RUN_S < limits.expected_seconds(200 * 160, 100, "flex")
    assert limits.expected_seconds(1 * 400_000, 100, "static") > LONG_RUN_S
