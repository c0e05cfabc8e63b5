"""ResNet-18/34/50/101 backbones in the torchvision (v1.5) layout, NHWC.

The layout, padding and layer names follow torchvision so that its ImageNet state dicts
(and the reference GAC checkpoint, whose backbone keys are ``core.backbone.`` + the
torchvision keys) convert 1:1 with :mod:`gac_jax.models.naming`:

=====================================  ==========================================
torchvision key prefix                 Flax module path (in this ``ResNet``)
=====================================  ==========================================
``conv1``                              ``conv1``
``bn1``                                ``bn1``
``layer{L}.{B}.conv{i}`` / ``bn{i}``   ``layer{L}_{B}/conv{i}`` / ``bn{i}``
``layer{L}.{B}.downsample.0`` / ``.1`` ``layer{L}_{B}/downsample_0`` / ``downsample_1``
=====================================  ==========================================

Stem: conv 7x7/2 (pad 3, no bias) -> BN -> ReLU -> max-pool 3x3/2 (pad 1, -inf padding).
Stage strides are (1, 2, 2, 2), so ``layer{L}`` has stride ``2 ** (L + 1)`` w.r.t. the input
(layer1: 4, layer2: 8, layer3: 16, layer4: 32). All paddings are explicit and symmetric like
PyTorch's (Flax's ``'SAME'`` pads stride-2 convolutions asymmetrically, which would shift the
features of converted weights). BasicBlock (18/34) has two 3x3 convs; Bottleneck (50/101) is
1x1 -> 3x3 (carrying the stride, "v1.5") -> 1x1 with expansion 4.

BatchNorm: ``train=True`` normalises with batch statistics and updates ``batch_stats`` (apply
with ``mutable=['batch_stats']``); ``train=False`` uses the running averages. Momentum 0.9 and
epsilon 1e-5 match PyTorch's momentum 0.1 / eps 1e-5. (PyTorch stores the *unbiased* batch
variance in ``running_var``, Flax the biased one: a factor n/(n-1), negligible here.)
"""

from __future__ import annotations

import contextlib
import contextvars
from collections.abc import Callable, Iterator, Sequence
from typing import Any

import jax
import jax.numpy as jnp
from flax import linen as nn

from gac_jax.models import batch_norm, stride2_conv
from gac_jax.models.initializers import torchvision_resnet_kernel_init
from gac_jax.models.max_pool import max_pool

_PLAIN_FORMULATION = contextvars.ContextVar("gac_jax_resnet_plain_formulation", default=False)


@contextlib.contextmanager
def plain_formulation() -> Iterator[None]:
    """Within this block, ResNets *traced* use the plain Flax ops (``nn.max_pool``, ...).

    The default formulation computes the same values and gradients but runs faster on
    XLA:CPU: the stem max-pool's gradient (:mod:`gac_jax.models.max_pool`) and the stem
    convolution as a space-to-depth stride-1 convolution (:mod:`gac_jax.models.stride2_conv`,
    same sum in another order) and train-mode BatchNorm (+ ReLU) with a closed-form backward
    (:mod:`gac_jax.models.batch_norm`, same variables); benchmarks and tests use this switch to
    compare the two. It acts at trace time: jit (or ``lower``) inside the block.
    """
    token = _PLAIN_FORMULATION.set(True)
    try:
        yield
    finally:
        _PLAIN_FORMULATION.reset(token)


def uses_plain_formulation() -> bool:
    """True while tracing inside :func:`plain_formulation`."""
    return _PLAIN_FORMULATION.get()


# depth -> (block kind, blocks per stage)
RESNET_SPECS: dict[int, tuple[str, tuple[int, int, int, int]]] = {
    18: ("basic", (2, 2, 2, 2)),
    34: ("basic", (3, 4, 6, 3)),
    50: ("bottleneck", (3, 4, 6, 3)),
    101: ("bottleneck", (3, 4, 23, 3)),
}
BOTTLENECK_EXPANSION = 4


def layer_stride(layer: int) -> int:
    """Output stride (w.r.t. the input image) of ``layer{layer}``, layer in 1..4."""
    if not 1 <= layer <= 4:
        raise ValueError(f"ResNet layer index must be in 1..4, got {layer}")
    return 2 ** (layer + 1)


