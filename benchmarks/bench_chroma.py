"""How much RGB PSNR the 4:2:0 colour format itself leaves an annotated stream picture, and
whether the drawing or the colour conversion could raise it.

An H.264 stream that browsers play is yuv420p: one colour (chroma) sample per 2x2 pixels.
This script converts pictures to yuv420p and back with no codec at all and prints the RGB
PSNR against the picture (median over frames; luma PSNR beside it), for

* pictures: ``frame``, the camera frame alone; ``frame + empty BEV``, the picture a stream
  writes without boxes (the frame beside the empty bird's-eye view); ``annotated``, today's
  picture (anti-aliased 2-px boxes, labels, the bird's-eye view's boxes; generated clip 0 with
  its ground-truth boxes, as ``bench_video_codecs.py``); ``annotated, no labels``: the same
  boxes without their text labels; ``annotated, 2x2 grid``: the same
  annotations snapped to the chroma grid (every 2x2 block that the drawing touched painted
  whole in the drawing's colour there: even coordinates and widths, no anti-aliasing), the
  most a drawing change could give to chroma; with ``--real DIR`` also a real drive's frames;
* conversions, ``to yuv420p>back``: ``encoder``, the stream encoder's own
  (``cv2.COLOR_RGB2YUV_I420``), or FFmpeg's (``sws``, PyAV ``reformat``) with ``area`` or
  ``bicubic`` filtering; back with OpenCV (``opencv``: the "yuv420p alone" row of
  ``bench_video_codecs.py``) or PyAV's ``to_ndarray("rgb24")`` (``pyav``: how that script and
  a player decode the H.264); ``exact 601`` / ``exact 709``: in floating point, full range,
  chroma the mean of each 2x2 block and interpolated bilinearly back (as a GPU does), with
  BT.601 or BT.709 weights: what a better conversion could reach.

    python benchmarks/bench_chroma.py [--frames 20] [--real DIR] [--json OUT]
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np
from machine_info import describe_machine, one_line  # benchmarks/ is on sys.path

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

WEIGHTS = {"601": (0.299, 0.114), "709": (0.2126, 0.0722)}  # (Kr, Kb)


def psnr(a: np.ndarray, b: np.ndarray) -> float:
    mse = float(np.mean((a.astype(np.float64) - b.astype(np.float64)) ** 2))
    return 10 * np.log10(255.0**2 / max(mse, 1e-12))


def luma(rgb: np.ndarray) -> np.ndarray:
    return rgb.astype(np.float64) @ np.array([0.299, 0.587, 0.114])


def even(rgb: np.ndarray) -> np.ndarray:
    """The picture padded to even height and width (last row / column repeated)."""
    h, w = rgb.shape[:2]
    return np.pad(rgb, ((0, h % 2), (0, w % 2), (0, 0)), mode="edge")


def encoder_i420(rgb: np.ndarray) -> np.ndarray:
    """The stream encoder's conversion (:mod:`gac_jax.streams.video_encoder`): (3H/2, W)."""
    import cv2

    return cv2.cvtColor(even(rgb), cv2.COLOR_RGB2YUV_I420)


def swscale_i420(rgb: np.ndarray, interpolation: str) -> np.ndarray:
    """FFmpeg's conversion (PyAV ``reformat``) with ``interpolation``: (3H/2, W)."""
    import av

    frame = av.VideoFrame.from_ndarray(np.ascontiguousarray(even(rgb)), format="rgb24")
    return frame.reformat(format="yuv420p", interpolation=interpolation).to_ndarray()


def opencv_rgb(i420: np.ndarray, size: tuple[int, int]) -> np.ndarray:
    import cv2

    return cv2.cvtColor(i420, cv2.COLOR_YUV2RGB_I420)[: size[0], : size[1]]


