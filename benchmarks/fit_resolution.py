"""The resolution a calibration problem's model runs at (its `[model]`; default:
calibrate/engelmayr2005.toml) against `simulate`'s default grids: the 3-week DNA,
collagen and E_eff of each condition at the paper's parameters and at a fitted
parameter set, their relative differences, and the milliseconds one log-posterior
gradient costs (the residuals' forward-mode Jacobian, what each NUTS leapfrog step
evaluates) at the problem's resolution.

    python benchmarks/fit_resolution.py [PROBLEM.toml] [--fitted FITTED.toml]
"""

from __future__ import annotations

import argparse
import pathlib
import time

import jax
import jax.numpy as jnp
import numpy as np

jax.config.update("jax_enable_x64", True)

from jaxtissue import Params, simulate  # noqa: E402
from jaxtissue.io import read_params_toml  # noqa: E402
from jaxtissue.studies.calibration import read_problem  # noqa: E402

ROOT = pathlib.Path(__file__).resolve().parents[1]
OUTPUTS = ("dna_ug_per_g", "collagen_mg_per_g", "E_eff_kPa")


def three_weeks(params, protocol, t_end, **resolution):
    r = simulate(params, protocol, t_end_s=t_end, save="end", **resolution)
    return np.array([float(getattr(r, o)[-1]) for o in OUTPUTS])


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("problem", nargs="?", default=str(ROOT / "calibrate" / "engelmayr2005.toml"))
    parser.add_argument("--fitted", default=str(ROOT / "jaxtissue" / "studies" / "engelmayr2005_posterior" / "fitted.toml"))
    args = parser.parse_args()
    problem = read_problem(args.problem)
    m = problem.model
    print(f"{problem.name} [model]: flex grid {m.flex_nx} x {m.ny}, static 1 x {m.ny}, beam {m.beam_segments} x "
          f"{m.beam_steps_per_cycle}, T_g = {m.coupling_interval_s:g} s, rtol = {m.rtol:g}")
    t_end = max(o.time_s for o in problem.observations)
    print(f"relative difference of the {t_end:g} s values from the default grids' (%): " + ", ".join(OUTPUTS))
    for label, params in (("paper's values", Params()), (f"fitted ({pathlib.Path(args.fitted).name})", read_params_toml(args.fitted))):
        for name, protocol in problem.conditions.items():
            fine = three_weeks(params, protocol, t_end)
            coarse = three_weeks(params, protocol, t_end, grid=m.grid(protocol.regime), beam=m.beam(),
                                 coupling_interval_s=m.coupling_interval_s, options=m.options())
            print(f"  {label:34s}{name:8s}" + "".join(f"{100 * (c / f - 1):+9.3f}" for c, f in zip(coarse, fine)))
    jacobian = jax.jit(jax.jacfwd(problem.residuals))
    t = problem.t_from_values(jnp.asarray([getattr(read_params_toml(args.fitted), n) for n in problem.names]))
    jax.block_until_ready(jacobian(t))
    times = []
    for _ in range(7):
        start = time.perf_counter()
        jax.block_until_ready(jacobian(t))
        times.append(time.perf_counter() - start)
    print(f"one forward-mode Jacobian of the residuals ({len(problem.free)} tangents): {1e3 * min(times):.1f} ms (best of 7)")


if __name__ == "__main__":
    main()
