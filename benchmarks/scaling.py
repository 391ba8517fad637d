"""Cost against grid size: the 3-week flex run (1 Hz, 5 mm) on refined growth grids, in
one process.

For each grid: wall time after compilation (best of `--repeat`), growth steps, time per
cell-step, the compiled program's XLA buffer memory, the compile time, and the 3-week
collagen — which doubles as a grid-convergence table (the observed order from the
three finest grids). With `--gradient`, the gradient of 3-week collagen with respect to
all parameters on the two smallest grids, and with `--large` also on 400 × 320 (nested
intervals stored in float32).

    python benchmarks/scaling.py [--large] [--gradient] [--repeat N] [--grids 50x40,100x80] [--xla-defaults]
      (--large adds 400 x 320, 128 000 cells; --grids runs the grids named instead;
      --xla-defaults: XLA's default CPU emitters instead of the command line's
      `jaxtissue.cache.use_fast_compilation`)
"""

from __future__ import annotations

import sys
import time

from jaxtissue.cache import collect_less, use_fast_compilation

FAST = "--xla-defaults" not in sys.argv and use_fast_compilation()  # as the command line, before JAX starts

import jax  # noqa: E402
import numpy as np  # noqa: E402

import jaxtissue as jt  # noqa: E402

collect_less()  # Python's cycle collector as the command line sets it, after the imports

GRIDS = [(50, 40), (100, 80), (200, 160)]
LARGE = (400, 320)


def run(grid, gradient=False, repeat=1):
    p = jt.paper_parameters()
    options = jt.SolverOptions(nest_intervals=True, store_float32=True) if gradient else jt.SolverOptions()

    def collagen(p):
        r = jt.simulate(p, jt.Protocol.flex(), t_end_s=jt.THREE_WEEKS_S, grid=grid, save="end", options=options)
        return r.collagen_mg_per_g[-1], r.num_steps

    fn = jax.jit(jax.grad(lambda p: collagen(p)[0])) if gradient else jax.jit(collagen)
    start = time.perf_counter()
    compiled = fn.lower(p).compile()
    compile_s = time.perf_counter() - start
    memory = compiled.memory_analysis()
    mib = (memory.temp_size_in_bytes + memory.output_size_in_bytes + memory.argument_size_in_bytes) / 2**20
    best = np.inf
    for _ in range(repeat):
        start = time.perf_counter()
        out = jax.block_until_ready(compiled(p))
        best = min(best, time.perf_counter() - start)
    return best, compile_s, mib, out


def main(large=False, gradient=False, repeat=1, grids=None):
    grids = grids or GRIDS + ([LARGE] if large else [])
    print("3-week flex run (1 Hz, 5 mm), default solver options, on 2 CPU cores unless the device says otherwise:", jax.devices()[0],
          "; XLA's " + ("classic CPU fusion emitter (the command line's setting)" if FAST else "default CPU emitters"))
    print(f"{'grid':>10s}{'cells':>8s}{'run (s)':>10s}{'x 50x40':>9s}{'steps':>7s}{'us/cell-step':>14s}"
          f"{'MiB':>8s}{'compile (s)':>13s}{'collagen (mg/g)':>18s}")
    rows, base = [], None
    for nx, ny in grids:
        seconds, compile_s, mib, (c, steps) = run(jt.Grid(nx, ny), repeat=repeat)
        base = seconds if base is None else base
        cells, steps = nx * ny, int(steps)
        rows.append(float(c))
        print(f"{nx:>4d} x {ny:<3d}{cells:>8d}{seconds:>10.2f}{seconds / base:>9.1f}{steps:>7d}{1e6 * seconds / (cells * steps):>14.3f}"
              f"{mib:>8.1f}{compile_s:>13.1f}{float(c):>18.9f}", flush=True)
    c = np.asarray(rows)
    if len(c) >= 3:
        d1, d2 = c[-2] - c[-3], c[-1] - c[-2]
        print(f"grid convergence: successive changes {abs(d1):.2e}, {abs(d2):.2e}; observed order log2(ratio) = "
              f"{np.log2(abs(d1 / d2)) if d2 else float('inf'):.2f}; Richardson estimate of the limit {c[-1] + d2 / (abs(d1 / d2) - 1) if d2 and abs(d1 / d2) > 1 else c[-1]:.9f}")
    if gradient:
        print("\ngradient of 3-week collagen w.r.t. all parameters (nested intervals, float32 storage)")
        for nx, ny in grids[:2] + ([LARGE] if large and LARGE not in grids[:2] else []):
            seconds, compile_s, mib, g = run(jt.Grid(nx, ny), gradient=True, repeat=repeat)
            finite = all(np.all(np.isfinite(np.asarray(x))) for x in jax.tree_util.tree_leaves(g))
            print(f"{nx:>4d} x {ny:<3d}  {seconds:.2f} s, {mib:.1f} MiB, compile {compile_s:.1f} s, finite: {finite}", flush=True)


if __name__ == "__main__":
    args = sys.argv[1:]
    repeat = int(args[args.index("--repeat") + 1]) if "--repeat" in args else 1
    grids = [tuple(int(n) for n in g.split("x")) for g in args[args.index("--grids") + 1].split(",")] if "--grids" in args else None
    main(large="--large" in args, gradient="--gradient" in args, repeat=repeat, grids=grids)
