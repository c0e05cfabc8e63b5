"""TFDS builders that turn KITTI folders into prepared ArrayRecord datasets (no TensorFlow).

Records hold the raw file bytes (PNG bytes, calibration text, label text) plus
an explicit frame id; :mod:`gac_jax.data.sources` decodes them with OpenCV and
the same parsers as the folder readers, so prepared and folder samples are
identical. Shuffling is disabled (``DatasetInfo(disable_shuffling=True)``,
integer keys), so record ``i`` of a split is line ``i`` of its split file.
Reading goes through ``tfds.builder_from_directory(...).as_data_source(split)``,
which needs neither TensorFlow nor this module.

* ``gac_kitti_object``: one split per ``ImageSets/<name>.txt`` (or ``frames``: every
  calib file when there are none). Features: ``frame_id``, ``image_2``,
  ``image_3`` (empty bytes when absent), ``calib``, ``label`` (empty when
  absent), ``has_label``, ``plane`` (the ``planes/`` file's text, empty when absent;
  version 1.1.0, older datasets have none).
* ``gac_kitti_depth``: one split per (folder under ``data_depth_annotated``,
  camera), named ``<split>_image_0<camera>``, frames sorted by (drive, frame).
  Features: ``frame_id`` (``<drive>/<frame>``), ``camera``, ``image``, ``depth``
  (16-bit PNG bytes), ``calib`` (the day's ``calib_cam_to_cam.txt``), ``plane`` (the
  ``planes/<drive>/<frame>.txt`` file's text, empty when absent; version 1.1.0, older
  datasets have none).

Command line::

    python -m gac_jax.data.tfds_builders object --src KITTI_OBJECT_ROOT --out DIR
    python -m gac_jax.data.tfds_builders depth --src KITTI_DEPTH_ROOT --out DIR

Data files are parsed while building (calib and labels fully; images and depth
PNGs by their PNG signature), so a bad input fails here with its file name.
"""

from __future__ import annotations

import argparse
import os
import shutil
import sys
import tempfile
from collections.abc import Sequence
from pathlib import Path

import numpy as np
import tensorflow_datasets as tfds

from gac_jax.data import kitti_depth
from gac_jax.data.files import KittiFormatError, read_bytes
from gac_jax.data.kitti import (
    KittiObjectLayout,
    parse_calib,
    parse_label,
    parse_plane,
    read_split,
)
from gac_jax.data.sources import ALL_FRAMES, DEPTH_DATASET, OBJECT_DATASET, depth_split_name

_PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"


def _png(path: Path, what: str) -> bytes:
    data = read_bytes(path, what)
    if not data.startswith(_PNG_SIGNATURE):
        raise KittiFormatError(path, f"{what} is not a PNG file")
    return data


def _bytes_feature():
    return tfds.features.Scalar(dtype=np.object_)


