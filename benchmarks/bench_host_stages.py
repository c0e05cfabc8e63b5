"""The detector's frame outside the network, per stage.

For the paper config (configs/detect3d_kitti.py: ResNet-101, 288x1280) and the default
config (configs/detect3d_default.py: half-width ResNet-18, 160x720), batch 1, random
weights, on the real KITTI frames (the 13 labelled frames of ``../shared/data/kitti_samples``
when present, else the 4 of ``tests/data/kitti``), each frame is timed stage by stage:

* ``read``: the source's frame (image file + ``cv2`` PNG decode, calibration, label);
* ``transform``: the test transform (crop top, float resize, crop/pad width, normalise) and
  the batch arrays;
* ``network``: the jitted model call (only to set the rest against; run once per frame, its
  outputs are replayed to the stages after it);
* ``decode``: the jitted decoding, anchor filter and top-k (``select_candidates``), to numpy;
* ``nms``, ``hill climbing``, ``post other`` (threshold, back-projection, mapping to original
  pixels: the rest of ``postprocess``);
* ``write``: the KITTI result file.

``host total`` is their sum without the network (the serial loop's non-network time).
``loop``: the evaluator's own loop (:meth:`DetectionEvaluator.predict_split`, result files
written) with the network replaced by a stand-in that waits ``--loop-network-ms`` (default
4 ms, a fast accelerator's time for the default detector) without using the CPU, and returns
the recorded outputs: ``loop non-network`` is its wall time per frame minus that wait, so
what overlapping reading/writing with the network saves shows there.

Settings as ``bench_runtimes.py``: score threshold 0 and ``top_k`` 100 (``--top-k``), so 100
candidates go through NMS and hill-climbing, a crowded frame. Each config runs in its own
worker process; every round writes the result files again and the report says whether all
rounds wrote the same files. Reported: per-stage medians over frames and rounds, the machine
and its load. Figures: docs/performance.md.

    python benchmarks/bench_host_stages.py [--configs paper,default] [--rounds 5]
        [--top-k 100] [--loop-network-ms 4] [--json OUT]
"""

from __future__ import annotations

import argparse
import hashlib
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

HERE = Path(__file__).resolve().parent
REPO = HERE.parent
CONFIGS = {"paper": "configs/detect3d_kitti.py", "default": "configs/detect3d_default.py"}
STAGES = (
    "read",
    "transform",
    "decode",
    "nms",
    "hill climbing",
    "post other",
    "write",
)


def kitti_root() -> Path:
    shared = REPO.parent / "shared" / "data" / "kitti_samples" / "object"
    return shared if (shared / "training" / "calib").is_dir() else REPO / "tests/data/kitti/object"


