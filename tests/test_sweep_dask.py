"""Sweeps on Dask (`jaxtissue sweep --dask`): the shipped sweep file gives the serial
run's `sweep.nc` to 1e-12 although a worker process is killed mid-sweep; a killed
client's sweep completes with `--resume`; the SLURM cluster of the docs is built."""

import os
import pathlib
import signal
import subprocess
import sys
import time

import numpy as np
import psutil
import pytest
import xarray as xr

from helpers import wait_for

from jaxtissue import sweep as sw
from jaxtissue.cli import main

ROOT = pathlib.Path(__file__).resolve().parents[1]
SHIPPED = ROOT / "sweeps" / "kinetics.toml"
OUTPUTS = ("dna_ug_per_g", "collagen_mg_per_g", "E_eff_kPa", "EI_N_m2")


@pytest.fixture(scope="module")
def serial(tmp_path_factory):
    return sw.run(sw.read_sweep(SHIPPED), tmp_path_factory.mktemp("serial") / "s")


def assert_same(path, serial):
    ds = xr.load_dataset(path)
    for k in OUTPUTS:
        np.testing.assert_allclose(ds[k].values, serial[k].values, rtol=1e-12)
    np.testing.assert_array_equal(ds["failed"].values, serial["failed"].values)


def start(out, *extra):
    cmd = [sys.executable, "-m", "jaxtissue.cli", "sweep", str(SHIPPED), "--out", str(out), "--dask", "local:2", "--no-progress", *extra]
    return subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, start_new_session=True)


def workers(proc):
    """The Dask worker processes of a `--dask local:N` command."""
    return [p for p in psutil.Process(proc.pid).children(recursive=True) if "spawn_main" in " ".join(p.cmdline())]


def chunks_done(out) -> int:
    try:
        return int(xr.open_zarr(out / "sweep.zarr", consolidated=False)["chunk_done"].values.sum())
    except Exception:  # the store is being created
        return 0


def test_a_workers_chunk_program_is_kept_in_the_clients_folder(tmp_path, monkeypatch, serial):
    """`sweep_dask.run_chunk_saving`, each chunk's task: given the client's folder of
    saved programs (`cache.saved_folder`) it saves its program there, and a later worker
    (here: the programs in memory forgotten, tracing and compiling forbidden) loads it
    and gives the serial run's values."""
    from jaxtissue import cache
    from jaxtissue.studies import sweep_dask

    monkeypatch.delenv("JAXTISSUE_NO_SAVED_PROGRAMS", raising=False)
    sweep, folder = sw.read_sweep(SHIPPED), tmp_path / "programs"
    with cache.saved_executables(folder):
        assert cache.saved_folder() == folder
    sweep_dask.run_chunk_saving(sweep, 0, folder)
    assert len(list(folder.glob("*.jtx"))) == 1 and cache.saved_folder() is None
    monkeypatch.setattr(cache, "_loaded", {})  # as in a new worker
    monkeypatch.setattr(sw, "_BATCHED", {})
    with monkeypatch.context() as m:
        for where, name in ((cache, "_compile"), (sw, "simulate")):
            m.setattr(where, name, lambda *a, name=name, **k: pytest.fail(f"{name} again"))
        again = sweep_dask.run_chunk_saving(sweep, 2, folder)
    for k in OUTPUTS:
        np.testing.assert_allclose(again[k], serial[k].values.ravel()[2:4], rtol=1e-12)


