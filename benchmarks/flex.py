"""The full flex run (1 Hz, 5 mm, 2.0e6 s) on the default grids: jaxtissue versus the
same coupled scheme with SciPy for the growth solves, in one run.

Reports: compile time in JAX's stages (tracing, lowering, XLA) and the programs' sizes
(HLO instructions; fusions after XLA's passes); forward wall time split into beam
cycles and growth; the gradient of 3-week collagen with respect to all parameters and
the protocol (time and peak memory relative to the forward run, from XLA's memory
analysis), keeping every coupling interval's state or, nested, ~√n of them (in float64
or float32); the compile time of an interval's two pieces' gradients on their own, and
of the growth piece's with a hand-written discrete adjoint (`stepwise_adjoint`); and the SciPy
baseline — per growth interval the same jitted beam cycle, the same lumped dispersion,
then `solve_ivp(BDF)` with the 2-D Jacobian's sparsity pattern (a NumPy right-hand
side written from docs/model.md, as a user would).

    python benchmarks/flex.py [--quick] [--xla-defaults]
      (--quick: 1/10 of the culture time; --xla-defaults: XLA's default CPU emitters instead
      of the command line's `jaxtissue.cache.use_fast_compilation`)
"""

from __future__ import annotations

import pathlib
import sys
import time

from jaxtissue.cache import collect_less, use_fast_compilation

FAST = "--xla-defaults" not in sys.argv and use_fast_compilation()  # as the command line, before JAX starts

import jax  # noqa: E402
import jax.flatten_util  # noqa: E402
import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402
import scipy.integrate  # noqa: E402
import scipy.sparse  # noqa: E402

sys.path.insert(0, str(pathlib.Path(__file__).resolve().parents[1] / "tests"))  # the SciPy reference
import scipy_reference  # noqa: E402

import optimistix as optx  # noqa: E402

import jaxtissue as jt  # noqa: E402
from jaxtissue.beam import Beam, BeamGrid, loading_cycle  # noqa: E402
from jaxtissue.coupling import lumped_transport  # noqa: E402
from jaxtissue.growth import GrowthModel, has_cell_transport  # noqa: E402
from jaxtissue.params import nondimensionalise  # noqa: E402
from jaxtissue.protocol import interval_bounds  # noqa: E402
from jaxtissue.simulate import default_o2_sweeps, flex_cycle, growth_solve  # noqa: E402

collect_less()  # Python's cycle collector as the command line sets it, after the imports

T_END = 2.0e6
GRID = jt.Grid(nx=50, ny=40)
BEAM = BeamGrid()
PROTOCOL = jt.Protocol.flex()