class GacKittiObject(tfds.core.GeneratorBasedBuilder):
    """KITTI 3D-object frames as raw bytes (see module docstring)."""

    VERSION = tfds.core.Version("1.1.0")
    RELEASE_NOTES = {
        "1.0.0": "Raw image/calib/label bytes per frame, in split-file order.",
        "1.1.0": "Plus the planes/ file text (empty when absent).",
    }

    def __init__(
        self,
        *,
        src: str | os.PathLike | None = None,
        subset: str = "training",
        splits: Sequence[str] | None = None,
        **kwargs,
    ):
        self._layout = KittiObjectLayout(Path(src), subset) if src is not None else None
        self._splits = None if splits is None else list(splits)
        super().__init__(**kwargs)

    def _info(self) -> tfds.core.DatasetInfo:
        return tfds.core.DatasetInfo(
            builder=self,
            description="KITTI 3D object frames (raw PNG bytes, calib and label text).",
            features=tfds.features.FeaturesDict(
                {
                    "frame_id": tfds.features.Text(),
                    "image_2": _bytes_feature(),
                    "image_3": _bytes_feature(),
                    "calib": tfds.features.Text(),
                    "label": tfds.features.Text(),
                    "has_label": tfds.features.Scalar(dtype=np.bool_),
                    "plane": tfds.features.Text(),
                }
            ),
            disable_shuffling=True,
        )

    def _split_generators(self, dl_manager):
        del dl_manager
        if self._layout is None:
            raise ValueError("GacKittiObject needs src= to prepare a dataset")
        lay = self._layout
        names = self._splits
        if names is None:
            sets = sorted((lay.root / "ImageSets").glob("*.txt"))
            names = [p.stem for p in sets] or [ALL_FRAMES]
        out = {}
        for name in names:
            ids = lay.frame_ids(None) if name == ALL_FRAMES else read_split(lay.split_file(name))
            if not ids:
                where = lay.frames_dir / "calib" if name == ALL_FRAMES else lay.split_file(name)
                raise KittiFormatError(
                    where, f"split {name!r} has no frames (TFDS cannot store it)"
                )
            out[name] = self._generate_examples(ids)
        return out

    def _generate_examples(self, ids: list[str]):
        lay = self._layout
        for key, frame_id in enumerate(ids):
            calib = read_bytes(lay.calib(frame_id), "calibration file").decode("utf-8", "replace")
            parse_calib(calib, lay.calib(frame_id))
            label_path = lay.label(frame_id)
            label = ""
            if label_path.is_file():
                label = read_bytes(label_path, "label file").decode("utf-8", "replace")
                parse_label(label, label_path, with_score=False)
            plane_path, plane = lay.plane(frame_id), ""
            if plane_path.is_file():
                plane = read_bytes(plane_path, "plane file").decode("utf-8", "replace")
                parse_plane(plane, plane_path)
            right = lay.image(frame_id, 3)
            yield (
                key,
                {
                    "frame_id": frame_id,
                    "image_2": _png(lay.image(frame_id, 2), "image"),
                    "image_3": _png(right, "image") if right.is_file() else b"",
                    "calib": calib,
                    "label": label,
                    "has_label": label_path.is_file(),
                    "plane": plane,
                },
            )


class GacKittiDepth(tfds.core.GeneratorBasedBuilder):
    """Annotated KITTI-depth frames as raw bytes (see module docstring)."""

    VERSION = tfds.core.Version("1.1.0")
    RELEASE_NOTES = {
        "1.0.0": "Raw image/depth PNG bytes and calib text per (frame, camera).",
        "1.1.0": "Plus the planes/<drive>/<frame>.txt file text (empty when absent).",
    }

    def __init__(
        self,
        *,
        src: str | os.PathLike | None = None,
        splits: Sequence[str] | None = None,
        cameras: Sequence[int] = (2, 3),
        **kwargs,
    ):
        self._layout = kitti_depth.KittiDepthLayout(Path(src)) if src is not None else None
        self._splits = None if splits is None else list(splits)
        self._cameras = tuple(cameras)
        super().__init__(**kwargs)

    def _info(self) -> tfds.core.DatasetInfo:
        return tfds.core.DatasetInfo(
            builder=self,
            description="KITTI depth annotated frames (raw image/depth PNG bytes, calib text).",
            features=tfds.features.FeaturesDict(
                {
                    "frame_id": tfds.features.Text(),
                    "camera": tfds.features.Scalar(dtype=np.int32),
                    "image": _bytes_feature(),
                    "depth": _bytes_feature(),
                    "calib": tfds.features.Text(),
                    "plane": tfds.features.Text(),
                }
            ),
            disable_shuffling=True,
        )

    def _split_generators(self, dl_manager):
        del dl_manager
        if self._layout is None:
            raise ValueError("GacKittiDepth needs src= to prepare a dataset")
        names = self._splits
        if names is None:
            base = self._layout.root / "data_depth_annotated"
            names = sorted(p.name for p in base.iterdir() if p.is_dir()) if base.is_dir() else []
            if not names:
                raise KittiFormatError(base, "no split folders (train/, val/) found")
        out = {}
        for name in names:
            for cam in self._cameras:
                frames = self._layout.frames(name, (cam,))
                if not frames:
                    raise KittiFormatError(
                        self._layout.split_dir(name),
                        f"no frames of camera {cam} (TFDS cannot store an empty split; "
                        "choose cameras/splits that have frames)",
                    )
                out[depth_split_name(name, cam)] = self._generate_examples(name, frames)
        return out

    def _generate_examples(self, split: str, frames: list[kitti_depth.DepthFrame]):
        lay = self._layout
        calibs: dict[str, str] = {}
        for key, frame in enumerate(frames):
            camera = frame.camera
            calib_path = lay.calib(frame.drive)
            if frame.drive not in calibs:
                text = read_bytes(calib_path, "calibration file").decode("utf-8", "replace")
                parse_calib(text, calib_path, camera)
                calibs[frame.drive] = text
            plane_path, plane = lay.plane(frame), ""
            if plane_path.is_file():
                plane = read_bytes(plane_path, "plane file").decode("utf-8", "replace")
                parse_plane(plane, plane_path)
            yield (
                key,
                {
                    "frame_id": frame.frame_id,
                    "camera": camera,
                    "image": _png(lay.raw_image(frame), "image"),
                    "depth": _png(lay.groundtruth(split, frame), "depth PNG"),
                    "calib": calibs[frame.drive],
                    "plane": plane,
                },
            )