def test_a_lost_worker_changes_nothing(tmp_path, serial, capsys):
    """A worker process killed while it works on its first chunk: Dask re-runs its tasks
    and `sweep.nc` equals the serial run's to 1e-12. (Then the store damaged: `--resume`
    names it in one line before it starts a cluster.)"""
    out = tmp_path / "d"
    proc = start(out)
    try:
        # the store appears once the cluster is up, just before the tasks are submitted;
        # the victim is killed once it works on them (importing jaxtissue, compiling)
        wait_for(lambda: (out / "sweep.zarr").exists(), proc, 120, "a running cluster")
        victim = workers(proc)[0]
        busy = victim.cpu_times().user + 0.3
        wait_for(lambda: victim.cpu_times().user > busy, proc, 60, "a busy worker")
        victim.kill()
        stdout, stderr = proc.communicate(timeout=300)
    finally:
        if proc.poll() is None:
            os.killpg(proc.pid, signal.SIGKILL)
    assert proc.returncode == 0, stderr[-2000:]
    assert "16 parameter sets, 0 failed" in stdout
    assert "leaked" not in stderr  # the local cluster shut down with its client, not left to the process's end
    assert not victim.is_running()
    assert_same(out / "sweep.nc", serial)
    (out / "sweep.zarr" / "zarr.json").write_text("junk")
    assert main(["sweep", str(SHIPPED), "--out", str(out), "--dask", "local:2", "--resume", "--no-progress"]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "sweep.zarr is damaged (JSONDecodeError" in err and "remove it to start the sweep again" in err, err


@pytest.mark.slow  # the default run: test_a_lost_worker_changes_nothing, tests/test_sweep.py::test_interrupted_sweep_resumes_to_the_same_file
def test_a_killed_client_resumes(tmp_path, serial):
    """The client killed once a chunk is in the Zarr store: `--resume` runs the rest and
    writes the serial run's `sweep.nc`. (Chunks the killed client may still have
    finished are unmarked again, so that the resumed run always has chunks to run.)"""
    import xarray as xr

    out = tmp_path / "d"
    proc = start(out)
    try:
        deadline = time.time() + 300
        while chunks_done(out) < 1 and proc.poll() is None and time.time() < deadline:
            time.sleep(0.05)
        os.killpg(proc.pid, signal.SIGKILL)
        proc.wait(timeout=30)
    finally:
        if proc.poll() is None:
            os.killpg(proc.pid, signal.SIGKILL)
    assert chunks_done(out) >= 1
    (out / "sweep.nc").unlink(missing_ok=True)
    undone = xr.Dataset({"chunk_done": ("chunk", np.zeros(4, bool))})
    undone.to_zarr(out / "sweep.zarr", region={"chunk": slice(4, 8)}, consolidated=False)
    assert chunks_done(out) <= 4
    assert main(["sweep", str(SHIPPED), "--out", str(out), "--dask", "local:2", "--resume", "--no-progress"]) == 0
    assert_same(out / "sweep.nc", serial)
    assert chunks_done(out) == 8


def test_dask_mistakes_are_one_line_errors(tmp_path, capsys):
    import dask

    for cluster, words in (("local:0", "local:N needs 1 <= N <= 256"), ("nonsense", "expected local:N or a scheduler address"),
                           ("tcp://localhost:1", "no scheduler there")):
        with dask.config.set({"distributed.comm.timeouts.connect": "1s"}):
            assert main(["sweep", str(SHIPPED), "--out", str(tmp_path / "o"), "--dask", cluster]) == 2
        err = capsys.readouterr().err
        assert err.count("\n") == 1 and words in err, err
        assert not (tmp_path / "o").exists()
    assert main(["sweep", str(SHIPPED), "--out", str(tmp_path / "o"), "--dask", "local:2", "--resume"]) == 2
    assert "no interrupted --dask sweep there (sweep.zarr missing)" in capsys.readouterr().err


def test_a_cluster_that_does_not_start_is_one_line(tmp_path, capsys, monkeypatch):
    import dask.distributed

    def broken(**kwargs):
        raise RuntimeError("Nanny failed to start.")

    monkeypatch.setattr(dask.distributed, "LocalCluster", broken)
    assert main(["sweep", str(SHIPPED), "--out", str(tmp_path / "o"), "--dask", "local:2"]) == 1
    err = capsys.readouterr().err
    assert err == "jaxtissue: error: the Dask cluster local:2 did not start (Nanny failed to start.). Nothing was written.\n"
    assert not (tmp_path / "o").exists()


def test_the_documented_slurm_cluster_is_built():
    """docs/numerics.md's dask-jobqueue example: the cluster object and its job script
    (no scheduler is needed to build them)."""
    text = (ROOT / "docs" / "numerics.md").read_text()
    example = text.split("### On Dask", 1)[1].split("```python\n", 1)[1].split("```", 1)[0]
    assert "cluster.scale(jobs=4)" in example and "sweep_dask.run(" in example
    lines = [line for line in example.splitlines() if not line.startswith(("cluster.scale", "sweep_dask.run"))]
    namespace = {}
    exec(compile("\n".join(lines), "docs/numerics.md", "exec"), namespace)
    cluster = namespace["cluster"]
    try:
        script = cluster.job_script()
        assert "#SBATCH -A my_account" in script and "--cpus-per-task=8" in script and "--nworkers 8" in script
        assert namespace["address"] == cluster.scheduler_address and cluster.scheduler_address.startswith("tcp://")
    finally:
        cluster.close()
