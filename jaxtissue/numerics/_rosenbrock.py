"""Linearly implicit integrators for vector fields that factor their own Jacobian
approximation, as diffrax solvers (docs/numerics.md).

`ROS34PW2` (the default) is the Rosenbrock-W method of Rang & Angermann (2005): 4
stages, order 3 with an embedded order-2 solution for step control, L-stable and
stiffly accurate, and — being a W-method — of full order (as h → 0) for any
approximation of the Jacobian. `Rodas4P2` is the Rosenbrock method of Steinebach (2020):
6 stages, order 4 with an embedded order-3 solution, L-stable and stiffly accurate,
built to keep its order on parabolic problems; it is not a W-method, so it needs the
exact Jacobian (its order and error estimate collapse with an approximate one) and pays
off at tight tolerances (docs/numerics.md, "An order-4 stepper for static 1-D runs").

Their vector field is an `AbstractStructuredField`, which factors `I/(γh) − J̃` once per
step for some approximation J̃ of its Jacobian (structured: tridiagonal, line
relaxation; never dense); all stages solve with that factor. No nonlinear iterations:
the cost per step is fixed and reverse-mode differentiation runs straight through it.

diffrax supplies everything else: adaptive step control (`PIDController`, its steps
rounded by `ReproducibleSteps` so that checkpointed gradients retrace them), dense output
(cubic Hermite for ROS34PW2, Rodas4P2's own from its stages), saving, progress meters
and checkpointed adjoints. The vector field
must be autonomous (true of the growth model over one growth interval).
"""

from __future__ import annotations

from typing import ClassVar

import diffrax
import jax
import jax.numpy as jnp
import jax.tree_util as jtu
import numpy as np
from jaxtyping import PyTree

from ._structured import AbstractStructuredField


# Both methods in the transformed variables u_i = Σ_j γ_ij k_j (Hairer & Wanner IV.7),
# which need no products with J:  (I/(γh) − J̃) u_i = f(y0 + Σ_j a_ij u_j) + Σ_j c_ij u_j / h,
# y1 = y0 + Σ_i m_i u_i, the embedded solution with m̂_i.
#
# ROS34PW2 in the standard form (α_ij, γ_ij, b_i, b̂_i), transformed below:
_PW2_GAMMA = 4.3586652150845900e-01
_PW2_ALPHA = np.array(
    [
        [0.0, 0.0, 0.0, 0.0],
        [8.7173304301691801e-01, 0.0, 0.0, 0.0],
        [8.4457060015369423e-01, -1.1299064236484185e-01, 0.0, 0.0],
        [0.0, 0.0, 1.0, 0.0],
    ]
)
_PW2_GAMMA_MATRIX = np.array(
    [
        [_PW2_GAMMA, 0.0, 0.0, 0.0],
        [-8.7173304301691801e-01, _PW2_GAMMA, 0.0, 0.0],
        [-9.0338057013044082e-01, 5.4180672388095326e-02, _PW2_GAMMA, 0.0],
        [2.4212380706095346e-01, -1.2232505839045147e00, 5.4526025533510214e-01, _PW2_GAMMA],
    ]
)
_PW2_B = np.array([2.4212380706095346e-01, -1.2232505839045147e00, 1.5452602553351020e00, _PW2_GAMMA])
_PW2_B_EMBEDDED = np.array([3.7810903145819369e-01, -9.6042292212423178e-02, 0.5, 2.1793326075422950e-01])
_PW2_GINV = np.linalg.inv(_PW2_GAMMA_MATRIX)