class ScipyGrowth2D:
    """The 2-D growth system with a frozen dispersivity, NumPy + solve_ivp(BDF)."""

    def __init__(self, params: jt.Params, grid: jt.Grid):
        self.p = {k: float(v) for k, v in params.as_dict().items()}
        self.nx, self.ny = grid.nx, grid.ny
        self.dx = self.p["length_mm"] / 10 / self.nx
        self.dy = self.p["thickness_mm"] / 10 / self.ny
        self.k_p = scipy_reference.derived_k_p(self.p)
        n = self.nx * self.ny
        # unknowns ordered (species, x, y); pattern: 5-point in o, pointwise couplings
        lap = scipy.sparse.kronsum(
            scipy.sparse.diags([1.0, 1.0, 1.0], [-1, 0, 1], shape=(self.ny, self.ny)),
            scipy.sparse.diags([1.0, 1.0, 1.0], [-1, 0, 1], shape=(self.nx, self.nx)),
        )
        eye = scipy.sparse.identity(n)
        self.pattern = scipy.sparse.bmat([[lap, eye, lap], [eye, eye, None], [eye, eye, eye]]).tocsc()

    def rhs(self, t, u, disp):
        p, nx, ny, dx, dy = self.p, self.nx, self.ny, self.dx, self.dy
        o, c, m = u.reshape(3, nx, ny)
        k, psi = p["kappa"], p["psi"]
        D = p["D_o0"] * (9 * k * m - 6 * m * (1 - m) * (k - 1) + 2 * (1 - m) * k * psi) / (
            9 * m + 3 * m * (1 - m) * (k - 1) + (2 + m) * k * psi
        ) + disp
        hm = lambda a, b: 2 * a * b / (a + b)  # noqa: E731
        fx = np.zeros((nx + 1, ny))
        fx[1:-1] = hm(D[1:], D[:-1]) * (o[1:] - o[:-1]) / dx
        fy = np.empty((nx, ny + 1))
        fy[:, 1:-1] = hm(D[:, 1:], D[:, :-1]) * (o[:, 1:] - o[:, :-1]) / dy
        fy[:, 0] = D[:, 0] * (o[:, 0] - p["o_ext"]) / (dy / 2)
        fy[:, -1] = D[:, -1] * (p["o_ext"] - o[:, -1]) / (dy / 2)
        op = np.maximum(o, 0)
        do = (fx[1:] - fx[:-1]) / dx + (fy[:, 1:] - fy[:, :-1]) / dy - p["Q_o"] * c * op / (p["o_h"] + op)
        dc = (self.k_p * scipy_reference.moser_aiba(o, p) - p["k_a"]) * c * (p["c_max"] - c)
        dm = p["k_m0"] * np.maximum(o - p["o_m"], 0) * c * (1 - m)
        return np.concatenate([do.ravel(), dc.ravel(), dm.ravel()])

    def solve(self, u0, t0, t1, disp, rtol=1e-5):
        sol = scipy.integrate.solve_ivp(
            self.rhs, (t0, t1), u0, method="BDF", rtol=rtol, atol=rtol * 1e-3,
            jac_sparsity=self.pattern, args=(disp,),
        )
        return sol.y[:, -1]


class DenseNewtonBeam(Beam):
    """The same beam solved by optimistix's Newton (Jacobian by dense forward mode)."""

    def equilibrium(self, u, z0, a=None, b=None):
        sol = optx.root_find(self.residual, optx.Newton(rtol=1e-10, atol=1e-10), z0, args=(u, a, b),
                             max_steps=20, throw=False)
        return sol.value, sol.result == optx.RESULTS.successful


def timed(fn, *args, repeat=1):
    """(output, seconds) of `fn(*args)`, the fastest of `repeat` runs."""
    best = None
    for _ in range(repeat):
        t0 = time.perf_counter()
        out = jax.block_until_ready(fn(*args))
        seconds = time.perf_counter() - t0
        best = seconds if best is None else min(best, seconds)
    return out, best


def staged(fn, *args):
    """`fn` (jitted) compiled for `args` in JAX's stages: (compiled, seconds of tracing,
    lowering and XLA's compilation, (HLO instructions before XLA's passes, fusions after
    them: XLA's CPU compile time grows with the kernels it generates, one per fusion))."""
    t0 = time.perf_counter()
    traced = fn.trace(*args)
    t1 = time.perf_counter()
    lowered = traced.lower()
    t2 = time.perf_counter()
    compiled = lowered.compile()
    t3 = time.perf_counter()
    instructions = sum(" = " in line for line in lowered.as_text(dialect="hlo").splitlines())
    fusions = sum(" fusion(" in line for line in compiled.as_text().splitlines())
    return compiled, (t1 - t0, t2 - t1, t3 - t2), (instructions, fusions)


def program_size(size) -> str:
    return f"{size[0]} HLO instructions, {size[1]} fusions"


def stages(seconds) -> str:
    trace, lower, xla = seconds
    return f"{trace + lower + xla:.1f} s: tracing {trace:.1f}, lowering {lower:.1f}, XLA {xla:.1f}"


