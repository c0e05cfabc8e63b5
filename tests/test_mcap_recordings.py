# ruff: noqa: F811 - the stream_input fixture of test_stream_faults is a parameter here
"""The MCAP recording, read back with the ``mcap`` reader: channels, schemas, one message per
frame, boxes and transforms equal to what was written (and, from the command, to the result
files and the poses), ROS 2 CDR messages through mcap-ros2-support; a killed or full-disk
writer's file reads back to its last whole chunk, as does the partial MP4 of a killed stream."""

from __future__ import annotations

import errno
import importlib.util
import io
import json
import os
import time

import cv2
import numpy as np
import pytest
from test_stream_faults import count_frames, predict, stream_input  # noqa: F401 - a fixture
from test_stream_recordings import FPS, pictures, psnr

from gac_jax.data.kitti import KittiObjects
from gac_jax.streams.mcap_recording import TOPICS, McapRecording
from gac_jax.streams.recording_scene import matrix_quaternion, quaternion_matrix

# --------------------------------------------------------------------------- MCAP


def frame_objects(i: int) -> KittiObjects:
    return KittiObjects.from_arrays(
        type=["Car", "Pedestrian"],
        bbox=[[10, 10, 60, 40], [80, 5, 95, 45]],
        dimensions=[[1.5, 1.6, 3.9], [1.75, 0.6, 0.8]],
        location=[[1.0 + 0.1 * i, 1.6, 12.0], [-3.0, 1.7, 20.0 - 0.2 * i]],
        rotation_y=[0.3 + 0.05 * i, -2.9],
        score=[0.91, 0.47],
    )


class Tracks:
    """The fields a recording reads of :class:`~gac_jax.tracking.TrackedObjects`."""

    def __init__(self, i: int):
        self.objects = frame_objects(i)
        self.ids = np.array([3, 7])
        self.velocities = np.array([[1.0, 0.0, 0.5], [np.nan] * 3])

    def to_kitti_objects(self):
        return self.objects

    def to_dict(self):
        return {"objects": [{"track_id": int(t)} for t in self.ids]}


def poses(n: int) -> np.ndarray:
    out = np.zeros((n, 3, 4))
    for i in range(n):
        a = 0.1 * i
        out[i, :, :3] = [[np.cos(a), 0, np.sin(a)], [0, 1, 0], [-np.sin(a), 0, np.cos(a)]]
        out[i, :, 3] = [0.5 * i, 0.0, 2.0 * i]
    return out


def yaw_of(q) -> float:
    """ry of a quaternion about the camera's y axis."""
    R = quaternion_matrix([q.x, q.y, q.z, q.w])
    return float(np.arctan2(R[0, 2], R[0, 0]))


def test_quaternions_of_rotations():
    rng = np.random.default_rng(0)
    for _ in range(50):
        A = np.linalg.qr(rng.normal(size=(3, 3)))[0]
        A *= np.sign(np.linalg.det(A))
        np.testing.assert_allclose(quaternion_matrix(matrix_quaternion(A)), A, atol=1e-12)
    for angle in (0.0, np.pi, -np.pi / 2):  # the branches of a half turn
        R = np.array(
            [[np.cos(angle), 0, np.sin(angle)], [0, 1, 0], [-np.sin(angle), 0, np.cos(angle)]]
        )
        np.testing.assert_allclose(quaternion_matrix(matrix_quaternion(R)), R, atol=1e-12)


@pytest.mark.parametrize("profile", ["foxglove", "ros2"])
def test_an_mcap_recording_reads_back(tmp_path, profile):
    """Every channel of the profile once per frame with its schema; cubes at the boxes'
    centres with their size and yaw; the transforms equal to the poses; the calibration's P
    the projection; the JSON records; stamps the frames' times. Decoded with the profile's
    own library (protobuf classes, mcap-ros2-support)."""
    from mcap.reader import make_reader

    P2 = np.array([[700.0, 0, 80, 45.0], [0, 700.0, 37, 0.2], [0, 0, 1, 0.003]])
    n, pose = 6, poses(6)
    with McapRecording(tmp_path / "r.mcap", profile, default_plane=(0, -1, 0, 1.65)) as rec:
        for i, rgb in enumerate(pictures(n)):
            rec.write(rgb, P2, Tracks(i), timestamp=i / FPS, pose=pose[i], frame_id=f"{i:06d}")
    with open(tmp_path / "r.mcap", "rb") as f:
        reader = make_reader(f, decoder_factories=decoders(profile))
        summary = reader.get_summary()
        topics = {c.topic: summary.schemas[c.schema_id].name for c in summary.channels.values()}
        assert topics == dict(TOPICS[profile].values())
        counts = summary.statistics.channel_message_counts
        assert sorted(counts.values()) == [n] * len(topics)
        seen: dict[str, list] = {}
        for _, channel, message, decoded in reader.iter_decoded_messages():
            assert message.log_time == round(len(seen.get(channel.topic, [])) / FPS * 1e9)
            seen.setdefault(channel.topic, []).append(decoded)
    check_messages(profile, seen, P2, pose, n)


