"""The Engelmayr fit (calibrate/engelmayr2005.toml): jaxtissue's Levenberg–Marquardt
(`calibration`'s own solve: in the bounds' box, exact forward-mode Jacobians with
Broyden updates between them) against SciPy's
`least_squares` (trust-region reflective, bounds, 2-point finite differences at four
difference steps: its default √eps and 1e-6, 1e-4, 1e-3) on the same jitted model, in
one run, after compilation.

From the paper's values: the seconds each takes to its own termination and the χ² it
reaches, and the seconds each needs to first evaluate a point within 10 % of the
optimum's χ² (the best of all runs) — the time to calibrate — and within 10 % of
SciPy-default's final χ², from a timestamped record of every point each evaluates.
Then the same over the eight starts of `jaxtissue calibrate` (a Latin hypercube) for LM,
SciPy's default step and its best step from the paper's values.

    python benchmarks/calibrate.py
"""

from __future__ import annotations

import pathlib
import time

import jax
import jax.numpy as jnp
import numpy as np
import scipy.optimize

from jaxtissue import calibration as cal

jax.config.update("jax_enable_x64", True)

PROBLEM = pathlib.Path(__file__).resolve().parents[1] / "calibrate" / "engelmayr2005.toml"
STEPS = (None, 1e-6, 1e-4, 1e-3)  # SciPy's relative difference steps (None: √eps)


def label(step):
    return "default" if step is None else f"{step:g}"


