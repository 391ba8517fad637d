"""Two identical cold command-line runs in fresh processes, sharing a new, empty
compilation cache folder (`jaxtissue.cache`): the second loads its programs from disk.
Prints each run's wall time and the second's share of the first. The posterior (of the
static data: `--hold-out flex`) and the optimisation are cut short (2 chains of 40 + 40
draws; 2 starts of 3 steps, a 4 × 4 grid): their compilation is the same.

    python benchmarks/cache.py [--simulate-only]
"""

from __future__ import annotations

import os
import subprocess
import sys
import tempfile
import time

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
COMMANDS = {
    "simulate --regime flex": ["simulate", "--regime", "flex", "--no-progress"],
    "reproduce": ["reproduce", "--no-progress"],
    "calibrate (no profiles)": ["calibrate", os.path.join(ROOT, "calibrate", "engelmayr2005.toml"), "--no-profiles", "--no-progress"],
    "calibrate --posterior (short)": ["calibrate", os.path.join(ROOT, "calibrate", "engelmayr2005.toml"), "--no-profiles",
                                      "--posterior", "--chains", "2", "--warmup", "40", "--samples", "40", "--hold-out", "flex",
                                      "--no-progress"],
    "sensitivity --regime flex": ["sensitivity", "--regime", "flex"],
    "optimize (short)": ["optimize", os.path.join(ROOT, "optimize", "max_collagen.toml"), "--starts", "2", "--steps", "3",
                         "--grid-points", "4", "--no-progress"],
    "sweep sweeps/kinetics.toml": ["sweep", os.path.join(ROOT, "sweeps", "kinetics.toml"), "--no-progress"],
    "sweep --dask local:2": ["sweep", os.path.join(ROOT, "sweeps", "kinetics.toml"), "--dask", "local:2", "--no-progress"],
}


def timed_run(args, cache_home, out):
    env = {k: v for k, v in os.environ.items() if not k.startswith("JAX_COMPILATION_CACHE") and k != "JAXTISSUE_NO_CACHE"}
    env["XDG_CACHE_HOME"] = cache_home
    start = time.perf_counter()
    proc = subprocess.run([sys.executable, "-m", "jaxtissue.cli", *args, "--out", out], capture_output=True, text=True, env=env, check=False)
    seconds = time.perf_counter() - start
    if proc.returncode != 0:
        sys.exit(f"jaxtissue {' '.join(args)} failed: {proc.stderr.strip().splitlines()[-1:]}")
    return seconds


def main(simulate_only=False):
    print(f"{'command':26s}{'first (s)':>12s}{'second (s)':>12s}{'second/first':>14s}")
    for label, args in COMMANDS.items():
        if simulate_only and not label.startswith("simulate"):
            continue
        with tempfile.TemporaryDirectory() as tmp:
            first = timed_run(args, tmp, os.path.join(tmp, "first"))
            second = timed_run(args, tmp, os.path.join(tmp, "second"))
        print(f"{label:26s}{first:12.1f}{second:12.1f}{second / first:13.0%}")


if __name__ == "__main__":
    main(simulate_only="--simulate-only" in sys.argv[1:])
