"""The shipped (CPU-fast) formulation gives the plain formulation's outputs and gradients.

:func:`plain_formulation` switches the CPU-specific formulation back to plain Flax ops: the
ResNet's max-pool and stem conv, and train-mode BatchNorm + ReLU (ResNet, detection head and
depth decoder all build theirs with ``resnet.batch_norm_layer``). A tiny trunk in train mode
(batch statistics, compared too) covers the first two and the BatchNorm; the BatchNorm itself
is checked against float64 in ``test_batch_norm.py``.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np

from gac_jax.models.resnet import ResNet, plain_formulation


def test_resnet_gradients_match_plain_formulation():
    model = ResNet(depth=18, num_stages=1, width=4)
    rng = np.random.default_rng(0)
    images = jnp.asarray(rng.standard_normal((2, 32, 48, 3)), jnp.float32)
    variables = model.init(jax.random.key(0), images, train=False)
    traces = []

    def loss_fn(params):
        traces.append(1)
        out, mutated = model.apply(
            {"params": params, "batch_stats": variables["batch_stats"]},
            images,
            train=True,
            mutable=["batch_stats"],
        )
        loss = sum(jnp.sum(jnp.sin(v)) for v in out.values())
        return loss, mutated["batch_stats"]

    params = variables["params"]
    with plain_formulation():
        plain = jax.jit(jax.value_and_grad(loss_fn, has_aux=True)).lower(params).compile()
    fast = jax.jit(jax.value_and_grad(loss_fn, has_aux=True))
    (loss0, stats0), grads0 = plain(params)
    (loss1, stats1), grads1 = fast(params)
    fast(jax.tree.map(lambda x: x * 1.5, params))
    assert len(traces) == 2  # one trace each: the second call of `fast` hit the cache
    np.testing.assert_allclose(loss1, loss0, rtol=1e-6)
    for a, b in zip(jax.tree.leaves(stats1), jax.tree.leaves(stats0), strict=True):
        np.testing.assert_allclose(a, b, rtol=1e-5, atol=1e-6)
    assert jax.tree.structure(grads1) == jax.tree.structure(grads0)
    for g0, g1 in zip(jax.tree.leaves(grads0), jax.tree.leaves(grads1), strict=True):
        scale = float(jnp.max(jnp.abs(g0)))
        np.testing.assert_allclose(g1, g0, rtol=1e-4, atol=1e-5 * scale)
    stem = grads1["conv1"]["kernel"]
    assert float(jnp.max(jnp.abs(stem))) > 0  # the gradient reaches the stem through the pool
