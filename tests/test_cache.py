"""The persistent compilation cache of the command line (`jaxtissue.cache`): a second
run loads its programs; an unusable folder or a corrupt entry costs a warning only."""

import os
import subprocess
import sys

import jax
import pytest
import xarray as xr

import jaxtissue as jt
from jaxtissue.cache import default_folder, enable_compilation_cache

RUN = ["simulate", "--regime", "flex", "--t-end", "4e4", "--grid", "4", "8", "--period", "2"]


def run_cli(args, cache_home):
    env = {k: v for k, v in os.environ.items() if not k.startswith("JAX_COMPILATION_CACHE") and k != "JAXTISSUE_NO_CACHE"}
    env["XDG_CACHE_HOME"] = str(cache_home)
    proc = subprocess.run([sys.executable, "-m", "jaxtissue.cli", *args], capture_output=True, text=True, timeout=600, env=env, check=False)
    return proc.returncode, proc.stdout, proc.stderr


def test_default_folder_follows_xdg_and_can_be_turned_off(monkeypatch, tmp_path):
    monkeypatch.delenv("JAXTISSUE_NO_CACHE", raising=False)
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path))
    assert default_folder() == tmp_path / "jaxtissue"
    monkeypatch.delenv("XDG_CACHE_HOME")
    monkeypatch.setenv("HOME", str(tmp_path / "home"))
    assert default_folder() == tmp_path / "home" / ".cache" / "jaxtissue"
    monkeypatch.setenv("JAXTISSUE_NO_CACHE", "1")
    assert default_folder() is None
    monkeypatch.setenv("JAXTISSUE_NO_CACHE", "0")
    assert default_folder() is not None


def test_an_unusable_folder_is_a_warning(tmp_path):
    blocker = tmp_path / "a-file"
    blocker.write_text("not a folder")
    with pytest.warns(RuntimeWarning, match="not usable"):
        assert enable_compilation_cache(blocker / "jaxtissue") is None


@pytest.mark.parametrize("regime", ["flex", "static"])
def test_runs_have_no_host_callbacks(regime):
    """What keeps a program out of the cache: a flex run, and a static run saved at its
    end (a sweep's), have none (the static series' saved times are checked by diffrax
    with one)."""
    protocol = jt.Protocol.flex(period_s=2.0) if regime == "flex" else jt.Protocol.static()
    grid = jt.Grid(2, 4) if regime == "flex" else jt.Grid(1, 8)
    run = jax.jit(lambda p: jt.simulate(p, protocol, t_end_s=4e4, grid=grid, beam=jt.BeamGrid(8, 16), save="end").collagen_mg_per_g)
    text = run.lower(jt.paper_parameters()).as_text()
    assert "callback" not in text


@pytest.mark.slow
def test_second_run_loads_its_programs_and_survives_a_corrupt_cache(tmp_path):
    blocker = tmp_path / "a-file"
    blocker.write_text("not a folder")
    code, _, stderr = run_cli(["params"], blocker)  # the cache cannot be made: a warning
    assert code == 0 and "jaxtissue: warning: compilation cache folder" in stderr and "Traceback" not in stderr

    home = tmp_path / "cache"
    code, _, stderr = run_cli([*RUN, "--out", str(tmp_path / "first")], home)
    assert code == 0, stderr
    entries = [p for p in (home / "jaxtissue").iterdir() if p.is_file() and not p.name.startswith(".")]
    assert any("simulate" in p.name for p in entries), [p.name for p in entries]  # the run's program is kept

    for p in entries:  # every entry corrupt: the next run recompiles, with a warning at most
        p.write_bytes(b"\0garbage")
    code, _, stderr = run_cli([*RUN, "--out", str(tmp_path / "second")], home)
    assert code == 0, stderr
    first = xr.open_dataset(tmp_path / "first" / "result.nc", engine="h5netcdf")
    second = xr.open_dataset(tmp_path / "second" / "result.nc", engine="h5netcdf")
    assert float(second["collagen_mg_per_g"][-1]) == float(first["collagen_mg_per_g"][-1])


def test_fast_compilation_is_set_before_jax_starts_and_never_over_the_users_flags(monkeypatch):
    """`use_fast_compilation`: in a fresh process it adds its flag, which XLA then accepts
    (a flag XLA did not know would abort the process); the user's own value of the flag,
    `JAXTISSUE_XLA_DEFAULTS=1`, or a backend already started leave `XLA_FLAGS` alone."""
    from jaxtissue.cache import FAST_COMPILATION_FLAG, use_fast_compilation

    code = ("import os; from jaxtissue.cache import use_fast_compilation as u; made = u(); import jax.numpy as jnp; "
            "print(made, float(jnp.sum(jnp.arange(4.0))), os.environ.get('XLA_FLAGS', ''))")
    env = {k: v for k, v in os.environ.items() if k not in ("XLA_FLAGS", "JAXTISSUE_XLA_DEFAULTS")}
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120, env=env, check=True).stdout
    assert out.split() == ["True", "6.0", FAST_COMPILATION_FLAG]
    env["XLA_FLAGS"] = "--xla_cpu_use_fusion_emitters=true --xla_force_host_platform_device_count=2"
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120, env=env, check=True).stdout
    assert out.split() == ["False", "6.0", "--xla_cpu_use_fusion_emitters=true", "--xla_force_host_platform_device_count=2"]
    monkeypatch.setenv("JAXTISSUE_XLA_DEFAULTS", "1")
    monkeypatch.setenv("XLA_FLAGS", "")
    assert use_fast_compilation() is False and os.environ["XLA_FLAGS"] == ""
    monkeypatch.delenv("JAXTISSUE_XLA_DEFAULTS")
    jax.numpy.zeros(1)  # this process's backend has started
    assert use_fast_compilation() is False and os.environ["XLA_FLAGS"] == ""
