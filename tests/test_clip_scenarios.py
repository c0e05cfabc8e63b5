"""Generated clips where tracking is hard: every scenario in one 4 s sequence.

One sequence (40 frames at 10 Hz, KITTI-equivalent 188x621) with every scenario switched on
is written once per module by two worker processes. The checks derive what they need from
the written labels and poses (world positions, velocities, lateral road positions) and
compare with the simulation (:class:`drive.Drive`), and frames rendered again in this
process against the files.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from gac_jax.data import kitti_tracking as tracking
from gac_jax.data.synthetic import drive, traffic
from gac_jax.data.synthetic.clips import ClipSpec, generate_clips
from gac_jax.geometry import box2d_from_corners
from tests.test_clips import (
    _tracks,
    _world,
    _world_velocity_errors,
    assert_labels_match_render,
    assert_one_world_plane,
)

SIZE = (188, 621)
SEED, FRAMES = 11, 40
ALL = {name: 1.0 for name in traffic.SCENARIOS}
SEQ = "0000"

pytestmark = pytest.mark.xdist_group("clip_scenarios")


@pytest.fixture(scope="module")
def clip(tmp_path_factory) -> Path:
    root = tmp_path_factory.mktemp("scenarios") / "clips"
    generate_clips(root, 1, FRAMES, SEED, height=SIZE[0], width=SIZE[1], scenarios=ALL, workers=2)
    return root


@pytest.fixture(scope="module")
def world() -> drive.Drive:
    return drive.make_drive(SEED, 0, FRAMES, SIZE, mix=tuple(ALL.items()))


def _layout(clip):
    return tracking.KittiTrackingLayout(clip)


def _to_road(world, poses, k, loc):
    """Road ``(t, s)`` of a camera-frame point of frame ``k`` (through the written pose)."""
    R0, P0 = world.camera(0)
    x, _, z = R0.T @ _world(poses[k], loc) + P0
    t, s = world.ego.path.to_road(np.array([x]), np.array([z]))
    return float(t[0]), float(s[0])


def test_every_scenario_is_in_the_labels(clip, world):
    assert world.ego.scenarios == frozenset(traffic.SCENARIOS)
    roles = {m.track_id: m.role for m in world.movers}
    labelled = {roles[tid] for tid in _tracks(_layout(clip), SEQ)}
    wanted = {"lane_change", "brake", "oncoming", "cross_traffic", "occluder", "occluded"}
    assert wanted | {"crossing", "parked"} <= labelled


def test_velocities_from_labels_and_poses_match_the_simulation(clip, world):
    errors, roles = _world_velocity_errors(_layout(clip), SEQ, world)
    assert len(errors) >= 100
    assert (errors < 0.1).all(), (errors.max(), roles[int(errors.argmax())])


def test_ego_turns_changes_speed_and_stays_on_one_ground_plane(clip, world):
    layout = _layout(clip)
    poses = layout.read_poses(SEQ)
    yaw = np.rad2deg(np.arctan2(poses[:, 0, 2], poses[:, 2, 2]))  # heading of z in frame 0
    assert np.ptp(yaw) > 1.0
    road = np.rad2deg(world.ego.path.heading([world.ego.travelled(k) for k in range(FRAMES)]))
    np.testing.assert_allclose(np.diff(yaw), np.diff(road), atol=0.05)  # turns with the road
    speed = np.linalg.norm(np.diff(poses[:, :, 3], axis=0), axis=1) * drive.FRAME_RATE
    assert np.ptp(speed) > 1.0
    assert_one_world_plane(layout, SEQ, poses)


def test_lane_change_moves_across_the_road(clip, world):
    layout = _layout(clip)
    poses = layout.read_poses(SEQ)
    movers = {m.track_id: m for m in world.movers}
    moved = []
    for tid, items in _tracks(layout, SEQ).items():
        m = movers[tid]
        if m.role != "lane_change":
            continue
        lateral = [_to_road(world, poses, it[0], it[3])[0] for it in items]
        ks = np.array([it[0] for it in items]) / drive.FRAME_RATE
        expected = m.motion.at(ks)[0]
        np.testing.assert_allclose(lateral, expected, atol=0.05)
        moved.append(np.ptp(lateral))
    assert max(moved) > 1.0


def test_oncoming_cars_approach(clip, world):
    layout = _layout(clip)
    roles = {m.track_id: m.role for m in world.movers}
    closing = []
    for tid, items in _tracks(layout, SEQ).items():
        if roles[tid] == "oncoming" and len(items) >= 2:
            (k0, *_, a, _), (k1, *_, b, _) = items[0], items[-1]
            closing.append((b[2] - a[2]) / ((k1 - k0) / drive.FRAME_RATE))
    assert closing and max(closing) < -5.0  # faster than the ego alone


def test_crossing_road_users_move_across_and_parked_cars_stand(clip, world):
    layout = _layout(clip)
    poses = layout.read_poses(SEQ)
    roles = {m.track_id: m.role for m in world.movers}
    across = parked = 0
    for tid, items in _tracks(layout, SEQ).items():
        if len(items) < 2 or roles[tid] not in ("cross_traffic", "crossing", "parked"):
            continue
        first, last = items[0], items[-1]
        t0, s0 = _to_road(world, poses, first[0], first[3])
        t1, s1 = _to_road(world, poses, last[0], last[3])
        if roles[tid] == "parked":
            assert abs(t1 - t0) < 0.03 and abs(s1 - s0) < 0.03
            parked += 1
        elif abs(t1 - t0) > 0.3:
            assert abs(s1 - s0) < 0.03  # straight across the road
            across += 1
    assert across >= 2 and parked >= 2


def test_hidden_road_user_keeps_its_id(clip, world):
    """A road user passes behind a nearer one: its lines stop while a nearer labelled
    object's box covers where it is, then resume with the same id, type and size."""
    layout = _layout(clip)
    labels = layout.read_labels(SEQ)
    P2 = layout.read_P2(SEQ)
    found, scenes = 0, {}
    for tid, items in _tracks(layout, SEQ).items():
        ks = [it[0] for it in items]
        gaps = [(a, b) for a, b in zip(ks[:-1], ks[1:], strict=True) if b - a >= 3]
        for a, b in gaps:
            covered = True
            for k in range(a + 1, b):
                if k not in scenes:
                    scenes[k] = world.scene(k)
                scene, ids = scenes[k]
                obj = scene.objects[list(ids).index(tid)]
                box = box2d_from_corners(obj.corners()[None], P2, SIZE)[0]
                area = (box[2] - box[0]) * (box[3] - box[1])
                o = labels[k].objects
                nearer = (o.type != "DontCare") & (o.location[:, 2] < obj.location[2])
                lo, hi = np.maximum(o.bbox[:, :2], box[:2]), np.minimum(o.bbox[:, 2:], box[2:])
                overlap = np.prod(np.clip(hi - lo, 0, None), axis=1)
                covered &= bool(area > 0 and (overlap[nearer] >= 0.5 * area).any())
            if covered:
                before, after = items[ks.index(a)], items[ks.index(b)]
                assert before[1] == after[1]
                np.testing.assert_array_equal(before[2], after[2])
                found += 1
    assert found >= 1


def test_rendered_again_same_labels_which_match_the_render(clip):
    layout = _layout(clip)
    P2 = layout.read_P2(SEQ)
    spec = ClipSpec(1, FRAMES, SEED, height=SIZE[0], width=SIZE[1], scenarios=tuple(ALL.items()))
    checked = 0
    for k in (0, FRAMES // 2, FRAMES - 1):
        frame = drive.render_clip_frame(spec.drive(0), SEED, 0, k)
        written = layout.read_labels(SEQ)[k]
        np.testing.assert_array_equal(written.track_ids, frame.track_ids)
        np.testing.assert_array_equal(written.objects.bbox, frame.objects.bbox)
        np.testing.assert_array_equal(written.objects.occluded, frame.objects.occluded)
        checked += assert_labels_match_render(frame, written.objects, P2, SIZE)
    assert checked >= 10
