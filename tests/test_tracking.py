"""The multi-object tracker (gac_jax.tracking, gac_jax.Tracker3D): its Kalman filter against
plain float64 equations, one id through an occlusion on a generated clip with a velocity that
converges to the truth, world and camera frames agreeing for a static ego, no 180-degree
flips, and bad input named."""

from __future__ import annotations

import numpy as np
import pytest

from gac_jax.data.kitti import KittiObjects
from gac_jax.geometry import box2d_from_corners, box3d_corners, wrap_angle
from gac_jax.tracking import kalman
from gac_jax.tracking.poses import to_world

CAR = (1.5, 1.7, 4.2)  # h, w, l


def objects(locations, rotation_y, boxes=None, names=None) -> KittiObjects:
    n = len(locations)
    return KittiObjects.from_arrays(
        type=np.array(names or ["Car"] * n),
        location=np.asarray(locations, np.float64).reshape(n, 3),
        dimensions=np.tile(CAR, (n, 1)),
        rotation_y=np.asarray(rotation_y, np.float64).reshape(n),
        bbox=np.zeros((n, 4)) if boxes is None else boxes,
        score=np.full(n, 0.9),
    )


def test_the_kalman_filter_equals_the_textbook_equations_in_float64():
    """Batched predict/update (Joseph form) = a single filter written out with explicit
    F, Q, H and the simple covariance update, on a noisy constant-velocity trajectory with
    uneven time steps; two filters at once."""
    rng = np.random.default_rng(0)
    accel = 1.5
    times = np.cumsum(rng.uniform(0.05, 0.3, 40))
    truth = np.array([1.0, 0.5, 10.0]) + np.outer(times, [2.0, 0.0, -3.0])
    R = np.diag([0.2, 0.05, 1.0])
    z = truth + rng.multivariate_normal(np.zeros(3), R, len(times))

    x_ref = np.concatenate([z[0], np.zeros(3)])
    P_ref = np.zeros((6, 6))
    P_ref[:3, :3], P_ref[3:, 3:] = R, 25.0 * np.eye(3)
    x, P = kalman.initial_state(np.stack([z[0], z[0]]), np.stack([R, R]), 5.0)
    H = np.hstack([np.eye(3), np.zeros((3, 3))])
    for k in range(1, len(times)):
        dt = times[k] - times[k - 1]
        F = np.eye(6)
        F[:3, 3:] = dt * np.eye(3)
        G = np.vstack([0.5 * dt**2 * np.eye(3), dt * np.eye(3)])  # acceleration -> state
        Q = G @ (accel**2 * np.eye(3)) @ G.T
        x_ref, P_ref = F @ x_ref, F @ P_ref @ F.T + Q
        S = H @ P_ref @ H.T + R
        K = P_ref @ H.T @ np.linalg.inv(S)
        x_ref = x_ref + K @ (z[k] - H @ x_ref)
        P_ref = (np.eye(6) - K @ H) @ P_ref
        x, P = kalman.predict(x, P, dt, accel)
        x, P = kalman.update(x, P, np.stack([z[k], z[k]]), np.stack([R, R]))
        np.testing.assert_allclose(x, np.stack([x_ref, x_ref]), rtol=1e-9, atol=1e-9)
        np.testing.assert_allclose(P, np.stack([P_ref, P_ref]), rtol=1e-7, atol=1e-10)
    np.testing.assert_allclose(x_ref[3:], [2.0, 0.0, -3.0], atol=0.6)  # it does track


@pytest.fixture(scope="module")
def clip(tmp_path_factory):
    """A small generated clip (1 sequence, 40 frames, 94 x 311 pixels): labels and poses.

    Road users at constant speed (no scenario): the velocity test checks convergence to a
    constant truth; a braking car's estimate lags by about the deceleration times the filter's
    time constant (measured on this seed with the default mix: 1.2-1.6 m/s at 1.7 m/s^2)."""
    from gac_jax.data.kitti_tracking import KittiTrackingLayout
    from gac_jax.data.synthetic.clips import generate_clips

    root = tmp_path_factory.mktemp("clip")
    generate_clips(root, 1, 40, seed=3, height=94, width=311, workers=1, scenarios={})
    layout = KittiTrackingLayout(root)
    return layout.read_labels("0000"), layout.read_poses("0000")


