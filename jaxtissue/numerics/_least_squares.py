"""Bounded nonlinear least squares: Levenberg–Marquardt in a box, as an optimistix
solver (`optx.least_squares(fn, LevenbergMarquardt(...), y0, args)`; docs/numerics.md).

optimistix's own LM has no bounds and linearises the model anew at every trial point;
this one keeps an active set on the bounds and refreshes its exact Jacobian only when
needed (Broyden updates in between): for fits whose model evaluations are expensive.
"""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
import optimistix as optx


class _LMState(eqx.Module):
    residual: jax.Array  # r at y
    jac: jax.Array  # ∂r/∂y at y: exact (`exact`) or Broyden-updated
    exact: jax.Array
    absorbed: jax.Array  # jac has absorbed a rejected step since it was last exact or moved
    stale: jax.Array  # the next step starts by recomputing the exact Jacobian at y
    damping: jax.Array  # λ
    nu: jax.Array
    terminate: jax.Array
    result: optx.RESULTS
    steps: jax.Array
    jacobians: jax.Array  # exact Jacobians computed (each also gives the residuals)


class LevenbergMarquardt(optx.AbstractLeastSquaresSolver):
    """Levenberg–Marquardt in a box lower ≤ y ≤ upper, with exact forward-mode Jacobians
    refreshed only when needed and Broyden's rank-one update in between (an
    `optimistix` least-squares solver: `optx.least_squares(fn, solver, y0, args)`).

    * **Step.** δ minimises ‖r + J δ‖² + λ‖δ‖² with an active set held: coordinates on a
      bound that the gradient Jᵀr pushes outwards stay there; coordinates the step would
      carry out of the box are held on the bound they cross and the others re-solved,
      until the step stays inside. An optimum on a bound is then reached as an interior
      one (a map to unbounded coordinates flattens χ² at the bound, where Gauss–Newton
      converges to it linearly).
    * **Damping** (Nielsen's rule; Madsen, Nielsen & Tingleff 2004, §3.2): with gain
      ratio ρ = actual / predicted reduction of χ², a step with ρ > 10⁻³ is accepted and
      λ ← λ·max(1/3, 1 − (2ρ − 1)³); a rejected one sets λ ← νλ, ν ← 2ν.
    * **Jacobian.** Each step evaluates the residuals once, at the trial point. After an
      accepted step J takes Broyden's update J + (Δr − J δ) δᵀ/δᵀδ, exact along δ (one
      evaluation instead of a forward-mode Jacobian, which costs about three for the
      Engelmayr problem's five parameters; Transtrum & Sethna 2012). After a rejected
      step with an updated J, the first absorbs the secant of the rejected step and
      raises λ; a second recomputes the exact J at y, keeping λ. A trial point where
      the model fails (non-finite residuals) only raises λ.
    * **Stopping**, judged only on a step made with an exact J (an updated one is first
      refreshed): the step is small in y and in r (`rtol`, `atol`, per component), or
      (as SciPy's `ftol`) it lowered χ² by < `ftol` χ² and by at least a quarter of the
      prediction; or a rejected step's successor, at the raised λ, moves y by less than
      the tolerance (MINPACK's xtol rule: no progress is left at this resolution). A
      converged solve returns the point of that exact J (its final step is below the
      tolerance), so the state's `jac` and `residual` are exact there.
    * With `cap_steps`, `args[-1]` caps the steps below `max_steps` (a dynamic limit, so
      that one compiled solve serves several; reaching it ends the solve as not
      converged). `record(chi2)` is called on the host with χ² of every evaluation.

    Under `vmap` the refresh's `lax.cond` runs both branches (a Jacobian every step)."""

    rtol: float
    atol: float
    ftol: float
    lower: jax.Array
    upper: jax.Array
    cap_steps: bool = eqx.field(static=True, default=False)
    record: object = eqx.field(static=True, default=None)
    low_cutoff: float = 1e-3
    norm = staticmethod(optx.max_norm)

    def __init__(self, rtol, atol, ftol, lower=-jnp.inf, upper=jnp.inf, cap_steps=False, record=None):
        self.rtol, self.atol, self.ftol = rtol, atol, ftol
        self.lower, self.upper = jnp.asarray(lower, float), jnp.asarray(upper, float)
        self.cap_steps, self.record = cap_steps, record

    @staticmethod
    def _linearise(fn, y, args):
        def twice(v):
            r = fn(v, args)[0]
            return r, r

        jac, r = jax.jacfwd(twice, has_aux=True)(y)
        return r, jac

    def _step(self, y, jac, r, damping):
        """The damped step from y inside the box (class docstring)."""
        n = y.shape[0]
        lower, upper = jnp.broadcast_to(self.lower, y.shape), jnp.broadcast_to(self.upper, y.shape)
        grad = jac.T @ r
        damped = jnp.sqrt(damping) * jnp.eye(n, dtype=y.dtype)

        def solve(held, fixed):  # δ with δ[held] = fixed[held]
            rhs = jnp.concatenate([-(r + jac @ jnp.where(held, fixed, 0.0)), jnp.zeros(n, y.dtype)])
            free = jnp.linalg.lstsq(jnp.concatenate([jnp.where(held, 0.0, jac), damped]), rhs)[0]
            return jnp.where(held, fixed, free)

        held = ((y <= lower) & (grad > 0)) | ((y >= upper) & (grad < 0))
        fixed = jnp.zeros_like(y)
        for _ in range(n):  # each pass holds at least one more coordinate, or changes nothing
            delta = solve(held, fixed)
            out = ~held & ((y + delta < lower) | (y + delta > upper))
            fixed = jnp.where(out, jnp.clip(y + delta, lower, upper) - y, fixed)
            held = held | out
        return jnp.clip(y + solve(held, fixed), lower, upper) - y

    def init(self, fn, y, args, options, f_struct, aux_struct, tags):
        m, false = f_struct.shape[0], jnp.array(False)
        return _LMState(jnp.zeros(m, y.dtype), jnp.zeros((m,) + y.shape, y.dtype), false, false, jnp.array(True),
                        jnp.array(1.0), jnp.array(2.0), false, optx.RESULTS.successful, jnp.array(0), jnp.array(0))

    def step(self, fn, y, args, options, state, tags):
        # an exact Jacobian (and residuals) at y where the previous step asked for one:
        # the start, and refreshes (the model's Jacobian appears once in the program)
        def exact_at_y():
            r, jac = self._linearise(fn, y, args)
            if self.record is not None:
                jax.debug.callback(self.record, jnp.sum(r**2))
            return r, jac

        r, jac = jax.lax.cond(state.stale, exact_at_y, lambda: (state.residual, state.jac))
        exact = state.exact | state.stale
        delta = self._step(y, jac, r, state.damping)
        y_trial = y + delta
        r_trial, aux = fn(y_trial, args)
        chi2, chi2_trial = jnp.sum(r**2), jnp.sum(r_trial**2)
        if self.record is not None:
            jax.debug.callback(self.record, chi2_trial)
        linear = jac @ delta  # the change of r that J predicts
        predicted = chi2 - jnp.sum((r + linear) ** 2)
        actual = chi2 - chi2_trial
        rho = jnp.where(predicted > 0, actual / jnp.where(predicted > 0, predicted, 1.0), 0.0)
        finite = jnp.isfinite(chi2_trial)  # not where the model failed
        accept = (rho > self.low_cutoff) & finite

        raised = state.damping * state.nu
        small = (self.norm(delta / (self.atol + self.rtol * jnp.abs(y_trial))) < 1) & (
            self.norm((r_trial - r) / (self.atol + self.rtol * jnp.abs(r_trial))) < 1)
        flat = (actual <= self.ftol * chi2_trial) & (actual >= 0.25 * predicted)
        converged = accept & (small | flat)
        stalled = ~accept & (self.norm(self._step(y, jac, r, raised) / (self.atol + self.rtol * jnp.abs(y))) < 1)
        done = exact & (converged | stalled)

        # the next y, its residuals and Jacobian: Broyden-updated along δ, or exact (kept,
        # or recomputed at the start of the next step)
        secant = jac + jnp.outer(r_trial - r - linear, delta) / jnp.maximum(delta @ delta, jnp.finfo(y.dtype).tiny)
        absorb = ~accept & finite & ~exact & ~state.absorbed
        refresh = ~done & ((converged & ~exact) | (~accept & finite & ~exact & state.absorbed))
        damping = jnp.where(accept, state.damping * jnp.maximum(1 / 3, 1 - (2 * rho - 1) ** 3),
                            jnp.where(refresh, state.damping, raised))
        nu = jnp.where(accept, 2.0, jnp.where(refresh, state.nu, 2 * state.nu))

        steps = state.steps + 1
        terminate, result = done, optx.RESULTS.successful
        if self.cap_steps:
            capped = ~terminate & (steps >= args[-1])
            terminate = terminate | capped
            result = optx.RESULTS.where(capped, optx.RESULTS.max_steps_reached, result)
        # a converged solve stays where its Jacobian is exact (the step from there is below
        # the tolerance): its residuals and Jacobian are then those of the returned point
        move = accept & ~done
        new = _LMState(jnp.where(move, r_trial, r), jnp.where(move | absorb, secant, jac), ~move & exact, absorb,
                       refresh, damping, nu, terminate, result, steps, state.jacobians + state.stale.astype(int))
        return jnp.where(move, y_trial, y), new, aux

    def terminate(self, fn, y, args, options, state, tags):
        return state.terminate, state.result

    def postprocess(self, fn, y, aux, args, options, state, tags, result):
        return y, aux, dict(residual_evaluations=state.steps, jacobian_evaluations=state.jacobians)