def test_frames_of_jpeg_files_are_stored_as_they_are(tmp_path):
    """A sequence of JPEG files: each frame carries its file's bytes and the recording's
    images are those bytes, not a JPEG encoded again; a PNG's frame carries none and its
    image is a JPEG of the picture."""
    from mcap.reader import make_reader

    from gac_jax.data.files import write_png
    from gac_jax.streams.mcap_recording import McapResults
    from gac_jax.streams.sources import SequenceSource

    folder = tmp_path / "seq"
    folder.mkdir()
    rgb = pictures(3)
    files = [cv2.imencode(".jpg", image[..., ::-1])[1].tobytes() for image in rgb[:2]]
    for i, data in enumerate(files):
        (folder / f"{i:06d}.jpg").write_bytes(data)
    write_png(folder / "000002.png", rgb[2])
    (folder / "calib.txt").write_text("P2: 700 0 80 45 0 700 37 0.2 0 0 1 0.003\n")
    source = SequenceSource(folder)
    frames = [source.read() for _ in range(3)]
    assert [f.jpeg for f in frames] == [*files, None]
    with McapRecording(tmp_path / "r.mcap") as rec:
        results = McapResults(rec, FPS)
        for i, frame in enumerate(frames):
            results.write_frame(frame, Tracks(i), None)
    with open(tmp_path / "r.mcap", "rb") as f:
        reader = make_reader(f, decoder_factories=decoders("foxglove"))
        images = [m for _, c, _, m in reader.iter_decoded_messages() if c.topic == "/camera/image"]
    assert [im.data for im in images[:2]] == files and images[2].data not in files
    assert {im.format for im in images} == {"jpeg"}
    decoded = cv2.imdecode(np.frombuffer(images[2].data, np.uint8), cv2.IMREAD_COLOR)
    assert psnr(decoded[..., ::-1], rgb[2]) > 25


def decoders(profile):
    from mcap.decoder import DecoderFactory as Factory

    class JsonDecoder(Factory):
        def decoder_for(self, message_encoding, schema):
            return (lambda data: bytes(data).decode()) if message_encoding == "json" else None

    if profile == "ros2":
        from mcap_ros2.decoder import DecoderFactory
    else:
        from mcap_protobuf.decoder import DecoderFactory
    return [DecoderFactory(), JsonDecoder()]


def whole_chunk_stamps(data: bytes, channel: int = 1) -> list[int]:
    """log_time of ``channel``'s messages in the whole chunks of an MCAP file without a
    summary (the ``mcap`` stream reader, which then fails at the cut: EndOfFile, or a record
    cut short)."""
    from mcap.stream_reader import StreamReader

    stamps = []
    with pytest.raises(Exception) as info:  # noqa: PT011 - the cut, whatever the reader says
        for record in StreamReader(io.BytesIO(data), skip_magic=False).records:
            if type(record).__name__ == "Message" and record.channel_id == channel:
                stamps.append(record.log_time)
    assert type(info.value).__name__ in ("EndOfFile", "error"), info.value
    return stamps