def longest_track(labels) -> int:
    counts: dict[int, int] = {}
    for frame in labels.values():
        for t in frame.track_ids.tolist():
            if t >= 0:
                counts[t] = counts.get(t, 0) + 1
    return max(counts, key=counts.get)


def test_one_id_through_an_occlusion_and_the_velocity_converges(clip):
    """The clip's ground-truth boxes as detections, depth multiplied by noise of 3 % (a
    monocular detector's error) and the longest track's detections removed for 3 frames: the
    tracker (world frame, the clip's poses) keeps one id for it over the whole clip, and its
    velocity over the last 10 frames is within 0.6 m/s of the true world velocity (finite
    differences of the labelled centres mapped to the world by the poses)."""
    from gac_jax import Tracker3D

    labels, poses = clip
    target = longest_track(labels)
    rng = np.random.default_rng(1)
    tracker = Tracker3D()
    ids, errors, world = [], [], {}
    for k in range(len(poses)):
        gt = labels[k].objects
        tid = labels[k].track_ids
        keep = (gt.type != "DontCare") & ~((tid == target) & (15 <= k < 18))
        det, det_ids = gt.select(keep), tid[keep]
        noisy = det.location * rng.normal(1.0, 0.03, (len(det), 1))
        tracks = tracker.update(det.replace(location=noisy), pose=poses[k], timestamp=k / 10)
        here = np.flatnonzero(tid == target)
        if len(here):
            world[k] = to_world(gt.location[here], poses[k])[0]
        for i in range(len(tracks)):  # the tracks carry their detection's box
            j = np.flatnonzero(np.all(det.bbox == tracks.boxes_2d[i], axis=1))
            if len(j) == 1 and det_ids[j[0]] == target:
                ids.append(int(tracks.ids[i]))
                if k >= len(poses) - 10 and k - 1 in world:
                    true_v = (world[k] - world[k - 1]) * 10
                    v = poses[k][:, :3] @ tracks.velocities[i]
                    errors.append(np.linalg.norm((v - true_v)[[0, 2]]))
    assert len(ids) >= len(poses) - 3 - 3  # reported from its 3rd frame, but for the gap
    assert len(set(ids)) == 1, ids
    assert errors and max(errors) < 0.6, errors


def moving_cars(frames: int, rng) -> tuple[list, list]:
    """Three cars driving straight (headings along their motion), positions per frame."""
    start = np.array([[-4.0, 1.6, 15.0], [3.0, 1.6, 40.0], [0.5, 1.6, 25.0]])
    velocity = np.array([[0.0, 0.0, 6.0], [0.0, 0.0, -9.0], [4.0, 0.0, 4.0]])
    heading = np.arctan2(-velocity[:, 2], velocity[:, 0])
    locations = [
        start + velocity * k / 10 + rng.normal(0, 0.2, (3, 3)) * [1, 0, 1] for k in range(frames)
    ]
    return locations, [heading] * frames


def test_world_and_camera_frame_tracking_agree_for_a_static_ego():
    """The same detections tracked without poses (camera frame) and with one constant pose
    (a turned and moved camera; world frame) give the same ids, boxes and velocities."""
    from gac_jax import Tracker3D

    rng = np.random.default_rng(2)
    c, s = np.cos(0.4), np.sin(0.4)
    pose = np.array([[c, 0, s, 5.0], [0, 1, 0, -0.3], [-s, 0, c, 12.0]])
    camera, world = Tracker3D(), Tracker3D()
    locations, headings = moving_cars(20, rng)
    for k, (loc, ry) in enumerate(zip(locations, headings, strict=True)):
        a = camera.update(objects(loc, ry), timestamp=k / 10)
        b = world.update(objects(loc, ry), pose=pose, timestamp=k / 10)
        np.testing.assert_array_equal(a.ids, b.ids)
        for field in ("locations", "velocities", "dimensions", "velocity_covariances"):
            np.testing.assert_allclose(getattr(a, field), getattr(b, field), atol=1e-9)
        np.testing.assert_allclose(wrap_angle(a.rotation_y - b.rotation_y), 0, atol=1e-9)
    assert len(a) == 3


