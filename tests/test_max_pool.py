"""The custom-VJP max-pool equals flax's ``nn.max_pool`` in value and gradient."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from flax import linen as nn

from gac_jax.models.max_pool import max_pool

# (window, strides, padding): the ResNet stem (its own 3x3/2 scatter) and the generic path
CASES = [
    ((3, 3), (2, 2), ((1, 1), (1, 1))),
    ((2, 3), (1, 2), ((0, 1), (1, 0))),
    ((3, 3), (1, 1), ((1, 1), (1, 1))),
]


def _inputs(kind: str, shape, rng) -> jax.Array:
    if kind == "random":
        x = rng.standard_normal(shape)
    elif kind == "ties":  # many equal maxima per window (like ReLU zeros)
        x = rng.integers(0, 3, shape).astype(float)
    else:  # negative values and -inf entries: padding must behave like -inf
        x = np.where(rng.random(shape) < 0.5, -np.inf, rng.integers(-3, 0, shape))
    return jnp.asarray(x, jnp.float32)


def _value_and_vjp(pool, x, g, window, strides, padding):
    y, vjp = jax.vjp(lambda x: pool(x, window, strides, padding), x)
    return np.asarray(y), np.asarray(vjp(g)[0])


@pytest.mark.parametrize("kind", ["random", "ties", "neginf"])
@pytest.mark.parametrize("window,strides,padding", CASES)
def test_matches_flax(kind, window, strides, padding):
    rng = np.random.default_rng(sum(map(ord, kind)) + 10 * window[0] + window[1])
    x = _inputs(kind, (2, 7, 10, 3), rng)  # odd height, even width
    y_ref = nn.max_pool(x, window, strides, padding)
    g = jnp.asarray(rng.standard_normal(y_ref.shape), jnp.float32)
    y0, dx0 = _value_and_vjp(nn.max_pool, x, g, window, strides, padding)
    y1, dx1 = _value_and_vjp(max_pool, x, g, window, strides, padding)
    np.testing.assert_array_equal(y1, y0)
    # each input's gradient is a sum of the same cotangents; only the summation order differs
    np.testing.assert_allclose(dx1, dx0, rtol=1e-6, atol=1e-6)


def test_ties_go_to_the_first_window_position():
    """Hand-computed: zeros everywhere -> each window's top-left real element gets 1."""
    x = jnp.zeros((1, 5, 5, 1))
    grad = jax.grad(lambda x: max_pool(x, (3, 3), (2, 2), ((1, 1), (1, 1))).sum())(x)
    expected = np.zeros((5, 5))
    for oi in range(3):
        for oj in range(3):
            expected[max(2 * oi - 1, 0), max(2 * oj - 1, 0)] += 1.0
    np.testing.assert_array_equal(np.asarray(grad)[0, :, :, 0], expected)


def test_all_neginf_window_drops_gradient_like_flax():
    """A window whose first position is padding and whose values are all -inf: no gradient."""
    x = jnp.full((1, 5, 5, 1), -jnp.inf)
    pool_args = ((3, 3), (2, 2), ((1, 1), (1, 1)))
    ref = jax.grad(lambda x: nn.max_pool(x, *pool_args).sum())(x)
    got = jax.grad(lambda x: max_pool(x, *pool_args).sum())(x)
    np.testing.assert_array_equal(np.asarray(got), np.asarray(ref))
    assert float(got.sum()) == 4.0  # only the 4 windows starting at a real element


def test_jitted_gradient_traces_once():
    traces = []

    @jax.jit
    def grad(x):
        traces.append(1)
        return jax.grad(lambda x: max_pool(x, (3, 3), (2, 2), ((1, 1), (1, 1))).sum())(x)

    rng = np.random.default_rng(0)
    for _ in range(3):
        jax.block_until_ready(grad(jnp.asarray(rng.standard_normal((1, 6, 6, 2)), jnp.float32)))
    assert len(traces) == 1


def test_rejects_wrong_rank():
    with pytest.raises(ValueError, match="max_pool expects"):
        max_pool(jnp.zeros((4, 4, 2)), (3, 3), (2, 2), ((1, 1), (1, 1)))
