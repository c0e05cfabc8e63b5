"""Deployment runtimes: the exported ONNX networks under ONNX Runtime or OpenVINO (CPU).

``--runtime jax|onnxruntime|openvino [--precision f32|bf16|int8]`` of ``evaluate.py`` and
``python -m gac_jax.cli.predict`` select how the *network* runs; decoding, the anchor filter and
top-k (:func:`gac_jax.detection.inference.select_candidates`, jitted), NMS and hill-climbing
(:func:`gac_jax.detection.inference.postprocess`) and the depth post-processing
(:func:`gac_jax.evaluation.depth_evaluator.to_original_geometry`) are the project's own code,
shared with the jitted path.

Precision. ``bf16`` means OpenVINO's ``INFERENCE_PRECISION_HINT=bf16``: the CPU plugin runs
convolutions/matmuls in bfloat16 (float32 accumulation). It is *native* when the plugin lists
``BF16`` in ``OPTIMIZATION_CAPABILITIES``, which it does on CPUs with AVX512_BF16 (e.g. AMD
Zen 4 EPYC: ``vdpbf16ps`` dot products) or AMX-BF16 (Intel Sapphire Rapids and later: tile
matrix units, the big speed-up); elsewhere it is refused in one line. OpenVINO's own default
on such CPUs is bf16, so ``f32`` is always requested explicitly. ONNX Runtime's CPU provider
has no bf16 convolutions (refused); JAX's ``bf16`` is the model's compute dtype, which XLA:CPU
emulates in float32 (rounded, not faster: a one-line note says so). ``int8`` is OpenVINO only:
the NNCF-quantized IR of :mod:`gac_jax.deploy.int8` (its remaining float ops in float32),
refused where the CPU plugin lists no ``INT8``, with a one-line note on a CPU without int8
dot products (AVX512_VNNI, AVX_VNNI, AMX-INT8).
"""

from __future__ import annotations

import contextlib
import importlib.util
import os
from pathlib import Path

import jax
import numpy as np

from gac_jax.data.files import KittiFormatError
from gac_jax.deploy.telemetry import import_openvino
from gac_jax.geometry import DEFAULT_CAMERA_HEIGHT, level_plane

RUNTIMES = ("jax", "onnxruntime", "openvino")
PRECISIONS = ("f32", "bf16", "int8")
# every runtime/precision pair there is (check_runtime says which of them run on this machine)
RUNTIME_PRECISIONS = (
    ("jax", "f32"),
    ("jax", "bf16"),
    ("onnxruntime", "f32"),
    ("openvino", "f32"),
    ("openvino", "bf16"),
    ("openvino", "int8"),
)
DETECTOR_OUTPUTS = ("cls_logits", "sign_logits", "reg")
DEPTH_OUTPUTS = ("log_depth",)
INPUTS = ("images", "P2", "plane")
EXTRA_HINT = "pip install 'gac-jax[deploy]'"


class RuntimeUnavailableError(RuntimeError):
    """This runtime/precision cannot run here; the message is one line saying why."""


def cpu_flags() -> dict:
    """CPU model and its bf16-relevant flags (``/proc/cpuinfo``; False where unreadable)."""
    text = ""
    with contextlib.suppress(OSError):
        text = Path("/proc/cpuinfo").read_text()
    model = next(
        (ln.split(":", 1)[1].strip() for ln in text.splitlines() if ln.startswith("model name")),
        "unknown CPU",
    )
    flags = set()
    for line in text.splitlines():
        if line.startswith("flags"):
            flags = set(line.split(":", 1)[1].split())
            break
    return {
        "cpu": model,
        "avx512_bf16": "avx512_bf16" in flags,
        "amx_bf16": "amx_bf16" in flags,
        "amx_tile": "amx_tile" in flags,
        # int8 dot products: AVX512_VNNI (Cascade Lake, Zen 4), AVX_VNNI (Alder Lake), AMX-INT8
        "int8_dot": bool(flags & {"avx512_vnni", "avx_vnni", "amx_int8"}),
        "amx_int8": "amx_int8" in flags,
    }


