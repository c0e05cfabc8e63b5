"""Which runtime runs the network: ``--runtime jax|onnxruntime|openvino --precision f32|bf16|int8``.

:func:`resolve_runtime` checks that a runtime/precision can run here; :func:`runtime_predict`
is a detector's exported network as a predict function and :func:`use_runtime` points a
detector's evaluator at it (exported into the run folder on first
use, refused when stale; for ``int8`` quantized beside it, :mod:`gac_jax.deploy.int8`),
:func:`runtime_predictor` does the same for a depth network.
Decoding, NMS and hill-climbing stay the project's own code for every runtime.
"""

from __future__ import annotations

import contextlib
import os
import sys
from pathlib import Path

import jax.numpy as jnp

from gac_jax.builders.detect3d import filter_options
from gac_jax.data.files import KittiFormatError
from gac_jax.deploy.int8 import Int8Settings
from gac_jax.evaluation.depth_evaluator import NetworkPredictor
from gac_jax.evaluation.detector_evaluator import DetectionEvaluator
from gac_jax.trained.detector import LoadedDetector
from gac_jax.training import workdir_lock


def resolve_runtime(runtime: str | None, precision: str | None) -> tuple[str, str]:
    """``(runtime, precision)`` with the defaults (jax, f32) after checking they can run here.

    Prints ``error: <why>`` (one line) and exits with code 2 when they cannot (missing
    package, no native bf16); prints a one-line note for emulated precisions (JAX bf16).
    """
    from gac_jax.deploy.runtimes import RuntimeUnavailableError, check_runtime

    runtime, precision = runtime or "jax", precision or "f32"
    try:
        note = check_runtime(runtime, precision)
    except RuntimeUnavailableError as e:
        print(f"error: {e}", file=sys.stderr)
        raise SystemExit(2) from None
    if note:
        print(note, flush=True)
    return runtime, precision


def run_suffix(runtime: str, precision: str) -> str:
    """Result-folder suffix of a runtime/precision ('' for the default jitted float32)."""
    if runtime == "jax" and precision == "f32":
        return ""
    return f"_{runtime}_{precision}"


def default_export_dir(workdir: str | os.PathLike, detector: LoadedDetector) -> Path:
    """Where ``--runtime onnxruntime|openvino`` keeps the export of these weights."""
    return Path(workdir) / "export" / detector.tag


def network_file(
    source, out: Path, precision: str, int8: Int8Settings | None, workdir=None
) -> Path:
    """The file the runtime loads: ``out/model.onnx`` of ``source`` (an
    :class:`~gac_jax.deploy.export.sources.ExportSource`; exported when the folder is empty,
    refused when stale), or for ``int8`` the quantized ``out/model_int8.xml`` made from it.

    Writing into ``out`` (a first export, an export of other weights replaced, an int8 model
    that may be rebuilt) holds the lock of ``workdir`` when ``out`` lies inside it; using an
    existing float export of these weights only reads.

    Raises:
      KittiFormatError: a stale or corrupted export, a failed export or quantization, a
        ``--int8-keep-float`` pattern that matches no layer (naming the folder's file).
    """
    from gac_jax.deploy.export.artifact import MODEL_FILE
    from gac_jax.deploy.export.networks import ExportError
    from gac_jax.deploy.export.sources import ensure_export, will_write

    writes = will_write(source, out) or precision == "int8"
    lock = workdir_lock.hold_if_inside(workdir, out) if writes else contextlib.nullcontext()
    with lock:
        try:
            _, exported = ensure_export(source, out)
        except ExportError as e:
            raise KittiFormatError(out, str(e)) from None
        if exported:
            print(f"exported the network to {out}", flush=True)
        if precision != "int8":
            return out / MODEL_FILE
        from gac_jax.deploy.int8 import ensure_int8

        try:
            return ensure_int8(
                out, source.task, source.config, int8 or Int8Settings(), source.workdir
            )
        except ValueError as e:
            if isinstance(e, KittiFormatError):
                raise
            raise KittiFormatError(out / MODEL_FILE, str(e)) from None


