"""Generated driving clips (``python -m gac_jax.data.synthetic --sequences N ...``).

Two tiny clips (2 sequences x 6 frames, KITTI-equivalent 188x621) are generated once per
module. The checks are independent of how the generator moved things: labels against the
render's object masks and depth (as the frames' test does), static road users standing
still in the world the poses define, one ground plane in that world for every frame, tracks
keeping one id, size and heading while moving at a constant velocity.
"""

from __future__ import annotations

import json
import shutil
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from gac_jax.data import files, kitti
from gac_jax.data import kitti_tracking as tracking
from gac_jax.data.files import KittiFormatError
from gac_jax.data.synthetic import drive, rigs, traffic
from gac_jax.data.synthetic.clips import (
    DONE,
    MARKER,
    ClipSpec,
    default_clip_dir,
    ensure_clips,
    generate_clips,
)
from gac_jax.geometry import box2d_from_corners, box3d_corners, unproject
from tests.test_synthetic import _box_local, _inside_box, _tree_digest

SIZE = (188, 621)
SEED = 4
SEQUENCES, FRAMES = 2, 6
ARGS = dict(height=SIZE[0], width=SIZE[1], workers=1)
REPO = Path(__file__).resolve().parents[1]


@pytest.fixture(scope="module")
def clips(tmp_path_factory) -> Path:
    root = tmp_path_factory.mktemp("clips") / "clips"
    result = generate_clips(root, SEQUENCES, FRAMES, SEED, **ARGS)
    assert result.generated == SEQUENCES * FRAMES
    return root


@pytest.fixture(scope="module")
def rendered():
    """(sequence, frame) -> ClipFrame, rendered in memory."""
    spec = ClipSpec(SEQUENCES, FRAMES, SEED, height=SIZE[0], width=SIZE[1])
    return {
        (s, k): drive.render_clip_frame(spec.drive(s), SEED, s, k)
        for s in range(SEQUENCES)
        for k in range(FRAMES)
    }


def _world(pose: np.ndarray, points: np.ndarray) -> np.ndarray:
    return points @ pose[:, :3].T + pose[:, 3]


def test_layout_manifest_and_reader(clips):
    layout = tracking.KittiTrackingLayout(clips)
    assert layout.sequences() == ["0000", "0001"]
    manifest = json.loads((clips / DONE).read_text())
    assert manifest["seed"] == SEED and manifest["rigs"] == "kitti"
    assert (manifest["num_sequences"], manifest["frames_per_sequence"]) == (SEQUENCES, FRAMES)
    assert not (clips / MARKER).exists() and not (clips / ".clips_partial").exists()
    assert not list(clips.rglob(".*.tmp"))
    found, seq = tracking.KittiTrackingLayout.locate(clips / "training" / "image_02" / "0001")
    assert (found.root, found.subset, seq) == (clips.resolve(), "training", "0001")
    assert tracking.KittiTrackingLayout.locate(clips / "training") is None
    for seq in layout.sequences():
        assert layout.frame_numbers(seq) == list(range(FRAMES))
        calib = kitti.read_calib(layout.calib(seq))  # the project's reader, P2 and the rest
        assert calib.P3 is not None and calib.Tr_velo_to_cam is not None
        fx_full = calib.P2[0, 0] * 1242 / SIZE[1]
        assert min(abs(fx_full - f) for f in (721.5377, 718.3351, 707.0493)) < 1e-6
        lines = layout.label(seq).read_text().splitlines()
        assert lines and all(len(line.split()) == 17 for line in lines)
        frames = list(layout.frames(seq))
        assert [f.frame for f in frames] == list(range(FRAMES))
        for f in frames:
            assert files.read_image(f.image).shape == (*SIZE, 3)
            np.testing.assert_array_equal(f.P2, calib.P2)
            assert f.plane is not None and f.plane[3] == pytest.approx(1.65, abs=0.06)
            assert f.pose.shape == (3, 4) and f.labels is not None
            objects, ids = f.labels.objects, f.labels.track_ids
            dc = objects.type == "DontCare"
            assert set(objects.type) <= {"Car", "Pedestrian", "Cyclist", "DontCare"}
            np.testing.assert_array_equal(ids[dc], -1)
            assert (ids[~dc] >= 0).all() and len(set(ids[~dc])) == (~dc).sum()
            assert set(objects.truncated[~dc]) <= {0.0, 1.0, 2.0}


