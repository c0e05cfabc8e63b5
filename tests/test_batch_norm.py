"""The closed-form-backward BatchNorm (+ ReLU) equals Flax's and a float64 numpy reference."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from flax import linen as nn

from gac_jax.models.batch_norm import BatchNorm, _channel_sums, batch_norm_train

EPS = 1e-5


def _reference(x, scale, bias, w, relu):
    """float64: y, batch mean, biased var, and the gradients of sum(w * y) wrt x, scale, bias."""
    x, scale, bias, w = (np.asarray(a, np.float64) for a in (x, scale, bias, w))
    axes = tuple(range(x.ndim - 1))
    mean, var = x.mean(axes), x.var(axes)
    inv = 1.0 / np.sqrt(var + EPS)
    xhat = (x - mean) * inv
    pre = xhat * scale + bias
    y = np.maximum(pre, 0.0) if relu else pre
    g = w * (pre > 0) if relu else w
    n = x.size / x.shape[-1]
    dbias, dscale = g.sum(axes), (g * xhat).sum(axes)
    dx = scale * inv * (g - dbias / n - xhat * dscale / n)
    return y, mean, var, dx, dscale, dbias


def _inputs(seed, offset):
    rng = np.random.default_rng(seed)
    x = offset + 2.0 * rng.standard_normal((3, 5, 7, 6))
    scale = 1.0 + 0.3 * rng.standard_normal(6)
    bias = 0.2 * rng.standard_normal(6)
    w = rng.standard_normal(x.shape)
    return [jnp.asarray(a, jnp.float32) for a in (x, scale, bias, w)]


def _grads(f, x, scale, bias, w):
    def loss(x, scale, bias):
        y, mean, var = f(x, scale, bias)
        return jnp.sum(w * y), (y, mean, var)

    (_, aux), grads = jax.value_and_grad(loss, argnums=(0, 1, 2), has_aux=True)(x, scale, bias)
    return (*aux, *grads)


def _flax(relu):
    def f(x, scale, bias):
        variables = {
            "params": {"scale": scale, "bias": bias},
            "batch_stats": {"mean": jnp.zeros_like(scale), "var": jnp.ones_like(scale)},
        }
        bn = nn.BatchNorm(use_running_average=False, momentum=0.0, epsilon=EPS)
        y, st = bn.apply(variables, x, mutable=["batch_stats"])  # momentum 0: stats = batch
        return (nn.relu(y) if relu else y), st["batch_stats"]["mean"], st["batch_stats"]["var"]

    return f


@pytest.mark.parametrize("relu", [False, True])
@pytest.mark.parametrize("offset", [0.5, 1000.0])
def test_batch_norm_train_matches_float64_and_flax(relu, offset):
    x, scale, bias, w = _inputs(int(offset) + relu, offset)
    ref = _reference(x, scale, bias, w, relu)
    ours = jax.jit(lambda *a: _grads(lambda *b: batch_norm_train(*b, EPS, relu), *a))(
        x, scale, bias, w
    )
    names = ("y", "mean", "var", "dx", "dscale", "dbias")
    for name, a, r in zip(names, ours, ref, strict=True):
        tol = 2e-5 * max(1.0, float(np.max(np.abs(r)))) if name != "mean" else 2e-6 * offset
        np.testing.assert_allclose(a, r, rtol=0, atol=tol, err_msg=name)
    if offset < 10:  # Flax's one-pass E[x^2] - E[x]^2 cancels catastrophically at offset 1000
        flax = jax.jit(lambda *a: _grads(_flax(relu), *a))(x, scale, bias, w)
        for name, a, b in zip(names, ours, flax, strict=True):
            tol = 1e-5 * max(1.0, float(jnp.max(jnp.abs(b))))
            np.testing.assert_allclose(a, b, rtol=0, atol=tol, err_msg=name)


def test_module_keeps_flax_variables_and_running_average_update():
    x, _, _, _ = _inputs(3, 0.5)
    ours = BatchNorm(use_running_average=False, momentum=0.9, relu=True)
    theirs = nn.BatchNorm(use_running_average=False, momentum=0.9, epsilon=EPS)
    variables = ours.init(jax.random.key(0), x)
    assert jax.tree.map(jnp.shape, variables) == jax.tree.map(
        jnp.shape, theirs.init(jax.random.key(0), x)
    )
    variables = {  # non-trivial parameters and running statistics
        "params": {"scale": jnp.linspace(0.5, 2.0, 6), "bias": jnp.linspace(-1.0, 1.0, 6)},
        "batch_stats": {"mean": jnp.linspace(-0.3, 0.3, 6), "var": jnp.linspace(0.5, 1.5, 6)},
    }
    y, stats = ours.apply(variables, x, mutable=["batch_stats"])
    y_ref, stats_ref = theirs.apply(variables, x, mutable=["batch_stats"])
    np.testing.assert_allclose(y, nn.relu(y_ref), atol=1e-5)
    for a, b in zip(jax.tree.leaves(stats), jax.tree.leaves(stats_ref), strict=True):
        np.testing.assert_allclose(a, b, rtol=1e-5, atol=1e-6)
    # eval mode: running averages, nothing mutated
    y_eval = BatchNorm(use_running_average=True, momentum=0.9, relu=False).apply(variables, x)
    y_eval_ref = nn.BatchNorm(use_running_average=True, epsilon=EPS).apply(variables, x)
    np.testing.assert_array_equal(y_eval, y_eval_ref)


def test_batch_norm_train_traces_once():
    traces = []

    def loss(x, scale, bias):
        traces.append(1)
        return jnp.sum(jnp.sin(batch_norm_train(x, scale, bias, EPS, relu=True)[0]))

    grad = jax.jit(jax.grad(loss, argnums=(0, 1, 2)))
    x, scale, bias, _ = _inputs(5, 0.5)
    grad(x, scale, bias)
    grad(x * 2.0, scale + 1.0, bias)
    assert len(traces) == 1


@pytest.mark.parametrize("shape", [(8, 20, 90, 4), (1, 37, 41, 3), (2, 1, 1, 5), (1, 7, 1, 2)])
def test_channel_sums_match_float64(shape):
    """Divisible, prime-ish (zero-padded blocks) and tiny row counts: float64 sums."""
    rng = np.random.default_rng(len(shape) + shape[1])
    a = 3.0 + rng.standard_normal(shape)
    b = rng.standard_normal(shape)
    sa, sb = jax.jit(_channel_sums)(jnp.asarray(a, jnp.float32), jnp.asarray(b, jnp.float32))
    axes = tuple(range(len(shape) - 1))
    np.testing.assert_allclose(sa, a.sum(axes), rtol=1e-6, atol=1e-5)
    np.testing.assert_allclose(sb, b.sum(axes), rtol=1e-5, atol=1e-4)
