"""The tracking picture: a track's box in its own colour (not its class's), camera-view trails
of the last second of image positions in front of the camera only, the bird's-eye view's
caption (over the ground / relative)."""

from __future__ import annotations

import numpy as np

from gac_jax.data.kitti import KittiObjects
from gac_jax.drawing.boxes import class_color
from gac_jax.drawing.track_pictures import ImageTrails, track_color, track_picture

P2 = np.array([[700.0, 0, 450, 0], [0, 700.0, 40, 0], [0, 0, 1, 0]])


class Tracks:
    def __init__(self, x: float, ids=(5,), velocity=(2.0, 0.0, 1.0)):
        n = len(ids)
        self.ids = np.array(ids)
        self.objects = KittiObjects.from_arrays(
            type=["Car"] * n,
            bbox=[[250, 60, 350, 120]] * n,
            dimensions=[[1.5, 1.6, 3.9]] * n,
            location=[[x, 1.6, 12.0]] * n,
            rotation_y=[0.2] * n,
            score=[0.9] * n,
        )
        self.locations = self.objects.location
        self.velocities = np.tile(np.asarray(velocity, np.float64), (n, 1))
        self.trails = tuple(np.array([[x - 1, 1.6, 12.0], [x, 1.6, 12.0]]) for _ in ids)

    def to_kitti_objects(self):
        return self.objects


def count_color(picture: np.ndarray, color) -> int:
    return int(np.all(picture == np.array(color, np.uint8), axis=-1).sum())


def test_a_track_is_drawn_in_its_own_colour_with_a_caption():
    image = np.full((180, 600, 3), 90, np.uint8)
    over = track_picture(image, P2, Tracks(0.0), over_ground=True)
    relative = track_picture(image, P2, Tracks(0.0), over_ground=False)
    bare = track_picture(image, P2, Tracks(0.0))
    camera = over[:, :600]
    assert count_color(camera, track_color(5)) > 100  # wireframe and label strip
    assert count_color(camera, class_color("Car")) == 0
    bev = slice(600, None)
    assert not np.array_equal(over[:20, bev], relative[:20, bev])  # the caption differs
    assert not np.array_equal(over[:20, bev], bare[:20, bev])
    np.testing.assert_array_equal(over[:, :600], bare[:, :600])  # the caption is the BEV's


def test_image_trails_keep_the_last_second_in_front_of_the_camera():
    trails = ImageTrails(seconds=1.0)
    out = []
    for k in range(15):
        uv = np.array([[10.0 * k, 5.0], [np.nan, np.nan] if k % 2 else [1.0, 2.0]])
        out = trails.update([5, 9], uv, timestamp=k / 10)
    assert [len(t) for t in out] == [11, 6]  # 0.4 .. 1.4 s; the even frames in front only
    np.testing.assert_allclose(out[0][0], [40.0, 5.0])
    np.testing.assert_allclose(out[0][-1], [140.0, 5.0])
    out = trails.update([9], np.array([[3.0, 3.0]]), timestamp=1.5)  # track 5 ended
    assert len(out) == 1 and len(out[0]) == 6
    assert [len(t) for t in trails.update([5], np.array([[0.0, 0.0]]), 1.6)] == [1]


def test_a_trail_follows_the_box_in_the_picture():
    """A car moving right: its trail is a line in its colour left of its box's bottom centre,
    and a picture drawn without trails has none."""
    image = np.full((180, 600, 3), 90, np.uint8)
    trails = ImageTrails()
    for k in range(6):
        with_trail = track_picture(image, P2, Tracks(-6.0 + 1.0 * k), trails=trails,
                                   timestamp=k / 10)  # fmt: skip
    without = track_picture(image, P2, Tracks(-1.0))
    foot_v = int(700 * 1.6 / 12 + 40)
    row = slice(foot_v - 2, foot_v + 3)
    left = slice(int(450 + 700 * -5.5 / 12), int(450 + 700 * -3.2 / 12))  # no box there
    color = track_color(5)
    assert count_color(with_trail[row, left], color) > 0
    assert count_color(without[row, left], color) == 0
