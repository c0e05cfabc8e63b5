"""CPU cost of an MCAP recording (``--mcap``): core-ms per frame inside the recorder's
``write``, per profile and per kind of input frame, optionally beside an earlier commit's.

The frames are the vendored real KITTI frames (``tests/data/kitti``, cropped/resized to
1242x375 and cycled; ``--real DIR``: a folder of PNG frames instead), each with ``--boxes``
tracks (``TrackedObjects`` with velocities: a ``--track`` stream), a pose (``--poses``) and
the JSON record the stream passes. Each frame goes through
:class:`gac_jax.streams.mcap_recording.McapRecording` ``write`` as the stream's recorder
calls it; the kinds of input frame are

* ``array``: a decoded frame (``--video``, ``--camera``, or a sequence of PNG files such as
  ``--clip`` and KITTI's): the recorder encodes it as JPEG;
* ``jpeg``: a frame read from a JPEG file (a ``--sequence`` of JPEGs, here the frames as JPEG
  quality 95): the recorder is also given the file's bytes (``Frame.jpeg``), which code that
  takes them stores as they are (a commit without that encodes a JPEG as for ``array``).

Printed per row: the median over ``--rounds`` of the core-ms per frame (the writing
thread's CPU time inside ``write``, ``time.thread_time``, over the frames after the first,
which registers the schemas), the file's kB per frame and, where the code reports them, the
parts (``image``: the JPEG; ``messages``: the boxes' entities, the JSON and the messages;
``write``: serialisation and the chunk). Every measurement runs in its own process and the
rounds interleave the rows (and, with ``--against REV``, that commit's code: its ``gac_jax``
from ``git archive``; with ``--jpeg-quality Q``, the code now with the recorder's
``jpeg_quality`` Q), so all see the same load. CPU time, not wall time: the machine may be
shared.

    python benchmarks/bench_mcap.py [--frames 30] [--rounds 5] [--boxes 10]
        [--profiles foxglove,ros2] [--inputs array,jpeg] [--against REV] [--real DIR]
        [--jpeg-quality Q] [--json OUT]
"""

from __future__ import annotations

import argparse
import inspect
import json
import os
import subprocess
import sys
import tempfile
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
KITTI = REPO / "tests" / "data" / "kitti" / "object" / "training" / "image_2"
FRAME_SIZE = (375, 1242)  # KITTI's
FPS = 10.0


# --------------------------------------------------------------------------- the worker


def load_frames(folder: Path, n: int) -> list[np.ndarray]:
    """``n`` (375, 1242, 3) uint8 RGB frames of the PNGs in ``folder`` (cropped or resized,
    cycled)."""
    import cv2

    paths = sorted(folder.glob("*.png"))
    h, w = FRAME_SIZE
    frames = []
    for path in paths[:n]:
        image = cv2.imread(str(path), cv2.IMREAD_COLOR)[:h, :w, ::-1]
        if image.shape[:2] != (h, w):
            image = cv2.resize(image, (w, h), interpolation=cv2.INTER_LINEAR)
        frames.append(np.ascontiguousarray(image))
    return [frames[i % len(frames)] for i in range(n)]


def jpeg_files(frames: list[np.ndarray]) -> list[bytes]:
    """The frames as the JPEG files (quality 95) a sequence would hold."""
    import cv2

    params = [cv2.IMWRITE_JPEG_QUALITY, 95]
    return [cv2.imencode(".jpg", image[..., ::-1], params)[1].tobytes() for image in frames]