def assert_labels_match_render(frame, objects, P2, size) -> int:
    """Labels of a rendered clip frame against its object masks and depth; returns the
    number of labelled (not DontCare) objects checked."""
    object_ids = frame.view.object_ids
    visible = set(np.unique(object_ids[object_ids >= 0]).tolist())
    assert sorted(frame.label_source.tolist()) == sorted(visible)  # each visible object once
    checked = 0
    for line, i in enumerate(frame.label_source):
        rr, cc = np.nonzero(object_ids == i)
        x1, y1, x2, y2 = cc.min(), rr.min(), cc.max(), rr.max()
        if objects.type[line] == "DontCare":  # the extent of its visible pixels
            np.testing.assert_allclose(objects.bbox[line], [x1, y1, x2, y2], atol=1.0)
            continue
        depth = frame.view.depth[rr, cc].astype(np.float64)
        pts = unproject(np.stack([cc, rr], 1).astype(np.float64), depth, P2)
        local = _box_local(pts, objects, line)
        assert _inside_box(local, objects.dimensions[line], tol=0.03).all()
        # the 3D box projects around its visible 2D box
        corners = box3d_corners(
            objects.location[[line]], objects.dimensions[[line]], objects.rotation_y[[line]]
        )
        hull = box2d_from_corners(corners, P2, size)[0]
        assert hull[0] <= x1 + 1 and hull[1] <= y1 + 1 and hull[2] >= x2 - 1
        assert hull[3] >= y2 - 1
        # ... and is the 2D box, as on KITTI's labels (clipped to the image)
        np.testing.assert_allclose(objects.bbox[line], hull, atol=0.006)
        checked += 1
    return checked


def test_labels_match_render(clips, rendered):
    layout = tracking.KittiTrackingLayout(clips)
    checked = 0
    for (s, k), frame in rendered.items():
        seq = f"{s:04d}"
        labels = layout.read_labels(seq).get(k)
        np.testing.assert_array_equal(labels.objects.bbox, frame.objects.bbox)  # file == memory
        np.testing.assert_array_equal(labels.track_ids, frame.track_ids)
        checked += assert_labels_match_render(frame, labels.objects, layout.read_P2(seq), SIZE)
    assert checked >= 10


def _tracks(layout, seq):
    """track id -> list of (frame, type, dims, location, rotation_y)."""
    out: dict[int, list] = {}
    for k, labels in sorted(layout.read_labels(seq).items()):
        o = labels.objects
        for j, tid in enumerate(labels.track_ids):
            if tid >= 0:
                out.setdefault(int(tid), []).append(
                    (k, o.type[j], o.dimensions[j], o.location[j], o.rotation_y[j])
                )
    return out


def _world_velocity_errors(layout, seq, world):
    """|finite-difference world velocity from labels + poses - the simulated one| per
    labelled (track, middle frame) with both neighbours labelled and a velocity changing
    linearly over the three frames, and the role of each."""
    poses = layout.read_poses(seq)
    movers = {m.track_id: m for m in world.movers}
    errors, roles = [], []
    for tid, items in _tracks(layout, seq).items():
        ks = [it[0] for it in items]
        where = {k: _world(poses[k], it[3]) for k, it in zip(ks, items, strict=True)}
        for k in ks:
            if k - 1 in where and k + 1 in where:
                measured = (where[k + 1] - where[k - 1]) / (2 / drive.FRAME_RATE)
                v = [world.velocity(movers[tid], j / drive.FRAME_RATE) for j in (k - 1, k, k + 1)]
                if np.linalg.norm(v[0] + v[2] - 2 * v[1]) > 0.2:
                    continue  # not linear over the two frames (a walk starts or stops)
                truth = v[1]
                errors.append(np.linalg.norm(measured - truth))
                roles.append(movers[tid].role)
    return np.array(errors), roles


