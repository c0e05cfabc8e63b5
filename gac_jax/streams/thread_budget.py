"""One thread budget for a stream: how many threads each library may run, so the stages do
not oversubscribe the cores.

A stream runs five stage threads (read, prepare, network, finish + draw, write) and, for an
MP4 video, an encoder thread (colour conversion, libx264 with one thread of its own work,
muxing: :mod:`gac_jax.streams.video_encoder`). Only the network is worth parallelising inside:
the host stages already run side by side, so OpenCV (resize, colour conversion, drawing,
encoding) and the BLAS under numpy get one thread each (a second would only compete with the
other stages), and the network gets every usable core:

* ONNX Runtime / OpenVINO: ``network_threads`` inference threads; with ``requests`` > 1
  OpenVINO's throughput hint splits them into that many streams (2 cores, 2 requests: two
  streams of one thread), one per call in flight;
* OpenCV: ``cv2.setNumThreads(host_threads)``;
* a video file's decoder (FFmpeg): ``host_threads`` (FFmpeg's own default is every core; on
  two cores its threads' hand-offs cost about 10 % more CPU per frame, which a stream's other
  stages would have used: ``benchmarks/bench_video_decode.py``);
* BLAS (numpy's OpenBLAS, and OpenCV's own): ``threadpoolctl`` limits, when it is installed;
* XLA (the jax runtime's network, and every runtime's decoding and top-k): its CPU thread
  pool is sized when JAX starts (every usable core, or ``--threads``) and is not changed here;
  :func:`thread_settings` reports it.
"""

from __future__ import annotations

import dataclasses
import os
from pathlib import Path

XLA_THREAD_NAME = "tf_XLAEigen"  # XLA:CPU's compute threads


def usable_cores() -> int:
    """Cores this process may run on (its affinity; else the CPU count)."""
    if hasattr(os, "sched_getaffinity"):
        return len(os.sched_getaffinity(0))
    return os.cpu_count() or 1


@dataclasses.dataclass(frozen=True)
class ThreadBudget:
    """Threads per library for one stream.

    Attributes:
      cores: usable cores; network_threads: ONNX Runtime / OpenVINO inference threads;
      requests: network calls in flight (OpenVINO streams); host_threads: OpenCV, BLAS and
      video decoder threads (each host stage is already a thread of its own).
    """

    cores: int
    network_threads: int
    requests: int = 1
    host_threads: int = 1

    def describe(self, runtime: str) -> str:
        """One line for the stream's output."""
        if runtime == "jax":
            network = f"network in XLA ({xla_threads() or self.cores} threads, set at start)"
        else:
            network = f"network {self.network_threads} {runtime} threads"
            if self.requests > 1:
                network += f" in {self.requests} streams ({self.requests} calls in flight)"
        return (
            f"threads: {network}; OpenCV, BLAS and decoder {self.host_threads} per stage; "
            "video encoder 1 thread"
        )


def plan_thread_budget(
    threads: int | None = None, requests: int = 1, cores: int | None = None
) -> ThreadBudget:
    """The budget for a stream: ``threads`` (default every usable core) for the network,
    ``requests`` calls in flight, one OpenCV/BLAS thread per host stage."""
    cores = usable_cores() if cores is None else cores
    if requests < 1:
        raise ValueError(f"requests must be >= 1, got {requests}")
    network = cores if threads is None else threads
    if network < 1:
        raise ValueError(f"threads must be >= 1, got {threads}")
    return ThreadBudget(cores=cores, network_threads=network, requests=requests)


def apply_host_threads(budget: ThreadBudget) -> None:
    """Sets OpenCV's and the BLAS libraries' thread counts to ``budget.host_threads`` for the
    process (they are process-wide settings)."""
    import cv2

    cv2.setNumThreads(budget.host_threads)
    try:
        from threadpoolctl import threadpool_limits
    except ImportError:  # an optional helper: without it BLAS keeps its own count
        return
    threadpool_limits(budget.host_threads)


def xla_threads() -> int | None:
    """XLA:CPU compute threads alive in this process (Linux ``/proc``; None elsewhere, or 0
    before JAX has started its backend)."""
    tasks = Path("/proc/self/task")
    if not tasks.is_dir():
        return None
    count = 0
    for task in tasks.iterdir():
        try:
            count += (task / "comm").read_text().strip() == XLA_THREAD_NAME
        except OSError:
            continue
    return count


def thread_settings(network=None, source=None) -> dict:
    """What the libraries run with now, read from the libraries themselves: ``opencv``
    (``cv2.getNumThreads``), ``blas`` (threads of each BLAS threadpoolctl sees), ``openmp``
    (of each OpenMP runtime loaded, e.g. by PyTorch: a per-thread setting, as this thread
    sees it; no stage runs OpenMP code), ``xla``
    (:func:`xla_threads`), for an OpenVINO ``network``
    (:class:`~gac_jax.deploy.runtimes.OnnxNetwork`) its compiled ``INFERENCE_NUM_THREADS``
    and ``NUM_STREAMS``, and for a video ``source``
    (:class:`~gac_jax.streams.sources.VideoSource`) its ``decoder`` threads."""
    import cv2

    out: dict = {"opencv": cv2.getNumThreads(), "xla": xla_threads()}
    try:
        from threadpoolctl import threadpool_info

        info = threadpool_info()
        out["blas"] = sorted({int(i["num_threads"]) for i in info if i["user_api"] == "blas"})
        # OpenMP's count is per thread (a stage thread starts with the default); reported only
        out["openmp"] = sorted({int(i["num_threads"]) for i in info if i["user_api"] == "openmp"})
    except ImportError:
        out["blas"] = out["openmp"] = None
    if network is not None and getattr(network, "runtime", None) == "openvino":
        out["openvino_threads"] = int(network.compiled_property("INFERENCE_NUM_THREADS"))
        out["openvino_streams"] = int(network.compiled_property("NUM_STREAMS"))
    if source is not None and hasattr(source, "decode_threads"):
        out["decoder"] = source.decode_threads
    return out