@pytest.mark.parametrize("with_poses", [False, True])
def test_headings_never_flip(with_poses):
    """Detections whose heading is turned by 180 degrees in a third of the frames (front /
    back confusion; the oncoming car's in two frames of three, from the first): without
    poses every reported heading is within 0.3 rad of the truth or of its reverse, the same
    one throughout the track; with poses (over the ground the motion tells front from back)
    a track turned the wrong way by its first detection is turned round once its motion is
    sure, and from the second second on every heading is within 0.3 rad of the truth."""
    from gac_jax import Tracker3D

    rng = np.random.default_rng(3)
    tracker = Tracker3D()
    ego = np.concatenate([np.eye(3), np.zeros((3, 1))], axis=1)
    locations, headings = moving_cars(30, rng)
    reversed_ = {}
    for k, (loc, ry) in enumerate(zip(locations, headings, strict=True)):
        flip = rng.random(3) < 1 / 3
        flip[1] = k % 3 != 1
        measured = wrap_angle(ry + np.pi * flip + rng.normal(0, 0.05, 3))
        pose = ego if with_poses else None
        tracks = tracker.update(objects(loc, measured), pose=pose, timestamp=k / 10)
        assert len(tracks) == 3 and set(tracks.ids.tolist()) == {0, 1, 2}
        err = np.abs(wrap_angle(tracks.rotation_y - ry[tracks.ids]))
        assert np.all((err < 0.3) | (err > np.pi - 0.3)), (k, err)
        if with_poses and k >= 10:
            assert err.max() < 0.3, (k, err)
        elif not with_poses:
            for track_id, e in zip(tracks.ids.tolist(), err, strict=True):
                assert reversed_.setdefault(track_id, e > np.pi / 2) == (e > np.pi / 2), k
    assert with_poses or reversed_[1]  # the first detection decides without a motion cue
    car = int(np.flatnonzero(tracks.ids == 0)[0])  # 30 frames: the trail keeps the last 20
    assert len(tracks.trails[car]) == 20 and np.all(np.diff(tracks.trails[car][:, 2]) > 0)


def test_bad_poses_and_timestamps_are_named():
    from gac_jax import InputError, Tracker3D

    tracker = Tracker3D()
    empty = objects(np.zeros((0, 3)), np.zeros(0))
    with pytest.raises(InputError, match="^pose: expected a \\(3, 4\\)"):
        tracker.update(empty, pose=np.eye(3))
    tracker.update(empty, timestamp=2.0)
    with pytest.raises(InputError, match="^timestamp: 1.5 s is not after"):
        tracker.update(empty, timestamp=1.5)
    with pytest.raises(InputError, match="^pose: given here but missing"):
        tracker.update(empty, pose=np.eye(4)[:3], timestamp=3.0)
    with pytest.raises(InputError, match="^config: unknown tracker parameter"):
        Tracker3D(min_hitz=2)