# Rodas4P2, given in the transformed variables (a_ij, c_ij); stiffly accurate: y1 is
# stage 6's argument plus u_6, the embedded solution stage 6's argument (its error u_6).
_P2_A = np.array(
    [
        [0.0, 0.0, 0.0, 0.0, 0.0, 0.0],
        [3.0, 0.0, 0.0, 0.0, 0.0, 0.0],
        [0.906377755268814, -0.189707390391685, 0.0, 0.0, 0.0, 0.0],
        [3.758617027739064, 1.161741776019525, -0.849258085312803, 0.0, 0.0, 0.0],
        [7.089566927282776, 4.573591406461604, -8.423496976860259, -0.959280113459775, 0.0, 0.0],
        [7.089566927282776, 4.573591406461604, -8.423496976860259, -0.959280113459775, 1.0, 0.0],
    ]
)
_P2_C = np.array(
    [
        [0.0, 0.0, 0.0, 0.0, 0.0, 0.0],
        [-12.0, 0.0, 0.0, 0.0, 0.0, 0.0],
        [-6.354581592719008, 0.338972550544623, 0.0, 0.0, 0.0, 0.0],
        [-8.575016317114033, -7.606483992117508, 12.22499765012482, 0.0, 0.0, 0.0],
        [-5.888975457523102, -8.157396617841821, 24.805546872612922, 12.790401512796979, 0.0, 0.0],
        [-4.408651676063871, -6.692003137674639, 24.625568527593117, 16.627521966636085, -5.714285714285718, 0.0],
    ]
)
# its dense output (order 3) from the stages: y(θ) = (1 − θ) y0 + θ (y1 + (1 − θ)(d1 + θ d2)),
# d_k = Σ_j h_kj u_j
_P2_DENSE = np.array(
    [
        [-5.323528268423303, -10.042123754867493, 17.175254928256965, -5.079931171878093, -0.016185991706112, 0.0],
        [6.984505741529879, 6.914061169603662, -0.849178943070653, 18.104410789349338, -3.516963011559032, 0.0],
    ]
)


def _combine(coefs, stacked):
    """Σ_j coefs[j] * stacked[j] for a pytree whose leaves have a leading stage axis."""
    return jtu.tree_map(lambda x: jnp.tensordot(coefs, x, axes=1), stacked)


def _structured_field(terms) -> AbstractStructuredField:
    """The `AbstractStructuredField` inside diffrax's wrappers of an `ODETerm`."""
    is_field = lambda x: isinstance(x, AbstractStructuredField)  # noqa: E731
    fields = [x for x in jtu.tree_leaves(terms, is_leaf=is_field) if is_field(x)]
    if len(fields) != 1:
        raise TypeError("a Rosenbrock solver needs an ODETerm whose vector field is an AbstractStructuredField")
    return fields[0]


class _StageInterpolation(diffrax.AbstractLocalInterpolation):
    """A Rodas method's own dense output over a step [t0, t1]: y(θ) = (1 − θ) y0 +
    θ (y1 + (1 − θ)(d[0] + θ d[1])), θ = (t − t0)/(t1 − t0), d from the stages."""

    t0: jax.Array
    t1: jax.Array
    y0: PyTree
    y1: PyTree
    d: PyTree  # leaves with a leading axis of 2

    def evaluate(self, t0, t1=None, left=True):
        del left
        if t1 is not None:
            return jtu.tree_map(jnp.subtract, self.evaluate(t1), self.evaluate(t0))
        span = self.t1 - self.t0
        theta = jnp.where(span > 0, (t0 - self.t0) / jnp.where(span > 0, span, 1.0), 0.0)
        return jtu.tree_map(lambda y0, y1, d: (1 - theta) * y0 + theta * (y1 + (1 - theta) * (d[0] + theta * d[1])),
                            self.y0, self.y1, self.d)


