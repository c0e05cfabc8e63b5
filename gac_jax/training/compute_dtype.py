"""Mixed precision in training: ``train.compute_dtype`` ('float32' or 'bfloat16').

With ``'bfloat16'`` the model's convolutions and activations run in bfloat16 (the modules'
``dtype``); everything that accumulates stays float32: the parameters (``param_dtype``) and so
the gradients and the optimizer state, the BatchNorm statistics (Flax keeps them in float32),
the GAC's sampling coordinates (``promote_types(dtype, float32)``), and the network outputs,
which the models cast to float32 before the losses and their reductions. The checkpoint holds
only float32 state, so a bfloat16 run and a float32 run resume each other's checkpoints.
"""

from __future__ import annotations

import jax.numpy as jnp
import ml_collections

from gac_jax.config import ConfigError

COMPUTE_DTYPES = {"float32": jnp.float32, "bfloat16": jnp.bfloat16}


def compute_dtype(config: ml_collections.ConfigDict):
    """The jnp dtype named by ``config.train.compute_dtype`` (absent: float32).

    Raises:
      ConfigError: the name is not one of :data:`COMPUTE_DTYPES`.
    """
    name = config.train.get("compute_dtype", "float32")
    if name not in COMPUTE_DTYPES:
        raise ConfigError(
            f"train.compute_dtype: {name!r} is not one of {', '.join(sorted(COMPUTE_DTYPES))}"
        )
    return COMPUTE_DTYPES[name]


def training_model(model, config: ml_collections.ConfigDict):
    """``model`` (a Flax module with ``dtype`` / ``param_dtype``) computing in the configured
    dtype; parameters stay float32, so its variables are those of ``model``."""
    dtype = compute_dtype(config)
    return model if dtype == model.dtype else model.clone(dtype=dtype)
