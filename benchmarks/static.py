"""Static culture, 1-D transmural grid (ny = 200), 3 weeks: jaxtissue versus SciPy.

Both sides solve the same problem on the same grid in the same run (the paper's
D_c = χ = 0: no cell flux, see `same_equations`; DNA, collagen and E_eff at
`simulate`'s default save times), over the same ladder of tolerances; for each accuracy
target (max relative error of the 3-week values against a tight reference) the fastest
run of each that reaches it is compared:

* forward: `jt.simulate` (jitted, after compilation) with each of its time steppers
  (`SolverOptions.method`: "ros34pw2", the default, and "rodas4p2", order 4 with the
  exact Jacobian of these 1-D runs) versus `solve_ivp(BDF)` with the Jacobian's
  sparsity pattern, `t_eval` those save times (`scipy_reference.py`);
* gradient of 3-week collagen with respect to all kinetic parameters: one reverse-mode
  pass (each stepper) versus central finite differences of the SciPy solve (2 solves
  per parameter), each at the loosest tolerance whose gradient is within `GRAD_TARGET`
  of a tight one;
* compile time of the jitted forward run;
* per step: wall time and, alone, the O2 solve's Thomas factor and stage solves; and
  a step's cost against the number of cells (25 to 800), fitted by a line.

    python benchmarks/static.py [--xla-defaults]
      (--xla-defaults: XLA's default CPU emitters instead of the command line's
      `jaxtissue.cache.use_fast_compilation`)
"""

from __future__ import annotations

import pathlib
import sys
import time

from jaxtissue.cache import collect_less, use_fast_compilation

if "--xla-defaults" not in sys.argv:
    use_fast_compilation()  # as the command line, before JAX starts

import jax  # noqa: E402
import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402

sys.path.insert(0, str(pathlib.Path(__file__).resolve().parents[1] / "tests"))  # the SciPy reference
import scipy_reference  # noqa: E402

import jaxtissue as jt  # noqa: E402
from jaxtissue.protocol import save_times  # noqa: E402
from jaxtissue.simulate import METHODS  # noqa: E402  (the time steppers)

collect_less()  # Python's cycle collector as the command line sets it, after the imports

NY = 200
T = jt.THREE_WEEKS_S
SAVE_TIMES = save_times(T, jt.COUPLING_INTERVAL_S)  # `simulate`'s default
TARGETS = (1e-4, 3e-5, 1e-5, 3e-6)
GRAD_TARGET = 1e-3
KINETIC = ["k_c_max", "k_a", "n_moser", "o_c", "k_i", "Q_o", "o_h", "k_m0", "o_m", "D_o0", "c_max"]
KEYS = ("dna_ug_per_g", "collagen_mg_per_g", "E_eff_kPa")
LADDER = [1e-3, 5e-4, 2e-4, 1e-4, 5e-5, 2e-5, 1e-5, 5e-6, 2e-6, 1e-6]


def best_time(fn, repeats):
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t0)
    return min(times)


def rel_err(values, ref):
    return max(abs(values[k] - ref[k]) / abs(ref[k]) for k in KEYS)


def same_equations(p):
    """p with the cell flux's D_c and χ held at the paper's zeros, untraced: the SciPy
    reference has no cell flux, and `jt.simulate` then drops it (as for a user's call
    with those parameters) instead of computing a zero flux from traced ones."""
    base = jt.paper_parameters()
    return p.replace(D_c=base.D_c, chi=base.chi)


def jax_forward(rtol, ny=NY, method="ros34pw2"):
    options = jt.SolverOptions(rtol=rtol, atol=rtol * 1e-3, method=method)

    @jax.jit
    def run(p):
        r = jt.simulate(same_equations(p), t_end_s=T, grid=jt.Grid(ny=ny), options=options)
        return {k: getattr(r, k)[-1] for k in KEYS} | {"steps": r.num_steps}

    return run


STEP_COST_CELLS = (25, 50, 100, 200, 400, 800)
STEP_COST_RTOL = 3e-5