def whole_chunks(data: bytes) -> tuple[int, dict[str, list[int]]]:
    """``(whole chunks, {topic: log_time of its messages in them})`` of an MCAP file without a
    summary, read as a killed run's file can be: the ``mcap`` stream reader, which stops at
    the cut (the chunk that was being written), schemas and channels from the chunks."""
    from mcap.stream_reader import StreamReader

    chunks, topics, stamps = 0, {}, {}
    with pytest.raises(Exception) as info:  # noqa: PT011 - the cut, whatever the reader says
        for record in StreamReader(io.BytesIO(data), skip_magic=False, emit_chunks=True).records:
            chunks += type(record).__name__ == "Chunk"
    assert type(info.value).__name__ in ("EndOfFile", "error"), info.value
    with pytest.raises(Exception) as info:  # noqa: PT011
        for record in StreamReader(io.BytesIO(data), skip_magic=False).records:
            if type(record).__name__ == "Channel":
                topics[record.id] = record.topic
            elif type(record).__name__ == "Message":
                stamps.setdefault(topics[record.channel_id], []).append(record.log_time)
    assert type(info.value).__name__ in ("EndOfFile", "error"), info.value
    return chunks, stamps


def field(message, name):
    return message[name] if isinstance(message, dict) else getattr(message, name)


def check_messages(profile, seen, P2, pose, n) -> None:
    scenes = seen["/detections/scene"]
    for i in range(n):
        want = frame_objects(i)
        entities = field(scenes[i], "entities")
        assert [e.id for e in entities] == ["track 3", "track 7"]
        for k, entity in enumerate(entities):
            cube = entity.cubes[0]
            h, w, l = want.dimensions[k]
            centre = want.location[k] - [0, h / 2, 0]
            p = cube.pose.position
            np.testing.assert_allclose([p.x, p.y, p.z], centre, atol=1e-9)
            np.testing.assert_allclose([cube.size.x, cube.size.y, cube.size.z], [l, h, w])
            assert yaw_of(cube.pose.orientation) == pytest.approx(want.rotation_y[k], abs=1e-9)
            meta = {m.key: m.value for m in entity.metadata}
            assert meta["id"] == ["3", "7"][k] and meta["class"] == want.type[k]
            assert float(meta["score"]) == pytest.approx(want.score[k], abs=1e-4)
            assert ("velocity" in meta) == (k == 0)
        assert "over the ground" in {m.key: m.value for m in entities[0].metadata}["velocity"]
        assert entities[0].texts[0].text.startswith("#3 Car 0.91 1.1 m/s")
        tf = seen["/tf"][i]
        transforms = tf.transforms
        assert len(transforms) == 1
        t = transforms[0].transform if profile == "ros2" else transforms[0]
        translation, rotation = t.translation, t.rotation
        np.testing.assert_allclose([translation.x, translation.y, translation.z], pose[i][:, 3])
        q = [rotation.x, rotation.y, rotation.z, rotation.w]
        np.testing.assert_allclose(quaternion_matrix(q), pose[i][:, :3], atol=1e-12)
        record = seen["/detections/json"][i]
        record = json.loads(record.data if profile == "ros2" else record)
        assert record["frame"] == f"{i:06d}" and record["timestamp"] == pytest.approx(i / FPS)
    calibration = "/camera/camera_info" if profile == "ros2" else "/camera/calibration"
    P = seen[calibration][0].p if profile == "ros2" else seen[calibration][0].P
    np.testing.assert_allclose(np.reshape(P, (3, 4)), P2)
    image = seen["/camera/image/compressed" if profile == "ros2" else "/camera/image"][0]
    assert image.format == "jpeg"
    decoded = cv2.imdecode(np.frombuffer(bytes(image.data), np.uint8), cv2.IMREAD_COLOR)
    assert psnr(decoded[..., ::-1], pictures(1)[0]) > 25
    ground = field(seen["/ground_plane"][0], "entities")[0].cubes[0].pose.position
    assert ground.y == pytest.approx(1.65)
    if profile == "ros2":
        boxes = seen["/detections"][0].detections
        assert [d.id for d in boxes] == ["3", "7"]
        assert boxes[0].results[0].hypothesis.class_id == "Car"
        assert boxes[0].bbox.size.x == pytest.approx(3.9)


def test_a_killed_recording_reads_back_to_its_last_chunk(tmp_path):
    """The hidden partial of a writer that never closed (a kill), cut inside a chunk: the
    ``mcap`` stream reader gives every message of the whole chunks, in order, then stops at
    the cut (no summary: the seeking reader cannot open it, ``mcap recover`` repairs it)."""
    # JPEG quality 90: the chunks end where this test was laid out for (at 80 the last frame's
    # write writes a chunk, and 100 bytes less cut only the message indexes after it)
    rec = McapRecording(tmp_path / "r.mcap", chunk_size=64 << 10, jpeg_quality=90)
    for i, rgb in enumerate(pictures(40, (150, 300))):
        rec.write(rgb, np.eye(3, 4) * 100, Tracks(i), timestamp=i / FPS)
    data = rec.partial.read_bytes()  # what a kill leaves: whole chunks, the last one pending
    assert not (tmp_path / "r.mcap").exists()
    frames = whole_chunk_stamps(data[: len(data) - 100])
    assert 10 < len(frames) < 40 and frames == [round(i / FPS * 1e9) for i in range(len(frames))]
    rec.close()
    assert (tmp_path / "r.mcap").is_file() and not rec.partial.exists()