def frame_tracks(n: int, i: int):
    """``n`` tracks of frame ``i`` ahead of the camera (ids 0..n-1, classes in turn, moving
    a little each frame; the last one without a velocity when n > 1)."""
    from gac_jax.tracking.tracks import TrackedObjects

    rng = np.random.default_rng(n)
    names = np.array(["Car", "Pedestrian", "Cyclist"])[np.arange(n) % 3]
    dims = np.where(names[:, None] == "Car", [1.5, 1.6, 3.9], [1.75, 0.6, 0.8])
    loc = np.stack([rng.uniform(-8, 8, n), np.full(n, 1.65), rng.uniform(5, 50, n)], -1)
    loc[:, 2] += 0.3 * i
    velocities = np.stack([rng.normal(0, 1, n), np.zeros(n), rng.normal(3, 2, n)], -1)
    if n > 1:
        velocities[-1] = np.nan
    return TrackedObjects(
        ids=np.arange(n),
        names=names,
        scores=np.linspace(0.95, 0.3, n),
        boxes_2d=np.tile([100.0, 150.0, 220.0, 230.0], (n, 1)),
        dimensions=dims,
        locations=loc,
        rotation_y=rng.uniform(-np.pi, np.pi, n),
        velocities=velocities,
        velocity_covariances=np.zeros((n, 3, 3)),
        ages=np.full(n, i),
        hits=np.full(n, i + 1),
        trails=[np.zeros((0, 3))] * n,
    )


def measure(options: dict) -> dict:
    """One recording of ``options['frames']`` frames (see the module doc); its core-ms per
    frame, parts and kB per frame."""
    import cv2

    from gac_jax.streams.mcap_recording import McapRecording

    cv2.setNumThreads(1)  # the stream's budget: one OpenCV thread per stage
    n, boxes = options["frames"], options["boxes"]
    frames = load_frames(Path(options["folder"]), n)
    files = jpeg_files(frames) if options["input"] == "jpeg" else None
    tracks = [frame_tracks(boxes, i) for i in range(n)]
    records = [t.to_dict() for t in tracks]
    P2 = np.array([[721.5, 0, 609.6, 44.9], [0, 721.5, 172.9, 0.2], [0, 0, 1, 0.003]])
    poses = np.zeros((n, 3, 4))
    poses[:, :, :3] = np.eye(3)
    poses[:, 2, 3] = np.arange(n) * 1.2
    path = Path(options["out"]) / f"run_{os.getpid()}.mcap"
    quality = {} if options["jpeg_quality"] is None else {"jpeg_quality": options["jpeg_quality"]}
    recording = McapRecording(
        path, options["profile"], default_plane=(0.0, -1.0, 0.0, 1.65), **quality
    )
    takes_bytes = "jpeg" in inspect.signature(recording.write).parameters
    cpu0, parts0 = 0.0, {}
    for i in range(n):
        extra = {"jpeg": files[i]} if files is not None and takes_bytes else {}
        recording.write(frames[i], P2, tracks[i], timestamp=i / FPS, pose=poses[i],
                        record=records[i], frame_id=f"{i:06d}", **extra)  # fmt: skip
        if i == 0:  # the first frame registers the schemas and channels
            cpu0, parts0 = recording.cpu_s, dict(getattr(recording, "cpu_parts", {}))
    recording.close()
    size = path.stat().st_size
    path.unlink()
    parts = getattr(recording, "cpu_parts", {})
    per_frame = 1e3 / (n - 1)
    return {
        "core_ms": (recording.cpu_s - cpu0) * per_frame,
        "parts": {k: (v - parts0.get(k, 0.0)) * per_frame for k, v in parts.items()},
        "kb_per_frame": size / n / 1e3,
    }


# --------------------------------------------------------------------------- the runner


def run_worker(src: Path, options: dict) -> dict:
    """``measure(options)`` in a process that imports ``gac_jax`` from ``src``."""
    env = {**os.environ, "PYTHONPATH": str(src)}
    argv = [
        sys.executable,
        str(Path(__file__).resolve()),
        "--worker",
        json.dumps({**options, "src": str(src)}),
    ]
    done = subprocess.run(argv, env=env, capture_output=True, text=True, cwd=src, check=False)
    if done.returncode != 0:
        raise RuntimeError(f"worker failed ({src}):\n{done.stderr[-3000:]}")
    return json.loads(done.stdout.strip().splitlines()[-1])


