"""The ground-aware depth network as a Python object: :class:`DepthPredictor`.

    depth_net = DepthPredictor.from_workdir("runs/depth_default")
    depth = depth_net.predict(image, P2)   # (H, W) float32 metres at the image's size

The code of ``evaluate.py --task depth --workdir``: the checkpoint
(:func:`gac_jax.trained.depth.restore_depth_model`), the config's test transform, the network
(jitted, or exported to ONNX Runtime / OpenVINO by
:func:`gac_jax.deploy.runtime_choice.runtime_predictor`) and the resampling to the original
image grid (:func:`gac_jax.evaluation.depth_evaluator.to_original_geometry`), so the maps are
the ones ``evaluate.py`` writes as 16-bit PNGs (before their ``round(256 z)`` quantisation).
"""

from __future__ import annotations

import dataclasses
import os
import threading
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import jax
import ml_collections
import numpy as np

from gac_jax.api import runtime_args
from gac_jax.api.inputs import (
    InputError,
    check_step,
    image_sample,
)
from gac_jax.api.stages import StagedModel, checked_prepared, padded_chunks
from gac_jax.builders.depth import eval_transform
from gac_jax.data.loader import collate
from gac_jax.evaluation.depth_evaluator import NetworkPredictor
from gac_jax.trained.depth import restore_depth_model
from gac_jax.trained.fingerprint import weights_sha256


@dataclasses.dataclass(frozen=True)
class PreparedDepthImage:
    """One image after :meth:`DepthPredictor.prepare` (arrays of the depth evaluator's batch).

    ``arrays``: ``image`` (h, w, 3) float32 network input, ``P2`` (3, 4), ``plane`` (4,)
    (NaN: the model's level camera), ``image_transform`` (3, 3) original -> input pixels,
    ``original_size`` (2,) int32.
    """

    arrays: dict[str, np.ndarray]


class DepthPredictor(StagedModel):
    """A trained depth network (:class:`~gac_jax.models.depth_unet.DepthUNet`); build it with
    :meth:`from_workdir`.

    Attributes:
      config, input_size ((h, w) of the network input), runtime, precision, batch_size, step.
    """

    def __init__(
        self,
        config: ml_collections.ConfigDict,
        model,
        variables: dict,
        step: int,
        workdir: Path,
        runtime: str = "jax",
        precision: str = "f32",
        *,
        batch_size: int = 1,
        export_dir: str | os.PathLike | None = None,
    ):
        from gac_jax.deploy.runtime_choice import runtime_predictor

        self.config, self.step = config, step
        self.runtime, self.precision, self.batch_size = runtime, precision, batch_size
        self._export_dir = Path(export_dir or Path(workdir) / "export" / f"step{step}")
        self.input_size = (int(config.data.height), int(config.data.eval_width))
        self.min_image_rows = 1  # shorter images than the crop are padded on top
        self._transform = eval_transform(config)
        self._lock = threading.Lock()
        self.weights_sha256 = weights_sha256(variables)
        with runtime_args.file_errors_as("workdir"):
            self._predictor = runtime_predictor(
                config,
                model,
                variables,
                step,
                workdir,
                runtime,
                precision,
                export_dir,
                weights_sha256=self.weights_sha256,
            )
        if isinstance(self._predictor, NetworkPredictor):  # weights on the device once
            self._predictor.variables = jax.device_put(self._predictor.variables)

    @classmethod
    def from_workdir(
        cls,
        workdir: str | os.PathLike,
        step: int | None = None,
        runtime: str = "jax",
        precision: str = "f32",
        batch_size: int = 1,
        *,
        export_dir: str | os.PathLike | None = None,
    ) -> DepthPredictor:
        """The depth network of a training workdir (``config.json``, ``prior_mean.json``,
        ``checkpoints/``) at checkpoint ``step`` (default: the latest); ``runtime`` /
        ``precision`` as :meth:`gac_jax.api.Detector3D.from_workdir` (exports go to
        ``export_dir``, default ``W/export/step<N>``).

        Raises:
          InputError: a missing workdir / step, an unknown or unavailable runtime /
            precision, a bad batch size.
        """
        workdir = runtime_args.check_workdir(workdir)
        step = check_step(step)
        options = runtime_args.model_options(runtime, precision, None, batch_size, export_dir)
        del options["threads"]  # the depth runtimes take every usable core
        try:
            config, model, variables, step = restore_depth_model(workdir, step)
        except ValueError as e:  # KittiFormatError: no config / prior / checkpoint (step)
            argument = "step" if step is not None and "no checkpoint" in str(e) else "workdir"
            raise InputError(argument, str(e)) from None
        return cls(config, model, variables, step, workdir, **options)

    def __repr__(self) -> str:
        return f"DepthPredictor(step {self.step}; {self._describe()})"

    def precision_line(self) -> str:
        """Which precision runs and what the accuracy guard (``python -m gac_jax.cli.guard``)
        decided for these weights: the line ``evaluate.py --task depth`` prints."""
        from gac_jax.deploy.int8 import Int8Settings
        from gac_jax.guard.verdict_file import describe_precision

        int8 = Int8Settings() if self.precision == "int8" else None
        return describe_precision(
            self._export_dir,
            f"step{self.step}",
            self.runtime,
            self.precision,
            int8,
            weights_sha256=self.weights_sha256,
        )

    def prepare(self, image: np.ndarray, P2: Any, plane: Any = None) -> PreparedDepthImage:
        """Checks one image (arguments as :meth:`gac_jax.api.Detector3D.prepare`, any height)
        and applies the config's test transform (bottom rows, resize, the left columns,
        normalise). Thread-safe."""
        sample = self._transform(image_sample(image, P2, plane))
        arrays = {
            "image": np.asarray(sample["image"], np.float32),
            "P2": np.asarray(sample["P2"], np.float32),
            "plane": np.asarray(sample.get("plane", np.full(4, np.nan)), np.float32),
            "image_transform": np.asarray(sample["image_transform"], np.float32),
            "original_size": np.asarray(sample["original_size"], np.int32).reshape(2),
        }
        return PreparedDepthImage(arrays)

    def infer(self, prepared: Sequence[PreparedDepthImage]) -> list[np.ndarray]:
        """The network on prepared images in chunks of ``batch_size`` (the last padded: one
        compiled shape), each map resampled to its original image grid: (H, W) float32 metres.
        Calls are serialised (a lock)."""
        prepared = checked_prepared(prepared, PreparedDepthImage, "DepthPredictor.prepare")
        out: list[np.ndarray] = []
        with self._lock:
            for part, n in padded_chunks(prepared, self.batch_size):
                out.extend(self._predictor(collate([p.arrays for p in part]))[:n])
        return out

    def finish(
        self, raw: list[np.ndarray], prepared: Sequence[PreparedDepthImage]
    ) -> list[np.ndarray]:
        """The depth maps of :meth:`infer` (already at the original size: nothing left to do
        but check that they belong to ``prepared``); for symmetry with the detector."""
        prepared = list(prepared)
        if len(raw) != len(prepared):
            raise InputError("prepared", f"{len(prepared)} prepared images for {len(raw)} maps")
        return list(raw)
