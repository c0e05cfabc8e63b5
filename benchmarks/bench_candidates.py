"""Cost of the candidate cap: jitted predict (+ transfer) and host post-processing per top_k.

Paper geometry (configs/detect3d_kitti.py: 288x1280, 46 080 anchors), made-up valid priors.
``top_k`` 100, 4096 (the KITTI config's cap) and None (every anchor).

* selection: the network replaced by given outputs (decode + invalid-prior and ground
  masks + count + top_k + gather, and the device->host transfer of the candidates), batch 1
  and 8: what the cap itself costs;
* post-processing (host): threshold, NMS, hill climbing, back-projection for one image with
  60 ("typical") or 600 ("crowded") anchors above the threshold;
* ``--full``: the whole jitted predict with the ResNet-101 detector (random weights), batch 1.

Variants alternate call by call (same machine load); medians (and min) in ms per call.

    python benchmarks/bench_candidates.py [--rounds 15] [--full] [--full-rounds 3]
"""

from __future__ import annotations

import argparse
import statistics
import sys
import time
from pathlib import Path

from machine_info import describe_machine, one_line  # benchmarks/ is on sys.path

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))
from gac_jax.cpu_backend import apply_default_xla_flags  # noqa: E402

apply_default_xla_flags()

TOP_KS = (100, 4096, None)
P2 = [[754.4, 0.0, 644.6, 48.8], [0.0, 754.2, 85.9, -0.9], [0.0, 0.0, 1.0, 0.005]]


class GivenOutputs:
    def apply(self, variables, images, P2, train, plane=None):
        return variables


def setup():
    import jax.numpy as jnp
    import numpy as np

    from gac_jax.builders.detect3d import anchor_layout, filter_options
    from gac_jax.config import load_config
    from gac_jax.detection.anchor_filter import ground_filter_mask_np
    from gac_jax.detection.anchor_priors import DetectionConstants
    from gac_jax.detection.anchors import generate_anchors

    config = load_config(str(REPO / "configs" / "detect3d_kitti.py"))
    anchors = generate_anchors(anchor_layout(config))
    n = len(anchors.boxes)
    rng = np.random.default_rng(0)
    mean = np.stack([rng.uniform(5, 60, n), np.zeros(n), np.zeros(n)], -1)[None]
    constants = DetectionConstants(
        anchor_boxes=jnp.asarray(anchors.boxes, jnp.float32),
        anchor_centers=jnp.asarray(anchors.centers, jnp.float32),
        prior_mean=jnp.asarray(mean, jnp.float32),
        prior_std=jnp.ones((1, n, 3), jnp.float32),
        prior_valid=jnp.ones((1, n), bool),
        dims_mean=jnp.asarray([[1.5, 1.6, 3.9]], jnp.float32),
        dims_std=jnp.asarray([[0.15, 0.1, 0.4]], jnp.float32),
        angle_mode="double",
    )
    options = filter_options(config)
    kept = ground_filter_mask_np(
        anchors.centers, mean[..., 0], np.ones((1, n), bool), np.asarray(P2)[None], **options
    )[0]
    return config, constants, options, kept


def outputs(kept, batch: int, above: int, seed: int = 1):
    """Given network outputs with ``above`` ground-filter-kept anchors per image above 0.75."""
    import numpy as np

    n = len(kept)
    rng = np.random.default_rng(seed)
    logits = rng.uniform(-8.0, 0.0, (batch, n, 1)).astype(np.float32)
    for b in range(batch):
        chosen = rng.choice(np.flatnonzero(kept), above, replace=False)
        logits[b, chosen, 0] = rng.uniform(1.3, 9.0, above)
    return {
        "cls_logits": logits,
        "sign_logits": rng.normal(size=(batch, n)).astype(np.float32),
        "reg": (0.3 * rng.normal(size=(batch, n, 12))).astype(np.float32),
    }


