"""The 3D detector as a Python object: :class:`Detector3D`, RGB arrays in, :class:`Detections` out.

    det = Detector3D.from_workdir("runs/detect3d_default")
    detections = det.predict(image, P2)          # image: (H, W, 3) uint8 RGB, P2: (3, 4)
    for obj in detections: print(obj.name, obj.score, obj.location)

It is the code of ``evaluate.py --workdir`` and ``python -m gac_jax.cli.predict`` with plain
arrays in place of files: the weights (:func:`gac_jax.trained.detector.load_detector`), the
config's test transform, the jitted network + decoding + ground filter + top-k
(:func:`gac_jax.detection.inference.make_predict_fn`) or the exported network in ONNX Runtime
/ OpenVINO (:func:`gac_jax.deploy.runtime_choice.runtime_predict`), and the host NMS,
hill-climbing and mapping back to original pixels
(:func:`gac_jax.detection.inference.candidates_to_objects`), so the numbers are the same.

``predict`` is three stages, callable one by one (e.g. from threads of a video pipeline):
:meth:`Detector3D.prepare` (host: checks + test transform; thread-safe),
:meth:`Detector3D.infer` (the network on a list of prepared images, in chunks of
``batch_size``, the last one padded: one compiled shape; calls are serialised by a lock) and
:meth:`Detector3D.finish` (host post-processing; thread-safe).
"""

from __future__ import annotations

import copy
import dataclasses
import os
import threading
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import jax
import jax.numpy as jnp
import ml_collections
import numpy as np

from gac_jax.api import runtime_args
from gac_jax.api.detections import Detections
from gac_jax.api.inputs import (
    InputError,
    check_score_threshold,
    check_step,
    image_sample,
)
from gac_jax.api.stages import StagedModel, checked_prepared, padded_chunks
from gac_jax.builders.detect3d import eval_transform, filter_options
from gac_jax.config import ConfigError, apply_overrides
from gac_jax.deploy.int8 import Int8Settings
from gac_jax.detection.inference import candidates_to_objects, make_predict_fn
from gac_jax.evaluation.detector_evaluator import InputArrays
from gac_jax.trained.detector import LoadedDetector, load_detector, postprocess_config
from gac_jax.trained.operating_point import apply_deploy_threshold
from gac_jax.trained.run_config import load_run_config


@dataclasses.dataclass(frozen=True)
class PreparedImage:
    """One image after :meth:`Detector3D.prepare` (the network's view of it).

    Attributes:
      image: (h, w, 3) float32 normalised network input (``input_size``).
      P2: (3, 4) float32 projection of the network input.
      plane: (4,) float32 ground plane (the given one or the config's level camera).
      image_transform: (3, 3) float32 affine, original pixels -> input pixels.
      original_size: (H, W) of the given image.
      cut_off: the image is wider than the input after the resize: its right part is unseen.
    """

    image: np.ndarray
    P2: np.ndarray
    plane: np.ndarray
    image_transform: np.ndarray
    original_size: tuple[int, int]
    cut_off: bool