def prepare(
    kind: str,
    src: str | os.PathLike,
    out: str | os.PathLike,
    overwrite: bool = False,
    **builder_kwargs,
) -> Path:
    """Builds ``gac_kitti_<kind>`` from ``src`` into ``out``; returns the prepared version folder.

    ``builder_kwargs`` go to the builder (``splits``, ``subset``, ``cameras``).
    An existing prepared version is an error unless ``overwrite``.
    """
    cls = {"object": GacKittiObject, "depth": GacKittiDepth}[kind]
    name = {"object": OBJECT_DATASET, "depth": DEPTH_DATASET}[kind]
    target = Path(out) / name / str(cls.VERSION)
    if target.exists():
        if not overwrite:
            raise FileExistsError(f"{target} already exists (pass overwrite=True / --overwrite)")
        shutil.rmtree(target)
    builder = cls(src=src, data_dir=os.fspath(out), file_format="array_record", **builder_kwargs)
    with tempfile.TemporaryDirectory(prefix="gac_tfds_dl_") as tmp:
        builder.download_and_prepare(download_dir=tmp)
    return target


def main(argv: Sequence[str] | None = None) -> int:
    parser = argparse.ArgumentParser(
        prog="python -m gac_jax.data.tfds_builders",
        description="Prepare a KITTI object or KITTI-depth folder as a TFDS ArrayRecord dataset.",
    )
    parser.add_argument("kind", choices=["object", "depth"])
    parser.add_argument("--src", required=True, help="KITTI object root or KITTI-depth root")
    parser.add_argument("--out", required=True, help="output data_dir")
    parser.add_argument("--splits", default=None, help="comma-separated split names (default: all)")
    parser.add_argument("--subset", default="training", help="object only: training or testing")
    parser.add_argument("--cameras", default="2,3", help="depth only: cameras to prepare")
    parser.add_argument("--overwrite", action="store_true", help="replace an existing dataset")
    args = parser.parse_args(argv)
    kwargs = {"splits": args.splits.split(",") if args.splits else None}
    if args.kind == "object":
        kwargs["subset"] = args.subset
    else:
        kwargs["cameras"] = tuple(int(c) for c in args.cameras.split(","))
    try:
        path = prepare(args.kind, args.src, args.out, overwrite=args.overwrite, **kwargs)
    except (KittiFormatError, FileExistsError) as e:
        print(f"error: {e}", file=sys.stderr)
        return 1
    print(path)
    return 0


if __name__ == "__main__":
    sys.exit(main())
