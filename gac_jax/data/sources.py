"""Random-access data sources: ``len(source)`` and ``source[i] -> sample``.

Folder readers (:class:`KittiObjectSource`, :class:`KittiDepthSource`,
:class:`KittiDepthSelectionSource`) and readers of the prepared TFDS datasets
written by :mod:`gac_jax.data.tfds_builders` (:class:`TfdsObjectSource`,
:class:`TfdsDepthSource`) decode the same bytes with the same functions, so a
folder and its prepared dataset give identical samples at every index.

Sample keys (see the project brief): ``frame_id``, ``camera``, ``image`` (H, W, 3)
uint8 RGB, ``P2`` (3, 4) float64 projection of this image, ``image_transform``
(identity), ``original_size`` (H, W), and ``objects`` (object sources with
labels) or ``depth`` (H, W) float32 metres, 0 = invalid (depth sources); ``plane`` (4,)
float64 ground plane when the frame has a plane file (:func:`gac_jax.data.kitti.parse_plane`;
absent otherwise, and the loader then uses the config's level plane): object frames'
``planes/NNNNNN.txt``, KITTI-depth frames' ``planes/<drive>/NNNNNNNNNN.txt``
(:mod:`gac_jax.data.kitti_depth`). The plane is in the rectified reference (camera 0) frame,
the frame the sample's ``P2`` projects from, for either camera: the file as it is.
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np

from gac_jax import geometry
from gac_jax.data import kitti_depth
from gac_jax.data.files import (
    KittiFormatError,
    decode_depth_png,
    decode_image,
    read_bytes,
)
from gac_jax.data.kitti import (
    KittiObjectLayout,
    KittiObjects,
    parse_label,
    parse_plane,
    read_split,
)
from gac_jax.data.kitti_calib import Calibration, parse_calib, read_calib

OBJECT_DATASET = "gac_kitti_object"
ALL_FRAMES = "frames"  # prepared split of every frame when a root has no ImageSets
DEPTH_DATASET = "gac_kitti_depth"


def new_sample(frame_id: str, camera: int, image: np.ndarray, P2: np.ndarray, **extra) -> dict:
    """A freshly loaded sample: identity ``image_transform``, ``original_size`` = image size."""
    return {
        "frame_id": frame_id,
        "camera": int(camera),
        "image": image,
        "P2": np.asarray(P2, dtype=np.float64),
        "image_transform": np.eye(3),
        "original_size": (int(image.shape[0]), int(image.shape[1])),
        **extra,
    }


def right_view_objects(
    objects: KittiObjects, P3: np.ndarray, image_size: tuple[int, int]
) -> KittiObjects:
    """Labels for the right image: same 3D boxes, 2D box and alpha re-derived through ``P3``.

    KITTI's labelled 2D boxes and alpha belong to the left image. Here the 2D
    box is the projected 3D box clipped to the image (like KITTI labels) and
    alpha is measured from ``P3``'s optical centre. DontCare rows have no 3D box
    to re-derive and are dropped.
    """
    objects = objects.select(objects.type != "DontCare")
    if not len(objects):
        return objects
    corners = geometry.box3d_corners(objects.location, objects.dimensions, objects.rotation_y)
    return objects.replace(
        bbox=geometry.box2d_from_corners(corners, P3, image_size=image_size),
        alpha=geometry.alpha_from_rotation_y(objects.rotation_y, objects.location, P3),
    )


def object_sample_from_bytes(
    frame_id: str,
    camera: int,
    image: bytes,
    calib: str,
    label: str | None,
    where: dict[str, str | os.PathLike],
    plane: str | None = None,
) -> dict:
    """Decodes one object frame. ``where`` names the image/calib/label(/plane) origin for error
    messages; ``plane`` is the text of its planes file, if it has one."""
    cal = parse_calib(calib, where["calib"])
    P = cal.P2 if camera == 2 else cal.P3
    if P is None:
        raise KittiFormatError(where["calib"], "calibration has no P3 (needed for the right image)")
    img = decode_image(image, where["image"])
    extra = {}
    if label is not None:
        objects = parse_label(label, where["label"], with_score=False)
        if camera == 3:
            objects = right_view_objects(objects, P, img.shape[:2])
        extra["objects"] = objects
    if plane is not None:
        extra["plane"] = parse_plane(plane, where["plane"])
    return new_sample(frame_id, camera, img, P, **extra)


def depth_sample_from_bytes(
    frame_id: str,
    camera: int,
    image: bytes,
    P: np.ndarray,
    depth: bytes | None,
    where: dict[str, str | os.PathLike],
    plane: str | None = None,
) -> dict:
    """Decodes one depth frame; the depth PNG must have the image's size. ``plane`` is the
    text of the frame's plane file, if it has one (``where['plane']`` names it)."""
    img = decode_image(image, where["image"])
    extra = {}
    if plane is not None:
        extra["plane"] = parse_plane(plane, where["plane"])
    if depth is not None:
        d = decode_depth_png(depth, where["depth"])
        if d.shape != img.shape[:2]:
            raise KittiFormatError(
                where["depth"],
                f"depth map is {d.shape[0]}x{d.shape[1]} but its image {where['image']} is "
                f"{img.shape[0]}x{img.shape[1]}",
            )
        extra["depth"] = d
    return new_sample(frame_id, camera, img, P, **extra)


