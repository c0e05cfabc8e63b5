"""Where a stream's CPU time goes, and the network's share of the CPU's measured peak.

* :func:`share_of_peak`: a MAC rate as a share of a peak measured by
  ``benchmarks/bench_peak.py`` (its median over rounds), and above 100 % why, in the same text.
* :class:`ThreadCpu`: CPU seconds of the process's threads between two readings of
  ``/proc/self/task/*/stat``, split into XLA's compute threads (by name) and the rest.
* :func:`openvino_layer_profile`: OpenVINO's per-layer performance counters (``PERF_COUNT``)
  summed per layer type and per executed precision.
"""

from __future__ import annotations

import os
from pathlib import Path


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
    from gac_jax.deploy.runtimes import openvino_config
    from gac_jax.deploy.telemetry import import_openvino

    core = import_openvino().Core()
    model = core.read_model(str(model_path))
    config = {**openvino_config(precision, threads), "PERF_COUNT": "YES"}
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


def share_of_peak(value: float, peak: dict, reasons: tuple[str, ...] = ()) -> str:
    """``value`` (MACs/s) as a share of ``peak`` (``{median, max}`` of a bench_peak.py rate):
    ``'87 % of 230'`` (GMAC/s); above 100 % the text says why: within the peak's spread over
    its rounds (the load varied between them), else ``reasons`` (e.g. Winograd convolutions,
    another runtime), else that the network ran faster than every round of the peak graph."""
    share = value / peak["median"]
    text = f"{100 * share:.0f} % of {peak['median'] / 1e9:.3g}"
    if share <= 1.0:
        return text
    if value <= peak["max"]:
        why = f"within the peak's rounds, up to {peak['max'] / 1e9:.3g}: the load varied"
    elif reasons:
        why = "; ".join(reasons)
    else:
        why = "faster than every round of the peak graph: not this network's ceiling"
    return f"{text} (above the median peak: {why})"


def mac_summary(rows: list[dict], name: str, macs: dict | None, peaks: dict) -> None:
    """The network's MACs, its achieved MAC rate (network alone: over the wall clock and per
    busy core-second) and their shares of the measured peaks (``peaks``: precision ->
    bench_peak.measure_peak's result; jax and ONNX Runtime rows against OpenVINO's f32)."""
    if not macs:
        return
    print(f"  network: {macs['total'] / 1e9:.2f} GMAC per frame (exported ONNX graph)")
    for row in rows:
        if row["config"] != name:
            continue
        ms = row.get("network_ms", row["infer_ms"])
        achieved = macs["total"] / (ms / 1e3)
        per_core = macs["total"] / (row["infer_cpu_ms"] / 1e3)
        row["macs"], row["achieved_macs_per_s"], row["macs_per_core_s"] = macs, achieved, per_core
        precision = row["precision"] if row["runtime"] == "openvino" else "f32"
        peak = peaks.get(precision)
        if peak is None:
            print(f"    {row['label']:24s} {achieved / 1e9:7.1f} GMAC/s (no {precision} peak)")
            continue
        reasons = []
        if row["runtime"] != "openvino":
            reasons.append(f"{row['runtime']} is not the peak's runtime (OpenVINO f32)")
        wino = sum(k for p, k in row.get("primitives", {}).items() if "wino" in p.lower())
        if wino:
            reasons.append(f"{wino} convolutions ran as Winograd, fewer MACs than counted")
        wall = share_of_peak(achieved, peak["wall_macs_per_s"], tuple(reasons))
        core = share_of_peak(per_core, peak["core_macs_per_s"], tuple(reasons))
        row["share_of_peak"] = achieved / peak["wall_macs_per_s"]["median"]
        row["share_of_core_peak"] = per_core / peak["core_macs_per_s"]["median"]
        print(
            f"    {row['label']:24s} {achieved / 1e9:7.1f} GMAC/s = {wall} GMAC/s measured "
            f"({precision} peak); per busy core-second {per_core / 1e9:.1f} GMAC = {core}"
        )


def primitives(detector) -> dict[str, int] | None:
    """``{primitive: count}`` of the convolutions of ``detector``'s OpenVINO network as it
    runs them (bench_peak.executed_primitives), or None for another runtime."""
    from bench_peak import executed_primitives

    network = getattr(getattr(detector, "_predict", None), "network", None)
    compiled = getattr(network, "_compiled", None) if network is not None else None
    return executed_primitives(compiled) if compiled is not None else None


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
