"""One detector training case for the train-step benchmarks: model, optimizer, state, the
jitted step and a random batch (``bench_train_step.py``)."""

from __future__ import annotations

from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
CONFIGS = {
    "paper": str(REPO / "configs" / "detect3d_kitti.py"),
    "default": str(REPO / "configs" / "detect3d_default.py"),
}


def build_detector_case(config_spec: str, batch_size: int, compute_dtype: str = "float32") -> dict:
    """Model, optimizer, train state, trainer step and a random batch for one detector config
    (``compute_dtype``: ``train.compute_dtype`` of the step's model)."""
    import time

    import jax
    import numpy as np

    from gac_jax.builders import detect3d as builders
    from gac_jax.config import load_config
    from gac_jax.detection.anchor_priors import AnchorPriors, make_detection_constants
    from gac_jax.detection.anchors import generate_anchors
    from gac_jax.trainers import detect3d
    from gac_jax.training import parallel
    from gac_jax.training.compute_dtype import training_model
    from gac_jax.training.train_state import TrainState, learning_rate_schedule, make_optimizer

    c = load_config(config_spec)
    c.data.batch_size = batch_size
    c.train.compute_dtype = compute_dtype
    layout = builders.anchor_layout(c)
    anchors = generate_anchors(layout)
    k, a = len(c.data.classes), layout.anchors_per_cell
    sizes = np.sqrt(np.prod(layout.bin_shapes(), axis=1))
    mean = np.zeros((k, a, 3))
    mean[..., 0] = 700.0 * 1.5 / sizes * c.data.height / 288  # depth ~ f H / h
    priors = AnchorPriors(
        layout=layout,
        class_names=tuple(c.data.classes),
        angle_mode="double",
        count=np.full((k, a), 100),
        mean=mean,
        std=np.ones((k, a, 3)),
        valid=np.ones((k, a), bool),
        dims_mean=np.tile([1.5, 1.6, 3.9], (k, 1)),
        dims_std=np.ones((k, 3)) * 0.2,
        num_objects=np.full(k, 1000),
        num_frames=1000,
        iou_threshold=0.5,
        min_count=10,
        min_std=1e-3,
    )
    constants = make_detection_constants(anchors, priors)
    model = builders.build_model(c, a)
    mesh = parallel.make_mesh()
    tx = make_optimizer(learning_rate_schedule(1e-4, 1e-5, 1000), 0.1)
    t0 = time.perf_counter()
    v = builders.init_variables(model, c, 0)
    init_s = time.perf_counter() - t0
    rep = parallel.replicated(mesh)
    state = jax.device_put(TrainState.create(v["params"], v["batch_stats"], tx, 0), rep)
    step = detect3d.make_train_step(
        training_model(model, c),
        tx,
        constants,
        builders.loss_config(c),
        c,
        mesh,
        jax.tree.map(lambda _: rep, state),
    )
    rng = np.random.default_rng(0)
    h, w, m = c.data.height, c.data.width, c.data.max_objects
    P2 = np.array([[700.0, 0, w / 2, 45], [0, 700.0, 75 * h / 288, 0], [0, 0, 1, 0.005]])
    x1 = rng.uniform(0, w - 100, (batch_size, m))
    y1 = rng.uniform(h / 3, h - 60, (batch_size, m))
    boxes = np.stack([x1, y1, x1 + rng.uniform(20, 100, x1.shape), y1 + 40], -1)
    batch = {
        "image": rng.standard_normal((batch_size, h, w, 3)).astype(np.float32),
        "P2": np.broadcast_to(P2, (batch_size, 3, 4)).astype(np.float32),
        "gt_mask": np.arange(m)[None].repeat(batch_size, 0) < 6,
        "gt_class": np.zeros((batch_size, m), np.int32),
        "gt_boxes": boxes.astype(np.float32),
        "gt_center": ((boxes[..., :2] + boxes[..., 2:]) / 2).astype(np.float32),
        "gt_depth": rng.uniform(5, 50, (batch_size, m)).astype(np.float32),
        "gt_dims": np.tile([1.5, 1.6, 3.9], (batch_size, m, 1)).astype(np.float32),
        "gt_alpha": rng.uniform(-3, 3, (batch_size, m)).astype(np.float32),
    }
    batch = parallel.to_global(batch, mesh)
    return dict(
        config=c, model=model, constants=constants, tx=tx, mesh=mesh, state=state,
        state_sharding=jax.tree.map(lambda _: rep, state), batch=batch, step=step, init_s=init_s,
        num_anchors=a,
    )  # fmt: skip
