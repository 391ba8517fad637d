"""`jaxtissue reproduce`'s five flex cases (1 Hz / 5 mm; 0.5 and 2 Hz; 2.5 and 10 mm;
default grids, 2.0e6 s), in one process split into a CPU device per core as the command
line splits it: one after another with the single run's program, as one program that
runs each device's cases one after another (`sweep.map_over_devices`, what reproduce
does), and vmapped over the devices (`sweep.vmap_over_devices`). Best of two runs each
after compilation, and the largest difference of the 3-week values from the single runs.

    python benchmarks/flex_cases.py
"""

from __future__ import annotations

import time

from jaxtissue.studies import sweep

sweep.use_all_cores()  # before JAX starts

import jax  # noqa: E402
import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402

import jaxtissue as jt  # noqa: E402
from jaxtissue.studies.reproduce import CASES  # noqa: E402

jax.config.update("jax_enable_x64", True)
KEYS = ("dna_ug_per_g", "collagen_mg_per_g", "E_eff_kPa", "post_force_max_N")


def best_of_two(run):
    run()  # compile
    times = []
    for _ in range(2):
        t0 = time.perf_counter()
        out = jax.block_until_ready(run())
        times.append(time.perf_counter() - t0)
    return out, min(times)


def main():
    params = jt.paper_parameters()
    protocols = [q for q in CASES.values() if q.regime == "flex"]
    n = sweep.even_batches(len(protocols), len(protocols))
    padded = protocols + protocols[-1:] * (n - len(protocols))
    stacked = jax.tree_util.tree_map(lambda *x: jnp.stack([jnp.asarray(v, float) for v in x]), *padded)
    one = lambda q: jt.simulate(params, q)  # noqa: E731
    print(f"{len(protocols)} flex cases (padded to {n}) on {len(jax.devices())} CPU devices")
    single, t_single = best_of_two(lambda: [one(q) for q in protocols])
    rows = {"one after another (the single run's program)": (single, t_single)}
    mapped = jax.jit(sweep.map_over_devices(one, n))
    vmapped = jax.jit(sweep.vmap_over_devices(one, n))
    for label, run in (("map_over_devices (reproduce)", mapped), ("vmap_over_devices", vmapped)):
        out, t = best_of_two(lambda run=run: run(stacked))
        rows[label] = ([jax.tree_util.tree_map(lambda x, i=i: x[i], out) for i in range(len(protocols))], t)
    for label, (results, t) in rows.items():
        differs = max(float(np.max(np.abs(np.asarray(getattr(r, k)) - np.asarray(getattr(s, k)))
                                    / np.maximum(np.abs(np.asarray(getattr(s, k))), 1e-300)))
                      for r, s in zip(results, single) for k in KEYS)
        print(f"{label:48s} {t:6.2f} s  ({t_single / t:4.2f} x one after another; values differ by {differs:.0e})")


if __name__ == "__main__":
    main()
