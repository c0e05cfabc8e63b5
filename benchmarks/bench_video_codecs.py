"""Bytes per frame, picture quality and encoder CPU of the annotated video's codecs.

The pictures are those a stream writes (:func:`gac_jax.drawing.detection_pictures.
detection_picture`: camera view with 3D boxes, 2D boxes and labels beside the bird's-eye view;
1564x375 for a 1242x375 frame), drawn from the ground-truth boxes of generated driving clip 0
(60 frames, the ``--clip`` of the stream command), so that no detector is needed. Each codec
writes them through :class:`gac_jax.streams.outputs.AnnotatedVideo` (the stream's writer):

* ``jpeg q90 (before)``: the frames as JPEG of quality 90 (``cv2.imencode``), what the
  hand-made fragmented MP4 muxer stored before H.264 (its ~100 bytes of fragment boxes per
  frame not counted);
* ``mjpeg``: ``--codec mjpeg``, Motion JPEG written by PyAV;
* ``h264``: the default, libx264 CRF 23 ``veryfast`` ``zerolatency``, High profile;
* ``yuv420p alone``: no codec, only the pictures' conversion to the 4:2:0 colour format that
  H.264 for browsers and JPEG use and back (OpenCV): the PSNR any such video can reach.

Printed per codec: bytes per frame (the file's size over its frames), the ratio to the JPEG
frames, PSNR against the uncompressed annotated picture (RGB, over the picture without its
padding, median over frames, and the worst frame) and on luma only (Y of BT.601), and the
encoder thread's CPU milliseconds per frame (colour conversion, encoding, muxing). With
``--real DIR`` the same for the frames of a real drive (a folder of PNGs; no labels: the
pictures are the frames and an empty bird's-eye view).

    python benchmarks/bench_video_codecs.py [--frames 60] [--real DIR] [--json OUT]
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
from machine_info import describe_machine, one_line  # benchmarks/ is on sys.path

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))


def clip_pictures(frames: int) -> list[np.ndarray]:
    """Annotated pictures of generated clip 0's first ``frames`` frames (ground truth)."""
    from gac_jax.cli.stream_start import clip_sequence
    from gac_jax.data.files import read_image
    from gac_jax.data.kitti_tracking import KittiTrackingLayout
    from gac_jax.drawing.detection_pictures import detection_picture

    layout, sequence = KittiTrackingLayout.locate(clip_sequence(0))
    out = []
    for frame in layout.frames(sequence):
        if len(out) == frames:
            break
        objects = frame.labels.objects
        objects = objects.select(objects.type != "DontCare")
        objects = objects.replace(score=np.ones(len(objects)))
        out.append(detection_picture(read_image(frame.image), frame.P2, objects))
    return out


def real_pictures(folder: Path, frames: int) -> list[np.ndarray]:
    from gac_jax.data.files import read_image
    from gac_jax.data.kitti import KittiObjects
    from gac_jax.drawing.detection_pictures import detection_picture

    P2 = np.array([[721.5, 0, 609.6, 44.9], [0, 721.5, 172.9, 0.2], [0, 0, 1, 0.003]])
    paths = sorted(folder.glob("*.png"))[:frames]
    return [detection_picture(read_image(p), P2, KittiObjects.empty()) for p in paths]


def psnr(a: np.ndarray, b: np.ndarray) -> float:
    mse = float(np.mean((a.astype(np.float64) - b.astype(np.float64)) ** 2))
    return 10 * np.log10(255.0**2 / max(mse, 1e-12))


def luma(rgb: np.ndarray) -> np.ndarray:
    return rgb.astype(np.float64) @ np.array([0.299, 0.587, 0.114])


def measure_codec(pictures: list[np.ndarray], codec: str, folder: Path) -> dict:
    """Writes ``pictures`` with the stream's writer and decodes them again (PyAV)."""
    import av

    from gac_jax.streams.outputs import AnnotatedVideo

    path = folder / f"{codec}.mp4"
    video = AnnotatedVideo(path, 10.0, codec)
    t0 = time.perf_counter()
    for picture in pictures:
        video.write(picture)
    video.close()
    wall_s = time.perf_counter() - t0
    cpu_s = video.encoder_cpu_s
    h, w = pictures[0].shape[:2]
    rgb, y = [], []
    with av.open(str(path)) as container:
        for frame, want in zip(container.decode(video=0), pictures, strict=True):
            got = frame.to_ndarray(format="rgb24")[:h, :w]
            rgb.append(psnr(got, want))
            y.append(psnr(luma(got), luma(want)))
    return {
        "bytes_per_frame": path.stat().st_size / len(pictures),
        "psnr_rgb_median": float(np.median(rgb)),
        "psnr_rgb_min": float(np.min(rgb)),
        "psnr_y_median": float(np.median(y)),
        "encoder_cpu_ms": 1e3 * cpu_s / len(pictures),
        "wall_ms": 1e3 * wall_s / len(pictures),
    }


