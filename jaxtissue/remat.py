"""Rematerialised loops: reverse-mode memory traded for recomputation."""

from __future__ import annotations

import functools
import math

import jax
import jax.numpy as jnp


def nested_checkpoint_scan(step, init, length: int, keep: tuple[str, ...] = ()):
    """`lax.scan(step, init, arange(length))` as chunks of ~√length steps, each chunk
    rematerialised in the reverse pass: a gradient stores ~√length carries and one
    chunk's intermediates at a time, for one more forward pass. The chunk length is
    the largest divisor of `length` up to √length if that is at least half of √length;
    otherwise (e.g. a prime `length`) ⌊√length⌋, the last chunk padded with steps that
    `lax.cond` skips. Values named in `keep` (`jax.ad_checkpoint.checkpoint_name`) are
    stored rather than recomputed."""
    root = math.isqrt(length)
    inner = max(d for d in range(1, root + 1) if length % d == 0)
    if 2 * inner < root:
        inner = root
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
