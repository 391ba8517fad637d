"""Simulations per second for 256 static parameter sets (3 weeks, 1 x 40 grid), in one
run: one jitted, vmapped batch (`jaxtissue.sweep`) sharded over one CPU device per core
(as `jaxtissue sweep` runs it) and on a single device, a Python loop over the jitted
single run, and a loop over the SciPy baseline (`scipy_reference.three_week_values`,
solve_ivp BDF with the sparsity pattern) at the same tolerances. The single-device
measurements run in a child process with JAX's default single CPU device (the device
count is fixed when JAX starts), so the loop is not slowed by the split.

    python benchmarks/sweep.py [--scipy-sets N]   (SciPy rate from N sets, default 64)
    python benchmarks/sweep.py --batch-sizes 256,4096   (the batch alone, by batch size)
"""

from __future__ import annotations

import json
import os
import pathlib
import subprocess
import sys
import time

sys.path.insert(0, str(pathlib.Path(__file__).resolve().parents[1] / "tests"))  # the SciPy reference
from jaxtissue import sweep as sw  # noqa: E402

CHILD = "--single-device" in sys.argv
if not CHILD:
    sw.use_all_cores()

import jax  # noqa: E402
import numpy as np  # noqa: E402
import scipy_reference  # noqa: E402

import jaxtissue as jt  # noqa: E402

N = 256
RTOL = 1e-5
NAMES = ("k_c_max", "k_a", "k_m0")


def problem(n=N):
    rng = np.random.default_rng(0)
    lo, hi = np.log([1.0e-5, 0.7e-5, 1.0e-7]), np.log([1.5e-5, 1.3e-5, 3.0e-7])
    points = np.exp(lo + (hi - lo) * rng.random((n, 3)))
    sweep = sw.Sweep(NAMES, points, None, jt.Protocol.static(), t_end_s=jt.THREE_WEEKS_S, chunk=n,
                     grid=jt.Grid(1, 40), rtol=RTOL)
    return sweep, points


def time_batch(sweep, points, first=None):
    """Seconds of the compiled batch on `points` (after a first call that compiles it; its
    seconds go into `first["seconds"]` when given) and the collagen it computed."""
    batch, _ = sw.batched(sweep)
    t0 = time.perf_counter()
    batch(points)  # returns NumPy arrays: the run has finished
    if first is not None:
        first["seconds"] = time.perf_counter() - t0
    t0 = time.perf_counter()
    out = batch(points)
    return time.perf_counter() - t0, out["collagen_mg_per_g"]


def single_device():
    """The child: the vmapped batch and the loop of jitted runs on one device."""
    sweep, points = problem()
    t_batch, _ = time_batch(sweep, points)
    single = jax.jit(sweep.run_one)
    jax.block_until_ready(single(points[0]))
    t0 = time.perf_counter()
    loop = [float(single(x)["collagen_mg_per_g"]) for x in points]
    t_loop = time.perf_counter() - t0
    print(json.dumps(dict(devices=len(jax.devices()), t_batch=t_batch, t_loop=t_loop, loop=loop)))


def by_batch_size(sizes):
    """The vmapped batch alone, one compiled program per batch size, on `jax.devices()`."""
    print(f"static parameter sets, 3 weeks, grid 1 x 40, rtol {RTOL:g}; devices: {jax.devices()}")
    print(f"{'sets':>8s}{'compile (s)':>13s}{'run (s)':>10s}{'simulations/s':>15s}")
    for n in sizes:
        first = {}
        t_batch, _ = time_batch(*problem(n), first)
        print(f"{n:>8d}{first['seconds'] - t_batch:>13.1f}{t_batch:>10.2f}{n / t_batch:>15.1f}", flush=True)


def main(scipy_sets=64):
    env = {k: v for k, v in os.environ.items() if k != "XLA_FLAGS"}
    child = subprocess.run([sys.executable, __file__, "--single-device"], env=env, capture_output=True, text=True, check=True)
    one = json.loads(child.stdout.strip().splitlines()[-1])

    sweep, points = problem()
    n_dev = len(jax.devices())
    print(f"{N} static parameter sets ({', '.join(NAMES)}), 3 weeks, grid 1 x 40, rtol {RTOL:g}; "
          f"{os.cpu_count()} cores")
    t_batch, coll = time_batch(sweep, points)

    t0 = time.perf_counter()
    ref = []
    for x in points[:scipy_sets]:
        ref.append(scipy_reference.three_week_values(40, rtol=RTOL, atol=RTOL * 1e-3, **dict(zip(NAMES, x)))["collagen_mg_per_g"])
    t_scipy = (time.perf_counter() - t0) / scipy_sets * N

    t_loop = one["t_loop"]
    err = np.max(np.abs(np.asarray(one["loop"]) - coll) / np.abs(one["loop"]))
    err_sp = np.max(np.abs(np.asarray(ref) - coll[:scipy_sets]) / np.abs(ref))
    print(f"\nvmapped batch, {n_dev} devices (one per core): {N / t_batch:8.1f} simulations/s ({t_batch:.2f} s)")
    print(f"vmapped batch, {one['devices']} device:               {N / one['t_batch']:8.1f} simulations/s ({one['t_batch']:.2f} s)")
    print(f"loop of jitted runs, {one['devices']} device:         {N / t_loop:8.1f} simulations/s ({t_loop:.2f} s)"
          f"  -> batch is {t_loop / t_batch:.1f}x (goal >= 2x); on one device {t_loop / one['t_batch']:.1f}x")
    print(f"loop of SciPy BDF:                     {N / t_scipy:8.1f} simulations/s ({t_scipy:.1f} s, from {scipy_sets} sets)"
          f"  -> batch is {t_scipy / t_batch:.0f}x (goal >= 50x)")
    print(f"collagen: batch vs loop max rel. difference {err:.1e}; vs SciPy {err_sp:.1e}")


if __name__ == "__main__":
    if CHILD:
        single_device()
    elif "--batch-sizes" in sys.argv:
        by_batch_size([int(n) for n in sys.argv[sys.argv.index("--batch-sizes") + 1].split(",")])
    else:
        main(int(sys.argv[sys.argv.index("--scipy-sets") + 1]) if "--scipy-sets" in sys.argv else 64)
