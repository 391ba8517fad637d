"""NUTS with the chains' pooled step size and metric (`posterior.pooled_adaptation`,
what `calibrate --posterior` does) against each chain keeping its own, on the Engelmayr
problem's static data (`--hold-out flex`: every log density a static run), over
several seeds: for each, the largest R-hat, the smallest bulk ESS, leapfrog steps a
draw and divergent draws, with the same warmup, starts and keys.

    python benchmarks/pooled_adaptation.py [--seeds 4] [--samples 300]
"""

from __future__ import annotations

import argparse
import pathlib

import jax
import numpy as np

from jaxtissue.cache import use_fast_compilation
from jaxtissue.studies import calibration as cal
from jaxtissue.studies import posterior as post

ROOT = pathlib.Path(__file__).resolve().parents[1]


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seeds", type=int, default=4)
    parser.add_argument("--samples", type=int, default=300)
    parser.add_argument("--warmup", type=int, default=300)
    parser.add_argument("--chains", type=int, default=4)
    args = parser.parse_args()
    use_fast_compilation()  # XLA's settings as the command line's (the chains' paths hang on rounding)
    problem, _ = post.hold_out(cal.read_problem(ROOT / "calibrate" / "engelmayr2005.toml"), "flex")
    post.split_cpu(problem, args.chains)  # the CPU's devices as the command line makes them, before JAX starts
    best = cal.fit(problem)  # the fit `calibrate` starts the sampler from
    az = post.import_arviz()
    print(f"{problem.name}, flex held out; {args.chains} chains x ({args.warmup} warmup + {args.samples} draws); "
          f"{len(jax.devices())} CPU devices")
    print(f"{'seed':>4s}  {'adaptation':12s}{'max R-hat':>10s}{'min ESS':>9s}{'steps/draw':>12s}{'divergent':>11s}")
    for seed in range(args.seeds):
        for pool in (False, True):
            settings = post.SamplerSettings(chains=args.chains, warmup=args.warmup, samples=args.samples, seed=seed, pool=pool)
            draws = post.sample(problem, best.t, best.jacobian, settings)
            stats = az.summary(az.from_dict(posterior={"t": draws.t}), kind="diagnostics", round_to="none")
            print(f"{seed:4d}  {'pooled' if pool else 'per chain':12s}{stats['r_hat'].max():10.3f}{stats['ess_bulk'].min():9.0f}"
                  f"{draws.leapfrog_steps.mean():12.1f}{int(draws.diverging.sum()):11d}")


if __name__ == "__main__":
    main()
