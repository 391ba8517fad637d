"""Rematerialised loops: reverse-mode memory traded for recomputation."""

from __future__ import annotations

import functools

import jax
import jax.numpy as jnp


def nested_checkpoint_scan(step, init, length: int, keep: tuple[str, ...] = ()):
    """`lax.scan(step, init, arange(length))` as chunks of ~√length steps, each chunk
    rematerialised in the reverse pass: a gradient stores ~√length carries and one
    chunk's intermediates at a time, for one more forward pass. The chunk length is
    the largest divisor of `length` up to √length (1, no nesting, for a prime).
    Values named in `keep` (`jax.ad_checkpoint.checkpoint_name`) are stored rather
    than recomputed."""
    inner = max(d for d in range(1, int(length**0.5) + 1) if length % d == 0)
    outer = length // inner
    policy = jax.checkpoint_policies.save_only_these_names(*keep) if keep else None

    @functools.partial(jax.checkpoint, policy=policy)
    def chunk(carry, i):
        return jax.lax.scan(step, carry, i * inner + jnp.arange(inner))

    carry, hist = jax.lax.scan(chunk, init, jnp.arange(outer))
    return carry, jax.tree_util.tree_map(lambda h: h.reshape((length,) + h.shape[2:]), hist)
