"""Rematerialised loops equal plain ones, in value and gradient."""

import math

import jax
import jax.flatten_util
import jax.numpy as jnp
import numpy as np
import pytest
from jax.ad_checkpoint import checkpoint_name

from jaxtissue.numerics import nested_checkpoint_scan, replayed_scan


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


def produce(theta, x, k):
    """An expensive part (kept) and a by-product with an integer leaf."""
    a, b = theta
    kept = jnp.tanh(a * x + 0.1 * k)
    return kept, (jnp.sum(kept), k)


def finish(theta, x, k, kept):
    a, b = theta
    x = x + 0.05 * (jnp.sin(b * x) + kept * x)
    return x, dict(first=x[0], count=k + 1)


def _loss(scan, theta, x0):
    x, ((s, ks), out) = scan(theta, x0)
    return jnp.sum(x**2) + jnp.sum(s * jnp.cos(ks)) + jnp.sum(out["first"] * out["count"])


def _plain(length):
    def scan(theta, x0):
        def step(x, k):
            kept, aux = produce(theta, x, k)
            x, out = finish(theta, x, k, kept)
            return x, (aux, out)

        return jax.lax.scan(step, x0, jnp.arange(length))

    return scan


@pytest.mark.parametrize("length, chunk", [(12, None), (13, None), (13, 5), (1, None)])
def test_replayed_scan_equals_scan(length, chunk):
    """Value and gradient (w.r.t. the carry and theta) as the plain scan's; the chunks
    need not divide the length."""
    theta, x0 = (jnp.asarray(0.7), jnp.asarray(1.3)), jnp.linspace(0.1, 0.5, 4)
    replayed = lambda th, x: replayed_scan(produce, finish, th, x, length, chunk_length=chunk)  # noqa: E731
    np.testing.assert_allclose(_loss(replayed, theta, x0), _loss(_plain(length), theta, x0), rtol=1e-14)
    got = jax.grad(_loss, argnums=(1, 2))(replayed, theta, x0)
    want = jax.grad(_loss, argnums=(1, 2))(_plain(length), theta, x0)
    for g, w in zip(jax.tree_util.tree_leaves(got), jax.tree_util.tree_leaves(want)):
        np.testing.assert_allclose(g, w, rtol=1e-12)


def test_replayed_scan_in_float32_storage():
    """Stored in float32, the forward pass is unchanged to the bit and the gradient
    (replayed from the rounded values) stays within ~1e-7 of the float64 one."""
    theta, x0, length = (jnp.asarray(0.7), jnp.asarray(1.3)), jnp.linspace(0.1, 0.5, 4), 30
    f32 = lambda th, x: replayed_scan(produce, finish, th, x, length, store_dtype=jnp.float32)  # noqa: E731
    assert _loss(f32, theta, x0) == _loss(_plain(length), theta, x0)
    got = jax.flatten_util.ravel_pytree(jax.grad(_loss, argnums=(1, 2))(f32, theta, x0))[0]
    want = jax.flatten_util.ravel_pytree(jax.grad(_loss, argnums=(1, 2))(_plain(length), theta, x0))[0]
    error = np.max(np.abs(got - want)) / np.max(np.abs(want))
    assert 0 < error < 1e-6  # rounded (not zero), and close


def test_replayed_scan_memory():
    """A gradient through 100 steps stores ~2√n carries and every step's kept value:
    in float32 those take half the bytes, and either way far less than the plain
    scan, which keeps every step's carry and kept value."""
    x0 = jnp.linspace(0.0, 1.0, 20_000)
    theta = (jnp.asarray(0.7), jnp.asarray(1.3))

    def memory(scan):
        return jax.jit(jax.grad(lambda x: _loss(scan, theta, x))).lower(x0).compile().memory_analysis().temp_size_in_bytes

    plain = memory(_plain(100))
    f64 = memory(lambda th, x: replayed_scan(produce, finish, th, x, 100))
    f32 = memory(lambda th, x: replayed_scan(produce, finish, th, x, 100, store_dtype=jnp.float32))
    assert plain > 3 * 100 * x0.nbytes  # per step: the carry, tanh's input, kept...
    assert f64 < (100 + 3 * math.isqrt(100)) * x0.nbytes  # kept per step, ~2√n carries
    assert f32 < 0.6 * f64


def test_replayed_scan_skips_steps_without_cotangent():
    """A loss that reads only step 3's output of 12: the gradient equals the plain
    scan's, and the reverse pass recomputes `produce` for steps 0-3 only (12 forward
    calls + 4), the later steps' cotangents being zero."""
    calls = []

    def counted(theta, x, k):
        jax.debug.callback(lambda k: calls.append(int(k)), k)
        return produce(theta, x, k)

    def loss(scan, theta, x0):
        _, (_, out) = scan(theta, x0)
        return out["first"][3]

    theta, x0 = (jnp.asarray(0.7), jnp.asarray(1.3)), jnp.linspace(0.1, 0.5, 4)
    replayed = lambda th, x: replayed_scan(counted, finish, th, x, 12, chunk_length=4)  # noqa: E731
    got = jax.block_until_ready(jax.jit(jax.grad(loss, argnums=(1, 2)), static_argnums=0)(replayed, theta, x0))
    want = jax.grad(loss, argnums=(1, 2))(_plain(12), theta, x0)
    for g, w in zip(jax.tree_util.tree_leaves(got), jax.tree_util.tree_leaves(want)):
        np.testing.assert_allclose(g, w, rtol=1e-12)
    assert sorted(calls) == sorted(list(range(12)) + [0, 1, 2, 3])
