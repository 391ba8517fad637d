"""Posterior sampling of a calibration problem (default: the Engelmayr fit,
calibrate/engelmayr2005.toml): jaxtissue's NUTS (blackjax, gradients by forward mode
through the coupled model, chains over the CPU cores) against emcee's affine-invariant
ensemble sampler (the gradient-free sampler pyPESTO offers), on the same jitted
log-posterior in the same unbounded coordinates, in one run.

Each sampler gets the same wall-clock budget: NUTS its warmup and draws, emcee as many
ensemble steps as fit in the same time (its first half discarded as burn-in). Effective
sample size: ArviZ's bulk ESS (minimum over the free parameters) of NUTS's chains;
for emcee, walkers × kept steps / its integrated autocorrelation time (emcee's own
estimate, the largest over the parameters). Compilation is timed apart; XLA compiles
as for the command line (`JAXTISSUE_XLA_DEFAULTS=1`: with its own defaults).

    python benchmarks/posterior.py [--chains 4] [--warmup 300] [--samples 1000] [--walkers 16] [--hold-out CONDITION]

`--hold-out flex` samples the posterior of the static data alone (every log density a
static run): minutes on 2 cores, where the full problem's flex runs take hours.
"""

from __future__ import annotations

import argparse
import pathlib
import time

import jax
import jax.numpy as jnp
import numpy as np

from jaxtissue.cache import use_fast_compilation
from jaxtissue.studies import calibration as cal
from jaxtissue.studies import posterior as post

jax.config.update("jax_enable_x64", True)

PROBLEM = pathlib.Path(__file__).resolve().parents[1] / "calibrate" / "engelmayr2005.toml"


def main():
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--problem", default=str(PROBLEM))
    parser.add_argument("--chains", type=int, default=4)
    parser.add_argument("--warmup", type=int, default=300)
    parser.add_argument("--samples", type=int, default=1000)
    parser.add_argument("--walkers", type=int, default=16)
    parser.add_argument("--hold-out", metavar="CONDITION", help="leave that condition's data out of the posterior")
    args = parser.parse_args()

    use_fast_compilation()  # XLA's settings as the command line's
    problem = cal.read_problem(args.problem, {"starts": 1})
    if args.hold_out:
        problem, _ = post.hold_out(problem, args.hold_out)
    post.split_cpu(problem, args.chains)  # the CPU's devices as the command line makes them, before JAX starts
    k = len(problem.free)
    held = f" ({args.hold_out} held out)" if args.hold_out else ""
    print(f"{problem.name}{held}: {k} free parameters, {len(problem.observations)} observations; {len(jax.devices())} CPU devices")
    best = cal.fit(problem)
    print(f"fit from the paper's values: chi2 = {best.chi2:.4g}")

    # ---- NUTS
    settings = post.SamplerSettings(chains=args.chains, warmup=args.warmup, samples=args.samples)
    white = post.whitening(problem, best.t, best.jacobian, args.chains)  # the coordinates `calibrate --posterior` samples in
    z0, sampler_args = white.z0, post.sampler_args(white)
    programs, refit = post.whitened_programs(problem, settings), post.warmup_refit(settings)  # as `calibrate --posterior`
    phases = post.warmup_phases(settings)
    start = time.perf_counter()
    short = post.SamplerSettings(chains=args.chains, warmup=args.warmup, samples=1)
    post.run_chains(programs, z0, np.eye(k), short, args=sampler_args, chunk=args.samples, refit=refit,
                    phases=phases)  # compiles both programs
    compile_s = time.perf_counter() - start
    (v, _, div, _, steps), _, _, seconds, used = post.run_chains(programs, z0, np.eye(k), settings, args=sampler_args,
                                                                 chunk=args.samples, refit=refit, phases=phases)
    u = np.asarray(post.u_from_v(problem, used, jnp.asarray(v)))
    nuts_s = seconds["warmup"] + seconds["sampling"]
    az = post.import_arviz()
    ess_nuts = np.asarray(az.ess(az.from_dict(posterior={"u": u}), method="bulk")["u"].values)
    print(f"NUTS: {args.chains} chains x ({args.warmup} warmup + {args.samples} draws), {steps.mean():.1f} leapfrog steps a draw, "
          f"{int(div.sum())} divergent; {nuts_s:.0f} s after {compile_s:.0f} s of compilation (and first run); "
          f"min bulk ESS {ess_nuts.min():.0f} -> {ess_nuts.min() / nuts_s:.3g} ESS/s")

    # ---- emcee, same log density (no gradient), walkers evaluated at once under vmap
    import emcee

    log_density = jax.jit(jax.vmap(post.log_density_fn(problem)))
    walkers = np.asarray(post.u_from_v(problem, sampler_args, jnp.asarray(0.1 * np.random.default_rng(0).normal(size=(args.walkers, k)))))
    start = time.perf_counter()
    jax.block_until_ready(log_density(jnp.asarray(walkers)))
    compile_e = time.perf_counter() - start
    sampler = emcee.EnsembleSampler(args.walkers, k, lambda x: np.asarray(log_density(jnp.asarray(x))), vectorize=True)
    state = walkers
    start = time.perf_counter()
    while time.perf_counter() - start < nuts_s:
        state = sampler.run_mcmc(state, 10, progress=False)
    emcee_s = time.perf_counter() - start
    n = sampler.iteration
    tau = np.max(sampler.get_autocorr_time(discard=n // 2, quiet=True))
    ess_emcee = args.walkers * (n - n // 2) / tau
    print(f"emcee: {args.walkers} walkers x {n} steps ({n // 2} kept), autocorrelation time {tau:.0f} steps "
          f"(a reliable estimate needs > 50 tau = {50 * tau:.0f} steps); {emcee_s:.0f} s after {compile_e:.0f} s of compilation; "
          f"ESS {ess_emcee:.0f} -> {ess_emcee / emcee_s:.3g} ESS/s")
    short_chain = n - n // 2 < 50 * tau  # emcee's tau is then an underestimate, its ESS an overestimate
    print(f"effective samples per second, NUTS / emcee: {(ess_nuts.min() / nuts_s) / (ess_emcee / emcee_s):.2f}x (goal >= 5x)"
          + ("; a lower bound: emcee's kept chain is shorter than 50 tau" if short_chain else ""))


if __name__ == "__main__":
    main()
