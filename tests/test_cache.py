"""The persistent compilation cache of the command line (`jaxtissue.cache`): a second
run loads its programs (JAX's compiled programs, and jaxtissue's saved executables that
skip tracing too); an unusable folder or a corrupt entry costs a warning only."""

import dataclasses
import os
import subprocess
import sys

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest
import xarray as xr

import jaxtissue as jt
from jaxtissue import cache
from jaxtissue.cache import default_folder, enable_compilation_cache, saved_executables

RUN = ["simulate", "--regime", "flex", "--t-end", "4e4", "--grid", "4", "8", "--period", "2"]


def run_cli(args, cache_home):
    env = {k: v for k, v in os.environ.items()
           if not k.startswith("JAX_COMPILATION_CACHE") and k not in ("JAXTISSUE_NO_CACHE", "JAXTISSUE_NO_SAVED_PROGRAMS")}
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
    monkeypatch.setenv("XDG_CACHE_HOME", "relative/cache")  # invalid (XDG): not a folder in the working one
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


@pytest.mark.parametrize("regime, save, series", [("flex", "end", "dense"), ("static", "end", "dense"),
                                                   ("static", "intervals", "intervals"), ("static", "intervals", "dense")])
def test_runs_have_no_host_callbacks(regime, save, series):
    """What keeps a program out of the cache: a flex run, a static run saved at its end
    (a sweep's) and a static series solved interval by interval (the command line's)
    have none; diffrax checks a dense static series' save times with one."""
    protocol = jt.Protocol.flex(period_s=2.0) if regime == "flex" else jt.Protocol.static()
    grid = jt.Grid(2, 4) if regime == "flex" else jt.Grid(1, 8)
    options = jt.SolverOptions(static_series=series)
    run = jax.jit(lambda p: jt.simulate(p, protocol, t_end_s=4e4, grid=grid, beam=jt.BeamGrid(8, 16), save=save, options=options).collagen_mg_per_g)
    text = run.lower(jt.paper_parameters()).as_text()
    assert ("callback" in text) == (regime == "static" and save == "intervals" and series == "dense")


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

    saved = list((home / "jaxtissue" / "executables").glob("*.jtx"))
    assert len(saved) == 1  # and the executable, which a second run loads without tracing

    code, _, stderr = run_cli([*RUN, "--out", str(tmp_path / "second")], home)
    assert code == 0 and "warning" not in stderr, stderr
    for p in entries + saved:  # every entry corrupt: the next run recompiles, with a warning at most
        p.write_bytes(b"\0garbage")
    code, _, stderr = run_cli([*RUN, "--out", str(tmp_path / "third")], home)
    assert code == 0 and "Traceback" not in stderr, stderr
    first = xr.open_dataset(tmp_path / "first" / "result.nc", engine="h5netcdf")
    for run in ("second", "third"):
        again = xr.open_dataset(tmp_path / run / "result.nc", engine="h5netcdf")
        assert float(again["collagen_mg_per_g"][-1]) == float(first["collagen_mg_per_g"][-1])


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


@eqx.filter_jit
def _affine(x, scale, label):
    """A cheap program with static arguments and static outputs."""
    return {"y": x * scale + 1.0, "label": label, "n": x.shape[0]}


@eqx.filter_jit
def _noisy(x):
    jax.debug.callback(lambda v: None, x)
    return x + 1.0


def _saved(folder):
    return sorted(folder.glob("*.jtx"))


class _Holder:
    """A static argument holding an array: its repr cannot name every value."""

    def __init__(self, values):
        self.values = values

    def __repr__(self):
        return f"_Holder({self.values!r})"


