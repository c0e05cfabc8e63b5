"""What the generated labels copy from KITTI's: on KITTI's own labelled real frames (the
13-frame set of ``../shared``), a Car's 2D box is the projection of its 3D box clipped to the
image, whatever its occlusion (``gac_jax.data.synthetic.labels``)."""

from __future__ import annotations

import cv2
import numpy as np

from gac_jax.data import kitti
from gac_jax.geometry import box2d_from_corners, box3d_corners


def test_kitti_label_boxes_are_projected_3d_boxes(kitti_samples_full):
    # What the generated labels copy: on KITTI's own labels, a Car's 2D box is the
    # projection of its 3D box clipped to the image, whatever its occlusion; it is not the
    # extent of its visible pixels (which would shrink with occlusion).
    root = kitti_samples_full / "object" / "training"
    names = kitti.read_split(kitti_samples_full / "object" / "ImageSets" / "labeled.txt")
    ratios = {0: [], 1: [], 2: []}
    for name in names:
        labels = kitti.read_label(root / "label_2" / f"{name}.txt")
        P2 = kitti.read_calib(root / "calib" / f"{name}.txt").P2
        height, width = cv2.imread(str(root / "image_2" / f"{name}.png")).shape[:2]
        for i in np.flatnonzero(labels.type == "Car"):
            corners = box3d_corners(
                labels.location[i][None], labels.dimensions[i][None], [labels.rotation_y[i]]
            )
            projected = box2d_from_corners(corners, P2, (height, width))[0]
            box = labels.bbox[i]
            if box[3] - box[1] < 25 or labels.truncated[i] > 0.1:
                continue
            size = np.array([box[2] - box[0], box[3] - box[1]])
            ratios[int(labels.occluded[i])].append(size / (projected[2:] - projected[:2]))
    for level, r in ratios.items():
        r = np.array(r)
        print(f"occlusion {level}: {len(r)} cars, median box / projection (w, h) {np.median(r, 0)}")
        assert len(r) >= 5
        np.testing.assert_allclose(np.median(r, axis=0), 1.0, atol=0.03)
