"""Batch sweeps (values, devices, resume, files) and local sensitivities."""

import dataclasses
import os
import re
import signal
import subprocess
import sys
import time

import numpy as np
import pytest
import xarray as xr

import jaxtissue as jt
from jaxtissue import sweep as sw
from jaxtissue.cli import main
from jaxtissue.io import InputError

STATIC = """
regime = "static"
t_end_s = 1.8144e6
chunk = 4
[parameters]
k_c_max = { linspace = [1.0e-5, 1.5e-5], n = 3 }
k_m0 = { logspace = [1.0e-7, 3.0e-7], n = 4 }
[model]
ny = 20
"""


def single(sweep, values):
    params, protocol = sweep.model(values)
    r = jt.simulate(params, protocol, sweep.t_end_s, sweep.grid, coupling_interval_s=sweep.coupling_interval_s,
                    beam=sweep.beam, options=jt.SolverOptions(rtol=sweep.rtol, atol=sweep.rtol * 1e-3))
    return {k: float(getattr(r, k)[-1]) for k in ("dna_ug_per_g", "collagen_mg_per_g", "E_eff_kPa")}


@pytest.fixture
def static_file(tmp_path):
    path = tmp_path / "static.toml"
    path.write_text(STATIC)
    return path


def test_grid_sweep_equals_single_runs(static_file, tmp_path):
    sweep = sw.read_sweep(static_file)
    assert sweep.size == 12 and sweep.points[1].tolist() == pytest.approx([1.0e-5, 1.0e-7 * 3 ** (1 / 3)])
    ds = sw.run(sweep, tmp_path / "out")
    assert dict(ds.sizes) == {"k_c_max": 3, "k_m0": 4}
    assert ds["collagen_mg_per_g"].attrs["units"] == "mg/g" and ds.attrs["param_k_a"] == 1e-5
    rng = np.random.default_rng(0)
    for i, j in zip(rng.integers(0, 3, 3), rng.integers(0, 4, 3)):
        values = np.array([ds.k_c_max.values[i], ds.k_m0.values[j]])
        ref = single(sweep, values)
        for k, v in ref.items():
            assert float(ds[k][i, j]) == pytest.approx(v, rel=1e-9), k
    assert xr.load_dataset(tmp_path / "out" / "sweep.nc").equals(ds)


def test_a_second_sweep_loads_its_program(static_file, tmp_path, monkeypatch):
    """Where the command line saves programs, a later sweep of the same model loads its
    chunks' program, named by the model alone (`Sweep.model_only`): here with the
    programs in memory forgotten and tracing and compiling forbidden, for other points,
    it gives the same values as a run of those points in memory."""
    from jaxtissue import cache

    monkeypatch.delenv("JAXTISSUE_NO_SAVED_PROGRAMS", raising=False)
    sweep = sw.read_sweep(static_file)
    moved = dataclasses.replace(sweep, points=sweep.points[::-1].copy())
    expected = sw.run(moved, tmp_path / "in_memory")
    with cache.saved_executables(tmp_path / "programs"):
        sw.run(sweep, tmp_path / "first")
        assert len(list((tmp_path / "programs").glob("*.jtx"))) == 1
        monkeypatch.setattr(cache, "_loaded", {})  # as in a new process
        monkeypatch.setattr(sw, "_BATCHED", {})
        with monkeypatch.context() as m:
            for where, name in ((cache, "_compile"), (sw, "simulate")):
                m.setattr(where, name, lambda *a, name=name, **k: pytest.fail(f"{name} again"))
            again = sw.run(moved, tmp_path / "second")
    for k in ("dna_ug_per_g", "collagen_mg_per_g", "E_eff_kPa"):
        np.testing.assert_array_equal(again[k].values, expected[k].values)