def layer_output_size(size: int, layer: int) -> int:
    """Spatial size (height or width) of ``layer{layer}``'s output for an input of ``size``.

    Every stride-2 step (stem conv, max-pool, first block of layers 2..4) maps
    ``n -> floor((n - 1) / 2) + 1`` (PyTorch rounding), e.g. 288 -> 18 and 1280 -> 80 at layer3.
    """
    n = size
    for _ in range(layer_stride(layer).bit_length() - 1):
        n = (n - 1) // 2 + 1
    return n


def layer_channels(depth: int, layer: int, width: int = 64) -> int:
    """Number of output channels of ``layer{layer}`` for a ResNet of this depth and base width."""
    if depth not in RESNET_SPECS:
        raise ValueError(f"unsupported ResNet depth {depth}; choose one of {sorted(RESNET_SPECS)}")
    kind, _ = RESNET_SPECS[depth]
    expansion = BOTTLENECK_EXPANSION if kind == "bottleneck" else 1
    return width * 2 ** (layer - 1) * expansion


def batch_norm_layer(
    train: bool, dtype: Any, param_dtype: Any, name: str, relu: bool = False
) -> Callable[[jax.Array], jax.Array]:
    """BatchNorm over the last axis (then ReLU when ``relu``), momentum 0.9 and eps 1e-5 like
    PyTorch's defaults: under the default formulation the closed-form-backward one of
    :mod:`gac_jax.models.batch_norm`, under :func:`plain_formulation` Flax's (same variables).
    Used by the ResNet, the detection head and the depth decoder."""
    kwargs = dict(
        use_running_average=not train,
        momentum=0.9,
        epsilon=1e-5,
        dtype=dtype,
        param_dtype=param_dtype,
        name=name,
    )
    if not _PLAIN_FORMULATION.get():
        return batch_norm.BatchNorm(relu=relu, **kwargs)
    bn = nn.BatchNorm(**kwargs)
    return (lambda x: nn.relu(bn(x))) if relu else bn


def _conv(
    features: int,
    kernel: int,
    stride: int,
    dtype: Any,
    param_dtype: Any,
    name: str,
    conv_general_dilated: Any = None,
) -> nn.Conv:
    pad = (kernel - 1) // 2
    return nn.Conv(
        features,
        (kernel, kernel),
        strides=(stride, stride),
        padding=((pad, pad), (pad, pad)),
        use_bias=False,
        kernel_init=torchvision_resnet_kernel_init,
        dtype=dtype,
        param_dtype=param_dtype,
        name=name,
        conv_general_dilated=conv_general_dilated,
    )


class BasicBlock(nn.Module):
    """Two 3x3 convs with an identity (or 1x1-conv + BN) shortcut. (B,H,W,Cin) -> (B,H/s,W/s,F)."""

    features: int
    stride: int = 1
    dtype: Any = jnp.float32
    param_dtype: Any = jnp.float32

    @nn.compact
    def __call__(self, x: jax.Array, train: bool) -> jax.Array:
        dt, pdt = self.dtype, self.param_dtype
        y = _conv(self.features, 3, self.stride, dt, pdt, "conv1")(x)
        y = batch_norm_layer(train, dt, pdt, "bn1", relu=True)(y)
        y = _conv(self.features, 3, 1, dt, pdt, "conv2")(y)
        y = batch_norm_layer(train, dt, pdt, "bn2")(y)
        shortcut = x
        if self.stride != 1 or x.shape[-1] != self.features:
            shortcut = _conv(self.features, 1, self.stride, dt, pdt, "downsample_0")(x)
            shortcut = batch_norm_layer(train, dt, pdt, "downsample_1")(shortcut)
        return nn.relu(y + shortcut)