def timed(fn, *args) -> float:
    """Milliseconds of ``fn(*args)`` with its result fetched to the host."""
    import jax

    t0 = time.perf_counter()
    jax.device_get(fn(*args))
    return 1e3 * (time.perf_counter() - t0)


def report(title: str, times: dict) -> None:
    print(f"\n{title}: ms per call, median (min)")
    for key, t in times.items():
        name = "None (all)" if key is None else str(key)
        print(f"  top_k {name:10s} {statistics.median(t):9.2f} ({min(t):.2f})")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--rounds", type=int, default=15)
    parser.add_argument("--full", action="store_true", help="also the ResNet-101 predict")
    parser.add_argument("--full-rounds", type=int, default=3)
    args = parser.parse_args()
    import jax
    import numpy as np

    from gac_jax.detection.inference import PostprocessConfig, make_predict_fn, postprocess

    print(one_line(describe_machine("numpy", "jax")), flush=True)
    config, constants, options, kept = setup()
    n = len(kept)
    print(f"{n} anchors, {kept.sum()} kept by the ground filter for this P2")
    post = PostprocessConfig(score_threshold=config.eval.score_threshold)
    for batch in (1, 8):
        given = outputs(kept, batch, 60)
        images = np.zeros((batch, 8, 8, 3), np.float32)
        P2s = np.tile(np.asarray(P2, np.float32), (batch, 1, 1))
        fns = {}
        for k in TOP_KS:
            fn = make_predict_fn(
                GivenOutputs(), constants, top_k=k, score_threshold=0.75, filter_options=options
            )
            fns[k] = fn.lower(given, images, P2s).compile()
        times = {k: [] for k in TOP_KS}
        for _ in range(args.rounds):
            for k, fn in fns.items():
                times[k].append(timed(fn, given, images, P2s))
        report(f"selection + transfer, batch {batch} ({n} anchors)", times)

    sample = {
        "P2": np.asarray(P2, np.float32)[None],
        "image": np.zeros((1, 288, 1280, 3), np.float32),
        "image_transform": np.eye(3)[None],
        "original_size": np.array([[375, 1242]]),
    }
    for label, above in (("typical", 60), ("crowded", 600)):
        given = outputs(kept, 1, above, seed=2)
        cands = {}
        for k in TOP_KS:
            fn = make_predict_fn(
                GivenOutputs(), constants, top_k=k, score_threshold=0.75, filter_options=options
            )
            cands[k] = jax.device_get(fn(given, sample["image"][:, :8, :8], sample["P2"]))
        times = {k: [] for k in TOP_KS}
        for _ in range(max(args.rounds // 3, 3)):
            for k, c in cands.items():
                times[k].append(timed(postprocess, c, sample, ("Car",), post))
        counts = {k: int(c["num_candidates"][0]) for k, c in cands.items()}
        report(f"host post-processing, {label} (kept above threshold: {counts[None]})", times)

    if args.full:
        from gac_jax.builders.detect3d import anchor_layout, build_model, init_variables

        model = build_model(config, anchor_layout(config).anchors_per_cell)
        variables = init_variables(model, config, seed=0)
        images = np.random.default_rng(0).normal(size=(1, 288, 1280, 3)).astype(np.float32)
        P2s = np.asarray(P2, np.float32)[None]
        fns = {}
        for k in TOP_KS:
            t0 = time.perf_counter()
            fn = make_predict_fn(model, constants, top_k=k, score_threshold=0.75)
            fns[k] = fn.lower(variables, images, P2s).compile()
            print(f"compiled top_k {k}: {time.perf_counter() - t0:.1f} s", flush=True)
        times = {k: [] for k in TOP_KS}
        for _ in range(args.full_rounds):
            for k, fn in fns.items():
                times[k].append(timed(fn, variables, images, P2s))
        report("full predict, ResNet-101 288x1280, batch 1", times)


if __name__ == "__main__":
    main()