@pytest.mark.slow  # sharding over devices: test_cli_sweep_uses_every_core
def test_four_host_devices_give_the_same_values(static_file, tmp_path):
    """The batch axis sharded over 4 CPU devices (a subprocess: the device count is
    fixed when JAX starts)."""
    code = (
        "import jax, numpy as np, sys; from jaxtissue import sweep as sw; "
        "assert len(jax.devices()) == 4, jax.devices(); "
        f"sw.run(sw.read_sweep({str(static_file)!r}), {str(tmp_path / 'four')!r})"
    )
    env = dict(os.environ, XLA_FLAGS="--xla_force_host_platform_device_count=4")
    proc = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True, timeout=600)
    assert proc.returncode == 0, proc.stderr[-2000:]
    one = sw.run(sw.read_sweep(static_file), tmp_path / "one")
    four = xr.load_dataset(tmp_path / "four" / "sweep.nc")
    for k in ("dna_ug_per_g", "collagen_mg_per_g", "E_eff_kPa"):
        np.testing.assert_allclose(four[k].values, one[k].values, rtol=1e-7)  # round-off differs with the per-device batch; far below the solver tolerance


def test_two_processes_share_a_sweep_with_one_device_per_core(static_file, tmp_path):
    """`jaxtissue sweep --distributed` in two local processes (jax.distributed, CPU
    collectives over gloo), each of which splits its CPU into one device per core before
    JAX starts: the chunks run over all four devices and process 0 writes what one
    process computes."""
    import socket

    with socket.socket() as s:
        s.bind(("localhost", 0))
        port = s.getsockname()[1]
    out = tmp_path / "two"
    code = (
        "import os, sys, jax; from jaxtissue.cli import main; "
        f"code = main(['sweep', {str(static_file)!r}, '--out', {str(out)!r}, '--distributed', 'localhost:{port}', "
        "'--num-processes', '2', '--process-id', sys.argv[1]]); "
        "assert code == 0, code; "
        "assert len(jax.local_devices()) == os.cpu_count() and len(jax.devices()) == 2 * os.cpu_count(), jax.devices()"
    )
    env = {k: v for k, v in os.environ.items() if k != "XLA_FLAGS"}
    procs = [subprocess.Popen([sys.executable, "-c", code, str(i)], env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                              text=True) for i in (0, 1)]
    try:
        outputs = [proc.communicate(timeout=600) for proc in procs]
    finally:
        for proc in procs:
            proc.kill()
    for proc, (stdout, stderr) in zip(procs, outputs):
        assert proc.returncode == 0, stderr[-2000:]
    assert "12 parameter sets, 0 failed" in outputs[0][0] and "parameter sets" not in outputs[1][0]  # process 0 reports and writes
    one = sw.run(sw.read_sweep(static_file), tmp_path / "one")
    assert not sw.use_all_cores()  # JAX has started in this process: a no-op
    two = xr.load_dataset(out / "sweep.nc")
    for k in ("dna_ug_per_g", "collagen_mg_per_g", "E_eff_kPa"):
        np.testing.assert_allclose(two[k].values, one[k].values, rtol=1e-12)
    assert sorted(p.name for p in (out / "chunks").iterdir()) == ["00000000.npz", "00000004.npz", "00000008.npz", "sweep.json"]


def test_even_batches_are_few_equal_and_split_over_every_device(monkeypatch):
    """`sweep.even_batches`: the fewest batches of at most `most` rows, each a multiple of
    the device count, padding as little as that allows."""
    import jax

    from jaxtissue.studies.sweep import even_batches

    assert [even_batches(n, 32) for n in (1, 32, 33, 100)] == [1, 32, 17, 25]
    monkeypatch.setattr(jax, "devices", lambda: [0, 1])
    assert [even_batches(n, 32) for n in (1, 5, 32, 33, 100)] == [2, 6, 32, 18, 26]
    monkeypatch.setattr(jax, "devices", lambda: [0, 1, 2, 3])
    assert even_batches(5, 5) == 8 and even_batches(100, 32) == 28


def test_space_filling_designs(tmp_path):
    path = tmp_path / "lhs.toml"
    path.write_text('regime = "static"\ndesign = "lhs"\nsamples = 8\nseed = 1\n[parameters]\n'
                    'k_a = { range = [0.5e-5, 1.5e-5], transform = "log" }\nk_m0 = { range = [1e-7, 3e-7] }\n')
    sweep = sw.read_sweep(path)
    assert sweep.points.shape == (8, 2) and sweep.axes is None
    strata = np.floor((np.log(sweep.points[:, 0]) - np.log(0.5e-5)) / (np.log(3) / 8)).astype(int)
    assert sorted(strata) == list(range(8))  # one point per stratum
    path.write_text(path.read_text().replace('"lhs"', '"sobol"'))
    sobol = sw.read_sweep(path)
    assert sobol.points.shape == (8, 2) and np.all((sobol.points[:, 1] >= 1e-7) & (sobol.points[:, 1] <= 3e-7))


