"""How benchmarks/bench_stream.py prints one measured row: the rate, each stage's time and
core-ms, the network alone, and the N / (N + H) bound the host stages set."""

from __future__ import annotations


def print_row(label: str, row: dict) -> None:
    rounds = ", ".join(f"{f:.2f}" for f in row["fps_rounds"])
    print(
        f"  {label:24s} {row['fps_median']:6.2f} frames/s  latency median "
        f"{row['latency_median_ms']:7.0f} ms  p95 {row['latency_p95_ms']:7.0f} ms  "
        f"(rounds {rounds}; set-up {row['setup_s']:.0f} s; load {row['load_avg_1min']})",
        flush=True,
    )
    busy = ", ".join(f"{k} {v:.1f}" for k, v in row["stage_ms"].items())
    print(f"    ms per frame, each stage (overlapping): {busy}")
    busy = ", ".join(f"{k} {v:.1f}" for k, v in row["stage_cpu_ms"].items())
    print(f"    CPU ms per frame of each stage's thread: {busy}")
    recording = (
        f" (of it the MCAP recording {row['mcap_cpu_ms']:.1f})" if row["mcap_cpu_ms"] else ""
    )
    print(
        f"    + XLA threads {row['xla_cpu_ms']:.1f}, video encoder thread "
        f"{row['encoder_cpu_ms']:.1f}, runtime/other threads {row['other_cpu_ms']:.1f}; the "
        f"write stage{recording} is above; total {row['cpu_ms_per_frame']:.1f} core-ms per frame "
        f"of {row['wall_core_ms_per_frame']:.1f} (wall x cores: "
        f"{row['cpu_ms_per_frame'] / row['wall_core_ms_per_frame']:.0%} busy)"
    )
    bare = f", bare network call {row['network_ms']:.1f} ms" if "network_ms" in row else ""
    print(
        f"    network alone (infer, decoding included) {row['infer_ms']:.1f} ms = "
        f"{1e3 / row['infer_ms']:.1f} frames/s{bare}; the stream runs at "
        f"{row['stream_over_network']:.0%} of it",
        flush=True,
    )
    print(
        f"    network alone {row['infer_cpu_ms']:.1f} core-ms per frame = "
        f"{row['network_cpu_share']:.0%} of the stream's core-ms (a CPU-bound stream's rate "
        "as a fraction of the network-alone rate)",
        flush=True,
    )
    host = sum(v for k, v in row["stage_cpu_ms"].items() if k != "network")
    host += row["encoder_cpu_ms"]
    net = row["infer_cpu_ms"]
    print(
        f"    host stages (read, prepare, finish + draw, write, encoder) H {host:.1f} core-ms per "
        "frame; "
        f"when the network alone (N) keeps every core busy, a stream reaches at most "
        f"N / (N + H) = {net / (net + host):.0%} of its rate",
        flush=True,
    )
    if "primitives" in row:
        prims = ", ".join(f"{p} x{k}" for p, k in row["primitives"].items())
        wino = any("wino" in p.lower() for p in row["primitives"])
        print(f"    convolutions run as {prims}{'' if wino else ' (no Winograd)'}", flush=True)
    if "live" in row:
        live = row["live"]
        print(
            f"    live at {live['fps']:g} frames/s (--realtime): {live['dropped']} of "
            f"{live['delivered']} frames dropped, latency median {live['latency_median_ms']:.0f} "
            f"ms, p95 {live['latency_p95_ms']:.0f} ms",
            flush=True,
        )
