"""Runs a detector over a split, writes KITTI result files per frame and scores them.

Shared by the trainer (periodic and final evaluation) and ``evaluate.py``.
Device work is one jitted predict function (fixed batch shape: the last batch
is padded); NMS, hill climbing, file I/O and the KITTI AP run on the host.
Result files are named by frame id and written atomically as each batch
finishes, so an interrupted run resumes without redoing finished frames. Reading
and transforming the next batch, and writing the results, run on one host thread
beside the network and post-processing (``overlap_io``).
"""

from __future__ import annotations

import dataclasses
import os
import time
from collections.abc import Callable, Sequence
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

from gac_jax.data.kitti import KittiObjects, read_label, write_label
from gac_jax.data.loader import Loader, collate, plane_array
from gac_jax.detection.inference import PostprocessConfig, make_predict_fn, postprocess
from gac_jax.evaluation.kitti_object import evaluate_detections
from gac_jax.evaluation.operating_point import check_beta, operating_point
from gac_jax.geometry import DEFAULT_CAMERA_HEIGHT

INPUT_KEYS = ("image", "P2", "plane", "image_transform", "original_size")


@dataclasses.dataclass(frozen=True)
class InputArrays:
    """Picklable ``sample -> arrays`` with only what prediction needs (plus the frame id);
    ``camera_height`` gives the level plane of frames without a ``plane``."""

    camera_height: float = DEFAULT_CAMERA_HEIGHT

    def __call__(self, sample: dict) -> dict[str, np.ndarray]:
        image = np.asarray(sample["image"], np.float32)
        return {
            "image": image,
            "P2": np.asarray(sample["P2"], np.float32),
            "plane": plane_array(sample, self.camera_height),
            "image_transform": np.asarray(sample["image_transform"], np.float32),
            "original_size": np.asarray(sample["original_size"], np.int32),
            "frame_id": np.asarray(sample["frame_id"]),
        }


def _default_readers() -> int:
    cores = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count()
    return 1 if (cores or 1) <= 4 else 2


class _Deferred:
    """``fn(*args)`` run when its result is asked for (the serial loop's stand-in for a Future)."""

    def __init__(self, fn: Callable, args: tuple):
        self._fn, self._args = fn, args

    def result(self):
        return self._fn(*self._args)


class _HostWork:
    """Where :meth:`DetectionEvaluator.predict_split` reads and writes.

    ``readers`` > 0: that many host threads read and transform batches (submitted in
    order, taken in order) and one more thread writes the result files, in submission
    (frame) order. ``readers == 0``: the calling thread reads when a batch is asked
    for and writes at once (the serial loop). Leaving the block waits for every
    submitted task and raises the first failed write.
    """

    def __init__(self, readers: int):
        self.readers = readers
        self._pools = []
        if readers:
            self._pools = [
                ThreadPoolExecutor(readers, thread_name_prefix="gac-eval-read"),
                ThreadPoolExecutor(1, thread_name_prefix="gac-eval-write"),
            ]
        self._writes: list = []

    def read(self, fn: Callable, *args):
        """A future (or, serially, a deferred call) of ``fn(*args)``."""
        return self._pools[0].submit(fn, *args) if self._pools else _Deferred(fn, args)

    def write(self, fn: Callable, *args) -> None:
        for future in self._writes:  # an earlier write failed: stop here
            if future.done() and future.exception() is not None:
                future.result()
        if not self._pools:
            fn(*args)
            return
        self._writes.append(self._pools[1].submit(fn, *args))

    def __enter__(self) -> _HostWork:
        return self

    def __exit__(self, exc_type, exc, tb) -> bool:
        for pool in self._pools:
            pool.shutdown(wait=True)
        if exc_type is None:
            for future in self._writes:
                future.result()
        return False


def ground_truth(source, index: int) -> KittiObjects:
    """Original labels of a source frame (label file when the source is a folder)."""
    layout = getattr(source, "layout", None)
    frame_ids = getattr(source, "frame_ids", None)
    if layout is not None and frame_ids is not None:
        return read_label(layout.label(frame_ids[index]))
    return source[index]["objects"]


