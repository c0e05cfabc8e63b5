"""Weight initialisers that reproduce PyTorch's defaults (for layers the paper does not pin).

PyTorch ``nn.Conv2d`` draws its weight from Kaiming-uniform with ``a = sqrt(5)``, i.e.
``U(-b, b)`` with ``b = sqrt(1 / fan_in)`` (variance ``1 / (3 fan_in)``), and its bias from
``U(-1/sqrt(fan_in), 1/sqrt(fan_in))``. torchvision's ResNet re-initialises its convolutions
with ``kaiming_normal_(mode='fan_out', nonlinearity='relu')`` (an untruncated normal with
variance ``2 / fan_out``). Flax's own defaults (LeCun normal, zero bias) differ from both.
"""

from __future__ import annotations

import math

import jax
import jax.numpy as jnp
from flax import linen as nn

# PyTorch nn.Conv2d default weight init: Kaiming-uniform(a=sqrt(5)) == variance 1/(3 fan_in).
torch_conv_kernel_init = nn.initializers.variance_scaling(1.0 / 3.0, "fan_in", "uniform")

# torchvision ResNet conv init: kaiming_normal_(mode='fan_out', nonlinearity='relu').
torchvision_resnet_kernel_init = nn.initializers.variance_scaling(2.0, "fan_out", "normal")


def torch_conv_bias_init(fan_in: int) -> nn.initializers.Initializer:
    """PyTorch nn.Conv2d default bias init: ``U(-1/sqrt(fan_in), 1/sqrt(fan_in))``.

    ``fan_in`` = in_channels * kernel_h * kernel_w of the convolution the bias belongs to.
    """
    bound = 1.0 / math.sqrt(fan_in)

    def init(key: jax.Array, shape, dtype=jnp.float32) -> jax.Array:
        return jax.random.uniform(key, shape, dtype, minval=-bound, maxval=bound)

    return init