def openvino_capabilities() -> list[str]:
    ov = import_openvino()

    return list(ov.Core().get_property("CPU", "OPTIMIZATION_CAPABILITIES"))


def check_runtime(runtime: str, precision: str) -> str | None:
    """Raises :class:`RuntimeUnavailableError` if ``runtime``/``precision`` cannot run here;
    returns a one-line note for a precision that runs but is emulated (JAX bf16)."""
    if runtime not in RUNTIMES:
        raise RuntimeUnavailableError(
            f"--runtime must be one of {', '.join(RUNTIMES)}, got {runtime}"
        )
    if precision not in PRECISIONS:
        raise RuntimeUnavailableError(
            f"--precision must be one of {', '.join(PRECISIONS)}, got {precision}"
        )
    if runtime != "jax":
        for module in ("onnx", runtime):
            if importlib.util.find_spec(module) is None:
                raise RuntimeUnavailableError(
                    f"--runtime {runtime} needs the {module} package: {EXTRA_HINT}"
                )
    if precision == "f32":
        return None
    if precision == "int8":
        return _check_int8(runtime)
    cpu = cpu_flags()["cpu"]
    if runtime == "onnxruntime":
        raise RuntimeUnavailableError(
            "--precision bf16: ONNX Runtime's CPU provider has no bf16 convolutions; use "
            "--runtime openvino --precision bf16 (or --precision f32)"
        )
    if runtime == "openvino":
        if "BF16" not in openvino_capabilities():
            raise RuntimeUnavailableError(
                f"--precision bf16: this CPU ({cpu}) has no native bf16 support (OpenVINO's CPU "
                "plugin lists no BF16 capability; it needs AVX512_BF16 or AMX); use --precision f32"
            )
        return None
    return (
        "note: --runtime jax --precision bf16: XLA:CPU has no native bf16 convolutions, it "
        "computes them in float32 and rounds (no speed-up); --runtime openvino uses bf16 kernels"
    )


def _check_int8(runtime: str) -> str | None:
    """int8 is OpenVINO's (an NNCF-quantized IR); a CPU without int8 dot products gets a note."""
    if runtime != "openvino":
        raise RuntimeUnavailableError(
            f"--precision int8 runs the NNCF-quantized network in OpenVINO only; use --runtime "
            f"openvino --precision int8 (--runtime {runtime}: f32"
            + (" or bf16)" if runtime == "jax" else ")")
        )
    if importlib.util.find_spec("nncf") is None:
        raise RuntimeUnavailableError(f"--precision int8 needs the nncf package: {EXTRA_HINT}")
    flags = cpu_flags()
    if "INT8" not in openvino_capabilities():
        raise RuntimeUnavailableError(
            f"--precision int8: OpenVINO's CPU plugin lists no INT8 capability on this CPU "
            f"({flags['cpu']}); use --precision f32"
        )
    if not flags["int8_dot"]:
        return (
            f"note: --precision int8: this CPU ({flags['cpu']}) has no int8 dot-product "
            "instructions (AVX512_VNNI, AVX_VNNI or AMX-INT8); OpenVINO emulates them with "
            "wider integer arithmetic, so int8 may be no faster than --precision f32"
        )
    return None


def _first_line(e: BaseException) -> str:
    text = str(e).strip().splitlines()
    return text[0] if text else type(e).__name__


