"""Rematerialised loops: reverse-mode memory traded for recomputation."""

from __future__ import annotations

import functools
import math

import jax
import jax.numpy as jnp


def chunking(length: int) -> int:
    """The chunk length for `nested_checkpoint_scan`: a gradient stores one carry per
    chunk, one per step of the chunk being reversed, and a padded last chunk's steps as
    well; the chunk length up to 2√length that stores fewest (ties: the nearest √length),
    e.g. 10 for 100 steps, 8 for 101 (13 chunks, 3 padding steps)."""

    def stored(inner):
        outer = -(-length // inner)
        return outer + inner + outer * inner - length

    return min(range(1, 2 * math.isqrt(length) + 2), key=lambda inner: (stored(inner), abs(inner - math.sqrt(length))))


def nested_checkpoint_scan(step, init, length: int, keep: tuple[str, ...] = (), chunk_length: int | None = None):
    """`lax.scan(step, init, arange(length))` as chunks of ~√length steps (`chunking`,
    or `chunk_length`), each chunk rematerialised in the reverse pass: a gradient
    stores ~√length carries and one chunk's intermediates at a time, for one more
    forward pass. Where the chunks do not divide `length` the last is padded with steps
    that `lax.cond` skips (the step is compiled once). Values named in `keep`
    (`jax.ad_checkpoint.checkpoint_name`) are stored rather than recomputed."""
    inner = min(chunk_length or chunking(length), length)
    outer = -(-length // inner)
    policy = jax.checkpoint_policies.save_only_these_names(*keep) if keep else None
    body = step
    if outer * inner > length:
        index = jax.ShapeDtypeStruct((), jnp.arange(1).dtype)
        out = jax.eval_shape(step, init, index)[1]

        def skip(carry, k):
            return carry, jax.tree_util.tree_map(lambda s: jnp.zeros(s.shape, s.dtype), out)

        def body(carry, k):
            return jax.lax.cond(k < length, step, skip, carry, k)

    @functools.partial(jax.checkpoint, policy=policy)
    def chunk(carry, i):
        return jax.lax.scan(body, carry, i * inner + jnp.arange(inner))

    carry, hist = jax.lax.scan(chunk, init, jnp.arange(outer))
    return carry, jax.tree_util.tree_map(lambda h: h.reshape((outer * inner,) + h.shape[2:])[:length], hist)


def _is_float(x) -> bool:
    dtype = jnp.result_type(x) if not hasattr(x, "dtype") else x.dtype
    return dtype != jax.dtypes.float0 and jnp.issubdtype(dtype, jnp.floating)


def _tied(tree, ct):
    """`tree` made data-dependent on the cotangent `ct` (+ 0·ct): what is computed from
    it waits for `ct`. (An optimisation barrier on the two did not stop XLA's CPU
    scheduler from hoisting the recomputation, and its buffers, to the start.)"""
    tie = sum(jnp.ravel(c)[0] for c in jax.tree_util.tree_leaves(ct) if _is_float(c) and jnp.size(c))
    return jax.tree_util.tree_map(lambda x: x + 0.0 * tie if _is_float(x) else x, tree)


def replayed_scan(produce, finish, theta, init, length: int, chunk_length: int | None = None, store_dtype=None):
    """A scan whose steps are `kept, aux = produce(theta, carry, k)` (expensive: in
    jaxtissue a loading cycle and its lumped transport) then `carry, out =
    finish(theta, carry, k, kept)` (a growth solve); returns the last carry and the
    stacked `(aux, out)`.

    Its reverse pass stores every step's `kept` and, per chunk of ~√length steps
    (`chunking`), the chunk's first carry. Reversing a chunk, it replays (and stores)
    the chunk's carries with `finish` alone, then takes each step's VJP in turn:
    `finish`'s first, then `produce`'s, whose recomputation waits for the cotangent of
    `kept` (so its intermediates are not held during `finish`'s reverse pass). Steps
    and chunks whose cotangents are all zero (after the last output a loss reads) are
    skipped: their contribution is exactly zero.

    `theta` holds the differentiable values the functions use (they must not close
    over traced values). `store_dtype` (e.g. `jnp.float32`): the stored carries and
    `kept` values are rounded to it (half their memory in float32); the replay then
    starts from values within that round-off (6e-8 relative in float32) of the
    forward pass's, and the gradient differs from that of the float64 discrete map at
    about that level. Reverse mode (`jax.grad`, `jax.vjp`, `vmap` of them); forward
    mode is not defined (a `custom_vjp`).
    """
    inner = min(chunk_length or chunking(length), length)
    outer = -(-length // inner)
    padded = outer * inner > length
    tmap = jax.tree_util.tree_map

    def store(tree):
        return tmap(lambda x: x.astype(store_dtype) if store_dtype is not None and _is_float(x) else x, tree)

    def load(tree, like):
        return tmap(lambda x, y: x.astype(y.dtype), tree, like)

    def step(th, carry, k):
        kept, aux = produce(th, carry, k)
        carry, out = finish(th, carry, k, kept)
        return carry, (aux, out), kept

    k0 = jnp.zeros((), jnp.arange(1).dtype)
    _, out_shape, kept_shape = jax.eval_shape(step, theta, init, k0)

    def zeros(shape):
        return tmap(lambda s: jnp.zeros(s.shape, s.dtype), shape)

    def guarded(fn, skip):
        """`fn(k, *a)` for the steps that exist, `skip(*a)` for the padding."""
        return (lambda k, *a: jax.lax.cond(k < length, lambda *b: fn(k, *b), skip, *a)) if padded else fn

    @jax.custom_vjp
    def run(theta, init):
        return jax.lax.scan(lambda c, k: step(theta, c, k)[:2], init, jnp.arange(length))

    def run_fwd(theta, init):
        body = guarded(lambda k, c: (lambda r: (r[0], r[1:]))(step(theta, c, k)), lambda c: (c, (zeros(out_shape), zeros(kept_shape))))

        def chunk(carry, i):
            last, (out, kept) = jax.lax.scan(lambda c, j: body(i * inner + j, c), carry, jnp.arange(inner))
            return last, (store(carry), out, store(kept))

        carry, (firsts, out, kept) = jax.lax.scan(chunk, init, jnp.arange(outer))
        out = tmap(lambda h: h.reshape((outer * inner,) + h.shape[2:])[:length], out)
        kept = tmap(lambda h: h.reshape((outer * inner,) + h.shape[2:]), kept)
        return (carry, out), (theta, firsts, kept)

    def floats(tree):
        return [x for x in jax.tree_util.tree_leaves(tree) if _is_float(x)]

    def run_bwd(res, cts):
        theta, firsts, kept = res
        ct_carry, (ct_aux, ct_out) = cts
        # the outputs' non-float leaves have float0 cotangents: the VJPs see floats only
        ct_aux, ct_out = (
            [jnp.concatenate([c, jnp.zeros((outer * inner - length,) + c.shape[1:], c.dtype)]) for c in floats(t)] for t in (ct_aux, ct_out)
        )

        def kept_at(k):
            return load(tmap(lambda h: h[k], kept), kept_shape)

        def back_step(k, acc, carry):
            ct_c, ct_th = acc
            _, vjp = jax.vjp(lambda th, c, kp: (lambda r: (r[0], floats(r[1])))(finish(th, c, k, kp)), theta, carry, kept_at(k))
            d_th, d_c, d_kept = vjp((ct_c, [c[k] for c in ct_out]))
            _, vjp = jax.vjp(lambda th, c: (lambda r: (r[0], floats(r[1])))(produce(th, c, k)), theta, _tied(carry, d_kept))
            d_th2, d_c2 = vjp((d_kept, [c[k] for c in ct_aux]))
            return tmap(jnp.add, d_c, d_c2), tmap(lambda a, b, c: a + b + c, ct_th, d_th, d_th2)

        def live(ct_carry, cts):
            """Whether any of these cotangents is non-zero."""
            return jnp.any(jnp.stack([jnp.any(c != 0) for c in jax.tree_util.tree_leaves(ct_carry) + cts]))

        def back_step_if_needed(k, acc, carry):
            # a step whose cotangents are all zero (padding, or a step after the last
            # output a loss reads) contributes zero: its VJP is skipped
            needed = (k < length) & live(acc[0], [c[k] for c in ct_out + ct_aux])
            return jax.lax.cond(needed, lambda a, c: back_step(k, a, c), lambda a, c: a, acc, carry)

        replay = guarded(lambda k, c: finish(theta, c, k, kept_at(k))[0], lambda c: c)

        def chunk_back(acc, i):
            first = load(tmap(lambda h: h[i], firsts), init)
            _, carries = jax.lax.scan(lambda c, j: (replay(i * inner + j, c), store(c)), first, jnp.arange(inner))  # steps' inputs
            acc, _ = jax.lax.scan(lambda a, xs: (back_step_if_needed(i * inner + xs[0], a, load(xs[1], init)), None), acc,
                                  (jnp.arange(inner), carries), reverse=True)
            return acc

        def chunk_back_if_needed(acc, i):  # nor is a chunk replayed whose steps all would be
            needed = live(acc[0], [jax.lax.dynamic_slice_in_dim(c, i * inner, inner) for c in ct_out + ct_aux])
            return jax.lax.cond(needed, chunk_back, lambda a, i: a, acc, i), None

        (ct_init, ct_theta), _ = jax.lax.scan(chunk_back_if_needed, (ct_carry, tmap(jnp.zeros_like, theta)), jnp.arange(outer), reverse=True)
        return ct_theta, ct_init

    run.defvjp(run_fwd, run_bwd)
    return run(theta, init)
