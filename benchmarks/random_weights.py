"""Random weights in a model's shapes, for timing benchmarks (nothing is compiled)."""

from __future__ import annotations


def random_variables(model, config, init, seed: int = 0) -> dict:
    """Random weights in the model's shapes (abstract init: nothing compiled)."""
    import jax
    import numpy as np

    rng = np.random.default_rng(seed)
    shapes = jax.eval_shape(lambda: init(model, config, 0))

    def f(path, s):
        name = jax.tree_util.keystr(path)
        if "'var'" in name:
            return rng.uniform(0.5, 1.5, s.shape).astype(np.float32)
        if "'scale'" in name:
            return rng.uniform(0.5, 1.0, s.shape).astype(np.float32)
        if "kernel" in name:
            fan_in = int(np.prod(s.shape[:-1]))
            return rng.normal(0, (2.0 / fan_in) ** 0.5, s.shape).astype(np.float32)
        return rng.normal(0, 0.05, s.shape).astype(np.float32)

    return jax.tree_util.tree_map_with_path(f, shapes)