def checkout(rev: str, into: Path) -> Path:
    """``rev``'s ``gac_jax`` package (``git archive``) under ``into``."""
    into.mkdir(parents=True)
    archive = subprocess.run(
        ["git", "-C", str(REPO), "archive", rev, "gac_jax"], capture_output=True, check=True
    ).stdout
    subprocess.run(["tar", "-x", "-C", str(into)], input=archive, check=True)
    return into


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--frames", type=int, default=30)
    p.add_argument("--rounds", type=int, default=5)
    p.add_argument("--boxes", type=int, default=10, help="tracks per frame")
    p.add_argument("--profiles", default="foxglove,ros2")
    p.add_argument("--inputs", default="array,jpeg")
    p.add_argument("--against", metavar="REV", help="also this commit's code, side by side")
    p.add_argument("--real", type=Path, help="a folder of PNG frames instead of tests/data")
    p.add_argument(
        "--jpeg-quality", type=int, help="also the code now with this JPEG quality (a row more)"
    )
    p.add_argument("--json", type=Path)
    args = p.parse_args()

    sys.path.insert(0, str(Path(__file__).parent))
    from machine_info import describe_machine, one_line

    info = describe_machine("mcap", "cv2", "numpy")
    print(one_line(info), flush=True)
    folder = (args.real or KITTI).resolve()
    rows = [(pr, kind) for pr in args.profiles.split(",") for kind in args.inputs.split(",")]
    with tempfile.TemporaryDirectory(prefix="bench_mcap_") as tmp:
        versions = {"now": (REPO, None)}  # label -> (the gac_jax to import, JPEG quality)
        if args.against:
            before = checkout(args.against, Path(tmp) / "before")
            versions = {args.against: (before, None), **versions}
        if args.jpeg_quality is not None:
            versions[f"now, JPEG {args.jpeg_quality}"] = (REPO, args.jpeg_quality)
        results: dict = {(r, v): [] for r in rows for v in versions}
        print(f"{args.frames} frames of {folder.name} (1242x375), {args.boxes} tracks each, "
              f"{args.rounds} rounds", flush=True)  # fmt: skip
        for k in range(args.rounds):
            for profile, kind in rows:
                for version, (src, quality) in versions.items():
                    options = {"profile": profile, "input": kind, "frames": args.frames,
                               "boxes": args.boxes, "folder": str(folder), "out": tmp,
                               "jpeg_quality": quality}  # fmt: skip
                    results[(profile, kind), version].append(run_worker(src, options))
            print(f"  round {k + 1}/{args.rounds} done (load {os.getloadavg()[0]:.1f})", flush=True)
    summary = report(rows, versions, results)
    info["load_avg_1min_end"] = round(os.getloadavg()[0], 2)
    print(f"\nload average (1 min) at the end: {info['load_avg_1min_end']}")
    if args.json:
        args.json.write_text(json.dumps({"machine": info, "rows": summary}, indent=1))


def report(rows, versions, results) -> list[dict]:
    """Prints a line per row and version (medians over the rounds); returns them."""
    print("\nprofile   input  code           core-ms/frame (median; min-max)  kB/frame  parts")
    out = []
    for profile, kind in rows:
        for version in versions:
            runs = results[(profile, kind), version]
            ms = [r["core_ms"] for r in runs]
            parts = {
                key: float(np.median([r["parts"].get(key, np.nan) for r in runs]))
                for key in runs[0]["parts"]
            }
            text = ", ".join(f"{key} {v:.2f}" for key, v in parts.items())
            kb = float(np.median([r["kb_per_frame"] for r in runs]))
            print(f"{profile:9s} {kind:6s} {version:13s}  {np.median(ms):6.2f} "
                  f"({min(ms):.2f}-{max(ms):.2f})              {kb:7.1f}  {text}")  # fmt: skip
            out.append({"profile": profile, "input": kind, "code": version,
                        "core_ms_median": float(np.median(ms)), "core_ms": ms,
                        "kb_per_frame": kb, "parts": parts})  # fmt: skip
    return out


if __name__ == "__main__":
    if len(sys.argv) == 3 and sys.argv[1] == "--worker":
        options = json.loads(sys.argv[2])
        sys.path.insert(0, options["src"])
        print(json.dumps(measure(options)))
    else:
        main()