def step_cost_by_cells(p):
    """Microseconds a step of the same run at `STEP_COST_RTOL` on 1-D grids of
    `STEP_COST_CELLS` cells (best of 10), and a least-squares line through them: what a
    step costs whatever the grid, and per cell."""
    costs = []
    for ny in STEP_COST_CELLS:
        run = jax_forward(STEP_COST_RTOL, ny)
        steps = int(run(p)["steps"])
        costs.append(best_time(lambda: jax.block_until_ready(run(p)), 10) / steps * 1e6)
    per_cell, fixed = np.polyfit(STEP_COST_CELLS, costs, 1)
    return costs, fixed, per_cell


def jax_collagen(rtol, method="ros34pw2"):
    options = jt.SolverOptions(rtol=rtol, atol=rtol * 1e-3, method=method)
    return lambda p: jt.simulate(same_equations(p), t_end_s=T, grid=jt.Grid(ny=NY), options=options).collagen_mg_per_g[-1]


def thomas_solve_seconds(repeats=1000):
    """A step's O2 solve alone: the Thomas factor of a 200-row tridiagonal system and
    the 4 stage solves with it, `repeats` times in one jitted loop (seconds each)."""
    from jaxtissue.numerics import thomas_factor, thomas_solve

    rng = np.random.default_rng(0)
    sub, sup = (jnp.asarray(-rng.random((1, NY))) for _ in range(2))
    diag, r0 = jnp.asarray(3.0 + rng.random((1, NY))), jnp.asarray(rng.random((1, NY)))

    def step(_, r):
        factor = thomas_factor(sub, diag, sup)
        for _ in range(4):
            r = thomas_solve(factor, r) + r0
        return 0.5 * r

    loop = jax.jit(lambda r: jax.lax.fori_loop(0, repeats, step, r))
    jax.block_until_ready(loop(r0))
    return best_time(lambda: jax.block_until_ready(loop(r0)), 3) / repeats


def scipy_values(rtol, **changes):
    series = scipy_reference.values_at(SAVE_TIMES, ny=NY, rtol=rtol, atol=rtol * 1e-3, **changes)
    return {k: v[-1] for k, v in series.items()}


def scipy_fd_gradient(rtol, rel_step=1e-4):
    base = jt.paper_parameters()
    grad = {}
    for name in KINETIC:
        v = getattr(base, name)
        h = rel_step * abs(v)
        up = scipy_values(rtol, **{name: v + h})["collagen_mg_per_g"]
        down = scipy_values(rtol, **{name: v - h})["collagen_mg_per_g"]
        grad[name] = (up - down) / (2 * h)
    return grad


def grad_err(grad, ref):
    return max(abs(grad[k] - ref[k]) / abs(ref[k]) for k in KINETIC)


