"""Checkpointed runs: a killed `jaxtissue simulate --checkpoint-every N` continues with
`--resume DIR` and gives the same result to the last bit."""

import os
import pathlib
import re
import signal
import subprocess
import sys
import time

import jax
import numpy as np
import pytest
import xarray as xr

import jaxtissue as jt
from jaxtissue.studies.checkpoint import segment_edges, simulate_checkpointed
from jaxtissue.cli import main
from jaxtissue.io import InputError
from jaxtissue.protocol import save_times

JAXPR_TRACE_EVENT = "/jax/core/compile/jaxpr_trace_duration"  # JAX's monitoring event of a new trace

# 80 segments of ~15-20 ms each once compiled: even on a loaded machine the killed run
# cannot write its last segment (a second or more of work) before the signal lands
RUN = ["simulate", "--t-end", "1.6e6", "--grid", "1", "8", "--checkpoint-every", "1", "--no-progress"]


def test_segment_edges():
    np.testing.assert_array_equal(segment_edges(1.0e5, 2.0e4, 2), [0, 4e4, 8e4, 1e5])
    np.testing.assert_array_equal(segment_edges(3.0e4, 2.0e4, 5), [0, 3e4])


def test_segments_agree_with_one_run_to_solver_tolerance(tmp_path):
    p, grid = jt.paper_parameters(), jt.Grid(1, 8)
    whole = jt.simulate(p, t_end_s=1.2e5, grid=grid)
    parts = simulate_checkpointed(p, jt.Protocol.static(), 1.2e5, grid, tmp_path / "k", 2)
    assert parts.ts == whole.ts and len(list((tmp_path / "k").glob("segment_*.npz"))) == 3
    np.testing.assert_allclose(parts.collagen_mg_per_g, whole.collagen_mg_per_g, rtol=1e-5, atol=1e-9)
    np.testing.assert_allclose(parts.final.o, whole.final.o, rtol=1e-4)


def test_a_damaged_segment_is_named_and_computed_again_once_removed(tmp_path):
    p, grid, folder = jt.paper_parameters(), jt.Grid(1, 8), tmp_path / "k"
    first = simulate_checkpointed(p, jt.Protocol.static(), 6e4, grid, folder, 1)
    segment = folder / "segment_0001.npz"
    for damage in (b"junk", segment.read_bytes()[:100]):  # not a zip file; cut short
        segment.write_bytes(damage)
        with pytest.raises(InputError, match=rf"^{re.escape(str(segment))} is damaged \(.*\); remove it to compute that segment again$"):
            simulate_checkpointed(p, jt.Protocol.static(), 6e4, grid, folder, 1)
    segment.unlink()
    again = simulate_checkpointed(p, jt.Protocol.static(), 6e4, grid, folder, 1)
    np.testing.assert_array_equal(again.collagen_mg_per_g, first.collagen_mg_per_g)


def test_segments_of_a_time_invariant_protocol_share_one_program(tmp_path):
    """Six segments, traced twice: the first (from the seeded state) and one program
    for the five after it, solved from t = 0 and moved to their times."""
    traced = []

    def listen(event, duration, **kwargs):
        if event == JAXPR_TRACE_EVENT and kwargs.get("fun_name") == "_simulate":
            traced.append(duration)

    jax.monitoring.register_event_duration_secs_listener(listen)
    try:
        r = simulate_checkpointed(jt.paper_parameters(), jt.Protocol.static(), 1.2e5, jt.Grid(1, 7), tmp_path / "k", 1)
    finally:
        jax.monitoring.unregister_event_duration_listener(listen)
    assert len(list((tmp_path / "k").glob("segment_*.npz"))) == 6 and len(traced) <= 2
    assert r.ts == tuple(save_times(1.2e5, jt.COUPLING_INTERVAL_S).tolist())