class OnnxNetwork:
    """An exported network (``model.onnx``) in ONNX Runtime or OpenVINO on the CPU.

    Args:
      path: the ``model.onnx`` (for OpenVINO ``int8``: the quantized ``model_int8.xml``).
      runtime: ``'onnxruntime'`` or ``'openvino'``; precision: ``'f32'``, ``'bf16'`` or
        ``'int8'`` (OpenVINO; :mod:`gac_jax.deploy.int8`).
      outputs: output names the caller needs (checked at load).
      image_size: (H, W) the caller feeds (checked against the model's input).
      threads: CPU threads (default: every usable core).
      batch_size: fixes the batch dimension (OpenVINO compiles a static shape), or None.
      requests: network calls that may be in flight at once (:meth:`start`). OpenVINO: 1
        compiles for latency (one stream using every thread); more compile its throughput
        hint with that many streams sharing ``threads`` and as many infer requests, so one
        call runs while the caller finishes the previous one. ONNX Runtime runs a started
        call on a worker thread.

    ``__call__(images (B,H,W,3) float32, P2 (B,3,4) float32, plane (B,4) float32)`` returns
    ``{name: ndarray}``; ``start(...)`` the same inputs returns a :class:`PendingOutputs`
    whose ``result()`` is that dictionary (the same values).

    Raises:
      KittiFormatError: the file cannot be loaded, or its inputs/outputs do not fit, naming it.
    """

    def __init__(
        self,
        path: str | os.PathLike,
        runtime: str,
        precision: str = "f32",
        *,
        outputs: tuple[str, ...],
        image_size: tuple[int, int],
        threads: int | None = None,
        batch_size: int | None = None,
        requests: int = 1,
    ):
        self.path = Path(path)
        self.requests = int(requests)
        if self.requests < 1:
            raise ValueError(f"requests must be >= 1, got {requests}")
        self.runtime = runtime
        self.precision = precision
        self.outputs = tuple(outputs)
        if threads is None:
            threads = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else 1
        self.threads = threads
        self.precision_in_effect = "f32"
        if runtime not in ("onnxruntime", "openvino"):
            raise ValueError(f"not an ONNX runtime: {runtime!r}")
        try:
            if runtime == "onnxruntime":
                shapes, names = self._load_onnxruntime(threads)
            else:
                shapes, names = self._load_openvino(precision, threads, batch_size)
        except Exception as e:  # each runtime raises its own exception types
            raise KittiFormatError(
                self.path, f"{runtime} cannot load it: {_first_line(e)}"
            ) from None
        missing = [n for n in (*INPUTS,) if n not in shapes]
        absent = [n for n in self.outputs if n not in names]
        if missing or absent:
            raise KittiFormatError(
                self.path,
                f"not the expected network: inputs {sorted(shapes)} and outputs {sorted(names)} "
                f"lack {', '.join(missing + absent)}",
            )
        have = tuple(shapes["images"][1:3])
        if have != tuple(image_size):
            raise KittiFormatError(
                self.path,
                f"model input is {have[0]}x{have[1]}, the run feeds {image_size[0]}x"
                f"{image_size[1]} (H x W): export again",
            )

    def _model_for(self, precision: str) -> str | bytes:
        """The file's path, or for float32 its bytes with the exporter's marked 5x5 convs
        rewritten to Winograd form (:mod:`gac_jax.deploy.export.winograd`) when there are any."""
        if precision != "f32":
            return str(self.path)
        import onnx

        from gac_jax.deploy.export.winograd import apply_winograd

        model = onnx.load(str(self.path))
        if not apply_winograd(model):
            return str(self.path)
        return model.SerializeToString()

    def _load_onnxruntime(self, threads: int):
        import onnxruntime as ort

        options = ort.SessionOptions()
        options.intra_op_num_threads = threads
        options.inter_op_num_threads = 1
        options.graph_optimization_level = ort.GraphOptimizationLevel.ORT_ENABLE_ALL
        self._session = ort.InferenceSession(
            self._model_for("f32"), options, providers=["CPUExecutionProvider"]
        )
        shapes = {i.name: list(i.shape) for i in self._session.get_inputs()}
        return shapes, [o.name for o in self._session.get_outputs()]

    def _load_openvino(self, precision, threads, batch_size):
        ov = import_openvino()

        core = ov.Core()
        source = self._model_for(precision)
        model = core.read_model(source) if isinstance(source, str) else core.read_model(source, b"")
        shapes = {}
        for port in model.inputs:
            shape = port.get_partial_shape()
            shapes[port.get_any_name()] = [d.get_length() if d.is_static else None for d in shape]
        if batch_size is not None and set(INPUTS) <= set(shapes):
            model.reshape(
                {
                    "images": [batch_size, *shapes["images"][1:]],
                    "P2": [batch_size, 3, 4],
                    "plane": [batch_size, 4],
                }
            )
        config = openvino_config(precision, threads, self.requests)
        self._compiled = core.compile_model(model, "CPU", config)
        self._infer_requests = [self._compiled.create_infer_request() for _ in range(self.requests)]
        self._request = self._infer_requests[0]
        self._next_request = 0
        hint = self._compiled.get_property("INFERENCE_PRECISION_HINT")
        self.precision_in_effect = hint.get_type_name() if hasattr(hint, "get_type_name") else hint
        # an output tensor may carry several names (OpenVINO merges the Identity ops)
        self._ports = {}
        for port in self._compiled.outputs:
            for name in port.get_names():
                self._ports[name] = port
        return shapes, list(self._ports)

    def compiled_property(self, name: str):
        """A property of the compiled OpenVINO model (e.g. ``INFERENCE_NUM_THREADS``,
        ``NUM_STREAMS``, ``PERF_COUNT``); None for ONNX Runtime."""
        if self.runtime != "openvino":
            return None
        return self._compiled.get_property(name)

    def __call__(
        self, images: np.ndarray, P2: np.ndarray, plane: np.ndarray
    ) -> dict[str, np.ndarray]:
        feed = _feed(images, P2, plane)
        if self.runtime == "onnxruntime":
            values = self._session.run(list(self.outputs), feed)
            return dict(zip(self.outputs, values, strict=True))
        result = self._request.infer(feed)
        # copy out of the request's buffers
        return {name: np.array(result[self._ports[name]]) for name in self.outputs}

    def start(self, images: np.ndarray, P2: np.ndarray, plane: np.ndarray) -> PendingOutputs:
        """Starts one call without waiting for it (at most ``requests`` in flight: the caller
        takes each :meth:`PendingOutputs.result` before starting more; OpenVINO reuses its
        infer requests in turn)."""
        feed = _feed(images, P2, plane)
        if self.runtime == "onnxruntime":
            if not hasattr(self, "_pool"):
                from concurrent.futures import ThreadPoolExecutor

                self._pool = ThreadPoolExecutor(self.requests, thread_name_prefix="gac-ort")
            future = self._pool.submit(self._session.run, list(self.outputs), feed)
            return PendingOutputs(lambda: dict(zip(self.outputs, future.result(), strict=True)))
        request = self._infer_requests[self._next_request]
        self._next_request = (self._next_request + 1) % len(self._infer_requests)
        request.start_async(feed)

        def result() -> dict[str, np.ndarray]:
            request.wait()
            return {
                name: np.array(request.get_tensor(self._ports[name]).data) for name in self.outputs
            }

        return PendingOutputs(result)