def _check_index(i: int, n: int) -> int:
    i = int(i)
    if not 0 <= i < n:
        raise IndexError(f"index {i} out of range for a source of length {n}")
    return i


def _split_lines(path: Path) -> list[tuple[str, int]]:
    """(frame id, line number) pairs of a split file (validated by the core reader first)."""
    read_split(path)
    lines = read_bytes(path, "split file").decode().splitlines()
    return [(s.strip(), n) for n, s in enumerate(lines, start=1) if s.strip()]


class KittiObjectSource:
    """Frames of a KITTI object root (``root/<subset>/{image_2,image_3,calib,label_2}``).

    Args:
      root: the KITTI object root.
      split: name of ``ImageSets/<split>.txt``, or None for every calib file.
      use_right_image: doubles the length: index ``i >= N`` is ``image_3`` of
        frame ``i - N`` with ``P2 := P3`` and the labels re-derived for that
        camera (:func:`right_view_objects`).
      subset: ``'training'`` or ``'testing'`` (or any frames folder).
      with_labels: read ``label_2`` (testing frames have none).

    Every listed frame's files must exist (checked here; a KittiFormatError
    names the split file and line otherwise).
    """

    def __init__(
        self,
        root: str | os.PathLike,
        split: str | None = "train",
        use_right_image: bool = False,
        subset: str = "training",
        with_labels: bool = True,
    ):
        self.layout = KittiObjectLayout(Path(root), subset)
        self.split = split
        self.use_right_image = use_right_image
        self.with_labels = with_labels
        if split is None:
            entries = [(f, None) for f in self.layout.frame_ids(None)]
            listed_in: Path = self.layout.frames_dir / "calib"
        else:
            listed_in = self.layout.split_file(split)
            entries = _split_lines(listed_in)
        for frame_id, line in entries:
            for what, path in self._paths(frame_id).items():
                if path is not None and not path.is_file():
                    raise KittiFormatError(
                        listed_in, f"frame {frame_id}: {what} not found ({path})", line
                    )
        self.frame_ids = [f for f, _ in entries]

    def _paths(self, frame_id: str) -> dict[str, Path | None]:
        lay = self.layout
        return {
            "image": lay.image(frame_id, 2),
            "calib": lay.calib(frame_id),
            "label": lay.label(frame_id) if self.with_labels else None,
            "right image": lay.image(frame_id, 3) if self.use_right_image else None,
        }

    def __len__(self) -> int:
        return len(self.frame_ids) * (2 if self.use_right_image else 1)

    def __getitem__(self, i: int) -> dict:
        i = _check_index(i, len(self))
        n = len(self.frame_ids)
        frame_id, camera = self.frame_ids[i % n], (3 if i >= n else 2)
        where = {
            "image": self.layout.image(frame_id, camera),
            "calib": self.layout.calib(frame_id),
            "label": self.layout.label(frame_id),
            "plane": self.layout.plane(frame_id),
        }
        label = plane = None
        if self.with_labels:
            label = read_bytes(where["label"], "label file").decode("utf-8", "replace")
        if where["plane"].is_file():
            plane = read_bytes(where["plane"], "plane file").decode("utf-8", "replace")
        return object_sample_from_bytes(
            frame_id,
            camera,
            read_bytes(where["image"], "image"),
            read_bytes(where["calib"], "calibration file").decode("utf-8", "replace"),
            label,
            where,
            plane,
        )