class _Rosenbrock(diffrax.AbstractAdaptiveSolver):
    """A linearly implicit method of `stages` stages in the transformed variables
    (`gamma`, `a`, `c`, `m`, `m_embedded`; module docstring), its term's vector field an
    `AbstractStructuredField`; dense output by cubic Hermite interpolation, or, with
    `dense` (rows h_k), by `_StageInterpolation`. Use with `diffrax.PIDController`."""

    term_structure: ClassVar = diffrax.AbstractTerm
    interpolation_cls: ClassVar = diffrax.ThirdOrderHermitePolynomialInterpolation
    gamma: ClassVar[float]
    a: ClassVar[np.ndarray]
    c: ClassVar[np.ndarray]
    m: ClassVar[np.ndarray]
    m_embedded: ClassVar[np.ndarray]
    method_order: ClassVar[int]
    dense: ClassVar[np.ndarray | None] = None

    def order(self, terms):
        return self.method_order

    def error_order(self, terms):
        return self.method_order  # the embedded solution's local error is O(h^order)

    def init(self, terms, t0, t1, y0, args):
        # No state: carrying f(y1) into the next step (first same as last) saves one
        # right-hand side a step, but the checkpointed adjoint then stores it with every
        # checkpoint (default flex gradient: 8.5 → 9.8 MiB; nested float32 4.6 → 5.9 MiB).
        return None

    def func(self, terms, t0, y0, args):
        return terms.vf(t0, y0, args)

    def step(self, terms, t0, t1, y0, args, solver_state, made_jump):
        # Under `vmap` a finished trajectory keeps being stepped with h = 0 and the
        # result discarded; a safe h keeps 1/h out of it (else 0 · inf = NaN gradients).
        active = t1 > t0
        h = jnp.where(active, t1 - t0, 1.0)
        # The right-hand side is autonomous, and rematerialised in the reverse pass: its
        # intermediates (~60 fields per stage) would be most of a step's residuals.
        # (prevent_cse=False: the step runs inside loops, where CSE cannot merge the
        # recomputation away; the forward program stays as it was.)
        vf = jax.checkpoint(lambda y: terms.vf(t0, y, args), prevent_cse=False)
        # The field holds J̃ constant under differentiation (a W-method's: the gradient
        # then differs from that of the discrete map only at the level of the local
        # error) or, where J̃ is exact, differentiates it with the step. (f0 is not
        # taken from the linearisation the field makes for J̃: used as stage 0's
        # right-hand side that gave wrong checkpointed gradients.)
        factor = _structured_field(terms).shifted_factor(t0, y0, args, 1.0 / (self.gamma * h))

        a, c = jnp.asarray(self.a), jnp.asarray(self.c)
        stages = len(self.m)

        def stage(carry, i):
            # stage i: (I/(γh) − J̃) u_i = f(y0 + Σ_j a_ij u_j) + Σ_j c_ij u_j / h, j < i
            us, f0 = carry
            yi = jtu.tree_map(jnp.add, y0, _combine(a[i], us))
            memory = _combine(c[i], us)
            fi = vf(yi)
            ui = factor.solve(jtu.tree_map(lambda f, mm: f + mm / h, fi, memory))
            f0 = jtu.tree_map(lambda a, b: jnp.where(i == 0, a, b), fi, f0)
            return (jtu.tree_map(lambda x, u: x.at[i].set(u), us, ui), f0), None

        # all stages in one loop (stage 0: y_0 = y0, no memory terms, its f is f0):
        # one copy of the stage in the program, forward and reverse
        zeros = jtu.tree_map(jnp.zeros_like, y0)
        us0 = jtu.tree_map(lambda x: jnp.zeros((stages,) + x.shape, x.dtype), y0)
        (us, f0), _ = jax.lax.scan(stage, (us0, zeros), jnp.arange(stages))
        increment = jtu.tree_map(lambda x: jnp.where(active, x, 0.0), _combine(jnp.asarray(self.m), us))
        y1 = jtu.tree_map(jnp.add, y0, increment)
        y_error = jtu.tree_map(lambda a, b: jnp.where(active, a - b, 0.0), increment, _combine(jnp.asarray(self.m_embedded), us))
        if self.dense is None:  # cubic Hermite: f at both ends (one more right-hand side)
            k0 = jtu.tree_map(lambda f: (t1 - t0) * f, f0)
            k1 = jtu.tree_map(lambda f: (t1 - t0) * f, vf(y1))
            dense_info = dict(y0=y0, y1=y1, k0=k0, k1=k1)
        else:  # from the stages (`_StageInterpolation`)
            d = jtu.tree_map(lambda x: jnp.where(active, x, 0.0), _combine(jnp.asarray(self.dense), us))
            dense_info = dict(y0=y0, y1=y1, d=d)
        return y1, y_error, dense_info, None, diffrax.RESULTS.successful


class ROS34PW2(_Rosenbrock):
    """Rosenbrock-W method of order 3, 4 stages (module docstring): of full order for any
    J̃, the default."""

    gamma: ClassVar[float] = _PW2_GAMMA
    a: ClassVar[np.ndarray] = _PW2_ALPHA @ _PW2_GINV
    c: ClassVar[np.ndarray] = np.diag(np.diag(_PW2_GINV)) - _PW2_GINV
    m: ClassVar[np.ndarray] = _PW2_B @ _PW2_GINV
    m_embedded: ClassVar[np.ndarray] = _PW2_B_EMBEDDED @ _PW2_GINV
    method_order: ClassVar[int] = 3