def openvino_config(precision: str, threads: int, requests: int = 1) -> dict[str, str]:
    """The CPU plugin's compile settings of a network run at ``precision`` on ``threads``
    threads with ``requests`` calls in flight (also what benchmarks/bench_peak.py compiles
    its peak graph with)."""
    config = {
        # int8: the quantized ops run in int8, the rest in float32 (not the CPU's bf16 default)
        "INFERENCE_PRECISION_HINT": "bf16" if precision == "bf16" else "f32",
        "PERFORMANCE_HINT": "LATENCY" if requests == 1 else "THROUGHPUT",
        "INFERENCE_NUM_THREADS": str(threads),
    }
    if requests > 1:  # one stream per request in flight, the threads shared out
        config["NUM_STREAMS"] = str(min(requests, threads))
    return config


def _feed(images, P2, plane) -> dict[str, np.ndarray]:
    return {
        "images": np.ascontiguousarray(images, np.float32),
        "P2": np.ascontiguousarray(P2, np.float32),
        "plane": np.ascontiguousarray(plane, np.float32),
    }


class PendingOutputs:
    """A started network call: :meth:`result` waits for it and returns its value (once)."""

    def __init__(self, wait):
        self._wait = wait

    def result(self):
        return self._wait()


class RuntimeDetectionPredict:
    """``predict(variables, images, P2, plane=None) -> candidates`` like
    :func:`gac_jax.detection.inference.make_predict_fn`, with the network in an :class:`OnnxNetwork`
    (``variables`` is ignored: the weights are in the file) and the jitted
    :func:`~gac_jax.detection.inference.select_candidates` after it; ``plane`` None is the level
    plane of ``filter_options['camera_height']``."""

    def __init__(
        self,
        network: OnnxNetwork,
        constants,
        *,
        top_k: int | None = 4096,
        score_threshold: float | None = None,
        filter_options: dict | None = None,
        use_ground_filter: bool = True,
    ):
        from gac_jax.detection.inference import select_candidates

        self.network = network
        options = dict(filter_options or {})
        self.camera_height = options.get("camera_height", DEFAULT_CAMERA_HEIGHT)

        def select(outputs, P2, plane):
            return select_candidates(
                outputs,
                constants,
                P2,
                top_k,
                options,
                use_ground_filter=use_ground_filter,
                score_threshold=score_threshold,
                plane=plane,
            )

        self._select = jax.jit(select)

    def compile(self, batch_size: int, image_size: tuple[int, int]) -> float:
        """Runs the network once (warm-up) and compiles the decoding; returns seconds."""
        import time

        t0 = time.perf_counter()
        images = np.zeros((batch_size, *image_size, 3), np.float32)
        P2 = np.tile(np.eye(3, 4, dtype=np.float32), (batch_size, 1, 1))
        plane = self._planes(None, batch_size)
        outputs = self.network(images, P2, plane)
        self._select = self._select.lower(outputs, P2, plane).compile()
        return time.perf_counter() - t0

    def _planes(self, plane, batch_size: int) -> np.ndarray:
        if plane is None:
            return np.tile(level_plane(self.camera_height).astype(np.float32), (batch_size, 1))
        return np.asarray(plane, np.float32)

    def __call__(self, variables, images, P2, plane=None) -> dict:
        del variables
        plane = self._planes(plane, len(images))
        return self._select(self.network(images, P2, plane), np.asarray(P2, np.float32), plane)

    def start(self, variables, images, P2, plane=None) -> PendingOutputs:
        """:meth:`__call__` started (:meth:`OnnxNetwork.start`); its ``result()`` decodes."""
        del variables
        plane = self._planes(plane, len(images))
        pending = self.network.start(images, P2, plane)
        P2 = np.asarray(P2, np.float32)
        return PendingOutputs(lambda: self._select(pending.result(), P2, plane))


class RuntimeDepthPredictor:
    """A depth predictor (like :class:`~gac_jax.evaluation.depth_evaluator.NetworkPredictor`)
    over an exported depth network: ``__call__(batch)`` -> original-geometry depth maps."""

    def __init__(self, network: OnnxNetwork, camera_height: float = DEFAULT_CAMERA_HEIGHT):
        self.network = network
        self.camera_height = camera_height  # the level plane of frames without one

    def __call__(self, batch: dict) -> list[np.ndarray]:
        from gac_jax.evaluation.depth_evaluator import frame_planes, to_original_geometry

        planes = frame_planes(batch, self.camera_height)
        log_depth = self.network(batch["image"], batch["P2"], planes)["log_depth"]
        return [
            to_original_geometry(
                log_depth[b], batch["image_transform"][b], batch["original_size"][b]
            )
            for b in range(len(log_depth))
        ]