def test_saved_executables_are_loaded_and_give_what_the_program_gives(tmp_path, monkeypatch):
    """`cache.call`: the first call compiles and saves; a later process (here: the
    in-memory programs forgotten, compiling forbidden) loads the file; other static
    values or shapes are other programs; traced arguments, host callbacks and static
    arguments known only by their address or holding arrays are not saved."""
    monkeypatch.delenv("JAXTISSUE_NO_SAVED_PROGRAMS", raising=False)  # the suite's setting (tests/conftest.py)
    x = jnp.arange(3.0)
    plain = _affine(x, 2.0, "a")
    with saved_executables(tmp_path):
        first = cache.call(_affine, x, 2.0, "a")
        assert len(_saved(tmp_path)) == 1
        monkeypatch.setattr(cache, "_loaded", {})
        with monkeypatch.context() as m:
            m.setattr(cache, "_compile", lambda *a: pytest.fail("compiled again"))
            loaded = cache.call(_affine, x, 2.0, "a")
        for out in (first, loaded):
            np.testing.assert_array_equal(out["y"], plain["y"])
            assert out["label"] == "a" and out["n"] == 3
        np.testing.assert_array_equal(cache.call(_affine, x, 3.0, "a")["y"], x * 3.0 + 1.0)  # another static value
        cache.call(_affine, jnp.arange(4.0), 2.0, "a")  # another shape
        assert len(_saved(tmp_path)) == 3
        np.testing.assert_array_equal(jax.jit(lambda v: cache.call(_affine, v, 2.0, "a")["y"])(x), plain["y"])  # traced: plain
        np.testing.assert_array_equal(cache.call(_noisy, x), x + 1.0)  # its callback lives in this process only
        assert callable(cache.call(_affine, x, 2.0, lambda: None)["label"])  # described by its address: never found again
        for held in (np.arange(2000.0), np.asarray([0.1234567891]), jt.paper_parameters().replace(k_m0=jnp.asarray(1e-7))):
            cache.call(_affine, x, 2.0, _Holder(held))  # its repr elides, rounds or hides the values
        assert len(_saved(tmp_path)) == 3
    with saved_executables(tmp_path):  # `prepared`: the program loaded now, run later
        monkeypatch.setattr(cache, "_loaded", {})
        with monkeypatch.context() as m:
            m.setattr(cache, "_compile", lambda *a: pytest.fail("compiled again"))
            run = cache.prepared(_affine, x, 2.0, "a")
        np.testing.assert_array_equal(run(x + 1.0, 2.0, "a")["y"], (x + 1.0) * 2.0 + 1.0)
    run = cache.prepared(_affine, x, 9.0, "a")  # off: compiled now, by equinox
    np.testing.assert_array_equal(run(x, 9.0, "a")["y"], x * 9.0 + 1.0)
    assert len(_saved(tmp_path)) == 3
    monkeypatch.setattr(cache, "MAX_EXECUTABLES", 3)
    with saved_executables(tmp_path):  # the least recently used go first
        cache.call(_affine, x, 2.0, "a")  # loaded from memory: its file keeps its age
        cache.call(_affine, x, 4.0, "a")
        assert len(_saved(tmp_path)) == 3
        monkeypatch.setattr(cache, "_loaded", {})
        with monkeypatch.context() as m:
            m.setattr(cache, "_compile", lambda *a: pytest.fail("the newest file was removed"))
            np.testing.assert_array_equal(cache.call(_affine, x, 4.0, "a")["y"], x * 4.0 + 1.0)
    monkeypatch.setenv("JAXTISSUE_NO_SAVED_PROGRAMS", "1")
    with saved_executables(tmp_path):  # turned off
        cache.call(_affine, x, 8.0, "a")
        assert len(_saved(tmp_path)) == 3
    cache.call(_affine, x, 7.0, "a")  # off again after the block
    assert len(_saved(tmp_path)) == 3


@dataclasses.dataclass(frozen=True, eq=False)  # hashed by identity, as `calibration.Problem`
class _Setting:
    """A static argument whose repr leaves out the values that change the program."""

    name: str
    factor: float = dataclasses.field(repr=False)
    offsets: tuple = dataclasses.field(default=(), repr=False)


@eqx.filter_jit
def _scaled(x, setting):
    return x * setting.factor + sum(setting.offsets, 0.0)


def test_static_values_their_repr_hides_name_other_programs(tmp_path, monkeypatch):
    """A static dataclass is named by every field, not by its repr: values the repr
    leaves out (here a factor, and an array with values NumPy's repr would round) are
    other programs, never one loaded for other values; a dict, a set or a tuple is named
    by its items (and their types)."""
    monkeypatch.delenv("JAXTISSUE_NO_SAVED_PROGRAMS", raising=False)
    x = jnp.arange(3.0)
    close = (np.asarray([0.1234567891]), np.asarray([0.1234567892]))
    settings = [_Setting("s", 2.0), _Setting("s", 3.0), _Setting("s", 2.0, (close[0],)), _Setting("s", 2.0, (close[1],))]
    assert len({repr(s) for s in settings}) == 1
    with saved_executables(tmp_path):
        for setting in settings:
            np.testing.assert_array_equal(cache.call(_scaled, x, setting), _scaled(x, setting))
        assert len(_saved(tmp_path)) == 4
        monkeypatch.setattr(cache, "_loaded", {})
        for setting in settings:  # loaded, each its own
            np.testing.assert_array_equal(cache.call(_scaled, x, setting), _scaled(x, setting))
        assert len(_saved(tmp_path)) == 4
    with saved_executables(tmp_path / "items"):
        labels = ({"a": 1.0, "b": (2, "c")}, {"b": (2, "c"), "a": 1.0}, {"a": 1.0, "b": (2, "d")},  # two programs
                  (1, 1.0, True), (1.0, 1, True), (1, 1, 1), frozenset({0.1, 0.2}), frozenset({0.2, 0.1}))  # four
        for label in labels:
            assert cache.call(_affine, x, 2.0, label)["label"] == label
        assert len(_saved(tmp_path / "items")) == 6


