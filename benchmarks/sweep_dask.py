"""The engine's overhead: 256 static parameter sets (3 weeks, 1 x 40 grid) in chunks of
32, on `--dask local:2` (two single-threaded worker processes, results into Zarr by
region) against the in-process sweep sharded over one device per core (`jaxtissue
sweep` without `--dask`), on the same machine in the same run. Each side runs twice:
the first run includes compilation (and the cluster's start), the second measures the
throughput once compiled (the same LocalCluster, whose workers keep their programs).

    python benchmarks/sweep_dask.py
"""

from __future__ import annotations

import os
import pathlib
import sys
import tempfile
import time

from jaxtissue import sweep as sw

sw.use_all_cores()  # the in-process side, as `jaxtissue sweep` runs it; the workers get their own processes

import jax  # noqa: E402
import numpy as np  # noqa: E402

import jaxtissue as jt  # noqa: E402
from jaxtissue.studies import sweep_dask  # noqa: E402

N, CHUNK = 256, 32
NAMES = ("k_c_max", "k_a", "k_m0")


def problem():
    rng = np.random.default_rng(0)
    lo, hi = np.log([1.0e-5, 0.7e-5, 1.0e-7]), np.log([1.5e-5, 1.3e-5, 3.0e-7])
    points = np.exp(lo + (hi - lo) * rng.random((N, 3)))
    return sw.Sweep(NAMES, points, None, jt.Protocol.static(), t_end_s=jt.THREE_WEEKS_S, chunk=CHUNK, grid=jt.Grid(1, 40))


def timed(run):
    t0 = time.perf_counter()
    ds = run()
    return time.perf_counter() - t0, ds


def main():
    from dask.distributed import LocalCluster

    sweep = problem()
    work = pathlib.Path(tempfile.mkdtemp(prefix="jaxtissue-bench-"))
    print(f"{N} static parameter sets in chunks of {CHUNK}, 3 weeks, grid 1 x 40; {os.cpu_count()} cores")
    first_local, _ = timed(lambda: sw.run(sweep, work / "local1"))
    again_local, local = timed(lambda: sw.run(sweep, work / "local2"))
    start = time.perf_counter()
    with LocalCluster(n_workers=2, threads_per_worker=1, processes=True, dashboard_address=None) as cluster:
        started = time.perf_counter() - start
        first_dask, _ = timed(lambda: sweep_dask.run(sweep, work / "dask1", cluster.scheduler_address))
        again_dask, dask = timed(lambda: sweep_dask.run(sweep, work / "dask2", cluster.scheduler_address))
    err = float(np.max(np.abs(dask["collagen_mg_per_g"].values - local["collagen_mg_per_g"].values) / local["collagen_mg_per_g"].values))
    print(f"\nin-process, {len(jax.devices())} devices:  first run {first_local:6.1f} s; compiled {N / again_local:7.1f} simulations/s "
          f"({again_local:.2f} s)")
    print(f"--dask local:2:            first run {started + first_dask:6.1f} s (cluster start {started:.1f} s); compiled "
          f"{N / again_dask:7.1f} simulations/s ({again_dask:.2f} s)")
    print(f"  -> Dask's throughput is {again_local / again_dask:.2f}x the in-process sweep's once compiled, "
          f"{first_local / (started + first_dask):.2f}x on a first run; collagen max rel. difference {err:.1e}")


if __name__ == "__main__":
    sys.exit(main())