class Worker:
    """One config (``gac_jax`` imported from ``tree``, the repository): set up once, then
    :meth:`run_round` times every frame (stages, then the evaluator loop)."""

    def __init__(self, tree: Path, name: str, top_k: int, loop_network_ms: float, tmp: Path):
        sys.path.insert(0, str(tree))
        import jax
        import numpy as np

        from gac_jax.cpu_backend import apply_default_xla_flags

        apply_default_xla_flags()
        from random_weights import random_variables

        from gac_jax.builders import detect3d as builders
        from gac_jax.config import apply_overrides, load_config
        from gac_jax.data.sources import open_object_source
        from gac_jax.detection import inference
        from gac_jax.detection.anchor_priors import make_detection_constants
        from gac_jax.detection.anchors import generate_anchors
        from gac_jax.trained.detector import postprocess_config

        assert Path(inference.__file__).resolve().is_relative_to(tree.resolve())
        root = kitti_root()
        config = load_config(str(tree / CONFIGS[name]))
        apply_overrides(
            config,
            [
                "data.source=kitti",
                f"data.root={root}",
                "data.train_split=labeled",
                "anchors.prior_min_count=1",
                "eval.score_threshold=0.0",
                f"eval.top_k={top_k}",
            ],
        )
        layout = builders.anchor_layout(config)
        self.model = builders.build_model(config, layout.anchors_per_cell)
        self.variables = random_variables(self.model, config, builders.init_variables)
        priors = builders.compute_priors(config, root, layout, tmp / f"priors_{name}")
        constants = make_detection_constants(
            generate_anchors(layout), priors, builders.sign_axis(config)
        )
        self.inference, self.np, self.tmp = inference, np, tmp
        self.source = open_object_source(root, "labeled", use_right_image=False)
        self.transform = builders.eval_transform(config)
        self.classes, self.post = tuple(config.data.classes), postprocess_config(config)
        self.config, self.loop_network_s = config, loop_network_ms / 1e3
        filter_options, use_filter = builders.filter_options(config), config.anchors.filter
        self.select = jax.jit(
            lambda outputs, P2, plane: inference.select_candidates(
                outputs,
                constants,
                P2,
                top_k,
                filter_options,
                use_ground_filter=use_filter,
                plane=plane,
            )
        )
        network = jax.jit(lambda v, x, P, g: self.model.apply(v, x, P, train=False, plane=g))
        self.outputs, self.network_ms = [], []
        for i in range(len(self.source)):  # the network once per frame (after a warm-up)
            batch = self._batch(self.transform(self.source[i]))
            if i == 0:
                jax.block_until_ready(network(self.variables, *self._inputs(batch)))
            t0 = time.perf_counter()
            out = jax.block_until_ready(network(self.variables, *self._inputs(batch)))
            self.network_ms.append(1e3 * (time.perf_counter() - t0))
            self.outputs.append(jax.device_get(out))
        self.select(self.outputs[0], batch["P2"], batch["plane"])  # compile
        self.round = 0

    @staticmethod
    def _inputs(batch):
        return batch["image"], batch["P2"], batch["plane"]

    def _batch(self, sample):
        from gac_jax.data.loader import collate
        from gac_jax.evaluation.detector_evaluator import InputArrays

        return collate([InputArrays()(sample)])

    def _timed(self, times, key, fn):
        def wrapper(*args, **kwargs):
            t0 = time.perf_counter()
            try:
                return fn(*args, **kwargs)
            finally:
                times[key] = times.get(key, 0.0) + 1e3 * (time.perf_counter() - t0)

        return wrapper

    def run_round(self) -> dict:
        from gac_jax.data.kitti import write_label

        np, inference = self.np, self.inference
        nms, climb = inference.batched_nms, inference.optimize_rotation_y_batch
        out_dir = self.tmp / f"round{self.round}"
        frames = []
        try:
            for i in range(len(self.source)):
                times: dict[str, float] = {}
                inference.batched_nms = self._timed(times, "nms", nms)
                inference.optimize_rotation_y_batch = self._timed(times, "hill climbing", climb)
                t0 = time.perf_counter()
                sample = self.source[i]
                t1 = time.perf_counter()
                batch = self._batch(self.transform(sample))
                t2 = time.perf_counter()
                cand = self.select(self.outputs[i], batch["P2"], batch["plane"])
                cand = {k: np.asarray(v) for k, v in cand.items()}
                t3 = time.perf_counter()
                (objects,) = inference.postprocess(cand, batch, self.classes, self.post)
                t4 = time.perf_counter()
                write_label(out_dir / "stages" / f"{sample['frame_id']}.txt", objects, True)
                t5 = time.perf_counter()
                times.setdefault("hill climbing", 0.0)
                times.update(read=1e3 * (t1 - t0), transform=1e3 * (t2 - t1))
                times.update(decode=1e3 * (t3 - t2), write=1e3 * (t5 - t4))
                times["post other"] = 1e3 * (t4 - t3) - times["nms"] - times["hill climbing"]
                times["host total"] = sum(times[k] for k in STAGES)
                times["network"] = self.network_ms[i]
                times["detections"] = float(len(objects))
                frames.append(times)
        finally:
            inference.batched_nms, inference.optimize_rotation_y_batch = nms, climb
        loop = self._loop(out_dir / "loop")
        self.round += 1
        digest = hashlib.sha256()
        for kind in ("stages", "loop"):
            for path in sorted((out_dir / kind).glob("*.txt")):
                digest.update(path.name.encode() + path.read_bytes())
        return {"frames": frames, "loop": loop, "results_sha256": digest.hexdigest()}

    def _loop(self, out_dir: Path) -> dict:
        from gac_jax.evaluation.detector_evaluator import DetectionEvaluator

        evaluator = DetectionEvaluator(
            self.model, None, self.source, self.transform, self.classes, self.post,
            batch_size=1, top_k=self.config.eval.top_k,
        )  # fmt: skip
        replay = iter(self.outputs)

        def predict(variables, images, P2, plane):  # the network's time, without its CPU work
            time.sleep(self.loop_network_s)
            return self.select(next(replay), P2, plane)

        evaluator.predict = predict
        t0 = time.perf_counter()
        _, timings = evaluator.predict_split(self.variables, out_dir, resume=False)
        wall = time.perf_counter() - t0
        n = timings["num_frames"]
        return {
            "wall_ms": 1e3 * wall / n,
            "non_network_ms": 1e3 * (wall / n - self.loop_network_s),
            "io_ms": 1e3 * timings["io_s"] / n,
            "postprocess_ms": 1e3 * timings["postprocess_s"] / n,
        }