def test_a_write_the_disk_refuses_keeps_the_checkpoint(tmp_path, capsys, monkeypatch):
    """A checkpointed run whose output the disk refuses (no space left in the output's
    folder) is one line naming the kept checkpoint; `--resume` then writes the result."""
    import errno
    import tempfile

    out = tmp_path / "run"
    mkstemp = tempfile.mkstemp

    def full_where_the_output_goes(*args, **kwargs):
        if ".run.partial-" in str(kwargs.get("dir", "")):
            raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC), str(kwargs["dir"]))
        return mkstemp(*args, **kwargs)

    run = ["simulate", "--t-end", "4e4", "--grid", "1", "8", "--checkpoint-every", "1", "--no-progress"]
    with monkeypatch.context() as m:
        m.setattr(tempfile, "mkstemp", full_where_the_output_goes)
        assert main([*run, "--out", f"{out}/"]) == 1  # DIR/ is DIR: its checkpoint DIR.checkpoint beside it
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("jaxtissue: error: No space left on device (") and err[0].endswith(
        f"; no output was written; the checkpoint {out}.checkpoint is kept: continue with `jaxtissue simulate --resume {out}`"), err
    assert not out.exists()
    assert main(["simulate", "--resume", f"{out}/"]) == 0  # (to the same bits: the killed run's test below)
    with xr.open_dataset(out / "result.nc") as done:
        assert done["time_s"].values[-1] == 4e4
    assert not pathlib.Path(f"{out}.checkpoint").exists()


def test_killed_run_resumes_to_the_same_bits(tmp_path):
    ref = tmp_path / "ref"
    assert main(RUN + ["--out", str(ref)]) == 0
    assert not pathlib.Path(f"{ref}.checkpoint").exists()  # removed once the results are written

    out = tmp_path / "run"
    kept = pathlib.Path(f"{out}.checkpoint")
    cmd = [sys.executable, "-m", "jaxtissue.cli", *RUN, "--out", str(out)]
    proc = subprocess.Popen(cmd, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True, start_new_session=True)
    deadline = time.time() + 300
    while not (kept / "segment_0001.npz").exists():
        assert proc.poll() is None and time.time() < deadline, "the run ended before it could be stopped"
        time.sleep(0.005)
    os.killpg(proc.pid, signal.SIGTERM)  # as a batch scheduler ends a job: exit 143, the checkpoint kept
    assert proc.wait(timeout=30) == 143
    assert proc.stderr.read().strip().splitlines()[-1] == (
        f"jaxtissue: interrupted by SIGTERM; no output was written; the checkpoint {out}.checkpoint is kept: "
        f"continue with `jaxtissue simulate --resume {out}`")
    assert not out.exists() and sorted(p.name for p in tmp_path.iterdir()) == ["ref", "run.checkpoint"]
    done = sorted(p.name for p in kept.glob("segment_*.npz"))
    assert 2 <= len(done) < 80 and not list(kept.glob(".*"))  # no partial segment file

    assert main(["simulate", "--out", str(out)]) == 2  # a fresh run does not clobber the kept one
    assert main(["simulate", "--resume", str(out), "--no-progress"]) == 0
    assert not kept.exists()
    a, b = xr.open_dataset(ref / "result.nc", engine="h5netcdf"), xr.open_dataset(out / "result.nc", engine="h5netcdf")
    for name in a.data_vars:
        np.testing.assert_array_equal(a[name].values, b[name].values)
    assert a.attrs == b.attrs


def test_resume_without_a_kept_run_is_an_error(tmp_path, capsys):
    assert main(["simulate", "--resume", str(tmp_path / "nothing")]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "no interrupted run there" in err
    (tmp_path / "run.checkpoint").mkdir()
    for damaged in ("nonsense", "[1]", '{"regime": "static"}'):
        (tmp_path / "run.checkpoint" / "run.json").write_text(damaged)
        assert main(["simulate", "--resume", str(tmp_path / "run")]) == 2
        err = capsys.readouterr().err
        assert err.count("\n") == 1 and "run.json is damaged" in err and "remove" in err, err