def runtime_predict(
    detector: LoadedDetector,
    workdir: str | os.PathLike,
    runtime: str,
    precision: str,
    batch_size: int,
    *,
    export_dir: str | os.PathLike | None = None,
    threads: int | None = None,
    int8: Int8Settings | None = None,
    requests: int = 1,
):
    """The exported network of ``detector`` in ``runtime`` as a predict function
    (:class:`~gac_jax.deploy.runtimes.RuntimeDetectionPredict`: the call of
    :func:`gac_jax.detection.inference.make_predict_fn`'s jitted function, with the config's
    ``eval.top_k``, score threshold and ground filter), warmed up for ``batch_size`` images.

    The export in ``export_dir`` (default :func:`default_export_dir`) is written when absent
    and refused when stale or corrupted (:func:`gac_jax.deploy.export.sources.ensure_export`);
    for ``int8`` the quantized network beside it is built when missing or stale
    (:func:`gac_jax.deploy.int8.ensure_int8` with ``int8``, default settings if None).
    ``requests``: network calls in flight at once (:class:`~gac_jax.deploy.runtimes.OnnxNetwork`).
    """
    from gac_jax.deploy.export.sources import detector_source
    from gac_jax.deploy.runtimes import DETECTOR_OUTPUTS, OnnxNetwork, RuntimeDetectionPredict

    config = detector.config
    out = Path(export_dir) if export_dir else default_export_dir(workdir, detector)
    source = detector_source(
        config,
        detector.model,
        detector.variables,
        step=detector.step,
        checkpoint=None
        if detector.step is not None
        else detector.weights.removeprefix("converted weights "),
        workdir=workdir,
        weights_sha256=detector.weights_sha256,
    )
    size = (config.data.height, config.data.width)
    network = OnnxNetwork(
        network_file(source, out, precision, int8, workdir),
        runtime,
        precision,
        outputs=DETECTOR_OUTPUTS,
        image_size=size,
        threads=threads,
        batch_size=batch_size,
        requests=requests,
    )
    predict = RuntimeDetectionPredict(
        network,
        detector.constants,
        top_k=config.eval.top_k,
        score_threshold=config.eval.score_threshold,
        filter_options=filter_options(config),
        use_ground_filter=config.anchors.filter,
    )
    predict.compile(batch_size, size)
    return predict


def use_runtime(
    evaluator: DetectionEvaluator,
    detector: LoadedDetector,
    workdir: str | os.PathLike,
    runtime: str,
    precision: str,
    *,
    export_dir: str | os.PathLike | None = None,
    threads: int | None = None,
    int8: Int8Settings | None = None,
) -> float:
    """Points ``evaluator`` (made by :func:`gac_jax.trained.detector.evaluator_for`) at the
    exported network in ``runtime`` (:func:`runtime_predict`; the jitted decoding, top-k and
    host post-processing stay as they are); returns the load + warm-up seconds."""
    import time

    t0 = time.perf_counter()
    evaluator.predict = runtime_predict(
        detector,
        workdir,
        runtime,
        precision,
        evaluator.batch_size,
        export_dir=export_dir,
        threads=threads,
        int8=int8,
    )
    return time.perf_counter() - t0


def runtime_predictor(
    config,
    model,
    variables,
    step: int,
    workdir: str | Path,
    runtime: str,
    precision: str,
    export_dir: str | Path | None = None,
    int8: Int8Settings | None = None,
    weights_sha256: str | None = None,
):
    """The depth predictor of a runtime: the jitted network (``jax``; ``bf16`` = bfloat16
    compute dtype) or the exported one (written to ``export_dir``, default
    ``W/export/step<N>``, when absent or made from other weights; refused when corrupted or
    made for another config; ``int8``: how
    :mod:`gac_jax.deploy.int8` calibrates the quantized network, default settings if None)."""
    if runtime == "jax":
        if precision == "bf16":
            model = model.clone(dtype=jnp.bfloat16)
        return NetworkPredictor(model, variables)
    from gac_jax.deploy.export.sources import depth_source
    from gac_jax.deploy.runtimes import DEPTH_OUTPUTS, OnnxNetwork, RuntimeDepthPredictor

    out = Path(export_dir) if export_dir else Path(workdir) / "export" / f"step{step}"
    source = depth_source(config, model, variables, step=step, weights_sha256=weights_sha256)
    network = OnnxNetwork(
        network_file(source, out, precision, int8, workdir),
        runtime,
        precision,
        outputs=DEPTH_OUTPUTS,
        image_size=(config.data.height, config.data.eval_width),
    )
    return RuntimeDepthPredictor(network, model.camera_height)