class KittiDepthSource:
    """Annotated KITTI-depth frames: image, ``P2`` = ``P_rect_0<camera>``, ``depth`` from the GT.

    Args:
      root: KITTI-depth root (``data_depth_annotated/`` and ``raw/``).
      split: ``'train'`` or ``'val'`` (folder under ``data_depth_annotated``).
      cameras: which views; order is camera-major (all camera-2 frames first).
      frame_list: optional frame-list file (``<drive> <frame> <camera>`` lines)
        selecting frames of ``split`` in file order; a listed frame without GT
        or raw image is a KittiFormatError naming the list file and line.

    ``frame_id`` is ``'<drive>/<frame>'``. A frame with a ``planes/<drive>/<frame>.txt`` file
    gets its ``plane`` (the same for both cameras, see the module docstring).
    """

    def __init__(
        self,
        root: str | os.PathLike,
        split: str = "train",
        cameras: tuple[int, ...] = (2, 3),
        frame_list: str | os.PathLike | None = None,
    ):
        self.layout = kitti_depth.KittiDepthLayout(Path(root))
        self.split = split
        self.cameras = tuple(cameras)
        if frame_list is None:
            self.frames = self.layout.frames(split, self.cameras)
        else:
            self.frames = []
            for frame, line in kitti_depth.read_frame_list(frame_list):
                if frame.camera not in self.cameras:
                    continue
                for what, path in (
                    ("ground truth", self.layout.groundtruth(split, frame)),
                    ("raw image", self.layout.raw_image(frame)),
                ):
                    if not path.is_file():
                        raise KittiFormatError(
                            frame_list,
                            f"{frame.frame_id} camera {frame.camera}: {what} not found ({path})",
                            line,
                        )
                self.frames.append(frame)
        self._calib: dict[str, Calibration] = {}

    def _projection(self, frame: kitti_depth.DepthFrame) -> np.ndarray:
        date = kitti_depth.drive_date(frame.drive)
        if date not in self._calib:
            self._calib[date] = read_calib(self.layout.calib(frame.drive), camera=None)
        return self._calib[date].projection(frame.camera)

    def __len__(self) -> int:
        return len(self.frames)

    def __getitem__(self, i: int) -> dict:
        frame = self.frames[_check_index(i, len(self))]
        where = {
            "image": self.layout.raw_image(frame),
            "depth": self.layout.groundtruth(self.split, frame),
            "plane": self.layout.plane(frame),
        }
        plane = None
        if where["plane"].is_file():
            plane = read_bytes(where["plane"], "plane file").decode("utf-8", "replace")
        return depth_sample_from_bytes(
            frame.frame_id,
            frame.camera,
            read_bytes(where["image"], "image"),
            self._projection(frame),
            read_bytes(where["depth"], "depth PNG"),
            where,
            plane,
        )


class KittiDepthSelectionSource:
    """``val_selection_cropped`` (or the anonymous test set): ``P2 = [K | 0]``, depth if present.

    ``frame_id`` is the image file stem; ``camera`` comes from its ``image_0X`` suffix.
    """

    def __init__(self, directory: str | os.PathLike):
        self.items = kitti_depth.list_selection(directory)

    def __len__(self) -> int:
        return len(self.items)

    def __getitem__(self, i: int) -> dict:
        item = self.items[_check_index(i, len(self))]
        K = kitti_depth.read_selection_intrinsics(item.intrinsics)
        camera = 3 if item.name.endswith("image_03") else 2
        depth = None if item.groundtruth is None else read_bytes(item.groundtruth, "depth PNG")
        where = {"image": item.image, "depth": item.groundtruth}
        P = np.concatenate([K, np.zeros((3, 1))], axis=1)
        return depth_sample_from_bytes(
            item.name, camera, read_bytes(item.image, "image"), P, depth, where
        )


def find_prepared(path: str | os.PathLike, name: str) -> Path | None:
    """The version folder of prepared dataset ``name`` at or below ``path`` (None if none).

    Accepts the version folder itself, the dataset folder (newest version), or
    the ``--out`` folder that holds ``<name>/<version>/``.
    """
    path = Path(path)
    if (path / "dataset_info.json").is_file():
        return path
    for base in (path / name, path):
        if base.is_dir():
            versions = sorted(
                (p for p in base.iterdir() if (p / "dataset_info.json").is_file()),
                key=lambda p: tuple(int(x) for x in p.name.split(".") if x.isdigit()),
            )
            if versions:
                return versions[-1]
    return None


def _open_prepared(path: str | os.PathLike, name: str):
    import tensorflow_datasets as tfds

    found = find_prepared(path, name)
    if found is None:
        raise KittiFormatError(path, f"no prepared dataset {name!r} found here")
    builder = tfds.builder_from_directory(os.fspath(found))
    if builder.info.name != name:
        raise KittiFormatError(
            found, f"prepared dataset is {builder.info.name!r}, expected {name!r}"
        )
    if not builder.info.disable_shuffling:
        raise KittiFormatError(
            found, "prepared dataset was shuffled; rebuild it with tfds_builders"
        )
    return found, builder


def _text(value) -> str:
    return value.decode("utf-8") if isinstance(value, bytes) else str(value)


