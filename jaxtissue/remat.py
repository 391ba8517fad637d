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