def pyav_rgb(i420: np.ndarray, size: tuple[int, int]) -> np.ndarray:
    """As ``bench_video_codecs.py`` and a player decode: PyAV's ``to_ndarray("rgb24")``."""
    import av

    frame = av.VideoFrame.from_ndarray(np.ascontiguousarray(i420), format="yuv420p")
    return frame.to_ndarray(format="rgb24")[: size[0], : size[1]]


def via_exact(rgb: np.ndarray, weights: str) -> np.ndarray:
    """Full-range Y'CbCr with ``weights``, 8-bit planes, 2x2-mean chroma, bilinear back."""
    import cv2

    h, w = rgb.shape[:2]
    kr, kb = WEIGHTS[weights]
    x = even(rgb).astype(np.float64)
    y = kr * x[..., 0] + (1 - kr - kb) * x[..., 1] + kb * x[..., 2]
    cb = (x[..., 2] - y) / (2 * (1 - kb))
    cr = (x[..., 0] - y) / (2 * (1 - kr))
    H, W = y.shape
    planes = []
    for c in (cb, cr):
        small = np.round(c.reshape(H // 2, 2, W // 2, 2).mean(axis=(1, 3)) + 128)
        small = np.clip(small, 0, 255).astype(np.float32) - 128
        planes.append(cv2.resize(small, (W, H), interpolation=cv2.INTER_LINEAR))
    y = np.clip(np.round(y), 0, 255)
    cb, cr = planes
    r = y + 2 * (1 - kr) * cr
    b = y + 2 * (1 - kb) * cb
    g = (y - kr * r - kb * b) / (1 - kr - kb)
    out = np.stack([r, g, b], axis=-1)
    return np.clip(np.round(out), 0, 255).astype(np.uint8)[:h, :w]


CONVERSIONS = {  # name -> RGB picture -> RGB picture after yuv420p
    "encoder>opencv": lambda x: opencv_rgb(encoder_i420(x), x.shape[:2]),
    "encoder>pyav": lambda x: pyav_rgb(encoder_i420(x), x.shape[:2]),
    "sws area>pyav": lambda x: pyav_rgb(swscale_i420(x, "AREA"), x.shape[:2]),
    "sws bicubic>pyav": lambda x: pyav_rgb(swscale_i420(x, "BICUBIC"), x.shape[:2]),
    "exact 601": lambda x: via_exact(x, "601"),
    "exact 709": lambda x: via_exact(x, "709"),
}


def snap_to_grid(annotated: np.ndarray, plain: np.ndarray) -> np.ndarray:
    """``annotated`` with its drawing (the pixels that differ from ``plain``) snapped to the
    2x2 chroma grid: a block the drawing touched takes, whole, the colour of its pixel that
    differs most from ``plain``."""
    a, p = even(annotated), even(plain)
    H, W = a.shape[:2]
    blocks = a.reshape(H // 2, 2, W // 2, 2, 3).transpose(0, 2, 1, 3, 4).reshape(-1, 4, 3)
    diff = np.abs(a.astype(np.int16) - p).sum(-1)
    diff = diff.reshape(H // 2, 2, W // 2, 2).transpose(0, 2, 1, 3).reshape(-1, 4)
    strongest = blocks[np.arange(len(blocks)), diff.argmax(1)]
    touched = diff.max(1) > 0
    out = blocks.copy()
    out[touched] = strongest[touched][:, None]
    out = out.reshape(H // 2, W // 2, 2, 2, 3).transpose(0, 2, 1, 3, 4).reshape(H, W, 3)
    h, w = annotated.shape[:2]
    return np.ascontiguousarray(out[:h, :w])


def clip_variants(frames: int) -> dict[str, list[np.ndarray]]:
    """The pictures of generated clip 0 (see the module doc)."""
    from gac_jax.cli.stream_start import clip_sequence
    from gac_jax.data.files import read_image
    from gac_jax.data.kitti import KittiObjects
    from gac_jax.data.kitti_tracking import KittiTrackingLayout
    from gac_jax.drawing.detection_pictures import bev_grid_for_height, detection_picture
    from gac_jax.evaluation import viz

    layout, sequence = KittiTrackingLayout.locate(clip_sequence(0))
    out: dict[str, list[np.ndarray]] = {}
    for frame in layout.frames(sequence):
        if len(out.get("frame", [])) == frames:
            break
        image = read_image(frame.image)
        objects = frame.labels.objects
        objects = objects.select(objects.type != "DontCare")
        objects = objects.replace(score=np.ones(len(objects)))
        plain = detection_picture(image, frame.P2, KittiObjects.empty())
        annotated = detection_picture(image, frame.P2, objects)
        unlabelled = plain.copy()
        w = image.shape[1]
        viz.draw_detections_into(unlabelled[:, :w], frame.P2, objects, show_labels=False)
        viz.draw_bev_into(unlabelled[:, w:], objects, None, bev_grid_for_height(len(image)))
        pictures = {
            "frame": image,
            "frame + empty BEV": plain,
            "annotated": annotated,
            "annotated, no labels": unlabelled,
            "annotated, 2x2 grid": snap_to_grid(annotated, plain),
        }
        for name, picture in pictures.items():
            out.setdefault(name, []).append(picture)
    return out


def real_variants(folder: Path, frames: int) -> dict[str, list[np.ndarray]]:
    from gac_jax.data.files import read_image
    from gac_jax.data.kitti import KittiObjects
    from gac_jax.drawing.detection_pictures import detection_picture

    P2 = np.array([[721.5, 0, 609.6, 44.9], [0, 721.5, 172.9, 0.2], [0, 0, 1, 0.003]])
    images = [read_image(p) for p in sorted(folder.glob("*.png"))[:frames]]
    return {
        "frame": images,
        "frame + empty BEV": [detection_picture(i, P2, KittiObjects.empty()) for i in images],
    }


def report(name: str, variants: dict[str, list[np.ndarray]]) -> dict:
    print(f"\n=== {name}: {len(next(iter(variants.values())))} frames ===")
    print("RGB PSNR (dB) after yuv420p and back, median over frames (luma in brackets)")
    print(f"{'picture':20s}" + "".join(f"{c:>18s}" for c in CONVERSIONS))
    rows = {}
    for picture, images in variants.items():
        row = {}
        for conversion, convert in CONVERSIONS.items():
            got = [convert(image) for image in images]
            row[conversion] = {
                "rgb": float(np.median([psnr(g, i) for g, i in zip(got, images, strict=True)])),
                "luma": float(
                    np.median([psnr(luma(g), luma(i)) for g, i in zip(got, images, strict=True)])
                ),
            }
        cells = "".join(f"{v['rgb']:>11.1f} ({v['luma']:4.1f})" for v in row.values())
        print(f"{picture:20s}{cells}", flush=True)
        rows[picture] = row
    return rows


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--frames", type=int, default=20)
    p.add_argument("--real", type=Path, help="also a folder of real frames (PNG)")
    p.add_argument("--save", type=Path, help="write the first frame's pictures as PNG here")
    p.add_argument("--json", type=Path)
    args = p.parse_args()

    info = describe_machine("av", "cv2", "numpy")
    print(one_line(info))
    clip = clip_variants(args.frames)
    result = {"machine": info, "clip": report("generated clip 0", clip)}
    if args.real is not None:
        result["real"] = report(f"real frames of {args.real.name}", real_variants(args.real, 20))
    if args.save is not None:
        from gac_jax.data.files import write_png

        args.save.mkdir(parents=True, exist_ok=True)
        for name, pictures in clip.items():
            stem = name.replace(" ", "_").replace(",", "").replace("+", "and")
            write_png(args.save / f"{stem}.png", pictures[0])
            back = CONVERSIONS["encoder>pyav"](pictures[0])
            write_png(args.save / f"{stem}_yuv420p.png", back)
    if args.json:
        args.json.write_text(json.dumps(result))


if __name__ == "__main__":
    main()