class TfdsObjectSource:
    """:class:`KittiObjectSource` over a prepared ``gac_kitti_object`` dataset (no TensorFlow).

    Args:
      prepared: the prepared dataset (see :func:`find_prepared`).
      split: a split prepared from ``ImageSets/<split>.txt`` (``ALL_FRAMES`` = ``'frames'`` when the
        root had no split files).
    """

    def __init__(
        self,
        prepared: str | os.PathLike,
        split: str = "train",
        use_right_image: bool = False,
        with_labels: bool = True,
    ):
        self.path, builder = _open_prepared(prepared, OBJECT_DATASET)
        if split not in builder.info.splits:
            raise KittiFormatError(
                self.path, f"no split {split!r} (have {sorted(builder.info.splits.keys())})"
            )
        self.split = split
        self.use_right_image = use_right_image
        self.with_labels = with_labels
        self._records = builder.as_data_source(split=split)

    def __len__(self) -> int:
        return len(self._records) * (2 if self.use_right_image else 1)

    def __getitem__(self, i: int) -> dict:
        i = _check_index(i, len(self))
        n = len(self._records)
        camera = 3 if i >= n else 2
        rec = self._records[i % n]
        frame_id = _text(rec["frame_id"])
        base = f"{self.path}[{self.split}]/{frame_id}"
        where = {
            "image": f"{base}/image_{camera}",
            "calib": f"{base}/calib",
            "label": f"{base}/label_2",
            "plane": f"{base}/planes",
        }
        image = rec[f"image_{camera}"]
        if not image:
            raise KittiFormatError(where["image"], "prepared dataset has no image for this camera")
        label = None
        if self.with_labels:
            if not rec["has_label"]:
                raise KittiFormatError(
                    where["label"], "prepared dataset has no label for this frame"
                )
            label = _text(rec["label"])
        plane = _text(rec["plane"]) if "plane" in rec else ""  # datasets before 1.1.0 have none
        return object_sample_from_bytes(
            frame_id, camera, image, _text(rec["calib"]), label, where, plane or None
        )


class TfdsDepthSource:
    """:class:`KittiDepthSource` over a prepared ``gac_kitti_depth`` dataset (camera-major;
    ``plane`` from version 1.1.0 on)."""

    def __init__(
        self, prepared: str | os.PathLike, split: str = "train", cameras: tuple[int, ...] = (2, 3)
    ):
        self.path, builder = _open_prepared(prepared, DEPTH_DATASET)
        self.split = split
        self.cameras = tuple(cameras)
        self._parts = []
        for cam in self.cameras:
            name = depth_split_name(split, cam)
            if name not in builder.info.splits:
                raise KittiFormatError(
                    self.path, f"no split {name!r} (have {sorted(builder.info.splits.keys())})"
                )
            self._parts.append(builder.as_data_source(split=name))
        self._offsets = np.cumsum([0] + [len(p) for p in self._parts])

    def __len__(self) -> int:
        return int(self._offsets[-1])

    def __getitem__(self, i: int) -> dict:
        i = _check_index(i, len(self))
        part = int(np.searchsorted(self._offsets, i, side="right")) - 1
        rec = self._parts[part][i - int(self._offsets[part])]
        frame_id, camera = _text(rec["frame_id"]), int(rec["camera"])
        base = f"{self.path}[{depth_split_name(self.split, camera)}]/{frame_id}"
        calib = parse_calib(_text(rec["calib"]), f"{base}/calib_cam_to_cam", camera)
        P = calib.projection(camera)
        where = {"image": f"{base}/image", "depth": f"{base}/depth", "plane": f"{base}/plane"}
        plane = _text(rec["plane"]) if "plane" in rec else ""  # datasets before 1.1.0 have none
        return depth_sample_from_bytes(
            frame_id, camera, rec["image"], P, rec["depth"], where, plane or None
        )


def depth_split_name(split: str, camera: int) -> str:
    """TFDS split holding ``split``'s frames of one camera, e.g. ``'train_image_02'``."""
    return f"{split}_image_0{camera}"


def open_object_source(
    path: str | os.PathLike,
    split: str | None = "train",
    use_right_image: bool = False,
    subset: str = "training",
    with_labels: bool = True,
) -> KittiObjectSource | TfdsObjectSource:
    """A prepared dataset (TFDS) at ``path`` if there is one, else the KITTI folder."""
    if find_prepared(path, OBJECT_DATASET) is not None:
        return TfdsObjectSource(path, split or ALL_FRAMES, use_right_image, with_labels)
    return KittiObjectSource(path, split, use_right_image, subset, with_labels)


def open_depth_source(
    path: str | os.PathLike, split: str = "train", cameras: tuple[int, ...] = (2, 3)
) -> KittiDepthSource | TfdsDepthSource:
    """A prepared depth dataset at ``path`` if there is one, else the KITTI-depth folder."""
    if find_prepared(path, DEPTH_DATASET) is not None:
        return TfdsDepthSource(path, split, cameras)
    return KittiDepthSource(path, split, cameras)
