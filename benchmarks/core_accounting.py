"""Where a stream's CPU time goes, and the network's share of the CPU's peak.

* :func:`peak_macs_per_s`: the CPU's peak multiply-accumulates per second for a precision,
  an *estimate* from its instruction set (``/proc/cpuinfo`` flags), vendor and clock
  (``cpu MHz``, the nominal clock in a VM): MACs per cycle per core times cores times clock.
  Per core and cycle: AMX (Intel Sapphire Rapids+) 1024 int8 / 512 bf16; AVX-512 VNNI int8
  128 on Intel (two 512-bit FMA ports), 64 on AMD Zen 4 (512-bit ops on 256-bit units);
  AVX512_BF16 64 Intel / 32 AMD; float32 FMA 32 (Intel AVX-512) / 16 (AMD Zen 4, AVX2).
* :class:`ThreadCpu`: CPU seconds of the process's threads between two readings of
  ``/proc/self/task/*/stat``, split into XLA's compute threads (by name) and the rest.
* :func:`openvino_layer_profile`: OpenVINO's per-layer performance counters (``PERF_COUNT``)
  summed per layer type and per executed precision.
"""

from __future__ import annotations

import os
from pathlib import Path

# MACs per cycle per core: (precision, ISA) -> (Intel, AMD)
MACS_PER_CYCLE = {
    ("int8", "amx"): (1024, 1024),
    ("bf16", "amx"): (512, 512),
    ("int8", "avx512_vnni"): (128, 64),
    ("bf16", "avx512_bf16"): (64, 32),
    ("f32", "avx512f"): (32, 16),
    ("int8", "avx2"): (64, 32),  # vpmaddubsw + vpmaddwd, no VNNI
    ("f32", "avx2"): (16, 16),
}


def cpu_info() -> dict:
    """Vendor, flags, clock (MHz) and usable cores from ``/proc/cpuinfo``."""
    text = Path("/proc/cpuinfo").read_text() if Path("/proc/cpuinfo").exists() else ""
    fields = {}
    for line in text.splitlines():
        if ":" in line:
            key, value = (x.strip() for x in line.split(":", 1))
            fields.setdefault(key, value)
    cores = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count()
    return {
        "vendor": fields.get("vendor_id", "?"),
        "model": fields.get("model name", "?"),
        "flags": set(fields.get("flags", "").split()),
        "mhz": float(fields.get("cpu MHz", "nan")),
        "cores": cores,
    }


def peak_macs_per_s(precision: str, info: dict | None = None) -> tuple[float, str]:
    """(peak MACs/s, how it was estimated) for ``precision`` ('f32', 'bf16', 'int8') on this
    CPU: the best instruction set it has for that precision (OpenVINO's CPU plugin uses it)."""
    info = info or cpu_info()
    flags, amd = info["flags"], info["vendor"] == "AuthenticAMD"
    order = {
        "int8": (("amx", "amx_int8"), ("avx512_vnni", "avx512_vnni"), ("avx2", "avx2")),
        "bf16": (("amx", "amx_bf16"), ("avx512_bf16", "avx512_bf16")),
        "f32": (("avx512f", "avx512f"), ("avx2", "avx2")),
    }[precision]
    for isa, flag in order:
        if flag in flags:
            per_cycle = MACS_PER_CYCLE[(precision, isa)][1 if amd else 0]
            peak = per_cycle * info["cores"] * info["mhz"] * 1e6
            how = (
                f"{precision} {isa}: {per_cycle} MACs/cycle/core x {info['cores']} cores x "
                f"{info['mhz'] / 1e3:.2f} GHz (estimate)"
            )
            return peak, how
    return float("nan"), f"{precision}: no native instructions"


def _thread_ticks() -> dict[int, tuple[str, int]]:
    """tid -> (name, utime + stime clock ticks) of this process's threads now."""
    out = {}
    for task in Path("/proc/self/task").iterdir():
        try:
            name = (task / "comm").read_text().strip()
            stat = (task / "stat").read_text()
        except OSError:
            continue
        fields = stat[stat.rindex(")") + 2 :].split()
        out[int(task.name)] = (name, int(fields[11]) + int(fields[12]))
    return out


class ThreadCpu:
    """CPU seconds per kind of thread between :meth:`start` and :meth:`stop` (threads alive
    at :meth:`stop`; threads that ended in between count in the process total only)."""

    XLA = "tf_XLAEigen"

    def start(self) -> None:
        self._before = _thread_ticks()

    def stop(self) -> dict[str, float]:
        after = _thread_ticks()
        tick = os.sysconf("SC_CLK_TCK")
        xla = other = 0
        for tid, (name, ticks) in after.items():
            delta = ticks - self._before.get(tid, (name, 0))[1]
            if name == self.XLA:
                xla += delta
            else:
                other += delta
        return {"xla_s": xla / tick, "alive_other_s": other / tick}


