"""The Engelmayr fit (calibrate/engelmayr2005.toml) from the paper's values: jaxtissue's
Levenberg–Marquardt (`calibration`'s own solve) with exact forward-mode Jacobians against SciPy's
`least_squares` (trust-region reflective, bounds, 2-point finite differences) on the
same jitted model, in one run. Reports, after compilation, the seconds each takes to
its own termination and the χ² it reaches, and the seconds each needs to first reach
given χ² targets (from a timestamped record of LM's accepted steps and of SciPy's
evaluations).

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


def main():
    problem = cal.read_problem(PROBLEM, {"starts": 1})
    print(f"{problem.name}: {len(problem.free)} free parameters, {len(problem.observations)} observations; "
          f"flex grid {problem.model.flex_nx} x {problem.model.ny}, beam {problem.model.beam_segments} x "
          f"{problem.model.beam_steps_per_cycle}, T_g = {problem.model.coupling_interval_s:g} s")

    # jaxtissue: the LM of `calibration.fit`, its accepted χ² recorded with a host timestamp
    history = []

    def record(loss):
        history.append((time.perf_counter(), 2 * float(loss)))  # at each step: the last accepted χ²

    solve = cal._lm(problem, problem.fit.max_steps, pinned=False,
                    verbose=lambda **kw: jax.debug.callback(record, kw["loss_last_accepted_step"][1]))
    x0 = np.asarray(cal.latin_hypercube(problem, 1, 0)[0])
    lm = jax.jit(lambda u0: solve(u0, None))
    u0 = problem.u_from_t(jnp.asarray(x0))
    t0 = time.perf_counter()
    jax.block_until_ready(lm(u0))
    print(f"jaxtissue: compile + first fit {time.perf_counter() - t0:.1f} s")
    history.clear()
    t0_jax = t0 = time.perf_counter()
    u_best, _, steps, _ = jax.block_until_ready(lm(u0))
    history = history[1:]  # the first call reports the solver's initial placeholder, not a loss
    t_jax = time.perf_counter() - t0
    chi2_jax = float(np.sum(np.asarray(problem.residuals(problem.t_from_u(u_best))) ** 2))
    steps = int(steps)
    print(f"\njaxtissue LM (exact Jacobian): chi2 = {chi2_jax:.5g} in {t_jax:.1f} s, {steps} LM steps "
          f"(each: residuals + one forward-mode Jacobian)")

    residuals = jax.jit(problem.residuals)
    lo, hi = (np.asarray(b) for b in problem.t_bounds())
    residuals(jnp.asarray(x0)).block_until_ready()
    count = [0]
    sp_history = []

    def fun(x):
        count[0] += 1
        r = np.asarray(residuals(jnp.asarray(x)))
        sp_history.append((time.perf_counter(), float(np.sum(r**2))))
        return r

    t0_sp = t0 = time.perf_counter()
    sp = scipy.optimize.least_squares(fun, x0, bounds=(lo, hi), jac="2-point", method="trf", x_scale="jac",
                                       ftol=1e-10, xtol=1e-10, gtol=1e-10, max_nfev=600)
    t_sp = time.perf_counter() - t0
    chi2_sp = float(np.sum(sp.fun**2))
    print(f"SciPy least_squares (TRF, finite differences): chi2 = {chi2_sp:.5g} in {t_sp:.1f} s, {count[0]} model evaluations "
          f"({sp.nfev} steps; status {sp.status}: {sp.message})")
    print(f"\nto own termination: SciPy / jaxtissue = {t_sp / t_jax:.2f}x; chi2: jaxtissue {chi2_jax:.5g} vs SciPy {chi2_sp:.5g}")

    def reach(hist, start, target):
        return next((t - start for t, c in hist if c <= target), None)

    for target in (1.1 * chi2_jax, 1.1 * chi2_sp, 2.0, 10.0):
        a, b = reach(history, t0_jax, target), reach(sp_history, t0_sp, target)
        if a and b:
            ratio = f"SciPy / jaxtissue = {b / a:.1f}x (goal >= 5x)"
        elif a:
            ratio = f"SciPy stopped ({t_sp:.1f} s, {count[0]} evaluations) without reaching it"
        else:
            ratio = "n/a"
        print(f"seconds to chi2 <= {target:.3g}: jaxtissue {a if a is None else round(a, 2)}, SciPy {b if b is None else round(b, 2)}: {ratio}")
    print(f"seconds per step: jaxtissue LM (residuals + forward-mode Jacobian) {t_jax / max(steps, 1):.2f} s, "
          f"SciPy ({len(x0) + 1} evaluations) {t_sp / max(count[0], 1) * (len(x0) + 1):.2f} s")
    fitted = np.asarray(problem.values_from_t(problem.t_from_u(u_best)))
    for n, a, b in zip(problem.names, fitted, np.asarray(problem.values_from_t(jnp.asarray(sp.x)))):
        print(f"  {n:20s} jaxtissue {a:.5g}   SciPy {b:.5g}")


if __name__ == "__main__":
    main()