def test_tracks_keep_ids_and_move_at_their_simulated_velocity(clips):
    layout = tracking.KittiTrackingLayout(clips)
    checked = 0
    for s, seq in enumerate(layout.sequences()):
        world = drive.make_drive(SEED, s, FRAMES, SIZE)
        movers = {m.track_id: m for m in world.movers}
        for tid, items in _tracks(layout, seq).items():
            assert len({it[1] for it in items}) == 1 and movers[tid].type == items[0][1]
            np.testing.assert_array_equal([it[2] for it in items], [items[0][2]] * len(items))
            np.testing.assert_allclose(movers[tid].dimensions, items[0][2])
        errors, _ = _world_velocity_errors(layout, seq, world)
        # labels are rounded to 1 cm: <= 0.1 m/s over two frames
        assert (errors < 0.1).all(), errors.max()
        checked += len(errors)
    assert checked >= 10


def assert_one_world_plane(layout, seq, poses) -> None:
    """Every frame's plane, moved into the world by its pose, is the same plane (the road)."""
    world_planes = []
    for k, pose in enumerate(poses):
        plane = kitti.read_plane(layout.plane(seq, k))
        n = pose[:, :3] @ plane[:3]
        world_planes.append([*n, plane[3] - n @ pose[:, 3]])
    np.testing.assert_allclose(world_planes, [world_planes[0]] * len(poses), atol=1e-9)


def test_poses_advance_along_the_road_at_ego_speed(clips):
    layout = tracking.KittiTrackingLayout(clips)
    for s, seq in enumerate(layout.sequences()):
        poses = layout.read_poses(seq)
        assert poses.shape == (FRAMES, 3, 4)
        np.testing.assert_allclose(poses[0], np.eye(3, 4), atol=1e-12)
        for pose in poses:
            np.testing.assert_allclose(pose[:, :3] @ pose[:, :3].T, np.eye(3), atol=1e-12)
        steps = np.diff(poses[:, :, 3], axis=0)
        ego = drive.ego_motion(SEED, s)
        along = np.diff([ego.travelled(k) for k in range(FRAMES)])
        # the camera's path is the lane's: within 6 % of the centre line's on a bend
        np.testing.assert_allclose(np.linalg.norm(steps, axis=1), along, rtol=0.06, atol=1e-9)
        moving = np.linalg.norm(steps, axis=1) > 0.05
        # each step along the camera's own z (within heading/pitch), in its own frame
        forward = np.einsum("kji,kj->ki", poses[:-1, :, :3], steps)
        forward /= np.maximum(np.linalg.norm(forward, axis=1, keepdims=True), 1e-12)
        assert (forward[moving, 2] > np.cos(np.deg2rad(2.5))).all()
        assert drive.EGO_SPEED[0] <= ego.speed <= drive.EGO_SPEED[1]
        assert_one_world_plane(layout, seq, poses)
        normals = np.array([kitti.read_plane(layout.plane(seq, k))[:3] for k in range(FRAMES)])
        assert np.ptp(normals[:, 2]) > 1e-5  # the camera pitches
        # labelled road users stand on the road (or a kerb up to 0.16 m above it)
        for k, labels in layout.read_labels(seq).items():
            o = labels.objects.select(labels.objects.type != "DontCare")
            plane = kitti.read_plane(layout.plane(seq, k))
            height = o.location @ plane[:3] + plane[3]  # (normal up: above = positive)
            assert ((height > -0.02) & (height < 0.18)).all(), height


def test_same_bytes_any_workers(clips, tmp_path):
    other = tmp_path / "again"
    assert generate_clips(other, SEQUENCES, FRAMES, SEED, **{**ARGS, "workers": 2}).generated
    assert _tree_digest(other) == _tree_digest(clips)
    third = tmp_path / "different"
    generate_clips(third, 1, 2, SEED + 1, **ARGS)
    a = (third / "training" / "image_02" / "0000" / "000000.png").read_bytes()
    assert a != (clips / "training" / "image_02" / "0000" / "000000.png").read_bytes()