def measure_jpeg(pictures: list[np.ndarray]) -> dict:
    """The JPEG (quality 90) frames the hand-made muxer stored before."""
    import cv2

    sizes, rgb, y, cpu = [], [], [], []
    for picture in pictures:
        c0 = time.thread_time()
        bgr = cv2.cvtColor(picture, cv2.COLOR_RGB2BGR)
        ok, jpeg = cv2.imencode(".jpg", bgr, [cv2.IMWRITE_JPEG_QUALITY, 90])
        cpu.append(time.thread_time() - c0)
        got = cv2.cvtColor(cv2.imdecode(jpeg, cv2.IMREAD_COLOR), cv2.COLOR_BGR2RGB)
        sizes.append(len(jpeg))
        rgb.append(psnr(got, picture))
        y.append(psnr(luma(got), luma(picture)))
    return {
        "bytes_per_frame": float(np.mean(sizes)),
        "psnr_rgb_median": float(np.median(rgb)),
        "psnr_rgb_min": float(np.min(rgb)),
        "psnr_y_median": float(np.median(y)),
        "encoder_cpu_ms": 1e3 * float(np.mean(cpu)),
        "wall_ms": float("nan"),
    }


def measure_yuv420(pictures: list[np.ndarray]) -> dict:
    """RGB -> yuv420p (even size, last row / column repeated) -> RGB, no compression."""
    import cv2

    rgb, y = [], []
    for picture in pictures:
        h, w = picture.shape[:2]
        padded = cv2.copyMakeBorder(picture, 0, h % 2, 0, w % 2, cv2.BORDER_REPLICATE)
        i420 = cv2.cvtColor(padded, cv2.COLOR_RGB2YUV_I420)
        got = cv2.cvtColor(i420, cv2.COLOR_YUV2RGB_I420)[:h, :w]
        rgb.append(psnr(got, picture))
        y.append(psnr(luma(got), luma(picture)))
    nan = float("nan")
    return {"bytes_per_frame": nan, "psnr_rgb_median": float(np.median(rgb)),
            "psnr_rgb_min": float(np.min(rgb)), "psnr_y_median": float(np.median(y)),
            "encoder_cpu_ms": nan, "wall_ms": nan}  # fmt: skip


def report(name: str, pictures: list[np.ndarray], folder: Path) -> dict:
    h, w = pictures[0].shape[:2]
    print(f"\n=== {name}: {len(pictures)} annotated pictures of {w}x{h} ===")
    rows = {"jpeg q90 (before)": measure_jpeg(pictures)}
    for codec in ("mjpeg", "h264"):
        rows[codec] = measure_codec(pictures, codec, folder)
    rows["yuv420p alone"] = measure_yuv420(pictures)
    base = rows["jpeg q90 (before)"]["bytes_per_frame"]
    for label, row in rows.items():
        print(
            f"  {label:18s} {row['bytes_per_frame'] / 1e3:7.1f} kB/frame "
            f"({row['bytes_per_frame'] / base:5.1%} of the JPEG frames)  PSNR RGB median "
            f"{row['psnr_rgb_median']:.1f} dB (worst frame {row['psnr_rgb_min']:.1f}), "
            f"luma {row['psnr_y_median']:.1f} dB  encoder {row['encoder_cpu_ms']:.1f} "
            "core-ms/frame",
            flush=True,
        )
    return rows


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--frames", type=int, default=60)
    p.add_argument("--real", type=Path, help="also a folder of real frames (PNG)")
    p.add_argument("--json", type=Path)
    args = p.parse_args()

    import cv2

    cv2.setNumThreads(1)  # the stream's budget: one OpenCV thread per stage
    info = describe_machine("av", "cv2", "numpy")
    print(one_line(info))
    result = {"machine": info}
    with tempfile.TemporaryDirectory(prefix="bench_video_codecs_") as tmp:
        result["clip"] = report("generated clip 0", clip_pictures(args.frames), Path(tmp))
        if args.real is not None:
            result["real"] = report(
                f"real frames of {args.real.name}", real_pictures(args.real, args.frames), Path(tmp)
            )
    info["load_avg_1min_end"] = round(os.getloadavg()[0], 2)
    print(f"\nload average (1 min) at the end: {info['load_avg_1min_end']}")
    if args.json:
        args.json.write_text(json.dumps(result))


if __name__ == "__main__":
    main()