def worker_main(args) -> int:
    """Serves rounds over stdin/stdout (one JSON line each) for the parent process."""
    tmp = Path(tempfile.mkdtemp(prefix="bench_host_worker_"))
    worker = Worker(Path(args.worker), args.configs, args.top_k, args.loop_network_ms, tmp)
    print(json.dumps({"ready": len(worker.source)}), flush=True)
    for line in sys.stdin:
        if line.strip() != "round":
            break
        print(json.dumps(worker.run_round()), flush=True)
    return 0


def start_worker(tree: Path, name: str, args) -> subprocess.Popen:
    cmd = [sys.executable, str(Path(__file__).resolve()), "--worker", str(tree)]
    cmd += ["--configs", name, "--top-k", str(args.top_k)]
    cmd += ["--loop-network-ms", str(args.loop_network_ms)]
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(tree), str(HERE)])}
    proc = subprocess.Popen(cmd, stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True, env=env)
    ready = json.loads(proc.stdout.readline())
    print(f"  {tree}: ready ({ready['ready']} frames)", flush=True)
    return proc


def ask(proc: subprocess.Popen) -> dict:
    proc.stdin.write("round\n")
    proc.stdin.flush()
    line = proc.stdout.readline()
    if not line:
        raise RuntimeError("benchmark worker ended early (see its error above)")
    return json.loads(line)


def summarise(rounds: list[dict]) -> dict:
    import numpy as np

    frames = [f for r in rounds for f in r["frames"]]
    keys = ("network", *STAGES, "host total", "detections")
    out = {k: float(np.median([f[k] for f in frames])) for k in keys}
    for k in ("non_network_ms", "io_ms", "postprocess_ms", "wall_ms"):
        out[f"loop {k}"] = float(np.median([r["loop"][k] for r in rounds]))
    return out


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--configs", default="paper,default")
    p.add_argument("--rounds", type=int, default=5)
    p.add_argument("--top-k", type=int, default=100)
    p.add_argument("--loop-network-ms", type=float, default=4.0)
    p.add_argument("--json", type=Path)
    p.add_argument("--worker", help=argparse.SUPPRESS)
    args = p.parse_args(argv)
    if args.worker:
        return worker_main(args)

    from machine_info import describe_machine, one_line

    info = describe_machine("numpy", "cv2")
    print(one_line(info), f"frames from {kitti_root()}", flush=True)
    report = {"machine": info, "configs": {}}
    for name in args.configs.split(","):
        print(f"\n=== {name} ({CONFIGS[name]}), batch 1, top_k {args.top_k} ===", flush=True)
        proc = start_worker(REPO, name, args)
        rounds = [ask(proc) for _ in range(args.rounds)]
        proc.stdin.close()
        proc.wait()
        summary = summarise(rounds)
        same = len({r["results_sha256"] for r in rounds}) == 1
        report["configs"][name] = {"summary": summary, "identical_results": same}
        print(f"  {'stage (median ms/frame)':26s}{'median':>10s}")
        for key, value in summary.items():
            print(f"  {key:26s}{value:10.2f}")
        print(f"  result files identical across rounds: {'yes' if same else 'NO'}")
    info["load_avg_1min_end"] = round(os.getloadavg()[0], 2)
    print(f"\nload average (1 min) at the end: {info['load_avg_1min_end']}")
    if args.json:
        args.json.write_text(json.dumps(report, indent=2) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