def test_noop_and_resume(clips, tmp_path):
    root = tmp_path / "copy"
    shutil.copytree(clips, root)
    before = _tree_digest(root)
    stamps = {p: p.stat().st_mtime_ns for p in root.rglob("*") if p.is_file()}
    start = time.perf_counter()
    assert generate_clips(root, SEQUENCES, FRAMES, SEED, **ARGS).generated == 0
    assert time.perf_counter() - start < 1.0
    assert {p: p.stat().st_mtime_ns for p in root.rglob("*") if p.is_file()} == stamps

    training = root / "training"
    (training / "image_02" / "0001" / "000003.png").unlink()
    (training / "poses" / "0000.txt").unlink()
    assert generate_clips(root, SEQUENCES, FRAMES, SEED, **ARGS).generated == 1
    assert _tree_digest(root) == before

    # interrupted: marker, no manifest, a half-written file, labels not gathered yet
    (root / DONE).unlink()
    (root / MARKER).write_text((clips / DONE).read_text())
    (training / "image_02" / "0000" / ".000002.png.x.tmp").write_bytes(b"half")
    (training / "label_02" / "0000.txt").unlink()
    (training / "planes" / "0000" / "000004.txt").unlink()
    assert generate_clips(root, SEQUENCES, FRAMES, SEED, **ARGS).generated == FRAMES
    assert _tree_digest(root) == before

    with pytest.raises(ValueError, match="other arguments.*frames_per_sequence"):
        generate_clips(root, SEQUENCES, FRAMES + 1, SEED, **ARGS)
    foreign = tmp_path / "foreign"
    foreign.mkdir()
    (foreign / "notes.txt").write_text("mine")
    with pytest.raises(ValueError, match="not empty"):
        generate_clips(foreign, 1, 1, SEED, **ARGS)


def test_multi_rig_clip_one_vehicle_pitching(tmp_path):
    root = tmp_path / "multi"
    generate_clips(root, 1, 4, 2, rigs="multi", **ARGS)
    layout = tracking.KittiTrackingLayout(root)
    ego = drive.ego_motion(2, 0, "multi")
    mount = rigs.MULTI_RIGS[ego.rig]
    P2 = layout.read_P2("0000")
    np.testing.assert_allclose(P2[:, :3], drive.clip_calibration(ego, SIZE, "multi")[0].P2[:, :3])
    frames = list(layout.frames("0000"))
    assert files.read_image(frames[0].image).shape[:2] == rigs.image_size(mount.camera, SIZE)
    pitches = [np.rad2deg(np.arctan2(-f.plane[2], -f.plane[1])) for f in frames]  # + = down
    jitter = 2 * rigs.POSE_JITTER_PITCH + drive.PITCH_AMPLITUDE[1]
    assert all(abs(p - mount.pitch) <= jitter + 1e-6 for p in pitches), (pitches, mount)
    assert np.ptp(pitches) > 0.0
    heights = [f.plane[3] for f in frames]
    assert np.ptp(heights) < 1e-9 and abs(heights[0] - mount.height) <= 0.05 + 1e-9


def test_tracking_label_format_roundtrip_and_errors(tmp_path):
    objects = kitti.KittiObjects.from_arrays(
        type=["Car", "DontCare"],
        truncated=[0.3, -1.0],
        occluded=[1, -1],
        alpha=[0.5, -10.0],
        bbox=[[1, 2, 30, 40], [5, 6, 7, 8]],
        dimensions=[[1.5, 1.6, 3.9], [-1, -1, -1]],
        location=[[1.0, 1.6, 20.0], [-1000, -1000, -1000]],
        rotation_y=[0.55, -10.0],
    )
    text = tracking.format_tracking_labels(7, objects, np.array([3, -1]))
    assert text.splitlines()[0].split()[:5] == ["7", "3", "Car", "1", "1"]
    parsed = tracking.parse_tracking_labels(
        text + "".join("9" + line[1:] for line in text.splitlines(True))
    )
    assert sorted(parsed) == [7, 9]
    np.testing.assert_array_equal(parsed[7].track_ids, [3, -1])
    np.testing.assert_allclose(parsed[7].objects.location, objects.location)
    np.testing.assert_array_equal(
        tracking.truncation_level([0.0, 0.01, 0.49, 0.5, -1]), [0, 1, 1, 2, -1]
    )
    bad = tmp_path / "0000.txt"
    bad.write_text("0 1 Car 0 0 0.1 1 2 3\n")
    with pytest.raises(KittiFormatError, match="0000.txt.*17 columns"):
        tracking.parse_tracking_labels(bad.read_text(), bad)


