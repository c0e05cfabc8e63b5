"""End-to-end speed of ``evaluate.py --task detect3d --workdir`` (predict + post-process + I/O).

Runs the model mode's code path (:func:`gac_jax.cli.evaluate_detector.
evaluate_detector_workdir`) on KITTI frames: by default the 13 real labelled frames of
``../shared`` repeated (symlinks under new ids) to ``--frames`` frames, in a temporary
folder. Weights are untrained (random initialisation, saved as converted weights), which
is fine for timing; the score threshold is 0 so every one of the ``top_k`` candidates
goes through NMS and hill climbing (an upper bound of the post-processing work).
Priors are computed from the same frames (min count 1).

Configs: ``paper`` = configs/detect3d_kitti.py (ResNet-101, 288x1280, batch 1);
``default`` = configs/detect3d_default.py (half-width ResNet-18, 160x720, its eval batch of 8).
Each runs in float32 and with ``Detector(dtype=bfloat16)`` (float32 parameters); as the
machine may be shared, the dtypes are also compared on the model call alone with the calls
alternating (same load for both), in wall and process-CPU time.
Reported: compile time (once, separately) and per-frame medians (means) of model,
post-processing and I/O time, end-to-end frames/s, and the process's CPU time per wall
second (at most the thread count; lower means other processes took cores).

    python benchmarks/bench_evaluate.py [--configs paper,default] [--dtypes float32,bfloat16]
        [--frames 16] [--default-frames 64] [--threads N] [--json OUT]
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import tempfile
import time
from pathlib import Path

from machine_info import describe_machine, one_line  # benchmarks/ is on sys.path

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))
from gac_jax.cpu_backend import apply_default_xla_flags  # noqa: E402

# Measure what train.py / evaluate.py run with (GAC_JAX_DEFAULT_XLA_FLAGS=0: JAX's own).
apply_default_xla_flags()

KITTI = REPO.parent / "shared" / "data" / "kitti_samples" / "object"
CONFIGS = {
    "paper": ("configs/detect3d_kitti.py", ["data.eval_batch_size=1"]),
    "default": ("configs/detect3d_default.py", []),
}


def make_dataset(src: Path, dst: Path, frames: int) -> None:
    """A KITTI folder of ``frames`` frames: the labelled frames of ``src`` repeated (symlinks)."""
    ids = (src / "ImageSets" / "labeled.txt").read_text().split()
    new_ids = [f"{i:06d}" for i in range(frames)]
    for kind, ext in (("image_2", "png"), ("calib", "txt"), ("label_2", "txt")):
        (dst / "training" / kind).mkdir(parents=True, exist_ok=True)
        for i, new in enumerate(new_ids):
            link = dst / "training" / kind / f"{new}.{ext}"
            link.symlink_to(src / "training" / kind / f"{ids[i % len(ids)]}.{ext}")
    (dst / "ImageSets").mkdir(parents=True, exist_ok=True)
    (dst / "ImageSets" / "bench.txt").write_text("\n".join(new_ids) + "\n")


def random_weights(config_spec: str, overrides: list[str], out: Path) -> None:
    import jax
    import numpy as np

    from gac_jax.builders.detect3d import anchor_layout, build_model, init_variables
    from gac_jax.config import apply_overrides, load_config
    from gac_jax.weights.pretrained import save_converted

    config = load_config(str(REPO / config_spec))
    apply_overrides(config, overrides)
    model = build_model(config, anchor_layout(config).anchors_per_cell)
    variables = jax.tree.map(np.asarray, init_variables(model, config, seed=0))
    save_converted(out, variables, {"kind": "gac_detector", "model": {}})


def interleaved_model_timing(workdir, config_spec, overrides, weights, dtypes, rounds) -> dict:
    """Model call alone, the dtypes alternating call by call so that they share the machine's
    load: median wall and process-CPU milliseconds per frame for each dtype."""
    import jax.numpy as jnp
    import numpy as np

    from gac_jax.builders.detect3d import eval_transform, filter_options
    from gac_jax.cli.evaluate_detector import load_detector
    from gac_jax.data.loader import Loader
    from gac_jax.data.sources import open_object_source
    from gac_jax.detection.inference import make_predict_fn
    from gac_jax.evaluation.detector_evaluator import InputArrays
    from gac_jax.trained.run_config import load_run_config

    config = load_run_config(workdir, config_spec, overrides)
    b = config.data.eval_batch_size
    source = open_object_source(config.data.root, config.data.val_split)
    batch = Loader(source, eval_transform(config), InputArrays(), batch_size=b, shuffle=False)
    batch = batch.load_batch(0)
    runs = {}
    for name in dtypes:
        det = load_detector(workdir, config, checkpoint=weights, dtype=getattr(jnp, name))
        predict = make_predict_fn(
            det.model, det.constants, top_k=config.eval.top_k, filter_options=filter_options(config)
        )
        fn = predict.lower(det.variables, batch["image"], batch["P2"]).compile()
        runs[name] = (fn, det.variables)
    times = {name: ([], []) for name in dtypes}
    for _ in range(rounds):
        for name, (fn, variables) in runs.items():
            w0, c0 = time.perf_counter(), time.process_time()
            out = fn(variables, batch["image"], batch["P2"])
            np.asarray(out["scores"])
            times[name][0].append((time.perf_counter() - w0) / b)
            times[name][1].append((time.process_time() - c0) / b)
    return {
        name: {"wall_ms": 1e3 * float(np.median(w)), "cpu_ms": 1e3 * float(np.median(c))}
        for name, (w, c) in times.items()
    }


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--configs", default="paper,default")
    parser.add_argument("--dtypes", default="float32,bfloat16")
    parser.add_argument("--frames", type=int, default=16, help="frames of the paper config")
    parser.add_argument("--default-frames", type=int, default=64, help="of the default config")
    parser.add_argument("--threads", type=int, help="XLA CPU threads (default: all usable)")
    parser.add_argument(
        "--data", type=Path, default=KITTI, help="KITTI object root (labeled split)"
    )
    parser.add_argument("--rounds", type=int, default=5, help="interleaved model-only calls")
    parser.add_argument("--json", type=Path)
    args = parser.parse_args(argv)

    from gac_jax.cli.model_mode import limit_cpu_threads

    threads = limit_cpu_threads(args.threads)
    import jax.numpy as jnp

    from gac_jax.cli.evaluate_detector import evaluate_detector_workdir

    print(
        f"{one_line(describe_machine('numpy', 'jax'))}, {threads} XLA threads; "
        f"frames from {args.data}",
        flush=True,
    )
    rows, models = [], {}
    with tempfile.TemporaryDirectory(prefix="bench_evaluate_") as tmp:
        tmp = Path(tmp)
        for name in args.configs.split(","):
            spec, extra = CONFIGS[name]
            data = tmp / f"kitti_{name}"
            make_dataset(args.data, data, args.frames if name == "paper" else args.default_frames)
            overrides = [
                "data.source=kitti",
                f"data.root={data}",
                "data.train_split=bench",
                "data.val_split=bench",
                "data.use_right_image=False",
                "anchors.prior_min_count=1",
                "eval.score_threshold=0.0",
                *extra,
            ]
            weights = tmp / f"weights_{name}"
            random_weights(spec, overrides, weights)
            for dtype_name in args.dtypes.split(","):
                print(f"\n=== {name} ({spec}), {dtype_name} ===", flush=True)
                t0, wall0 = os.times(), time.perf_counter()
                summary = evaluate_detector_workdir(
                    tmp / f"wd_{name}",
                    config_spec=str(REPO / spec),
                    overrides=overrides,
                    checkpoint=weights,
                    threads=threads,
                    dtype=getattr(jnp, dtype_name),
                    out_dir=tmp / f"wd_{name}" / f"eval_{dtype_name}",
                )
                t1, wall1 = os.times(), time.perf_counter()
                cpu = (t1.user - t0.user) + (t1.system - t0.system)
                rows.append(
                    {
                        "config": name,
                        "dtype": dtype_name,
                        "compile_s": summary["compile_s"],
                        "cpu_per_wall": cpu / (wall1 - wall0),  # <= threads; lower = contention
                        **summary["speed"],
                    }
                )
            if len(args.dtypes.split(",")) > 1 and args.rounds:
                models[name] = interleaved_model_timing(
                    tmp / f"wd_{name}",
                    str(REPO / spec),
                    overrides,
                    weights,
                    args.dtypes.split(","),
                    args.rounds,
                )
    load = os.getloadavg()
    print(f"\nload average at the end {load[0]:.2f}")
    header = (
        "config   dtype     compile s  model ms  post ms  io ms  frames/s  cpu/wall"
        "  (medians per frame)"
    )
    print(header)
    for r in rows:
        print(
            f"{r['config']:8s} {r['dtype']:9s} {r['compile_s']:9.1f} {r['model_ms_median']:9.1f} "
            f"{r['postprocess_ms_median']:8.1f} {r['io_ms_median']:6.1f} {r['frames_per_s']:9.2f} "
            f"{r['cpu_per_wall']:9.2f}"
        )
    if models:
        print("\nmodel call alone, dtypes interleaved (median ms per frame, wall / process CPU):")
        for name, per_dtype in models.items():
            cells = ", ".join(
                f"{d} {t['wall_ms']:.1f} / {t['cpu_ms']:.1f}" for d, t in per_dtype.items()
            )
            print(f"  {name}: {cells}")
    if args.json:
        args.json.write_text(json.dumps({"runs": rows, "model_only": models}, indent=2) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
