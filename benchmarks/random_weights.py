"""Random weights in a model's shapes, for timing benchmarks (nothing is compiled)."""

from __future__ import annotations

# A detector config for timing with random weights: priors from the real KITTI frames of
# ``data.root`` (split ``labeled``), score threshold 0 and ``top_k`` 100, so 100 candidates
# go through NMS and hill-climbing on every frame (a crowded frame; random weights would
# otherwise send a varying number, up to the configs' cap, through hill-climbing).
TIMING_DETECTOR_OVERRIDES = (
    "data.source=kitti",
    "data.train_split=labeled",
    "anchors.prior_min_count=1",
    "eval.score_threshold=0.0",
    "eval.top_k=100",
)


def timing_detector_config(spec: str, kitti_root):
    """The detector config ``spec`` (``file.py[:arg]``) with :data:`TIMING_DETECTOR_OVERRIDES`
    on the KITTI object folder ``kitti_root``."""
    from gac_jax.config import apply_overrides, load_config

    config = load_config(spec)
    apply_overrides(config, [*TIMING_DETECTOR_OVERRIDES, f"data.root={kitti_root}"])
    return config


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