def test_a_failed_recording_write_keeps_its_whole_chunks(tmp_path, monkeypatch):
    """ENOSPC inside a chunk's write: it raises naming the file, the file is cut back to the
    chunks before and kept as ``.incomplete.mcap``, and reads back to them."""
    real = os.write
    full = {"on": False}

    def full_disk(fd, data):
        if full["on"]:
            raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))
        return real(fd, data)

    monkeypatch.setattr(os, "write", full_disk)
    # JPEG quality 90: frame 20's messages fill a chunk, which its write then writes
    rec = McapRecording(tmp_path / "r.mcap", chunk_size=64 << 10, jpeg_quality=90)
    with pytest.raises(OSError, match="No space left") as info:
        for i, rgb in enumerate(pictures(40, (150, 300))):
            full["on"] = i == 20
            rec.write(rgb, np.eye(3, 4) * 100, Tracks(i), timestamp=i / FPS)
    assert info.value.filename == str(tmp_path / "r.mcap")
    full["on"] = False
    assert rec.close(complete=False) == tmp_path / "r.incomplete.mcap"
    stamps = whole_chunk_stamps((tmp_path / "r.incomplete.mcap").read_bytes())
    assert 0 < len(stamps) <= 20 and stamps == [round(i / FPS * 1e9) for i in range(len(stamps))]


# --------------------------------------------------------------------------- the command


def test_the_mp4_and_the_mcap_of_a_killed_stream_play_to_their_last_whole_part(
    tiny_detect3d_workdir,
    stream_input,
    tmp_path,
):
    """SIGKILL mid-stream (nothing can be finished): the hidden partial MP4 plays (PyAV and
    OpenCV) a prefix of at most as many frames as result files, and the hidden partial MCAP
    reads back to its last whole chunk: on every channel frames in order from the first, every
    frame with all its channels but the last one read (its messages may go on in the chunk
    that was cut), at least a frame per whole chunk."""
    make_video, calib = stream_input
    video = make_video("long.avi", 400, fps=10.0)
    out = tmp_path / "out"
    argv = ["--workdir", tiny_detect3d_workdir, "--video", video, "--calib", calib, "--out", out,
            "--mcap", out / "run.mcap", "--report-every", 0]  # fmt: skip
    process = predict(argv)
    deadline = time.monotonic() + 240
    while time.monotonic() < deadline and process.poll() is None:
        if out.is_dir() and len(list(out.glob("data/*.txt"))) >= 16:
            break
        time.sleep(0.05)
    assert process.poll() is None, process.communicate()
    process.kill()
    process.communicate(timeout=60)
    written = len(list((out / "data").glob("*.txt")))
    partial = out / ".annotated.partial.mp4"
    frames = playable_frames(partial)
    assert 1 <= frames <= written and count_frames(partial) == frames
    stamps = whole_chunk_stamps((out / ".run.partial.mcap").read_bytes())
    assert 1 <= len(stamps) <= written
    assert stamps == [round(i / 10.0 * 1e9) for i in range(len(stamps))]
    # every channel: frames from the first, one after another; all channels of every frame
    # but the last read, whose messages the cut chunk may have held the rest of
    chunks, topics = whole_chunks((out / ".run.partial.mcap").read_bytes())
    order = [topic for topic, _ in TOPICS["foxglove"].values() if topic != "/tf"]  # no poses
    assert chunks >= 1 and list(topics) == order
    counts = [len(topics[topic]) for topic in order]
    assert counts[0] >= chunks and counts == sorted(counts, reverse=True)
    assert counts[0] - counts[-1] <= 1 and counts[0] == len(stamps)
    for topic in order:
        assert topics[topic] == stamps[: len(topics[topic])]