def stepwise_adjoint(model: GrowthModel, y0, span, options, args, max_steps=64):
    """The state `growth_solve` reaches from y0 after `span` seconds (the same solver,
    controller and steps), with a hand-written discrete adjoint instead of diffrax's
    checkpointed one: the forward solve records its step times (at most `max_steps`);
    the reverse pass replays the steps from y0, keeping every state, then takes each
    step's VJP in reverse order."""
    import diffrax

    from jaxtissue.numerics import SOLVERS, Rescaled, Stacked, stack

    solver, treedef = SOLVERS[options.method](), jax.tree_util.tree_structure(y0)

    def term(m):
        return diffrax.ODETerm(Rescaled(Stacked(m, treedef), span))

    def step(m, u, a, t0, t1):
        return solver.step(term(m), t0, t1, u, a, solver.init(term(m), t0, t1, u, a), False)[0]

    def solve(m, u0, a):
        saveat = diffrax.SaveAt(subs=[diffrax.SubSaveAt(t1=True), diffrax.SubSaveAt(steps=True, fn=lambda t, y, a: jnp.zeros(()))])
        sol = diffrax.diffeqsolve(term(m), solver, 0.0, 1.0, None, u0, a, saveat=saveat, max_steps=max_steps,
                                  stepsize_controller=options.controller(span), throw=False)
        ends = sol.ts[1]
        return sol.ys[0][-1], (jnp.concatenate([jnp.zeros(1), ends[:-1]]), ends, sol.stats["num_accepted_steps"])

    @jax.custom_vjp
    def run(m, u0, a):
        return solve(m, u0, a)[0]

    def run_fwd(m, u0, a):
        u1, steps = solve(m, u0, a)
        return u1, (m, u0, a, steps)

    def run_bwd(res, ct):
        m, u0, a, (starts, ends, n) = res
        def replay(u, k):
            return jax.lax.cond(k < n, lambda u: step(m, u, a, starts[k], ends[k]), lambda u: u, u), u
        _, us = jax.lax.scan(replay, u0, jnp.arange(max_steps))

        def back(acc, k):
            def vjp(ct_u, ct_ma):
                d_m, d_u, d_a = jax.vjp(lambda m, u, a: step(m, u, a, starts[k], ends[k]), m, us[k], a)[1](ct_u)
                return d_u, jax.tree_util.tree_map(jnp.add, ct_ma, (d_m, d_a))
            return jax.lax.cond(k < n, vjp, lambda *acc: acc, *acc), None

        zero = jax.tree_util.tree_map(jnp.zeros_like, (m, a))
        (ct_u0, (ct_m, ct_a)), _ = jax.lax.scan(back, (ct, zero), jnp.arange(max_steps), reverse=True)
        return ct_m, ct_u0, ct_a

    run.defvjp(run_fwd, run_bwd)
    return Stacked(model, treedef).unstack(run(model, stack(y0), args))


def piece_compiles(params, protocol, y):
    """(seconds of tracing and lowering, of XLA, program size) for the gradient of one
    loading cycle's lumped transport and of one coupling interval's growth solve, each
    on its own (what the gradient of the whole run compiles at least once), and of the
    growth interval with a hand-written discrete adjoint (`stepwise_adjoint`), whose
    gradient differs from diffrax's by the last value returned (max, relative)."""
    options = jt.SolverOptions(o2_sweeps=default_o2_sweeps(GRID, params))

    def lumped(p, q, y):
        return lumped_transport(flex_cycle(y, p, q, GRID, BEAM)[1], p, GRID, BEAM, "dispersive", "centroid")

    def transport(p, q, y):
        return sum(jnp.sum(leaf) for leaf in jax.tree_util.tree_leaves(lumped(p, q, y)))

    def model(p, t):
        return GrowthModel(coeffs=nondimensionalise(p), grid=GRID, transport=t, cell_transport=has_cell_transport(params),
                           o2_sweeps=options.o2_sweeps)

    def growth(p, y, t):
        return jnp.sum(growth_solve(model(p, t), y, 0.0, 2.0e4, None, options, (p, GRID), checkpoints=8).ys.m)

    def growth_stepwise(p, y, t):
        return jnp.sum(stepwise_adjoint(model(p, t), y, 2.0e4, options, (p, GRID)).m)

    t = lumped(params, protocol, y)
    out, grads = {}, {}
    for name, fn, args in (("one loading cycle", transport, (params, protocol, y)), ("one growth interval", growth, (params, y, t)),
                           ("one growth interval with a hand-written adjoint", growth_stepwise, (params, y, t))):
        compiled, (trace, lower, xla), size = staged(jax.jit(jax.grad(fn, argnums=(0, 1, 2))), *args)
        out[name] = (trace + lower, xla, size)
        grads[name] = jax.flatten_util.ravel_pytree(compiled(*args))[0]
    diffrax_grad, own = grads["one growth interval"], grads["one growth interval with a hand-written adjoint"]
    return out, float(jnp.max(jnp.abs(own - diffrax_grad)) / jnp.max(jnp.abs(diffrax_grad)))