class Detector3D(StagedModel):
    """A trained GAC detector; build it with :meth:`from_workdir` or :meth:`from_weights`.

    Attributes:
      config: the run config; class_names: the model's classes (label order);
      input_size: (h, w) of the network input; runtime, precision: what runs the network;
      batch_size: images per network call; weights: where the weights came from; step: the
      checkpoint step (None for converted weights); score_threshold: detections below it are
      dropped; threshold_source: one line saying which threshold runs and where it came from
      (the operating point recorded for these weights, or the config's); load_s: seconds of
      setting up the runtime (exported runtimes: export on first use, load, warm-up; jax: the
      weights' transfer to the device; its jit compiles on the first call, or in :meth:`warmup`).
    """

    def __init__(
        self,
        detector: LoadedDetector,
        workdir: Path,
        runtime: str = "jax",
        precision: str = "f32",
        *,
        threads: int | None = None,
        batch_size: int = 1,
        export_dir: str | os.PathLike | None = None,
        int8: Int8Settings | None = None,
        requests: int = 1,
    ):
        import time

        self._detector = detector
        self._workdir, self._export_dir = Path(workdir), export_dir
        self._int8 = int8 if precision == "int8" else None
        config = detector.config
        self.runtime, self.precision, self.batch_size = runtime, precision, batch_size
        self.requests = runtime_args.check_positive_int(requests, "requests")
        self.input_size = (int(config.data.height), int(config.data.width))
        self.min_image_rows = int(config.data.crop_top) + 1  # the test transform crops the top
        self._transform = eval_transform(config)
        self._arrays = InputArrays(config.model.gac.camera_height)
        self._postprocess = postprocess_config(config)
        self.threshold_source = f"score threshold {float(config.eval.score_threshold):.2f}"
        self._lock = threading.Lock()
        t0 = time.perf_counter()
        if runtime == "jax":
            self._predict = make_predict_fn(
                detector.model,
                detector.constants,
                top_k=config.eval.top_k,
                score_threshold=config.eval.score_threshold,
                filter_options=filter_options(config),
                use_ground_filter=config.anchors.filter,
            )
            self._variables = jax.device_put(detector.variables)  # once, not per call
        else:
            from gac_jax.deploy.runtime_choice import runtime_predict

            with runtime_args.file_errors_as("workdir"):
                self._predict = runtime_predict(
                    detector,
                    workdir,
                    runtime,
                    precision,
                    batch_size,
                    export_dir=export_dir,
                    threads=threads,
                    int8=self._int8,
                    requests=requests,
                )
            self._variables = None
        self.load_s = time.perf_counter() - t0

    # ------------------------------------------------------------------ construction

    @classmethod
    def from_workdir(
        cls,
        workdir: str | os.PathLike,
        step: int | None = None,
        runtime: str = "jax",
        precision: str = "f32",
        threads: int | None = None,
        score_threshold: float | None = None,
        batch_size: int = 1,
        *,
        export_dir: str | os.PathLike | None = None,
        int8: Int8Settings | None = None,
        requests: int = 1,
    ) -> Detector3D:
        """The detector of a training workdir (``config.json``, ``anchor_priors.npz``,
        ``checkpoints/``) at checkpoint ``step`` (default: the latest).

        Args:
          runtime: ``jax`` (jitted), ``onnxruntime`` or ``openvino`` (the exported network,
            written to ``export_dir``, default ``W/export/step<N>``, on first use).
          precision: ``f32``; ``bf16`` (jax: bfloat16 compute dtype; openvino: native bf16
            kernels where the CPU has them); ``int8`` (openvino: the NNCF-quantized network,
            calibrated on the config's training split on first use).
          threads: CPU threads of ONNX Runtime / OpenVINO (default: every usable core).
          score_threshold: keep detections above it (default: the run's deployed threshold,
            its operating point where the config asks for it and one is recorded for these
            weights, else ``eval.score_threshold``; :mod:`gac_jax.trained.operating_point`).
          batch_size: images per network call.
          int8: how the int8 network is calibrated and which layers stay float32
            (:class:`~gac_jax.deploy.int8.Int8Settings`, e.g. ``keep_heading=True``;
            default settings if None).
          requests: network calls in flight at once through :meth:`infer_async` (ONNX
            Runtime / OpenVINO; OpenVINO compiles its throughput hint with that many streams).

        Raises:
          InputError: a missing workdir or step, a config / checkpoint that does not load, an
            unknown or unavailable runtime / precision, a bad threads / batch size / threshold.
        """
        workdir = runtime_args.check_workdir(workdir)
        step = check_step(step)
        score = check_score_threshold(score_threshold)
        options = runtime_args.model_options(runtime, precision, threads, batch_size, export_dir)
        overrides = [] if score is None else [f"eval.score_threshold={score!r}"]
        with runtime_args.file_errors_as("workdir"):
            config = load_run_config(workdir, None, overrides)
        if "anchors" not in config:
            raise InputError(
                "workdir",
                f"{workdir / 'config.json'}: not a detector run (no anchors; a depth run's "
                "workdir goes to DepthPredictor.from_workdir)",
            )
        try:
            detector = load_detector(workdir, config, step=step, dtype=_dtype(runtime, precision))
        except ValueError as e:  # KittiFormatError: a missing step or an unfitting checkpoint
            argument = "step" if step is not None and "no checkpoint step" in str(e) else "workdir"
            raise InputError(argument, str(e)) from None
        try:
            threshold_line = apply_deploy_threshold(workdir, detector, explicit=score is not None)
        except ValueError as e:  # an unknown eval.deploy_threshold
            raise InputError("workdir", f"{workdir / 'config.json'}: {e}") from None
        made = cls(detector, workdir, **options, int8=int8, requests=requests)
        made.threshold_source = threshold_line
        return made

    @classmethod
    def from_weights(
        cls,
        weights: str | os.PathLike,
        config: str | ml_collections.ConfigDict,
        runtime: str = "jax",
        precision: str = "f32",
        threads: int | None = None,
        score_threshold: float | None = None,
        batch_size: int = 1,
        *,
        workdir: str | os.PathLike | None = None,
        export_dir: str | os.PathLike | None = None,
        int8: Int8Settings | None = None,
        requests: int = 1,
    ) -> Detector3D:
        """The detector of converted weights (``python -m gac_jax.weights.convert``: ``OUT``
        or ``OUT/checkpoints/<step>``) with ``config`` (a config spec ``file.py[:arg]``, or a
        ConfigDict; copied, not changed).

        ``workdir`` holds the anchor priors (computed from the config's training split and
        cached there when absent) and the exports; default: the converted folder ``OUT``.
        Other arguments as :meth:`from_workdir`.
        """
        weights = Path(weights)
        if not weights.exists():
            raise InputError("weights", f"{weights}: not found")
        if workdir is None:
            workdir = weights.parent.parent if weights.parent.name == "checkpoints" else weights
        workdir = Path(workdir)
        score = check_score_threshold(score_threshold)
        options = runtime_args.model_options(runtime, precision, threads, batch_size, export_dir)
        overrides = [] if score is None else [f"eval.score_threshold={score!r}"]
        if isinstance(config, ml_collections.ConfigDict):
            config = copy.deepcopy(config)
            try:
                apply_overrides(config, overrides)
            except ConfigError as e:
                raise InputError("config", str(e)) from None
        elif isinstance(config, str | os.PathLike):
            with runtime_args.file_errors_as("config"):
                config = load_run_config(workdir, os.fspath(config), overrides)
        else:
            raise InputError("config", f"expected a config spec or a ConfigDict, got {config!r}")
        with runtime_args.file_errors_as("weights"):
            detector = load_detector(
                workdir, config, checkpoint=weights, dtype=_dtype(runtime, precision)
            )
        return cls(detector, workdir, **options, int8=int8, requests=requests)

    # ------------------------------------------------------------------ description

    @property
    def config(self) -> ml_collections.ConfigDict:
        return self._detector.config

    @property
    def class_names(self) -> tuple[str, ...]:
        return tuple(self._detector.config.data.classes)

    @property
    def weights(self) -> str:
        return self._detector.weights

    @property
    def step(self) -> int | None:
        return self._detector.step

    @property
    def score_threshold(self) -> float:
        return float(self._detector.config.eval.score_threshold)

    def __repr__(self) -> str:
        return f"Detector3D({self.weights}; {', '.join(self.class_names)}; {self._describe()})"

    def precision_line(self) -> str:
        """Which precision runs and what the accuracy guard (``python -m gac_jax.cli.guard``)
        decided for these weights and settings: the line ``evaluate.py`` and the predict CLI
        print, e.g. ``precision: openvino int8; not guarded for these weights (...)``."""
        from gac_jax.guard.verdict_file import precision_line

        int8 = (self._int8 or Int8Settings()) if self.precision == "int8" else None
        return precision_line(
            self._workdir, self._detector, self.runtime, self.precision, int8, self._export_dir
        )

    # ------------------------------------------------------------------ stages

    def prepare(self, image: np.ndarray, P2: Any, plane: Any = None) -> PreparedImage:
        """Checks one image and applies the config's test transform (crop the top rows,
        resize to the input height, crop/pad the width, normalise). Thread-safe.

        Args:
          image: (H, W, 3) uint8 RGB, any size taller than the config's ``data.crop_top``.
          P2: (3, 4) projection of ``image``.
          plane: (4,) ground plane (unit normal up, see :mod:`gac_jax.api.inputs`) or None:
            the config's level camera (``model.gac.camera_height``).

        Raises:
          InputError: naming ``image``, ``P2`` or ``plane``.
        """
        d = self.config.data
        sample = image_sample(
            image, P2, plane, min_rows=self.min_image_rows, resize=(d.crop_top, d.height)
        )
        arrays = self._arrays(self._transform(sample))
        h, w = image.shape[:2]
        return PreparedImage(
            image=arrays["image"],
            P2=arrays["P2"],
            plane=arrays["plane"],
            image_transform=arrays["image_transform"],
            original_size=(int(h), int(w)),
            cut_off=round(w * d.height / (h - d.crop_top)) > d.width,
        )

    def infer(self, prepared: Sequence[PreparedImage]) -> dict[str, np.ndarray]:
        """The network, decoding, ground filter and top-k of prepared images.

        Runs chunks of ``batch_size`` images (the last one padded by repeating its last
        image), so every call runs the one compiled shape. Calls are serialised (a lock).

        Returns:
          ``{key: (N, K, ...) numpy}``: the candidates of
          :func:`gac_jax.detection.inference.make_predict_fn` for the N images, in order.
        """
        prepared = checked_prepared(prepared, PreparedImage, "Detector3D.prepare")
        chunks = []
        with self._lock:
            for part, n in padded_chunks(prepared, self.batch_size):
                images = np.stack([p.image for p in part])
                P2 = np.stack([p.P2 for p in part])
                planes = np.stack([p.plane for p in part])
                out = self._predict(self._variables, images, P2, planes)
                chunks.append({k: np.asarray(v)[:n] for k, v in out.items()})
        return {k: np.concatenate([c[k] for c in chunks]) for k in chunks[0]}

    def infer_async(self, prepared: Sequence[PreparedImage]):
        """:meth:`infer` started without waiting: returns an object whose ``result()`` waits
        and gives what :meth:`infer` would (the same values). Up to ``requests`` may be in
        flight; take their results in the order they were started. For the jax runtime the
        call is dispatched (XLA runs it while the caller goes on); a list longer than one
        batch runs at once."""
        from gac_jax.deploy.runtimes import PendingOutputs

        prepared = checked_prepared(prepared, PreparedImage, "Detector3D.prepare")
        if len(prepared) > self.batch_size:
            raw = self.infer(prepared)
            return PendingOutputs(lambda: raw)
        ((part, n),) = padded_chunks(prepared, self.batch_size)
        arrays = [np.stack([getattr(p, k) for p in part]) for k in ("image", "P2", "plane")]
        with self._lock:
            if self.runtime == "jax":
                out = self._predict(self._variables, *arrays)  # dispatched, not waited for
                return PendingOutputs(lambda: {k: np.asarray(v)[:n] for k, v in out.items()})
            pending = self._predict.start(self._variables, *arrays)
        return PendingOutputs(lambda: {k: np.asarray(v)[:n] for k, v in pending.result().items()})

    def finish(
        self, raw: dict[str, np.ndarray], prepared: Sequence[PreparedImage]
    ) -> list[Detections]:
        """Score threshold, NMS, hill-climbing, 3D boxes and 2D boxes in original pixels of
        ``raw`` (:meth:`infer` of ``prepared``, same order). Thread-safe."""
        prepared = list(prepared)
        if len(raw["scores"]) != len(prepared):
            raise InputError(
                "prepared", f"{len(prepared)} prepared images for {len(raw['scores'])} results"
            )
        out = []
        for i, p in enumerate(prepared):
            objects = candidates_to_objects(
                {k: v[i] for k, v in raw.items()},
                p.P2,
                p.image_transform,
                self.input_size,
                p.original_size,
                self.class_names,
                self._postprocess,
            )
            out.append(Detections.from_kitti_objects(objects))
        return out


def _dtype(runtime: str, precision: str):
    return jnp.bfloat16 if (runtime, precision) == ("jax", "bf16") else jnp.float32