def test_the_config_section_and_its_defaults():
    """A run config's ``track`` section is read (overrides too); a run config from before the
    section gives the defaults; an unknown key is named."""
    import ml_collections

    from gac_jax.config import apply_overrides, load_config
    from gac_jax.tracking import TrackerParams

    config = load_config("configs/detect3d_default.py:tiny")
    apply_overrides(config, ["track.min_hits=2", "track.depth_std_per_m=0.1"])
    params = TrackerParams.from_config(config)
    assert (params.min_hits, params.depth_std_per_m, params.max_misses) == (2, 0.1, 4)
    old = ml_collections.ConfigDict({"model": {"backbone_depth": 18}, "data": {}})
    assert TrackerParams.from_config(old) == TrackerParams()
    with pytest.raises(ValueError, match="track.max_misses: expected an integer >= 1"):
        TrackerParams.from_config({"max_misses": 0})


def test_kitti_tracking_lines_and_dict():
    """One line per object: frame, id, type, -1 -1, alpha, box, h w l, x y z, ry, score; the
    box stands on the frame's ground plane (a pitched one: y from the plane at x, z)."""
    from gac_jax import Tracker3D

    tracker = Tracker3D(min_hits=1)
    loc = np.array([[1.0, 1.6, 20.0]])
    plane = np.array([0.0, -np.cos(0.02), np.sin(0.02), 1.65])  # normal up, tilted
    loc[0, 1] = (plane[2] * loc[0, 2] + plane[3]) / np.cos(0.02)
    corners = box3d_corners(loc, np.array([CAR]), np.array([0.3]))
    P2 = np.array([[700.0, 0, 600, 0], [0, 700, 180, 0], [0, 0, 1, 0]])
    box = np.asarray(box2d_from_corners(corners, P2)).reshape(1, 4)
    detected = loc + [0.0, 0.3, 0.0]  # 30 cm under the road
    tracks = tracker.update(objects(detected, [0.3], boxes=box.reshape(1, 4)), plane=plane)
    (line,) = tracks.to_kitti_tracking_lines(7)
    fields = line.split()
    assert len(fields) == 18 and fields[:5] == ["7", "0", "Car", "-1", "-1"]
    np.testing.assert_allclose([float(v) for v in fields[6:10]], box.reshape(4), atol=0.01)
    np.testing.assert_allclose([float(v) for v in fields[13:16]], loc[0], atol=1e-6)
    assert float(fields[16]) == pytest.approx(0.3) and float(fields[17]) == pytest.approx(0.9)
    record = tracks.to_dict()["objects"][0]
    assert record["track_id"] == 0 and record["speed"] == 0.0 and record["hits"] == 1


@pytest.mark.parametrize("realtime", [True, False])
def test_a_live_stream_tracks_with_the_times_frames_were_read(realtime):
    """The stream's tracking stage: live, a frame's time is when it was read (a camera that
    delivered frames 0.1-0.5 s apart: the car's 8 m/s is measured); from a file, ``index /
    fps`` (the same frames then look 0.1 s apart: the speed comes out wrong). The trail holds
    the track's positions in order."""
    from gac_jax import Tracker3D
    from gac_jax.streams.sources import Frame
    from gac_jax.streams.tracking import TrackingStage

    stage = TrackingStage(Tracker3D(), fps=10.0, realtime=realtime)
    P2 = np.array([[700.0, 0, 600, 0], [0, 700, 180, 0], [0, 0, 1, 0]])
    image = np.zeros((8, 8, 3), np.uint8)
    times = [0.0, 0.1, 0.2, 0.6, 0.7, 1.2, 1.3, 1.4, 1.9, 2.0, 2.1, 2.6, 2.7]
    for i, t in enumerate(times):
        frame = Frame(i, f"{i:06d}", image, P2, None, t_read=1000.0 + t)
        tracks = stage.update(frame, objects([[2.0, 1.6, 10.0 + 8.0 * t]], [-np.pi / 2]))
    trail = tracks.trails[0]  # the track's positions, oldest first, ending where it is now
    assert len(trail) == len(times) and np.all(np.diff(trail[:, 2]) > 0)
    np.testing.assert_allclose(trail[-1], tracks.locations[0])
    speed = float(tracks.speeds[0])
    if realtime:
        assert speed == pytest.approx(8.0, abs=0.5)
    else:
        assert speed > 12.0
