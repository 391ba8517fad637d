"""The Engelmayr fit (calibrate/engelmayr2005.toml) from the paper's values: jaxtissue's
Levenberg–Marquardt with exact forward-mode Jacobians against SciPy's
`least_squares` (trust-region reflective, bounds, 2-point finite differences) on the
same jitted model, in one run. Reports seconds (after compilation), model evaluations
and the χ² each reaches.

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

    # jaxtissue: compile once (a first call), then time the same fit
    t0 = time.perf_counter()
    cal.fit(problem)
    print(f"jaxtissue: compile + first fit {time.perf_counter() - t0:.1f} s")
    t0 = time.perf_counter()
    best = cal.fit(problem)
    t_jax = time.perf_counter() - t0
    print(f"\njaxtissue LM (exact Jacobian): chi2 = {best.chi2:.5g} in {t_jax:.1f} s, "
          f"{int(best.steps_all[0])} LM steps (each: residuals + one forward-mode Jacobian)")

    residuals = jax.jit(problem.residuals)
    lo, hi = (np.asarray(b) for b in problem.t_bounds())
    x0 = np.asarray(best.starts_t[0])
    residuals(jnp.asarray(x0)).block_until_ready()
    count = [0]

    def fun(x):
        count[0] += 1
        return np.asarray(residuals(jnp.asarray(x)))

    t0 = time.perf_counter()
    sol = scipy.optimize.least_squares(fun, x0, bounds=(lo, hi), jac="2-point", method="trf", x_scale="jac",
                                       ftol=1e-10, xtol=1e-10, gtol=1e-10, max_nfev=600)
    t_sp = time.perf_counter() - t0
    chi2_sp = float(np.sum(sol.fun**2))
    print(f"SciPy least_squares (TRF, finite differences): chi2 = {chi2_sp:.5g} in {t_sp:.1f} s, {count[0]} model evaluations "
          f"({sol.nfev} steps; status {sol.status}: {sol.message})")
    print(f"\nseconds: SciPy / jaxtissue = {t_sp / t_jax:.2f}x (goal >= 5x); chi2: jaxtissue {best.chi2:.5g} vs SciPy {chi2_sp:.5g}")
    print(f"seconds per Jacobian: jaxtissue (forward mode) {t_jax / max(int(best.steps_all[0]), 1):.2f} s, "
          f"SciPy ({len(x0) + 1} evaluations) {t_sp / max(count[0], 1) * (len(x0) + 1):.2f} s")
    for n, a, b in zip(problem.names, best.values, np.asarray(problem.values_from_t(jnp.asarray(sol.x)))):
        print(f"  {n:20s} jaxtissue {a:.5g}   SciPy {b:.5g}")


if __name__ == "__main__":
    main()