def main():
    problem = cal.read_problem(PROBLEM)
    print(f"{problem.name}: {len(problem.free)} free parameters, {len(problem.observations)} observations; "
          f"flex grid {problem.model.flex_nx} x {problem.model.ny}, beam {problem.model.beam_segments} x "
          f"{problem.model.beam_steps_per_cycle}, T_g = {problem.model.coupling_interval_s:g} s")
    starts = cal.latin_hypercube(problem, problem.fit.starts, problem.fit.seed)  # the first: the paper's values

    # jaxtissue: the LM of `calibration.fit`, the χ² of each point it evaluates recorded
    # with a host timestamp (as SciPy's evaluations are below)
    record = []
    solve = cal.lm_solve(problem, problem.fit.max_steps, record=lambda c: record.append((time.perf_counter(), float(c))))
    lm = jax.jit(lambda t0: solve(t0, cal.unpinned(problem.fit.max_steps)))
    t0 = time.perf_counter()
    jax.block_until_ready(lm(jnp.asarray(starts[0])))
    print(f"jaxtissue: compile + first fit {time.perf_counter() - t0:.1f} s")

    def lm_fit(x0):
        record.clear()
        t0 = time.perf_counter()
        out = jax.block_until_ready(lm(jnp.asarray(x0)))
        n, nj = int(out.evaluations), int(out.jacobians)
        return dict(x=np.asarray(out.t), chi2=float(out.chi2), seconds=time.perf_counter() - t0, t0=t0, record=list(record),
                    evaluations=n, jacobians=nj, steps=int(out.steps),
                    note=f"{int(out.steps)} LM steps: {n} residual evaluations + {nj} Jacobians, converged: {bool(out.converged)}")

    residuals = jax.jit(problem.residuals)
    lo, hi = (np.asarray(b) for b in problem.t_bounds())
    residuals(jnp.asarray(starts[0])).block_until_ready()

    def scipy_fit(x0, diff_step):
        rec = []

        def fun(x):
            r = np.asarray(residuals(jnp.asarray(x)))
            rec.append((time.perf_counter(), float(np.sum(r**2))))
            return r

        t0 = time.perf_counter()
        sp = scipy.optimize.least_squares(fun, x0, bounds=(lo, hi), jac="2-point", method="trf", x_scale="jac",
                                           diff_step=diff_step, ftol=1e-10, xtol=1e-10, gtol=1e-10, max_nfev=600)
        return dict(x=sp.x, chi2=float(np.sum(sp.fun**2)), seconds=time.perf_counter() - t0, t0=t0, record=rec,
                    evaluations=len(rec), note=sp.message)

    def reach(run, target):
        return next((t - run["t0"] for t, c in run["record"] if c <= target), None)

    # ---- from the paper's values
    jx = lm_fit(starts[0])
    print(f"\njaxtissue LM (exact Jacobians, Broyden updates between): chi2 = {jx['chi2']:.5g} in {jx['seconds']:.2f} s, "
          f"{jx['note']}")
    runs = {step: scipy_fit(starts[0], step) for step in STEPS}
    print("SciPy least_squares (TRF, bounds, 2-point finite differences), by relative difference step:")
    for step, run in runs.items():
        print(f"  diff_step {label(step):>8s}: chi2 = {run['chi2']:.5g} in {run['seconds']:.1f} s, "
              f"{run['evaluations']} model evaluations ({run['note']})")

    chi2_min = min([jx["chi2"]] + [run["chi2"] for run in runs.values()])
    calibrated = 1.1 * chi2_min
    for what, target in ((f"the optimum + 10 % (chi2 <= {calibrated:.3g}): the time to calibrate", calibrated),
                         (f"SciPy-default's final + 10 % (chi2 <= {1.1 * runs[None]['chi2']:.3g})", 1.1 * runs[None]["chi2"])):
        a = reach(jx, target)
        print(f"\nseconds to {what}:\n  jaxtissue LM {'never' if a is None else f'{a:.2f}'}")
        reached = {}
        for step, run in runs.items():
            b = reach(run, target)
            if b is not None:
                reached[step] = b
            print(f"  SciPy, diff_step {label(step):>8s}: "
                  + ("never (stopped first)" if b is None else f"{b:.2f}" + ("" if a is None else f" = {b / a:.1f}x jaxtissue")))
        if a is not None and reached:
            print(f"  fastest SciPy / jaxtissue = {min(reached.values()) / a:.1f}x (goal >= 5x)")
    evaluation = runs[None]["seconds"] / runs[None]["evaluations"]
    print(f"\nseconds per iteration: jaxtissue LM {jx['seconds'] / max(jx['steps'], 1):.3f} s "
          f"({(jx['evaluations'] + jx['jacobians']) / max(jx['steps'], 1):.2f} evaluations + Jacobians per step), "
          f"SciPy ({len(lo) + 1} evaluations) {evaluation * (len(lo) + 1):.3f} s; one model evaluation {evaluation:.3f} s")
    best = min(runs.values(), key=lambda run: run["chi2"])
    for n, a, b in zip(problem.names, np.asarray(problem.values_from_t(jnp.asarray(jx["x"]))),
                       np.asarray(problem.values_from_t(jnp.asarray(best["x"])))):
        print(f"  {n:20s} jaxtissue {a:.5g}   SciPy (its best fit) {b:.5g}")

    # ---- over the CLI's starts
    best_step = min((s for s in STEPS if reach(runs[s], calibrated) is not None),
                    key=lambda s: reach(runs[s], calibrated), default=None)
    methods = {"jaxtissue LM": lm_fit, "SciPy, default step": lambda x0: scipy_fit(x0, None)}
    if best_step is not None:
        methods[f"SciPy, diff_step {label(best_step)}"] = lambda x0: scipy_fit(x0, best_step)
    print(f"\nover the {len(starts)} starts of `jaxtissue calibrate` (to chi2 <= {calibrated:.3g}):")
    medians = {}
    for name, method in methods.items():
        fits = [method(x0) for x0 in starts]
        times = [reach(f, calibrated) for f in fits]
        done = [t for t in times if t is not None]
        medians[name] = np.median(done) if len(done) > len(starts) / 2 else None
        finals = ", ".join(f"{f['chi2']:.4g}" for f in fits)
        print(f"  {name:26s} reached by {len(done)}/{len(starts)}, median {medians[name] and round(medians[name], 2)} s, "
              f"total to termination {sum(f['seconds'] for f in fits):.1f} s, {sum(f['evaluations'] for f in fits)} evaluations"
              + (f" + {sum(f['jacobians'] for f in fits)} Jacobians" if name.startswith("jax") else "") + f"; final chi2 {finals}")
    scipy_medians = [v for k, v in medians.items() if k.startswith("SciPy") and v is not None]
    if medians["jaxtissue LM"] and scipy_medians:
        print(f"  median time to calibrate, fastest SciPy / jaxtissue = {min(scipy_medians) / medians['jaxtissue LM']:.1f}x (goal >= 5x)")


if __name__ == "__main__":
    main()
