"""Flax linen models of GAC (NHWC; modules return dicts of named outputs).

* :mod:`gac_jax.models.resnet` - torchvision-layout ResNet-18/34/50/101 trunks.
* :mod:`gac_jax.models.ground_aware_conv` - the ground-aware convolution and its geometry.
* :mod:`gac_jax.models.detection_head` - the GroundAwareYolo3D classification/regression head.
* :mod:`gac_jax.models.detector` - backbone + head, the monocular 3D detector.
* :mod:`gac_jax.models.deformable_conv` - modulated deformable convolution (DCNv2).
* :mod:`gac_jax.models.depth_unet` - the ground-aware monocular depth U-Net.
* :mod:`gac_jax.models.naming` - PyTorch state-dict keys -> Flax variables (weight import).
"""
