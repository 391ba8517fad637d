"""Rematerialised loops equal plain ones, in value and gradient."""

import math

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from jax.ad_checkpoint import checkpoint_name

from jaxtissue.remat import nested_checkpoint_scan


def step(carry, k):
    x, acc = carry
    x = checkpoint_name(jnp.sin(x) * (1.0 + 0.01 * k) + 0.1 * x**2, "kept")
    return (x, acc + jnp.sum(x**2)), jnp.cos(x[0])


@pytest.mark.parametrize("length, keep", [(12, ()), (12, ("kept",)), (13, ()), (13, ("kept",)), (1, ())])
def test_nested_checkpoint_scan_equals_scan(length, keep):
    x0 = jnp.linspace(0.1, 0.5, 4)

    def loss(x0, scan):
        (x, acc), ys = scan(x0)
        return acc + jnp.sum(ys * jnp.arange(length)) + jnp.sum(x)

    plain = lambda x0: jax.lax.scan(step, (x0, 0.0), jnp.arange(length))  # noqa: E731
    nested = lambda x0: nested_checkpoint_scan(step, (x0, 0.0), length, keep)  # noqa: E731
    np.testing.assert_allclose(loss(x0, nested), loss(x0, plain), rtol=1e-14)
    np.testing.assert_allclose(jax.grad(loss)(x0, nested), jax.grad(loss)(x0, plain), rtol=1e-12)


@pytest.mark.parametrize("length", [100, 101])
def test_nested_checkpoint_scan_stores_about_root_length_carries(length):
    """A gradient through 100 or 101 (prime: its last chunk padded) steps of a large
    carry keeps ~2√n carries, not n: its buffers are a fraction of the plain scan's."""
    x0 = jnp.linspace(0.0, 1.0, 20_000)

    def step(x, k):
        return jnp.sin(x) + 0.01 * k, x[0]

    def memory(scan):
        def loss(x):
            x, ys = scan(x)
            return jnp.sum(x) + jnp.sum(ys)

        analysis = jax.jit(jax.grad(loss)).lower(x0).compile().memory_analysis()
        return analysis.temp_size_in_bytes

    plain = memory(lambda x: jax.lax.scan(step, x, jnp.arange(length)))
    nested = memory(lambda x: nested_checkpoint_scan(step, x, length))
    assert plain > 0.8 * length * x0.nbytes  # every carry
    assert nested < 3 * math.isqrt(length) * x0.nbytes < plain / 3