def main():
    p = jax.tree_util.tree_map(jnp.asarray, jt.paper_parameters())
    print(f"static culture, nx = 1, ny = {NY}, t = 3 weeks")
    reference = {k: float(v) for k, v in scipy_values(1e-11).items()}
    print("reference (SciPy, rtol 1e-11):", {k: round(v, 6) for k, v in reference.items()})

    # ---- compile time (default tolerance)
    compile_s = {}
    for method in METHODS:
        run = jax_forward(1e-5, method=method)
        t0 = time.perf_counter()
        jax.block_until_ready(run(p))
        compile_s[method] = time.perf_counter() - t0 - best_time(lambda: jax.block_until_ready(run(p)), 3)

    # ---- forward: work-precision ladders of both, then the fastest run at each target
    jax_runs, sp_runs = {m: [] for m in METHODS}, []
    for rtol in LADDER:
        for method in METHODS:
            run = jax_forward(rtol, method=method)
            values = {k: float(v) for k, v in run(p).items()}
            jax_runs[method].append((rel_err(values, reference), best_time(lambda: jax.block_until_ready(run(p)), 10), rtol,
                                     int(values["steps"])))
        sp_runs.append((rel_err(scipy_values(rtol), reference), best_time(lambda: scipy_values(rtol), 3), rtol))
    print("\nwork-precision (max rel. error of the 3-week values, best time)")
    print(f"{'':8} | {'jaxtissue, ros34pw2 (default)':^37} | {'jaxtissue, rodas4p2':^37} | {'SciPy BDF':^22}")
    print(f"{'rtol':>8} | {'err':>8} {'ms':>8} {'steps':>6} {'us/step':>8} | {'err':>8} {'ms':>8} {'steps':>6} {'us/step':>8}"
          f" | {'err':>8} {'ms':>8}")
    for i, (se, st, r) in enumerate(sp_runs):
        cells = [f"{e:8.1e} {t * 1e3:8.2f} {n:6d} {t / n * 1e6:8.1f}" for e, t, _, n in (jax_runs[m][i] for m in METHODS)]
        print(f"{r:8.0e} | " + " | ".join(cells) + f" | {se:8.1e} {st * 1e3:8.2f}")
    print(f"of a step: the O2 solve's Thomas factor and 4 solves alone {thomas_solve_seconds() * 1e6:.1f} us")
    costs, fixed, per_cell = step_cost_by_cells(p)
    print(f"us a step (ros34pw2) at rtol {STEP_COST_RTOL:g} on {', '.join(map(str, STEP_COST_CELLS))} cells: "
          + ", ".join(f"{c:.1f}" for c in costs) + f"; fitted {fixed:.1f} us + {per_cell:.3f} us per cell")
    print("\nfastest run reaching each accuracy target")
    for target in TARGETS:
        t_sp = min((t for e, t, _ in sp_runs if e <= target), default=float("nan"))
        best = {m: min(((t, r) for e, t, r, _ in jax_runs[m] if e <= target), default=(float("nan"), None)) for m in METHODS}
        (t_jax, r_jax), method = min((best[m], m) for m in METHODS if best[m][1] is not None)
        default = best["ros34pw2"][0]
        print(f"target {target:6.0e}: jaxtissue {t_jax * 1e3:7.2f} ms ({method}, rtol {r_jax:g}), SciPy {t_sp * 1e3:7.2f} ms, "
              f"speed-up {t_sp / t_jax:5.1f}x   (goal >= 15x; ros34pw2 alone {t_sp / default:5.1f}x)")
    print("compile time of the jitted forward run: " + ", ".join(f"{m} {s:.1f} s" for m, s in compile_s.items()) + "   (goal < 15 s)")

    # ---- gradient at matched accuracy
    g_ref = jax.grad(jax_collagen(1e-10))(p)  # checked against FD in tests/test_gradients.py
    grad_ref = {n: float(getattr(g_ref, n)) for n in KINETIC}
    grads = {}  # method: (rtol, error, seconds, compile seconds) of the loosest rtol within GRAD_TARGET
    for method in METHODS:
        for rtol in LADDER[1:]:
            g = jax.jit(jax.grad(jax_collagen(rtol, method)))
            t0 = time.perf_counter()
            first = jax.block_until_ready(g(p))
            compile_grad = time.perf_counter() - t0
            gval = {n: float(getattr(first, n)) for n in KINETIC}
            if grad_err(gval, grad_ref) <= GRAD_TARGET:
                break
        grads[method] = (rtol, grad_err(gval, grad_ref), best_time(lambda: jax.block_until_ready(g(p)), 10), compile_grad)
    for fd_rtol in LADDER:
        if fd_rtol > 1e-5:
            continue  # FD of an adaptive solve needs tolerances well below its step
        fd = scipy_fd_gradient(fd_rtol)
        if grad_err(fd, grad_ref) <= GRAD_TARGET:
            break
    t_fd = best_time(lambda: scipy_fd_gradient(fd_rtol), 1)
    print(f"\ngradient of 3-week collagen w.r.t. {len(KINETIC)} kinetic parameters")
    for method, (rtol, err, t_grad, compile_grad) in grads.items():
        print(f"gradient  jaxtissue reverse mode, {method} (rtol {rtol:g}, err {err:.1e}): {t_grad * 1e3:8.1f} ms"
              f"   (first call, compiling: {compile_grad:.1f} s)")
    print(f"gradient  SciPy central FD, {2 * len(KINETIC)} solves (rtol {fd_rtol:g}, err {grad_err(fd, grad_ref):.1e}): {t_fd * 1e3:8.1f} ms")
    t_grad, method = min((g[2], m) for m, g in grads.items())
    print(f"gradient speed-up: {t_fd / t_grad:.1f}x ({method})   (goal >= 20x)")


if __name__ == "__main__":
    main()
