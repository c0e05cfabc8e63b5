"""KITTI labels from a render, derived the way KITTI's annotations are defined.

For each road user of the scene, from the left view (``P2``):

* 2D box: the projection of its 3D box, clipped to the image (pixel-centre extent,
  ``[0, W-1] x [0, H-1]``), not shrunk by occlusion. That is how KITTI's own labels are:
  on the labelled real frames of ``kitti_samples``, a Car's 2D box and the clipped
  projection of its 3D box differ by about 1 % of its width and height, at every
  occlusion level (``tests/test_kitti_label_boxes.py``), whereas the extent of its visible
  pixels is 5-30 % smaller.
* truncation: fraction of its unoccluded silhouette that falls outside the image.
* occlusion: from the visible fraction ``f`` of its unoccluded in-image
  silhouette: 0 if ``f >= 0.95``, 1 if ``f >= 0.5``, else 2 (3, "unknown",
  is never produced).
* alpha: from ``rotation_y`` and the location (KITTI label convention,
  relative to the reference camera).
* DontCare: objects whose visible pixels span fewer than ``MIN_HEIGHT`` rows (at
  375 rows; scaled with the image height) or whose depth exceeds
  ``MAX_LABEL_DEPTH`` are written as DontCare regions with KITTI's fields; a
  DontCare box is the extent of the visible pixels (the region to excuse).
* objects with no visible pixel are not written.
"""

from __future__ import annotations

import numpy as np

from gac_jax.data.kitti import KittiObjects
from gac_jax.data.synthetic.render import ViewRender, silhouette_outside
from gac_jax.data.synthetic.scene import Scene
from gac_jax.geometry import alpha_from_rotation_y, box2d_from_corners, box3d_corners

MIN_HEIGHT = 20.0  # pixels at 375 image rows
MAX_LABEL_DEPTH = 70.0  # metres
FULLY_VISIBLE, PARTLY_VISIBLE = 0.95, 0.5


def occlusion_level(visible_fraction: np.ndarray) -> np.ndarray:
    """KITTI occlusion level (0, 1, 2) from the visible fraction of the silhouette."""
    f = np.asarray(visible_fraction, np.float64)
    return np.where(f >= FULLY_VISIBLE, 0, np.where(f >= PARTLY_VISIBLE, 1, 2)).astype(np.int64)


def visible_boxes(object_ids: np.ndarray, num_objects: int) -> tuple[np.ndarray, np.ndarray]:
    """Per object: visible pixel count (N,) and pixel-centre extent xyxy (N, 4) (NaN if none)."""
    rr, cc = np.nonzero(object_ids >= 0)
    ids = object_ids[rr, cc].astype(np.int64)
    counts = np.bincount(ids, minlength=num_objects)
    boxes = np.full((num_objects, 4), np.nan)
    if len(ids):
        order = np.argsort(ids, kind="stable")
        ids, rr, cc = ids[order], rr[order], cc[order]
        starts = np.flatnonzero(np.r_[True, ids[1:] != ids[:-1]])
        present = ids[starts]
        boxes[present, 0] = np.minimum.reduceat(cc, starts)
        boxes[present, 1] = np.minimum.reduceat(rr, starts)
        boxes[present, 2] = np.maximum.reduceat(cc, starts)
        boxes[present, 3] = np.maximum.reduceat(rr, starts)
    return counts, boxes


def frame_labels(
    scene: Scene, view: ViewRender, P2: np.ndarray, image_size: tuple[int, int]
) -> tuple[KittiObjects, np.ndarray]:
    """Labels of one frame from its left-view render.

    Returns:
      objects: KittiObjects, labelled objects first (scene order), DontCare last.
      source: (M,) index into ``scene.objects`` of each label line.
    """
    n = len(scene.objects)
    counts, boxes = visible_boxes(view.object_ids, n)
    min_height = MIN_HEIGHT * image_size[0] / 375.0
    rows, dontcare = [], []
    for i, obj in enumerate(scene.objects):
        if counts[i] == 0:
            continue
        height = boxes[i, 3] - boxes[i, 1] + 1
        if height < min_height or obj.location[2] > MAX_LABEL_DEPTH:
            dontcare.append(i)
            continue
        outside = silhouette_outside(obj.parts, P2, image_size)
        inside = view.silhouette_px[i]
        corners = box3d_corners(obj.location[None], obj.dimensions[None], [obj.rotation_y])
        rows.append(
            dict(
                type=obj.type,
                truncated=round(outside / (outside + inside), 2),
                occluded=int(occlusion_level(counts[i] / inside)),
                alpha=float(alpha_from_rotation_y(obj.rotation_y, obj.location)[0]),
                bbox=np.round(box2d_from_corners(corners, P2, image_size)[0], 2),  # as written
                dimensions=obj.dimensions,
                location=obj.location,
                rotation_y=obj.rotation_y,
            )
        )
    for i in dontcare:
        rows.append(
            dict(
                type="DontCare",
                truncated=-1.0,
                occluded=-1,
                alpha=-10.0,
                bbox=boxes[i],
                dimensions=np.full(3, -1.0),
                location=np.full(3, -1000.0),
                rotation_y=-10.0,
            )
        )
    source = np.array(
        [i for i in range(n) if counts[i] > 0 and i not in dontcare] + dontcare, np.int64
    )
    if not rows:
        return KittiObjects.empty(), source
    fields = {key: [r[key] for r in rows] for key in rows[0]}
    return KittiObjects.from_arrays(**fields), source