def main(quick=False):
    t_end = T_END / 10 if quick else T_END
    params = jax.tree_util.tree_map(jnp.asarray, jt.paper_parameters())
    protocol = jax.tree_util.tree_map(jnp.asarray, PROTOCOL)
    bounds = interval_bounds(t_end, 2.0e4)  # as jaxtissue's: every 2e4 s, 3 weeks, the end
    n_intervals = len(bounds) - 1
    print(f"flex 1 Hz / 5 mm, t_end = {t_end:g} s ({n_intervals} growth intervals), growth grid "
          f"{GRID.nx} x {GRID.ny}, beam {BEAM.n_segments} segments x {BEAM.steps_per_cycle} steps per cycle; XLA's "
          + ("classic CPU fusion emitter (the command line's setting)" if FAST else "default CPU emitters"))

    forward, fwd_stages, fwd_size = staged(jax.jit(lambda p, q: jt.simulate(p, q, t_end_s=t_end, grid=GRID, beam=BEAM)), params, protocol)
    timed(forward, params, protocol)
    result, t_fwd = timed(forward, params, protocol, repeat=3)
    print(f"\nforward: {t_fwd:.1f} s after compilation; compile {stages(fwd_stages)} (goal <= 4 s); {program_size(fwd_size)}")

    # one coupling step's beam work: the cycle and its lumped dispersion on the growth grid
    transport_of = jax.jit(lambda y, p, q: lumped_transport(flex_cycle(y, p, q, GRID, BEAM)[1], p, GRID, BEAM, "dispersive", "centroid").dispersion)
    timed(transport_of, result.final, params, protocol)
    _, t_cycle = timed(transport_of, result.final, params, protocol, repeat=10)
    t_beam = t_cycle * (n_intervals + 1)
    print(f"  beam cycles: {n_intervals + 1} x {t_cycle * 1e3:.0f} ms = {t_beam:.1f} s; growth solves: {t_fwd - t_beam:.1f} s "
          f"({int(result.num_steps)} steps)")

    def dense_cycle(y, p, q):
        b = flex_cycle(y, p, q, GRID, BEAM)[0]
        b = DenseNewtonBeam(b.geometry, b.material, b.grid, b.fibre_law)
        cycle = loading_cycle(b, q.period_s, q.post_displacement_mm * 1e-3, q.hold_fraction)
        return lumped_transport(cycle, p, GRID, BEAM, "dispersive", "centroid").dispersion

    dense = jax.jit(dense_cycle)
    timed(dense, result.final, params, protocol)
    _, t_dense = timed(dense, result.final, params, protocol, repeat=3)
    print(f"  one beam cycle: structured Newton {t_cycle * 1e3:.0f} ms vs optimistix Newton (dense forward-mode "
          f"Jacobian, LU) {t_dense * 1e3:.0f} ms = {t_dense / t_cycle:.1f}x")

    def collagen(p, q, options=jt.SolverOptions()):
        r = jt.simulate(p, q, t_end_s=t_end, grid=GRID, beam=BEAM, options=options)
        return r.collagen_mg_per_g[r.index(jt.THREE_WEEKS_S)] if t_end >= jt.THREE_WEEKS_S else r.collagen_mg_per_g[-1]

    def memory(compiled):
        analysis = compiled.memory_analysis()
        return analysis.temp_size_in_bytes + analysis.output_size_in_bytes + analysis.argument_size_in_bytes

    m_fwd = memory(forward)
    variants = (("every interval's state kept", jt.SolverOptions()),
                ("nest_intervals (~sqrt(n) states kept)", jt.SolverOptions(nest_intervals=True)),
                ("nest_intervals, kept in float32", jt.SolverOptions(nest_intervals=True, store_float32=True)))
    grads, compile_s, sizes, values = [], [], [], []
    for _, options in variants:
        compiled, seconds, size = staged(jax.jit(jax.grad(lambda p, q, o=options: collagen(p, q, o), argnums=(0, 1))), params, protocol)
        grads.append(compiled)
        compile_s.append(seconds)
        sizes.append(size)
        values.append(jax.flatten_util.ravel_pytree(timed(compiled, params, protocol)[0])[0])
    # forward and gradients timed in turn, best of three each: the ratios compare runs
    # made under the same machine load
    best = [np.inf] * (1 + len(grads))
    for _ in range(3):
        for i, fn in enumerate([forward, *grads]):
            best[i] = min(best[i], timed(fn, params, protocol)[1])
    t_fwd = best[0]
    print(f"gradient of 3-week collagen w.r.t. all {len(jt.paper_parameters().as_dict())} parameters and the protocol "
          f"(goals: < 5x forward time, < 3x forward memory; forward {t_fwd:.2f} s and {m_fwd / 2**20:.1f} MiB of XLA buffers):")
    for (label, _), grad, t_grad, seconds, size, g in zip(variants, grads, best[1:], compile_s, sizes, values):
        m_grad = memory(grad)
        differs = float(jnp.max(jnp.abs(g - values[0])) / jnp.max(jnp.abs(values[0])))
        print(f"  {label}: {t_grad:.1f} s = {t_grad / t_fwd:.1f}x forward, memory {m_grad / 2**20:.1f} MiB = "
              f"{m_grad / m_fwd:.1f}x; compile {stages(seconds)} (goal <= 10 s), {program_size(size)} = "
              f"{size[0] / fwd_size[0]:.1f}x and {size[1] / fwd_size[1]:.1f}x forward's; gradient differs from the first by {differs:.0e} (max, relative)")
    pieces, differs = piece_compiles(params, protocol, result.final)
    print("  the pieces' gradients compiled on their own (tracing + XLA): "
          + "; ".join(f"{name} {a + b:.1f} s ({a:.1f} + {b:.1f}; {size[1]} fusions)" for name, (a, b, size) in pieces.items())
          + f"; the two growth gradients differ by {differs:.0e} (max, relative)")

    # ---- SciPy growth solves in the same staggered scheme
    p_concrete = jt.paper_parameters()
    growth = ScipyGrowth2D(p_concrete, GRID)
    y = jt.State.initial(jt.params.nondimensionalise(p_concrete), GRID)
    transport_of(y, params, protocol).block_until_ready()  # compile outside the timing
    u = np.concatenate([np.asarray(y.o).ravel(), np.asarray(y.c).ravel(), np.asarray(y.m).ravel()])
    t_sp_beam = t_sp_growth = 0.0
    for t0, t1 in zip(bounds[:-1], bounds[1:]):
        o, c, m = (jnp.asarray(a.reshape(GRID.shape)) for a in np.split(u, 3))
        t_a = time.perf_counter()
        disp = np.asarray(transport_of(jt.State(o=o, c=c, m=m), params, protocol))
        t_b = time.perf_counter()
        u = growth.solve(u, t0, t1, disp)
        t_sp_growth += time.perf_counter() - t_b
        t_sp_beam += t_b - t_a
    coll_sp = 108.3 * u[2 * GRID.nx * GRID.ny:].mean()
    t_sp = t_sp_beam + t_sp_growth
    print(f"\nSciPy growth solves in the same scheme: {t_sp:.1f} s (beam {t_sp_beam:.1f} s, SciPy BDF {t_sp_growth:.1f} s)")
    print(f"final collagen: jaxtissue {float(result.collagen_mg_per_g[-1]):.5f} mg/g, SciPy scheme {coll_sp:.5f} mg/g")
    print(f"growth solves alone: SciPy BDF {t_sp_growth:.1f} s vs jaxtissue {t_fwd - t_beam:.1f} s = {t_sp_growth / (t_fwd - t_beam):.1f}x")
    print(f"coupled run speed-up over the SciPy scheme: {t_sp / t_fwd:.1f}x (goal >= 10x; both share the beam cycles)")


if __name__ == "__main__":
    main(quick="--quick" in sys.argv)
