"""Times the ground-aware depth U-Net of the paper's KITTI config on this machine.

* inference: frames/s of the jitted ``scale_1`` prediction at 352x1216, ResNet-34, float32,
  batch 1 (network only: no data loading, no PNG writing);
* training: one optimizer step of ``configs/depth_kitti.py`` (loss on all three scales,
  Adam, clipping) at 352x1216 for the given batch sizes. The paper trains with batch 8 on a
  GPU; on a small CPU batch 8 is slow and large, so the default measures batch 1 and 2.

Compilation is timed separately (first call); the step times are medians of ``--repeats``
calls on random inputs with a KITTI projection. Prints a JSON record (``--json OUT`` saves it).

    python benchmarks/bench_depth.py [--variant ''|base|reference] [--train-batches 1,2]
    python benchmarks/bench_depth.py --config configs/depth_default.py --train-batches 8

``--config`` times another depth config at its own input size (e.g. the CPU default run).
"""

from __future__ import annotations

import argparse
import json
import statistics
import sys
import time
from pathlib import Path

import jax
import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from gac_jax.cpu_backend import apply_default_xla_flags  # noqa: E402

# Measure what train.py / evaluate.py run with (GAC_JAX_DEFAULT_XLA_FLAGS=0: JAX's own).
apply_default_xla_flags()

from machine_info import describe_machine  # noqa: E402  (benchmarks/ is on sys.path)

from gac_jax.builders import depth as depth_builders  # noqa: E402
from gac_jax.config import load_config  # noqa: E402
from gac_jax.trainers import depth  # noqa: E402
from gac_jax.trainers.common import create_train_state  # noqa: E402
from gac_jax.training import parallel  # noqa: E402
from gac_jax.training.train_state import learning_rate_schedule, make_optimizer  # noqa: E402

REPO = Path(__file__).resolve().parents[1]
# KITTI 2011_09_26 P_rect_02 with the 23 top rows cropped (375 -> 352).
P_CROP = np.array(
    [[721.5377, 0.0, 609.5593, 44.85728], [0.0, 721.5377, 149.854, 0.2163791], [0, 0, 1, 0.00274]]
)


def timed(fn, repeats: int) -> tuple[float, float, list[float], float]:
    """(first call = compile + run, median wall time of the next ``repeats`` calls, those wall
    times, median CPU seconds of this process (all threads) per call).

    On a shared machine the CPU time is the steadier figure: wall ~ CPU / usable cores.
    """
    t0 = time.perf_counter()
    jax.block_until_ready(fn())
    first = time.perf_counter() - t0
    times, cpu = [], []
    for _ in range(repeats):
        t0, c0 = time.perf_counter(), time.process_time()
        jax.block_until_ready(fn())
        times.append(time.perf_counter() - t0)
        cpu.append(time.process_time() - c0)
    return first, statistics.median(times), times, statistics.median(cpu)


def inputs(config, batch: int, width: int, seed: int = 0):
    """Random images and sparse depth with the KITTI projection of the config's input view."""
    height = config.data.height
    rng = np.random.default_rng(seed)
    images = rng.normal(size=(batch, height, width, 3)).astype(np.float32)
    scale = np.diag([height / config.data.crop_height] * 2 + [1.0])
    P = np.repeat((scale @ P_CROP)[None].astype(np.float32), batch, 0)
    z = rng.uniform(3.0, 80.0, (batch, height, width)).astype(np.float32)
    gt = np.where(rng.random((batch, height, width)) < 0.15, z, 0.0).astype(np.float32)
    return images, P, gt


def bench_inference(config, model, variables, repeats: int) -> dict:
    d = config.data
    images, P, _ = inputs(config, 1, d.eval_width)
    predict = jax.jit(lambda v, x, p: model.apply(v, x, p, train=False)["log_depth"]["scale_1"])
    first, median, times, cpu = timed(lambda: predict(variables, images, P), repeats)
    return {
        "input": [1, d.height, d.eval_width, 3],
        "compile_plus_first_s": first,
        "compile_s_estimate": first - median,
        "median_s": median,
        "frames_per_s": 1.0 / median,
        "median_cpu_s": cpu,
        "times_s": times,
    }


def bench_train(config, model, variables, batch: int, repeats: int) -> dict:
    d = config.data
    mesh = parallel.make_mesh(jax.devices()[:1])
    schedule = learning_rate_schedule(1e-4, 1e-5, 1000, 100)
    tx = make_optimizer(schedule, config.train.clip_norm, config.train.weight_decay)
    host = jax.tree.map(np.asarray, variables)
    state, sharding = create_train_state(host, tx, 0, mesh)
    step = depth.make_train_step(model, tx, depth_builders.loss_options(config), mesh, sharding)
    images, P, gt = inputs(config, batch, d.width, seed=batch)
    arrays = parallel.to_global({"image": images, "P2": P, "depth": gt}, mesh)
    holder = {"state": state}

    def run():
        holder["state"], metrics = step(holder["state"], arrays)
        return metrics["loss"]

    first, median, times, cpu = timed(run, repeats)
    return {
        "batch": batch,
        "input": [batch, d.height, d.width, 3],
        "compile_plus_first_s": first,
        "compile_s_estimate": first - median,
        "median_step_s": median,
        "images_per_s": batch / median,
        "median_cpu_s": cpu,
        "times_s": times,
    }


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--config", default=str(REPO / "configs" / "depth_kitti.py"))
    parser.add_argument("--variant", default="", help="config variant: '', base, reference")
    parser.add_argument("--repeats", type=int, default=10, help="timed inference calls")
    parser.add_argument("--train-repeats", type=int, default=5, help="timed train steps")
    parser.add_argument("--train-batches", default="1,2", help="comma-separated batch sizes")
    parser.add_argument("--json", help="also write the record here")
    args = parser.parse_args(argv)

    spec = args.config + (f":{args.variant}" if args.variant else "")
    config = load_config(spec)
    model = depth_builders.build_model(config, prior_mean=2.6)
    t0 = time.perf_counter()
    variables = jax.block_until_ready(depth_builders.init_variables(model, config, 0))
    init_s = time.perf_counter() - t0
    params = sum(x.size for x in jax.tree.leaves(variables["params"]))
    record = {
        "machine": describe_machine("numpy", "jax"),
        "model": {
            "config": spec.split("/")[-1],
            "encoder": f"ResNet-{config.model.encoder_depth} width {config.model.encoder_width}",
            "use_gac": config.model.use_gac,
            "decoder_conv": config.model.decoder_conv,
            "parameters": int(params),
            "dtype": "float32",
            "init_s": init_s,
        },
        "inference": bench_inference(config, model, variables, args.repeats),
        "train": [],
    }
    print(
        json.dumps({k: record[k] for k in ("machine", "model", "inference")}, indent=2), flush=True
    )
    for b in (int(x) for x in args.train_batches.split(",") if x.strip()):
        record["train"].append(bench_train(config, model, variables, b, args.train_repeats))
        print(json.dumps(record["train"][-1], indent=2), flush=True)
    if args.json:
        Path(args.json).write_text(json.dumps(record, indent=2) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
