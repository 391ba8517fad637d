"""Simulations per second for 256 static parameter sets (3 weeks, 1 x 40 grid), in one
run: one jitted, vmapped batch (`jaxtissue.sweep`), a Python loop over the jitted
single run, and a loop over the SciPy baseline (`scipy_reference.StaticProblem`,
solve_ivp BDF with the sparsity pattern) at the same tolerances.

    python benchmarks/sweep.py [--scipy-sets N]   (SciPy rate from N sets, default 64)
"""

from __future__ import annotations

import pathlib
import sys
import time

import jax
import numpy as np

sys.path.insert(0, str(pathlib.Path(__file__).parent))
import scipy_reference  # noqa: E402

import jaxtissue as jt  # noqa: E402
from jaxtissue import sweep as sw  # noqa: E402

N = 256
RTOL = 1e-5


def main(scipy_sets=64):
    rng = np.random.default_rng(0)
    names = ("k_c_max", "k_a", "k_m0")
    lo, hi = np.log([1.0e-5, 0.7e-5, 1.0e-7]), np.log([1.5e-5, 1.3e-5, 3.0e-7])
    points = np.exp(lo + (hi - lo) * rng.random((N, 3)))
    sweep = sw.Sweep(names, points, None, jt.Protocol.static(), t_end_s=jt.THREE_WEEKS_S, chunk=N,
                     grid=jt.Grid(1, 40), rtol=RTOL)
    print(f"{N} static parameter sets (k_c_max, k_a, k_m0), 3 weeks, grid 1 x 40, rtol {RTOL:g}; "
          f"{len(jax.devices())} device(s)")

    batch, _ = sw.batched(sweep)
    batch(points)
    t0 = time.perf_counter()
    out = batch(points)
    t_batch = time.perf_counter() - t0

    single = jax.jit(sweep.run_one)
    jax.block_until_ready(single(points[0]))
    t0 = time.perf_counter()
    loop = [float(single(x)["collagen_mg_per_g"]) for x in points]
    t_loop = time.perf_counter() - t0

    t0 = time.perf_counter()
    ref = []
    for x in points[:scipy_sets]:
        prob = scipy_reference.StaticProblem(40, **dict(zip(names, x)))
        sol = prob.solve(np.array([0.0, jt.THREE_WEEKS_S]), rtol=RTOL, atol=RTOL * 1e-3)
        ref.append(prob.observables(sol.y[:, -1])["collagen_mg_per_g"])
    t_scipy = (time.perf_counter() - t0) / scipy_sets * N

    err = np.max(np.abs(np.asarray(loop) - out["collagen_mg_per_g"]) / np.abs(loop))
    err_sp = np.max(np.abs(np.asarray(ref) - out["collagen_mg_per_g"][:scipy_sets]) / np.abs(ref))
    print(f"\nvmapped batch:        {N / t_batch:8.1f} simulations/s ({t_batch:.2f} s)")
    print(f"loop of jitted runs:  {N / t_loop:8.1f} simulations/s ({t_loop:.2f} s)  -> batch is {t_loop / t_batch:.1f}x (goal >= 2x)")
    print(f"loop of SciPy BDF:    {N / t_scipy:8.1f} simulations/s ({t_scipy:.1f} s, from {scipy_sets} sets)  -> batch is "
          f"{t_scipy / t_batch:.0f}x (goal >= 50x)")
    print(f"collagen: batch vs loop max rel. difference {err:.1e}; vs SciPy {err_sp:.1e}")


if __name__ == "__main__":
    n = int(sys.argv[sys.argv.index("--scipy-sets") + 1]) if "--scipy-sets" in sys.argv else 64
    main(n)
