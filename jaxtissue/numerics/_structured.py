"""Vector fields that factor their own Jacobian approximation: the interface of the
Rosenbrock-W solver (`ROS34PW2`, docs/numerics.md), and the wrappers that rescale time
and stack a pytree state into one array. No diffrax here: a run loaded as a saved
program (`jaxtissue.cache`) needs these types without importing the solver.
"""

from __future__ import annotations

import abc

import equinox as eqx
import jax
import jax.numpy as jnp
import jax.tree_util as jtu


class AbstractStructuredField(eqx.Module):
    """A vector field `(t, y, args) -> dy` (the same pytree as y) that factors
    `a I − J̃` at y for an approximation J̃ of its Jacobian: `ROS34PW2`'s field."""

    @abc.abstractmethod
    def __call__(self, t, y, args):
        """dy/dt at (t, y)."""

    @abc.abstractmethod
    def shifted_factor(self, t, y, args, a):
        """`a I − J̃` at (t, y), factored: an object whose `solve(r)` returns u with
        (a I − J̃) u = r (r and u pytrees like y). Hold J̃ constant under
        differentiation (`jax.lax.stop_gradient`) where second derivatives are not
        wanted."""


class Rescaled(AbstractStructuredField):
    """An autonomous `field` in the time s = t / `scale`: dy/ds = scale · field(y).
    Integrated over s ∈ [0, 1] with scale = t1 − t0, diffrax's time bounds are
    constants even where t0 and t1 are traced, and its setup of each solve on t1 (t1
    stepped down 100 ulp, one `prevbefore` at a time: ~4 400 scalar operations) folds
    away at compile time instead of being compiled into the program."""

    field: AbstractStructuredField
    scale: jax.Array | float

    def __call__(self, t, y, args):
        return jtu.tree_map(lambda d: self.scale * d, self.field(t, y, args))

    def shifted_factor(self, t, y, args, a):
        # a I − scale·J̃ = scale (a/scale I − J̃)
        return _ScaledFactor(self.field.shifted_factor(t, y, args, a / self.scale), self.scale)


class Stacked(AbstractStructuredField):
    """A `field` on a pytree of equal-shape leaves (`treedef`), integrated as one array:
    the leaves stacked along a new leading axis (`stack`). diffrax's per-leaf work in
    each step (stage combinations, error norm, interpolation, saving) then runs once on
    one array instead of once per leaf: fewer of the small XLA kernels that set a 1-D
    step's cost (docs/numerics.md)."""

    field: AbstractStructuredField
    treedef: jtu.PyTreeDef = eqx.field(static=True)

    def unstack(self, y):
        """The pytree whose leaves are y's rows (y from `stack`)."""
        return _unstack(self.treedef, y)

    def __call__(self, t, y, args):
        return stack(self.field(t, self.unstack(y), args))

    def shifted_factor(self, t, y, args, a):
        return _StackedFactor(self.field.shifted_factor(t, self.unstack(y), args, a), self.treedef)


def stack(tree) -> jax.Array:
    """The leaves of `tree` (equal shapes) stacked along a new leading axis."""
    return jnp.stack(jtu.tree_leaves(tree))


def _unstack(treedef, y):
    return jtu.tree_unflatten(treedef, list(y))


class _StackedFactor(eqx.Module):
    factor: eqx.Module
    treedef: jtu.PyTreeDef = eqx.field(static=True)

    def solve(self, r):
        return stack(self.factor.solve(_unstack(self.treedef, r)))


class _ScaledFactor(eqx.Module):
    factor: eqx.Module
    scale: jax.Array | float

    def solve(self, r):
        return jtu.tree_map(lambda u: u / self.scale, self.factor.solve(r))