class Rodas4P2(_Rosenbrock):
    """Rosenbrock method of order 4, 6 stages (module docstring): for a field whose J̃ is
    its exact Jacobian, at tight tolerances."""

    gamma: ClassVar[float] = 0.25
    a: ClassVar[np.ndarray] = _P2_A
    c: ClassVar[np.ndarray] = _P2_C
    m: ClassVar[np.ndarray] = _P2_A[-1] + np.eye(6)[-1]
    m_embedded: ClassVar[np.ndarray] = _P2_A[-1]
    method_order: ClassVar[int] = 4
    dense: ClassVar[np.ndarray] = _P2_DENSE
    interpolation_cls: ClassVar = _StageInterpolation


SOLVERS = {"ros34pw2": ROS34PW2, "rodas4p2": Rodas4P2}
"""The growth solve's methods by `SolverOptions.method`."""


def quantise(dt, bits=12):
    """dt rounded down to `bits` significant bits (relative change < 2^(1−bits))."""
    mantissa, exponent = jnp.frexp(dt)
    return jnp.ldexp(jnp.floor(jnp.ldexp(mantissa, bits)), exponent - bits)


class ReproducibleSteps(diffrax.AbstractAdaptiveStepSizeController):
    """A `diffrax.PIDController` whose step sizes are rounded down to 12 significant bits.

    The checkpointed adjoint recomputes steps from a few stored states inside the
    reverse pass, a program that XLA compiles differently: its error estimates differ
    from the forward pass's by round-off, and so would the raw step sizes, which then
    compound into a different time grid, so that the reverse pass differentiates steps
    the forward pass did not take. The error estimate is a difference of nearly equal
    stage combinations, so that round-off is far above 1 ulp: rounded to 24 bits, the
    steps of a static run saving its series (1 × 20 grid, rtol 1e-9, ~1560 steps) part,
    and the gradient of 3-week collagen w.r.t. k_m0 is 1.9e-3 off central differences
    (`tests/test_gradients.py`). Rounded to 12 bits they agree unless an
    error estimate sits within round-off of a rounding boundary; a vmapped batch then
    also equals the single runs to round-off. Each step is shortened by < 2.5e-4 of
    itself, far below what a tolerance decides.

    `dt0`: the first step, used when `diffeqsolve` is given `dt0=None` (diffeqsolve's
    own check of a given dt0 against traced t0, t1 is a host callback, which keeps a
    program out of JAX's persistent compilation cache); it may be traced.

    Its state is the inner controller's and the step it would take next: `next_step`
    of a solve's final state (`diffrax.SaveAt(controller_state=True)`) starts the next
    solve of a series of solves where the last one ended (a step shortened to end on
    t1 does not shrink it).
    """

    inner: diffrax.PIDController
    dt0: float | None = None

    @property
    def rtol(self):
        return self.inner.rtol

    @property
    def atol(self):
        return self.inner.atol

    @property
    def norm(self):
        return self.inner.norm

    def wrap(self, direction):
        return ReproducibleSteps(self.inner.wrap(direction), self.dt0)

    def init(self, terms, t0, t1, y0, dt0, args, func, error_order):
        dt0 = self.dt0 if dt0 is None else dt0
        t_next, state = self.inner.init(terms, t0, t1, y0, dt0, args, func, error_order)
        return t_next, (state, jax.lax.stop_gradient(t_next - t0))

    def adapt_step_size(self, t0, t1, y0, y1_candidate, args, y_error, error_order, controller_state):
        inner_state, proposed = controller_state
        keep, next_t0, next_t1, made_jump, state, result = self.inner.adapt_step_size(
            t0, t1, y0, y1_candidate, args, y_error, error_order, inner_state
        )
        dt = quantise(jax.lax.stop_gradient(next_t1 - next_t0))
        # an accepted step shorter than proposed was cut to end on t1: keep the proposal
        proposed = jnp.where(keep & (t1 - t0 < 0.999 * proposed), jnp.maximum(proposed, dt), dt)
        return keep, next_t0, next_t0 + dt, made_jump, (state, proposed), result

    @staticmethod
    def next_step(controller_state):
        """The step a solve that ended in `controller_state` would have taken next."""
        return controller_state[1]
