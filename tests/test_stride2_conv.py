"""The space-to-depth stride-2 convolution equals lax.conv_general_dilated (value, gradients)."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from jax import lax

from gac_jax.models.stride2_conv import conv_general_dilated

DN = ("NHWC", "HWIO", "NHWC")


@pytest.mark.parametrize(
    "hw,kernel,padding",
    [
        ((10, 13), 7, ((3, 3), (3, 3))),
        ((9, 8), 3, ((1, 1), (1, 1))),
        ((8, 11), 4, ((0, 1), (2, 0))),
    ],
)
def test_matches_lax(hw, kernel, padding):
    rng = np.random.default_rng(kernel)
    x = jnp.asarray(rng.standard_normal((2, *hw, 3)), jnp.float32)
    k = jnp.asarray(rng.standard_normal((kernel, kernel, 3, 5)), jnp.float32)

    def ref(x, k):
        return lax.conv_general_dilated(x, k, (2, 2), padding, dimension_numbers=DN)

    def ours(x, k):
        return conv_general_dilated(x, k, (2, 2), padding, dimension_numbers=DN)

    y0, vjp0 = jax.vjp(ref, x, k)
    y1, vjp1 = jax.vjp(ours, x, k)
    assert y1.shape == y0.shape
    np.testing.assert_allclose(y1, y0, rtol=1e-5, atol=1e-5)
    g = jnp.asarray(rng.standard_normal(y0.shape), jnp.float32)
    for a, b in zip(vjp1(g), vjp0(g), strict=True):
        np.testing.assert_allclose(a, b, rtol=1e-5, atol=1e-4)


def test_other_configurations_fall_through_to_lax():
    x = jnp.ones((1, 6, 6, 2))
    k = jnp.ones((3, 3, 2, 4))
    y = conv_general_dilated(x, k, (1, 1), "SAME", dimension_numbers=DN)
    np.testing.assert_array_equal(y, lax.conv_general_dilated(x, k, (1, 1), "SAME",
                                                             dimension_numbers=DN))  # fmt: skip