def playable_frames(path) -> int:
    """Frames PyAV decodes from the start of ``path`` (a cut last fragment ends it)."""
    import av

    n = 0
    with av.open(str(path)) as container:
        try:
            for _ in container.decode(video=0):
                n += 1
        except av.error.InvalidDataError:
            pass
    return n


@pytest.mark.parametrize("profile", ["foxglove", "ros2"])
def test_the_mcap_of_a_stream_holds_its_result_files_and_poses(
    tiny_detect3d_workdir,
    stream_input,
    tmp_path,
    profile,
):
    """``--mcap`` (with ``--poses``; ros2: ``--track`` too): one message per frame on every
    channel; the cubes are the result files' boxes to their printed digits (6 decimals), the
    transforms the poses, the stamps the frames' times, decoded by the profile's library
    (ros2: and by rosbags, when installed, to the same fields: tests/test_ros2_bag.py)."""
    from mcap.reader import make_reader

    from gac_jax.data.kitti import read_label
    from gac_jax.data.kitti_tracking import format_poses

    make_video, calib = stream_input
    n = 5
    video = make_video("five.avi", n, fps=10.0)
    pose = poses(n)
    (tmp_path / "poses.txt").write_text(format_poses(pose))
    out = tmp_path / "out"
    argv = ["--workdir", tiny_detect3d_workdir, "--video", video, "--calib", calib, "--out", out,
            "--mcap", out / "run.mcap", "--poses", tmp_path / "poses.txt", "--report-every", 0,
            "--no-video", "--mcap-profile", profile]  # fmt: skip
    if profile == "ros2":
        argv.append("--track")
    process = predict(argv)
    stdout, stderr = process.communicate(timeout=300)
    assert process.returncode == 0, (stdout, stderr)
    with open(out / "run.mcap", "rb") as f:
        reader = make_reader(f, decoder_factories=decoders(profile))
        summary = reader.get_summary()
        counts = summary.statistics.channel_message_counts
        assert sorted(counts.values()) == [n] * len(TOPICS[profile])
        seen: dict[str, list] = {}
        for _, channel, message, decoded in reader.iter_decoded_messages():
            assert message.log_time == round(len(seen.get(channel.topic, [])) / 10.0 * 1e9)
            seen.setdefault(channel.topic, []).append(decoded)
    if profile == "ros2" and importlib.util.find_spec("rosbags"):  # the dev extra
        from test_ros2_bag import plain, read_bag

        bag, _ = read_bag(out / "run.mcap")  # rosbags' reading: the same, field by field
        assert {t: [plain(m) for _, m in ms] for t, ms in bag.items()} == {
            t: [plain(m) for m in ms] for t, ms in seen.items()
        }
    for i in range(n):
        if profile == "ros2":
            want = tracking_frame(out / "tracking" / "0000.txt", i)
        else:
            want = read_label(out / "data" / f"{i:06d}.txt", with_score=True)
        entities = field(seen["/detections/scene"][i], "entities")
        assert len(entities) == len(want)
        for k, entity in enumerate(entities):
            cube = entity.cubes[0]
            h, w, l = want.dimensions[k]
            p = cube.pose.position
            centre = want.location[k] - [0, h / 2, 0]
            np.testing.assert_allclose([p.x, p.y, p.z], centre, atol=1e-6)
            np.testing.assert_allclose(
                [cube.size.x, cube.size.y, cube.size.z], [l, h, w], atol=1e-6
            )
            assert yaw_of(cube.pose.orientation) == pytest.approx(want.rotation_y[k], abs=1e-6)
        tf = seen["/tf"][i].transforms[0]
        t = tf.transform if profile == "ros2" else tf
        np.testing.assert_allclose([t.translation.x, t.translation.y, t.translation.z],
                                   pose[i][:, 3], atol=1e-9)  # fmt: skip
        q = [t.rotation.x, t.rotation.y, t.rotation.z, t.rotation.w]
        np.testing.assert_allclose(quaternion_matrix(q), pose[i][:, :3], atol=1e-9)


def tracking_frame(path, frame: int) -> KittiObjects:
    """The boxes of one frame of a KITTI tracking result file (``frame id type ...``)."""
    from gac_jax.data.kitti import parse_label

    lines = [line.split(" ", 2) for line in path.read_text().splitlines()]
    text = "".join(rest[2] + "\n" for rest in lines if int(rest[0]) == frame)
    return parse_label(text, with_score=True)