@pytest.mark.slow  # kills a subprocess; resuming in-process: test_resume_recomputes_only_missing_chunks
def test_interrupted_sweep_resumes_to_the_same_file(static_file, tmp_path):
    """Kill the sweep after its first chunk, resume, compare with an uninterrupted run."""
    static_file.write_text(STATIC.replace("chunk = 4", "chunk = 1").replace("ny = 20", "ny = 160\nrtol = 1e-9"))
    out = tmp_path / "killed"
    proc = subprocess.Popen([sys.executable, "-m", "jaxtissue.cli", "sweep", str(static_file), "--out", str(out)],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE)
    deadline = time.time() + 300
    while time.time() < deadline and len(list((out / "chunks").glob("*.npz"))) < 1:
        time.sleep(0.002)
    proc.send_signal(signal.SIGKILL)
    proc.wait()
    done = len(list((out / "chunks").glob("*.npz")))
    assert 1 <= done < 12 and not (out / "sweep.nc").exists()
    # resumed and fresh runs through the command, as the killed one (the same devices:
    # one per core; round-off may differ between device counts)
    fresh = tmp_path / "fresh"
    for extra in (["--out", str(out), "--resume"], ["--out", str(fresh)]):
        proc = subprocess.run([sys.executable, "-m", "jaxtissue.cli", "sweep", str(static_file), *extra], capture_output=True, text=True, timeout=600)
        assert proc.returncode == 0, proc.stderr[-2000:]
    xr.testing.assert_identical(xr.load_dataset(out / "sweep.nc"), xr.load_dataset(fresh / "sweep.nc"))
    # a chunk file holds the same sets whatever the device count: resuming in this
    # process (one device) recomputes only the missing chunk and reads the others
    (out / "chunks" / "00000003.npz").unlink()
    assert main(["sweep", str(static_file), "--out", str(out), "--resume"]) == 0
    resumed, ref = xr.load_dataset(out / "sweep.nc"), xr.load_dataset(fresh / "sweep.nc")
    np.testing.assert_allclose(resumed["collagen_mg_per_g"].values, ref["collagen_mg_per_g"].values, rtol=1e-7)


def test_resume_recomputes_only_missing_chunks(static_file, tmp_path):
    """A sweep folder missing a chunk (as a killed sweep leaves it) resumes to the same
    file, computing only that chunk."""
    out = tmp_path / "o"
    assert main(["sweep", str(static_file), "--out", str(out)]) == 0
    whole = xr.load_dataset(out / "sweep.nc")
    (out / "chunks" / "00000004.npz").unlink()
    (out / "sweep.nc").unlink()
    stamps = {p.name: p.stat().st_mtime_ns for p in (out / "chunks").glob("*.npz")}
    assert main(["sweep", str(static_file), "--out", str(out), "--resume"]) == 0
    assert {p.name: p.stat().st_mtime_ns for p in (out / "chunks").glob("*.npz") if p.name in stamps} == stamps
    xr.testing.assert_identical(xr.load_dataset(out / "sweep.nc"), whole)