class DetectionEvaluator:
    """Predict + post-process + (optionally) write + score one split.

    Args:
      model: the Detector.
      constants: anchors/priors (:class:`gac_jax.detection.anchor_priors.DetectionConstants`).
      source: a left-image object source of the split (labels needed to score).
      transform: the test-time transform chain (crop, resize, pad, normalise).
      class_names: class order of the model.
      postprocess_config: host post-processing.
      batch_size: images per predict call.
      top_k: candidates per image from the device (``None``: every anchor). Frames
        with more filter-kept anchors above the score threshold than that are
        counted (:meth:`candidate_summary`); the reference keeps them all.
      filter_options: ground filter options (as in training).
      use_ground_filter: apply the ground-plane anchor filter.
      worker_count: loader worker processes.
      camera_height: the level ground plane of frames without a ``planes/`` file.
      overlap_io: read the next batches and write the results on host threads while
        the network and post-processing run (:meth:`predict_split`); False: serially.
      io_threads: threads reading ahead with ``overlap_io`` (default: 1 on up to 4 usable
        cores, else 2); results are the same for any count.
      operating_point_beta: the F-beta of :meth:`evaluate`'s operating point
        (:mod:`gac_jax.evaluation.operating_point`).
    """

    def __init__(
        self,
        model,
        constants,
        source,
        transform,
        class_names: Sequence[str],
        postprocess_config: PostprocessConfig,
        *,
        batch_size: int = 8,
        top_k: int | None = 4096,
        filter_options: dict | None = None,
        use_ground_filter: bool = True,
        worker_count: int = 0,
        camera_height: float = DEFAULT_CAMERA_HEIGHT,
        overlap_io: bool = True,
        io_threads: int | None = None,
        operating_point_beta: float = 1.0,
    ):
        self.source = source
        self.operating_point_beta = check_beta(operating_point_beta)
        self.overlap_io = overlap_io
        self.io_threads = io_threads if io_threads is not None else _default_readers()
        self.class_names = tuple(class_names)
        self.batch_timings: list[dict[str, float]] = []
        self.top_k = top_k
        self.candidate_counts: dict[str, int] = {}  # frame id -> anchors above threshold
        self.num_kept = 0  # candidates the device returns per image (min(top_k, anchors))
        self.postprocess_config = postprocess_config
        self.batch_size = batch_size
        self.predict = make_predict_fn(
            model,
            constants,
            top_k=top_k,
            score_threshold=postprocess_config.score_threshold,
            filter_options=filter_options,
            use_ground_filter=use_ground_filter,
        )
        self.loader = Loader(
            source,
            transform,
            InputArrays(camera_height),
            batch_size=batch_size,
            shuffle=False,
            drop_remainder=False,
            num_epochs=1,
            worker_count=worker_count,
        )

    def compile(self, variables, image_size: tuple[int, int]) -> float:
        """Compiles predict ahead of time for ``(batch_size, H, W, 3)`` inputs; returns seconds.

        Afterwards every batch runs the one compiled executable (inputs of another
        shape raise instead of recompiling), and ``model_s`` no longer includes
        compilation.
        """
        h, w = image_size
        images = jax.ShapeDtypeStruct((self.batch_size, h, w, 3), jnp.float32)
        P2 = jax.ShapeDtypeStruct((self.batch_size, 3, 4), jnp.float32)
        plane = jax.ShapeDtypeStruct((self.batch_size, 4), jnp.float32)
        t0 = time.perf_counter()
        self.predict = self.predict.lower(variables, images, P2, plane).compile()
        return time.perf_counter() - t0

    def frame_ids(self) -> list[str]:
        ids = getattr(self.source, "frame_ids", None)
        if ids is not None:
            return list(ids)
        return [self.source[i]["frame_id"] for i in range(len(self.source))]

    def _load_batch(self, indices: Sequence[int], epoch: int) -> dict[str, np.ndarray]:
        """Reads and transforms frames ``indices``, padded to the compiled batch size."""
        batch = collate([self.loader.load_sample(i, epoch) for i in indices])
        n = len(batch["frame_id"])
        if n < self.batch_size:  # pad to the compiled batch shape
            batch = collate(
                [{k: v[min(i, n - 1)] for k, v in batch.items()} for i in range(self.batch_size)]
            )
        return batch

    def predict_split(
        self,
        variables,
        result_dir: str | Path | None = None,
        resume: bool = True,
        max_batches: int | None = None,
    ) -> tuple[dict[str, KittiObjects], dict[str, float]]:
        """Detections of every frame (by frame id) and timings (seconds).

        With :attr:`overlap_io` (the default) :attr:`io_threads` host threads read and
        transform the next batches while this one is in the network and post-processing,
        and one more writes each batch's result files (in frame order) while the next
        batch runs;
        results and files are those of the serial loop (``overlap_io = False``), and
        an error of a read or a write is raised here as in the serial loop.

        Timings cover the frames predicted in this call (not resumed ones); the
        per-batch split is kept in :attr:`batch_timings` (``frames``, ``io_s``,
        ``model_s``, ``postprocess_s`` per batch, padding excluded from ``frames``);
        ``io_s`` is the time the loop waited for reading + transforming and writing
        (all of it without the overlap).
        """
        result_dir = Path(result_dir) if result_dir is not None else None
        all_ids = self.frame_ids()
        done: dict[str, KittiObjects] = {}
        if result_dir is not None and resume:
            for fid in all_ids:
                path = result_dir / f"{fid}.txt"
                if path.exists():
                    done[fid] = read_label(path, with_score=True)
        timings = {"model_s": 0.0, "postprocess_s": 0.0, "io_s": 0.0}
        self.batch_timings = []
        self.candidate_counts = {}
        results = dict(done)
        steps = self.loader.steps_per_epoch
        work = []  # (epoch, frame indices) of the batches to predict
        for step in range(steps if max_batches is None else min(steps, max_batches)):
            epoch, indices = self.loader.step_indices(step)
            todo = [i for i in indices if all_ids[i] not in done]  # resume: only missing frames
            if todo:
                work.append((epoch, todo))

        def write(fids: list[str], objects: list[KittiObjects]) -> None:
            for fid, obj in zip(fids, objects, strict=True):
                write_label(result_dir / f"{fid}.txt", obj, with_score=True)

        with _HostWork(self.io_threads if self.overlap_io else 0) as host:
            ahead = max(host.readers, 1)  # batches read ahead of the one in the network
            loads = [host.read(self._load_batch, todo, ep) for ep, todo in work[:ahead]]
            for j, (_, todo) in enumerate(work):
                t_start = time.perf_counter()
                batch = loads[j].result()
                loads[j] = None  # the batch is not kept past its step
                if j + ahead < len(work):
                    next_epoch, next_todo = work[j + ahead]
                    loads.append(host.read(self._load_batch, next_todo, next_epoch))
                n = len(todo)
                t0 = time.perf_counter()
                candidates = self.predict(variables, batch["image"], batch["P2"], batch["plane"])
                candidates = {k: np.asarray(v)[:n] for k, v in candidates.items()}  # no padding
                t1 = time.perf_counter()
                self.num_kept = int(candidates["scores"].shape[1])
                fids = [str(f) for f in batch["frame_id"][:n]]
                for fid, count in zip(fids, candidates["num_candidates"], strict=True):
                    self.candidate_counts[fid] = int(count)
                objects = postprocess(candidates, batch, self.class_names, self.postprocess_config)
                t2 = time.perf_counter()
                results.update(zip(fids, objects, strict=True))
                if result_dir is not None:
                    host.write(write, fids, objects)
                t3 = time.perf_counter()
                split = {
                    "frames": float(n),
                    "io_s": (t0 - t_start) + (t3 - t2),  # read + transform, write (waited for)
                    "model_s": t1 - t0,  # device call incl. the transfer back
                    "postprocess_s": t2 - t1,
                }
                self.batch_timings.append(split)
                for key in timings:
                    timings[key] += split[key]
            t_end = time.perf_counter()
        if self.batch_timings:  # the writes still running when the loop ended
            wait = time.perf_counter() - t_end
            self.batch_timings[-1]["io_s"] += wait
            timings["io_s"] += wait
        timings["num_frames"] = float(len(results) - len(done))
        return results, timings

    def candidate_summary(self) -> dict:
        """How the candidate cap fared on the frames predicted by the last run.

        ``top_k``: candidates kept per image (``None``: every anchor);
        ``frames_over_cap``: frames with more filter-kept anchors above the score
        threshold than were kept (those lost candidates before NMS; 0 expected);
        ``max_candidates``: the largest such count of one frame.
        """
        counts = list(self.candidate_counts.values())
        over = [c for c in counts if self.num_kept and c > self.num_kept]
        return {
            "top_k": self.top_k,
            "kept_per_frame": self.num_kept,
            "frames": len(counts),
            "frames_over_cap": len(over),
            "max_candidates": max(counts, default=0),
        }

    def evaluate(
        self,
        variables,
        result_dir: str | Path | None = None,
        resume: bool = True,
        max_batches: int | None = None,
    ) -> dict:
        """Runs :meth:`predict_split` and the KITTI protocol.

        Returns ``{'metrics', 'timings', 'num_frames', 'candidates', 'operating_point'}``
        (:meth:`candidate_summary`; :func:`gac_jax.evaluation.operating_point.operating_point`
        of these detections).
        """
        detections, timings = self.predict_split(variables, result_dir, resume, max_batches)
        ids = self.frame_ids()
        index = [i for i, fid in enumerate(ids) if fid in detections]
        gt = [ground_truth(self.source, i) for i in index]
        dt = [detections[ids[i]] for i in index]
        t0 = time.perf_counter()
        metrics = evaluate_detections(gt, dt, classes=self.class_names)
        timings["kitti_eval_s"] = time.perf_counter() - t0
        return {
            "metrics": metrics,
            "timings": timings,
            "num_frames": len(index),
            "candidates": self.candidate_summary(),
            "operating_point": operating_point(
                gt,
                dt,
                self.class_names,
                self.postprocess_config.score_threshold,
                self.operating_point_beta,
            ),
        }