def openvino_layer_profile(model_path, precision: str, threads: int, feed: dict, runs: int = 3):
    """Per layer type and per executed precision: OpenVINO's own time of ``model_path``
    compiled as the runtime compiles it (latency hint, ``threads``) with ``PERF_COUNT``,
    summed over ``runs`` calls on ``feed``. Returns ``{'by_type': {type: ms}, 'by_precision':
    {precision: ms}, 'total_ms': ms, 'runs': runs}``."""
    import openvino as ov

    core = ov.Core()
    model = core.read_model(str(model_path))
    config = {
        "INFERENCE_PRECISION_HINT": "bf16" if precision == "bf16" else "f32",
        "PERFORMANCE_HINT": "LATENCY",
        "INFERENCE_NUM_THREADS": str(threads),
        "PERF_COUNT": "YES",
    }
    request = core.compile_model(model, "CPU", config).create_infer_request()
    request.infer(feed)  # warm-up
    by_type: dict[str, float] = {}
    by_precision: dict[str, float] = {}
    for _ in range(runs):
        request.infer(feed)
        for info in request.profiling_info:
            if info.status != info.Status.EXECUTED:
                continue
            ms = info.real_time.total_seconds() * 1e3
            by_type[info.node_type] = by_type.get(info.node_type, 0.0) + ms
            exec_precision = info.exec_type.rsplit("_", 1)[-1] if "_" in info.exec_type else "?"
            by_precision[exec_precision] = by_precision.get(exec_precision, 0.0) + ms
    total = sum(by_type.values())
    return {
        "by_type": dict(sorted(by_type.items(), key=lambda kv: -kv[1])),
        "by_precision": dict(sorted(by_precision.items(), key=lambda kv: -kv[1])),
        "total_ms": total,
        "runs": runs,
    }


def mac_summary(rows: list[dict], name: str, macs: dict | None, clock_ghz=None) -> None:
    """The network's MACs, achieved MAC/s (network alone) and share of the CPU's peak
    (``clock_ghz``: the clock to assume instead of ``/proc/cpuinfo``'s)."""
    if not macs:
        return
    info = cpu_info()
    if clock_ghz:
        info["mhz"] = 1e3 * clock_ghz
    print(f"  network: {macs['total'] / 1e9:.2f} GMAC per frame (exported ONNX graph)")
    for row in rows:
        if row["config"] != name:
            continue
        ms = row.get("network_ms", row["infer_ms"])
        achieved = macs["total"] / (ms / 1e3)
        peak, how = peak_macs_per_s(row["precision"] if row["runtime"] != "jax" else "f32", info)
        row["macs"], row["achieved_macs_per_s"], row["peak_macs_per_s"] = macs, achieved, peak
        # per core-second the network's threads ran: what a shared machine's load leaves alone
        per_core = macs["total"] / (row["infer_cpu_ms"] / 1e3)
        row["macs_per_core_s"] = per_core
        cores = info["cores"]
        print(
            f"    {row['label']:24s} {achieved / 1e9:7.1f} GMAC/s = {achieved / peak:6.1%} of "
            f"{peak / 1e9:.0f} GMAC/s ({how}); per busy core {per_core / 1e9:.1f} GMAC/s = "
            f"{per_core * cores / peak:.1%} of a core's peak"
        )


def exported_onnx(detector) -> Path | None:
    network = getattr(getattr(detector, "_predict", None), "network", None)
    if network is None:
        return None
    onnx = Path(network.path).with_name("model.onnx")
    return onnx if onnx.exists() else None


def profile(detector, row: dict, threads: int) -> None:
    """OpenVINO's per-layer counters of ``detector``'s network, per layer type."""
    import numpy as np

    network = detector._predict.network
    h, w = detector.input_size
    feed = {
        "images": np.zeros((1, h, w, 3), np.float32),
        "P2": np.array([np.eye(3, 4)], np.float32) * [[w], [w], [1]],
        "plane": np.array([[0, -1, 0, 1.65]], np.float32),
    }
    prof = openvino_layer_profile(network.path, row["precision"], threads, feed)
    row["profile"] = prof
    total = prof["total_ms"]
    shares = ", ".join(f"{k} {v / total:.0%}" for k, v in list(prof["by_type"].items())[:8])
    print(f"    OpenVINO per layer type ({total / prof['runs']:.1f} ms per call): {shares}")
    shares = ", ".join(f"{k} {v / total:.0%}" for k, v in prof["by_precision"].items())
    print(f"    by executed precision: {shares}", flush=True)