def test_resume_refuses_a_different_sweep_or_a_damaged_folder(static_file, tmp_path, monkeypatch):
    """A different sweep, or a chunk or manifest that is not what a sweep writes: one
    line naming the file, before any chunk is computed."""
    out = tmp_path / "o"
    assert main(["sweep", str(static_file), "--out", str(out)]) == 0
    sweep = sw.read_sweep(static_file)
    chunk, manifest = out / "chunks" / "00000004.npz", out / "chunks" / "sweep.json"
    kept = chunk.read_bytes()
    with monkeypatch.context() as m:
        m.setattr(sw, "run_chunk", lambda *a: pytest.fail("computed before the folder was checked"))
        for damage, message in ((b"junk", "ValueError"), (kept[:200], "BadZipFile|EOFError|OSError|ValueError"), (None, "ValueError: not 4 entries long\\)")):
            if damage is None:
                np.savez(chunk, failed=np.zeros(3))
            else:
                chunk.write_bytes(damage)
            with pytest.raises(InputError, match=rf"^{re.escape(str(chunk))} is damaged \(({message})"):
                sw.run(sweep, out, resume=True)
        chunk.write_bytes(kept)
        stamp = manifest.read_text()
        manifest.write_text("{")
        with pytest.raises(InputError, match=r"sweep.json is damaged \(JSONDecodeError.*remove .*chunks to start the sweep again"):
            sw.run(sweep, out, resume=True)
        manifest.write_text(stamp)
    static_file.write_text(STATIC.replace("n = 3", "n = 2"))
    with pytest.raises(InputError, match="holds a different sweep"):
        sw.run(sw.read_sweep(static_file), out, resume=True)


@pytest.mark.parametrize("text, message", [
    ("regime = \"static\"\n[parameters]\nk_cmax = { values = [1e-5] }\n", "unknown parameter 'k_cmax' in [parameters]; did you mean 'k_c_max'?"),
    ("[parameters]\nperiod_s = { values = [1.0] }\n", "protocol fields are swept only with regime = \"flex\""),
    ("[parameters]\nk_m0 = { logspace = [0.0, 3e-7], n = 3 }\n", "needs positive values"),
    ("[parameters]\no_m = { values = [1.5] }\n", "o_m = 1.5 must be in"),
    ("regime = \"flex\"\n[protocol]\nperiod_s = -1\n[parameters]\nk_m0 = { values = [1e-7] }\n", "bad.toml: [protocol] period_s = -1 must be > 0 s"),
    ("regime = \"flex\"\n[protocol]\nperiod_s = \"1\"\n[parameters]\nk_m0 = { values = [1e-7] }\n", "bad.toml: [protocol] period_s = '1' must be a number"),
    ("regime = \"flex\"\n[protocol]\nperiod_s = [1.0, 2.0]\n[parameters]\nk_m0 = { values = [1e-7] }\n", "bad.toml: [protocol] period_s = [1.0, 2.0] must be a number"),
    ("chunks = 3\n[parameters]\nk_m0 = { values = [1e-7] }\n", "unknown key 'chunks'; did you mean 'chunk'?"),
    ("design = \"lhs\"\n[parameters]\nk_m0 = { range = [1e-7, 3e-7] }\n", "samples = None must be an integer in [1, 10000000]"),
    ("[parameters]\nk_m0 = { values = [1e-7] }\n[model]\nmethod = \"rk4\"\n", "[model] solver option method = 'rk4'; allowed"),
    ("regime = \"flex\"\n[parameters]\nk_m0 = { values = [1e-7] }\n[model]\nmethod = \"rodas4p2\"\n", "this is a flex run on 50 x 40"),
    ("[parameters]\nD_c = { values = [1e-9] }\n[model]\nmethod = \"rodas4p2\"\n", "on 1 x 40 with cell flux"),
])
def test_bad_sweep_files_give_one_line_and_exit_2(tmp_path, capsys, text, message):
    path = tmp_path / "bad.toml"
    path.write_text(text)
    assert main(["sweep", str(path), "--out", str(tmp_path / "o")]) == 2
    err = capsys.readouterr().err
    assert message in err and err.count("\n") == 1


def test_a_sweep_steps_with_the_method_its_model_names(static_file, tmp_path, monkeypatch):
    """`[model] method = "rodas4p2"` reaches every set's `SolverOptions` (the runs
    themselves stopped before they compile; the stepper's own tests: tests/test_solver.py)."""
    path = tmp_path / "r.toml"
    path.write_text(STATIC.replace("ny = 20", 'ny = 8\nmethod = "rodas4p2"'))
    sweep = sw.read_sweep(path)
    assert sweep.method == "rodas4p2" and sw.read_sweep(static_file).method == "ros34pw2"

    def stop(*args, options, **kwargs):
        raise RuntimeError(f"stopped: {options.method}")

    monkeypatch.setattr(sw, "simulate", stop)
    with pytest.raises(RuntimeError, match="stopped: rodas4p2"):
        sweep.run_one(sweep.points[0])