def test_ensure_clips_in_the_cache(tmp_path, monkeypatch, capsys):
    monkeypatch.setenv("GAC_JAX_CACHE", str(tmp_path / "cache"))
    where = default_clip_dir(1, 2, seed=3)
    assert where.parent == tmp_path / "cache"
    assert default_clip_dir(1, 2, seed=3, rigs="multi") != where
    assert ensure_clips(None, 1, 2, seed=3, workers=1) == where
    err = capsys.readouterr().err
    first = err.splitlines()[0]
    assert "generating 2 frames" in first and str(where) in first and "about" in first
    assert len(list((where / "training" / "image_02" / "0000").glob("*.png"))) == 2
    assert files.read_image(where / "training" / "image_02" / "0000" / "000000.png").shape == (
        375,
        1242,
        3,
    )
    assert ensure_clips(None, 1, 2, seed=3, workers=1) == where  # no-op, silent
    assert capsys.readouterr().err == ""
    manifest = json.loads((where / DONE).read_text())
    (where / DONE).write_text(json.dumps({**manifest, "format_version": 1}))  # an older one
    assert ensure_clips(None, 1, 2, seed=3, workers=1) == where
    assert "generating 2 frames" in capsys.readouterr().err
    assert json.loads((where / DONE).read_text()) == manifest


@pytest.mark.parametrize(
    "argv, message",
    [
        (
            ["--sequences", "1", "--frames-per-sequence", "0"],
            "--frames-per-sequence: must be at least 1",
        ),
        (["--sequences", "2"], "need both --sequences N and --frames-per-sequence F"),
        (["--num", "3", "--sequences", "1", "--frames-per-sequence", "2"], "exclude each other"),
        (["--sequences", "1", "--frames-per-sequence", "2", "--val-fraction", "0.2"], "no splits"),
        (
            ["--sequences", "1", "--frames-per-sequence", "2", "--scenarios", "loop"],
            "unknown scenario 'loop'",
        ),
        (["--num", "2", "--scenarios", "curve"], "--scenarios is for clips"),
    ],
)
def test_cli_bad_arguments(tmp_path, argv, message):
    cmd = [sys.executable, "-m", "gac_jax.data.synthetic", "--out", str(tmp_path / "o"), *argv]
    run = subprocess.run(cmd, capture_output=True, text=True, timeout=60)
    assert run.returncode == 2
    assert message in run.stderr and "Traceback" not in run.stderr
    assert (
        run.stderr.strip().splitlines()[-1].startswith("python -m gac_jax.data.synthetic: error:")
    )


def test_cli_clips_end_to_end(tmp_path):
    out = tmp_path / "cli"
    cmd = [sys.executable, "-m", "gac_jax.data.synthetic", "--out", str(out), "--sequences", "1"]
    cmd += ["--frames-per-sequence", "2", "--height", "64", "--width", "256", "--quiet"]
    cmd += ["--workers", "1", "--classes", "Car:2-3", "--scenarios", "curve:1", "oncoming"]
    run = subprocess.run(cmd, capture_output=True, text=True, timeout=120)
    assert run.returncode == 0, run.stderr
    assert "wrote 2 of 2 clip frames" in run.stdout
    labels = tracking.KittiTrackingLayout(out).read_labels("0000")
    assert all(set(t.objects.type) <= {"Car", "DontCare"} for t in labels.values())
    manifest = json.loads((out / DONE).read_text())
    assert manifest["scenarios"] == {"curve": 1.0, "oncoming": traffic.DEFAULT_MIX["oncoming"]}
    assert drive.ego_motion(0, 0, mix=(("curve", 1.0),)).scenarios == {"curve"}
    again = subprocess.run(cmd, capture_output=True, text=True, timeout=120)
    assert again.returncode == 0 and "already there" in again.stdout
