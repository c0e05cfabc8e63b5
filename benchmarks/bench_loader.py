"""Images/s of ONE loader worker for each config's training chain, and the workers a step
rate needs.

    python benchmarks/bench_loader.py                                # all chains, 100 img/s
    python benchmarks/bench_loader.py --chains paper --target-images-per-s 200 --batches 8

A worker runs what ``Loader.load_batch`` runs for one training batch: read and decode the
frames (PNG), the config's training transforms (crop, resize, photometric distortion, flip,
box re-projection...), the arrays and the collate. Measured here in one process with
``worker_count=0``, which is one grain worker's work without the shared-memory hand-over.
Chains (all on the embedded generated 375x1242 KITTI-format frames, generated on first use):

* ``paper``: ``configs/detect3d_kitti.py`` (the paper's 288x1280 crop, batch 8);
* ``default``: ``configs/detect3d_default.py`` (160x720);
* ``depth``: ``configs/depth_default.py`` (96x320);
* ``depth_paper``: ``configs/depth_kitti.py`` (352x1216 crops).

Two rates: images per second of wall time on this machine now (a loaded machine shares its
cores), and images per CPU-second (process time: the rate of a worker with a core of its own).
Workers needed = ceil(target / images per CPU-second): grain's workers are independent
processes, so this holds while each has a free core beside the trainer's own; the trainer's
progress line shows the device's wait for data (``data N%``) to check it in a run. Prints
medians over ``--batches`` batches after one warm-up batch, and the machine.
"""

from __future__ import annotations

import argparse
import json
import math
import statistics
import sys
import time
from pathlib import Path

from machine_info import describe_machine, one_line  # benchmarks/ is on sys.path

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))  # run from a checkout without installing

CHAINS = {
    "paper": ("detect3d", "detect3d_kitti.py"),
    "default": ("detect3d", "detect3d_default.py"),
    "depth": ("depth", "depth_default.py"),
    "depth_paper": ("depth", "depth_kitti.py"),
}


def chain_loader(name: str, batch_size: int | None):
    """The training Loader of chain ``name`` (in-process: ``worker_count=0``) and its config."""
    from gac_jax.config import load_config
    from gac_jax.data.loader import DepthArrays, DetectionArrays, Loader

    task, file = CHAINS[name]
    config = load_config(str(REPO / "configs" / file))
    # The embedded generated dataset of the default configs (one cache for every chain).
    default = load_config(str(REPO / "configs" / f"{task}_default.py"))
    config.data.source = "synthetic"
    config.data.synthetic = default.data.synthetic
    if batch_size:
        config.data.batch_size = batch_size
    d = config.data
    if task == "detect3d":
        from gac_jax.builders.datasets import prepare_dataset
        from gac_jax.builders.detect3d import train_transform
        from gac_jax.data.sources import open_object_source

        source = open_object_source(prepare_dataset(d), d.train_split, d.use_right_image)
        arrays = DetectionArrays(
            tuple(d.classes), d.max_objects, True, config.model.gac.camera_height
        )
    else:
        from gac_jax.builders.depth import depth_root, train_source, train_transform

        d.train_views = "both"  # the per-item work of 'random' too; needs no frame list
        source = train_source(config, depth_root(d))
        arrays = DepthArrays(config.model.gac.camera_height)
    loader = Loader(source, train_transform(config), arrays, batch_size=d.batch_size, seed=0)
    return loader, config


def measure(name: str, batches: int, batch_size: int | None) -> dict:
    loader, config = chain_loader(name, batch_size)
    d = config.data
    times, cpu = [], []
    for step in range(batches + 1):
        t0, c0 = time.perf_counter(), time.process_time()
        batch = loader.load_batch(step)
        times.append(time.perf_counter() - t0)
        cpu.append(time.process_time() - c0)
    median = statistics.median(times[1:])  # the first batch warms caches up
    cpu_median = statistics.median(cpu[1:])
    h, w = batch["image"].shape[1:3]
    return {
        "chain": name,
        "config": f"configs/{CHAINS[name][1]}",
        "input": f"{h}x{w}",
        "batch_size": d.batch_size,
        "batches": batches,
        "s_per_batch_median": round(median, 4),
        "images_per_s_one_worker": round(d.batch_size / median, 2),
        "cpu_s_per_batch_median": round(cpu_median, 4),
        "images_per_cpu_s": round(d.batch_size / cpu_median, 2),
        "configured_workers": d.num_workers,
    }


def main() -> None:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawTextHelpFormatter
    )
    parser.add_argument("--chains", default=",".join(CHAINS), help=f"of {', '.join(CHAINS)}")
    parser.add_argument("--batches", type=int, default=5, help="timed batches per chain")
    parser.add_argument("--batch-size", type=int, help="default: each config's")
    parser.add_argument("--target-images-per-s", type=float, default=100.0)
    parser.add_argument("--json", help="write the results here")
    args = parser.parse_args()
    import cv2

    machine = describe_machine("numpy", "cv2", "grain")
    machine["cv2_threads"] = cv2.getNumThreads()
    print(f"machine: {one_line(machine)}", flush=True)
    results = []
    for name in args.chains.split(","):
        if name not in CHAINS:
            parser.error(f"--chains: unknown chain {name!r} (known: {', '.join(CHAINS)})")
        r = measure(name, args.batches, args.batch_size)
        # A worker with a core of its own: its CPU time is its wall time.
        r["workers_for_target"] = math.ceil(args.target_images_per_s / r["images_per_cpu_s"])
        results.append(r)
        print(
            f"{name:12s} {r['config']:28s} {r['input']:>9s} batch {r['batch_size']}: "
            f"{r['s_per_batch_median']:.3f} s/batch ({r['cpu_s_per_batch_median']:.3f} CPU-s): "
            f"{r['images_per_s_one_worker']:.1f} img/s per worker here, "
            f"{r['images_per_cpu_s']:.1f} per CPU-s -> {r['workers_for_target']} worker(s) for "
            f"{args.target_images_per_s:g} img/s (configured: {r['configured_workers']})",
            flush=True,
        )
    if args.json:
        report = {"machine": machine, "target_images_per_s": args.target_images_per_s}
        Path(args.json).write_text(json.dumps(report | {"results": results}, indent=2) + "\n")


if __name__ == "__main__":
    main()