def test_failed_parameter_sets_are_marked_not_fatal(tmp_path):
    """A step budget that one set needs ~85 steps for and the other ~375: the second
    fails, is NaN and flagged, and the first is still computed."""
    path = tmp_path / "f.toml"
    path.write_text('regime = "static"\nt_end_s = 1.8144e6\n[parameters]\nQ_o = { values = [8.393e-4, 8.393e-2] }\n'
                    '[model]\nny = 20\nmax_steps = 150\n')
    out = tmp_path / "o"
    assert main(["sweep", str(path), "--out", str(out)]) == 0
    ds = xr.load_dataset(out / "sweep.nc")
    assert ds["failed"].values.tolist() == [False, True] and ds.attrs["failures"] == 1
    assert np.isfinite(ds["dna_ug_per_g"].values[0]) and np.isnan(ds["dna_ug_per_g"].values[1])
    summary = __import__("json").loads((out / "summary.json").read_text())
    assert summary["failures"] == 1 and summary["failed_points"] == [[8.393e-2]]


# ---- sensitivity


def test_sensitivities_match_finite_differences():
    """Fixed steps: the same discrete map at every parameter value, so differences are
    not polluted by step-size control."""
    p = jt.paper_parameters()
    grid, options = jt.Grid(1, 16), jt.SolverOptions(fixed_steps=300)
    table = jt.sensitivity.sensitivities(p, jt.Protocol.static(), jt.THREE_WEEKS_S, grid=grid, options=options)
    assert "post_force_max_N" not in table  # zero in static culture
    for name in ("k_m0", "k_c_max", "o_m"):
        h = 1e-4

        def collagen(f):
            r = jt.simulate(p.replace(**{name: getattr(p, name) * f}), jt.Protocol.static(), jt.THREE_WEEKS_S, grid, options=options)
            return np.log(float(r.collagen_mg_per_g[-1]))
        fd = (collagen(1 + h) - collagen(1 - h)) / (np.log(1 + h) - np.log(1 - h))
        assert table["collagen_mg_per_g"][name] == pytest.approx(fd, rel=1e-3, abs=1e-6), name
    assert table["EI_N_m2"]["E_s_kPa"] > 0


@pytest.mark.slow  # compiles a gradient; saved programs' loading: tests/test_cache.py
def test_sensitivities_are_a_program_a_second_process_loads(tmp_path, monkeypatch):
    """Where the command line saves programs, a second process loads the sensitivities'
    program (here: the programs in memory forgotten, tracing and compiling forbidden)
    and gets the same table. (Not with `fixed_steps`: diffrax checks their times with a
    host callback.)"""
    from jaxtissue import cache

    monkeypatch.delenv("JAXTISSUE_NO_SAVED_PROGRAMS", raising=False)
    p, grid = jt.paper_parameters(), jt.Grid(1, 8)
    with cache.saved_executables(tmp_path):
        table = jt.sensitivity.sensitivities(p, jt.Protocol.static(), jt.THREE_WEEKS_S, grid=grid)
        monkeypatch.setattr(cache, "_loaded", {})
        with monkeypatch.context() as m:
            for where, name in ((cache, "_compile"), (sys.modules["jaxtissue.studies.sensitivity"], "simulate")):
                m.setattr(where, name, lambda *a, name=name, **k: pytest.fail(f"{name} again"))
            assert jt.sensitivity.sensitivities(p, jt.Protocol.static(), jt.THREE_WEEKS_S, grid=grid) == table


@pytest.mark.slow
def test_sensitivity_command(tmp_path, capsys):
    out = tmp_path / "s"
    assert main(["sensitivity", "--grid", "1", "12", "--nest-intervals", "--out", str(out)]) == 0
    assert (out / "sensitivity.json").exists() and (out / "sensitivity.png").exists()
    assert "k_m0" in capsys.readouterr().out


def test_unknown_top_level_key_lists_the_allowed_ones(tmp_path, capsys):
    path = tmp_path / "s.toml"
    path.write_text('measurements = "x.csv"\n')
    assert main(["sweep", str(path), "--out", str(tmp_path / "o")]) == 2
    assert "unknown key 'measurements'; allowed: chunk, design, fixed" in capsys.readouterr().err