class Bottleneck(nn.Module):
    """1x1 -> 3x3 (stride) -> 1x1 (x4 channels) with a shortcut. (B,H,W,Cin) -> (B,H/s,W/s,4F)."""

    features: int
    stride: int = 1
    dtype: Any = jnp.float32
    param_dtype: Any = jnp.float32

    @nn.compact
    def __call__(self, x: jax.Array, train: bool) -> jax.Array:
        dt, pdt = self.dtype, self.param_dtype
        out_features = self.features * BOTTLENECK_EXPANSION
        y = _conv(self.features, 1, 1, dt, pdt, "conv1")(x)
        y = batch_norm_layer(train, dt, pdt, "bn1", relu=True)(y)
        y = _conv(self.features, 3, self.stride, dt, pdt, "conv2")(y)
        y = batch_norm_layer(train, dt, pdt, "bn2", relu=True)(y)
        y = _conv(out_features, 1, 1, dt, pdt, "conv3")(y)
        y = batch_norm_layer(train, dt, pdt, "bn3")(y)
        shortcut = x
        if self.stride != 1 or x.shape[-1] != out_features:
            shortcut = _conv(out_features, 1, self.stride, dt, pdt, "downsample_0")(x)
            shortcut = batch_norm_layer(train, dt, pdt, "downsample_1")(shortcut)
        return nn.relu(y + shortcut)


class ResNet(nn.Module):
    """torchvision-layout ResNet trunk (no average pool, no fc).

    Attributes:
      depth: 18, 34, 50 or 101.
      num_stages: how many residual stages to build (1..4). 3 = through layer3 (stride 16,
        the GAC detector); 4 = all (the depth U-Net encoder).
      return_layers: names of the stage outputs to return, e.g. ``('layer3',)``; ``None``
        returns every built stage.
      width: base channel count (64 in torchvision). Stage L has ``width * 2**(L-1)``
        channels (times 4 for Bottleneck). Smaller values give tiny test models.
      dtype / param_dtype: computation / parameter dtypes.

    ``__call__(images (B,H,W,3), train) -> {'layer1': (B,H/4,W/4,C1), ..., 'layerN': ...}``
    (spatial sizes rounded like PyTorch: each stride-2 step maps n -> floor((n-1)/2) + 1).
    """

    depth: int = 101
    num_stages: int = 4
    return_layers: Sequence[str] | None = None
    width: int = 64
    dtype: Any = jnp.float32
    param_dtype: Any = jnp.float32

    @nn.compact
    def __call__(self, images: jax.Array, train: bool) -> dict[str, jax.Array]:
        if self.depth not in RESNET_SPECS:
            raise ValueError(
                f"unsupported ResNet depth {self.depth}; choose one of {sorted(RESNET_SPECS)}"
            )
        if not 1 <= self.num_stages <= 4:
            raise ValueError(f"num_stages must be in 1..4, got {self.num_stages}")
        built = [f"layer{i + 1}" for i in range(self.num_stages)]
        wanted = built if self.return_layers is None else list(self.return_layers)
        unknown = [name for name in wanted if name not in built]
        if unknown:
            raise ValueError(f"return_layers {unknown} not among the built stages {built}")
        if images.ndim != 4:
            raise ValueError(f"expected NHWC images (B,H,W,C), got shape {images.shape}")

        kind, blocks = RESNET_SPECS[self.depth]
        block_cls = Bottleneck if kind == "bottleneck" else BasicBlock
        dt, pdt = self.dtype, self.param_dtype

        plain = _PLAIN_FORMULATION.get()
        stem_conv = None if plain else stride2_conv.conv_general_dilated
        x = _conv(self.width, 7, 2, dt, pdt, "conv1", stem_conv)(images)
        x = batch_norm_layer(train, dt, pdt, "bn1", relu=True)(x)
        pool = nn.max_pool if plain else max_pool
        x = pool(x, (3, 3), strides=(2, 2), padding=((1, 1), (1, 1)))

        outputs: dict[str, jax.Array] = {}
        for stage in range(self.num_stages):
            features = self.width * 2**stage
            for b in range(blocks[stage]):
                stride = 2 if (stage > 0 and b == 0) else 1
                x = block_cls(
                    features,
                    stride=stride,
                    dtype=dt,
                    param_dtype=pdt,
                    name=f"layer{stage + 1}_{b}",
                )(x, train)
            name = f"layer{stage + 1}"
            if name in wanted:
                outputs[name] = x
        return outputs