def test_threads_keep_their_own_folder_of_saved_programs(tmp_path, monkeypatch):
    """Tasks in threads of one process (a Dask worker's) each in their own
    `saved_executables` block, the blocks interleaved: each thread's programs go to its
    folder, and one thread's block ending does not turn off another's."""
    import threading

    monkeypatch.delenv("JAXTISSUE_NO_SAVED_PROGRAMS", raising=False)
    x, entered, ended = jnp.arange(3.0), threading.Barrier(2), threading.Barrier(2)
    seen = {}

    def task(name, scale, leaves_first):
        with saved_executables(tmp_path / name):
            entered.wait()
            if leaves_first:
                seen[name] = cache.saved_folder()
        if leaves_first:
            ended.wait()
        else:
            with saved_executables(tmp_path / name):
                ended.wait()  # the other thread's block has ended
                seen[name] = cache.saved_folder()
                cache.call(_affine, x, scale, name)

    threads = [threading.Thread(target=task, args=("a", 5.0, True)), threading.Thread(target=task, args=("b", 6.0, False))]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    assert seen == {"a": tmp_path / "a", "b": tmp_path / "b"}
    assert len(_saved(tmp_path / "b")) == 1 and cache.saved_folder() is None


def test_a_corrupt_or_unwritable_saved_executable_costs_a_warning(tmp_path, monkeypatch):
    monkeypatch.delenv("JAXTISSUE_NO_SAVED_PROGRAMS", raising=False)
    x = jnp.arange(3.0)
    with saved_executables(tmp_path):
        cache.call(_affine, x, 5.0, "b")
    (path,) = _saved(tmp_path)
    path.write_bytes(b"\0garbage")
    monkeypatch.setattr(cache, "_loaded", {})
    with saved_executables(tmp_path), pytest.warns(RuntimeWarning, match="unreadable"):
        np.testing.assert_array_equal(cache.call(_affine, x, 5.0, "b")["y"], x * 5.0 + 1.0)
    blocker = tmp_path / "a-file"
    blocker.write_text("not a folder")
    with saved_executables(blocker / "executables"), pytest.warns(RuntimeWarning, match="could not save"):
        np.testing.assert_array_equal(cache.call(_affine, x, 6.0, "b")["y"], x * 6.0 + 1.0)


_OVER_TWO_DEVICES = """
import sys
import jax, jax.numpy as jnp, numpy as np
from jaxtissue import cache
from jaxtissue.studies.sweep import vmap_over_devices
import equinox as eqx

@eqx.filter_jit
def split(x, n):
    return vmap_over_devices(lambda v: jnp.sin(v) * 2.0, n)(x)

@eqx.filter_jit
def single(x):
    return jnp.cos(x)

@eqx.filter_jit
def least_squares(a, b):  # a LAPACK call (gesdd), whose kernels JAX readies only when it lowers one
    return jnp.linalg.lstsq(a, b)[0]

x = np.arange(8.0)
a_ls = np.vander(np.linspace(0.0, 1.0, 8), 3)
with cache.saved_executables(sys.argv[1]):
    a, b, c = cache.call(split, x, 8), cache.call(single, x), cache.call(least_squares, a_ls, x)
np.testing.assert_allclose(np.asarray(a), np.sin(x) * 2.0, rtol=1e-15)
np.testing.assert_allclose(np.asarray(b), np.cos(x), rtol=1e-15)
np.testing.assert_allclose(np.asarray(c), np.linalg.lstsq(a_ls, x, rcond=None)[0], rtol=1e-12, atol=1e-12)
print(len(jax.devices()), len(list(__import__("pathlib").Path(sys.argv[1]).glob("*.jtx"))))
"""


def test_saved_programs_over_two_devices_load_in_a_new_process(tmp_path):
    """A program split over the devices, one on a single device and one calling LAPACK,
    saved by one process with two CPU devices; their files lost, saved again by a
    process that finds them in JAX's cache (compiled afresh: JAX's copy serialises
    without its kernels); loaded by the next (LAPACK readied first: its first call
    would crash the process)."""
    env = {k: v for k, v in os.environ.items() if k not in ("XLA_FLAGS", "JAXTISSUE_NO_SAVED_PROGRAMS") and not k.startswith("JAX_")}
    env |= {"XLA_FLAGS": "--xla_force_host_platform_device_count=2", "JAX_COMPILATION_CACHE_DIR": str(tmp_path / "jax"),
            "JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS": "0"}
    saved = tmp_path / "executables"
    for run in range(3):
        if run == 1:
            for path in _saved(saved):
                path.unlink()
        out = subprocess.run([sys.executable, "-c", _OVER_TWO_DEVICES, str(saved)], env=env, capture_output=True, text=True,
                             timeout=300)
        assert out.returncode == 0, out.stderr[-2000:]
        assert out.stdout.split() == ["2", "3"]
