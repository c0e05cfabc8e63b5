"""gac_jax.streams: the threaded stream pipeline, its sources and outputs, with a stand-in
detector of the prepare/infer/finish interface (no network: these tests are about order,
counts, pacing and stopping; tests/test_stream_cli.py runs the real detector)."""

from __future__ import annotations

import json
import queue
import threading
import time

import cv2
import numpy as np
import pytest

from gac_jax.data.files import KittiFormatError, write_png
from gac_jax.data.kitti import KittiObjects, read_label
from gac_jax.streams import outputs, sources
from gac_jax.streams.pipeline import LatestSlot, StreamPipeline
from gac_jax.streams.rates import StreamRates

P2 = np.array([[100.0, 0, 40, 0], [0, 100.0, 24, 0], [0, 0, 1, 0]])
SIZE = (48, 80)


class FakeDetections:
    """One car per frame whose depth encodes the frame (``10 + mean pixel value``)."""

    def __init__(self, value: float):
        self.value = value

    def to_kitti_objects(self) -> KittiObjects:
        return KittiObjects.from_arrays(
            type=["Car"],
            bbox=[[10, 10, 30, 30]],
            dimensions=[[1.5, 1.6, 3.9]],
            location=[[0, 1.6, 10 + self.value]],
            score=[0.9],
        )

    def to_dict(self) -> dict:
        return {"depth": 10 + self.value}


class FakeDetector:
    """prepare/infer/finish with a fixed network time; records batch sizes and threads."""

    def __init__(self, infer_s: float = 0.0, fail_at: int | None = None):
        self.infer_s, self.fail_at = infer_s, fail_at
        self.batches: list[int] = []
        self.calls = 0

    def prepare(self, image, P2, plane):
        return float(image.mean())

    def infer(self, prepared):
        self.calls += 1
        if self.fail_at is not None and self.calls > self.fail_at:
            raise RuntimeError("network failed")
        time.sleep(self.infer_s)
        self.batches.append(len(prepared))
        return list(prepared)

    def finish(self, raw, prepared):
        return [FakeDetections(v) for v in raw]


class ListSource:
    """Frames ``value = 3 i`` (uniform images), optionally ``delay`` seconds each."""

    live = False

    def __init__(self, n: int, delay: float = 0.0):
        self.n, self.delay, self.i = n, delay, 0
        self.name, self.size, self.fps, self.expected_frames = "list", SIZE, 10.0, n

    def read(self):
        if self.i >= self.n:
            return None
        time.sleep(self.delay)
        i, self.i = self.i, self.i + 1
        image = np.full((*SIZE, 3), 3 * i, np.uint8)
        return sources.Frame(i, f"{i:06d}", image, P2, None, time.perf_counter())

    def check_complete(self):
        pass

    def close(self):
        pass


def count_frames(path) -> int:
    capture = cv2.VideoCapture(str(path))
    assert capture.isOpened(), path
    n = 0
    while capture.read()[0]:
        n += 1
    capture.release()
    return n


def run_stream(source, detector, tmp_path, **kwargs):
    video = outputs.AnnotatedVideo(tmp_path / "out.avi", source.fps)
    results = outputs.KittiResults(tmp_path / "data")
    pipeline = StreamPipeline(source, detector, video, results, report_every=0, **kwargs)
    report = pipeline.run()
    video.close()
    return pipeline, report


@pytest.mark.parametrize("batch_size", [1, 3])
def test_a_file_is_processed_whole_and_in_order(tmp_path, batch_size):
    detector = FakeDetector()
    _, report = run_stream(ListSource(10), detector, tmp_path, batch_size=batch_size)
    assert (report.delivered, report.written, report.dropped_live) == (10, 10, 0)
    assert report.error is None and not report.interrupted
    assert count_frames(tmp_path / "out.avi") == 10
    depths = [
        read_label(tmp_path / "data" / f"{i:06d}.txt", with_score=True).location[0, 2]
        for i in range(10)
    ]
    np.testing.assert_allclose(depths, [10 + 3 * i for i in range(10)], atol=0.01)
    assert sum(detector.batches) == 10 and max(detector.batches) == batch_size
    assert report.rates["frames"] == 10 and report.rates["latency_p95_ms"] > 0


def test_realtime_keeps_the_newest_frame_and_counts_the_dropped(tmp_path):
    """A source paced at 100 frames/s into a 25 frames/s detector: most frames are dropped,
    and every delivered frame is either written or counted as dropped."""
    src = sources.PacedSource(ListSource(60), fps=100.0)
    _, report = run_stream(src, FakeDetector(infer_s=0.04), tmp_path, realtime=True)
    assert report.dropped_live > 0
    assert report.written + report.dropped_live == report.delivered == 60
    assert count_frames(tmp_path / "out.avi") == report.written
    written = sorted(int(p.stem) for p in (tmp_path / "data").glob("*.txt"))
    assert len(written) == report.written and written[-1] == 59  # the newest frame is kept


def test_stop_finishes_the_frames_in_flight(tmp_path):
    src = ListSource(200, delay=0.005)
    video = outputs.AnnotatedVideo(tmp_path / "out.mp4", 10.0)
    pipeline = StreamPipeline(src, FakeDetector(infer_s=0.01), video, None, report_every=0)
    threading.Timer(0.3, pipeline.stop).start()
    report = pipeline.run()
    video.close()
    assert report.interrupted and 0 < report.written < 200
    assert report.written == report.delivered and report.dropped_in_flight == 0
    assert count_frames(tmp_path / "out.mp4") == report.written


def test_abort_drops_the_frames_in_flight_and_a_failure_is_reported(tmp_path):
    src = ListSource(200)
    video = outputs.AnnotatedVideo(tmp_path / "out.avi", 10.0)
    pipeline = StreamPipeline(
        src, FakeDetector(infer_s=0.02), video, None, report_every=0, queue_size=8
    )
    threading.Timer(0.3, pipeline.abort).start()
    report = pipeline.run()
    video.close()
    assert report.dropped_in_flight > 0
    assert report.written + report.dropped_in_flight == report.delivered
    assert count_frames(tmp_path / "out.avi") == report.written

    _, report = run_stream(ListSource(20), FakeDetector(fail_at=5), tmp_path)
    assert str(report.error) == "network failed"
    assert report.written == 5 and report.written + report.dropped_in_flight == report.delivered
    assert count_frames(tmp_path / "out.avi") == 5


def test_latest_slot():
    slot = LatestSlot()
    with pytest.raises(queue.Empty):
        slot.get_nowait()
    slot.put((["a"], 1))
    slot.put((["b"], 2))
    assert slot.get() == (["b"], 2) and slot.dropped == 1
    slot.put((["c"], 3))
    from gac_jax.streams.pipeline import END

    slot.put(END)  # the end replaces nothing: the last frame is still taken
    assert slot.get() == (["c"], 3) and slot.get() is END and slot.get() is END
    assert slot.dropped == 1


def test_rates():
    rates = StreamRates()
    for i in range(10):
        rates.frame_written(t_read=float(i), t_done=i + 0.1 + 0.01 * i)
    s = rates.summary()
    assert s["frames"] == 10 and s["wall_s"] == pytest.approx(9.19)
    assert s["fps"] == pytest.approx(10 / 9.19)
    assert s["latency_median_ms"] == pytest.approx(np.median(100 + 10 * np.arange(10)))


def test_jsonl_and_partial_files(tmp_path):
    path = tmp_path / "r.jsonl"
    (tmp_path / "r.jsonl").write_text("earlier run\n")
    results = outputs.JsonlResults(path)
    results.write("000007", 7, KittiObjects.empty(), {"n": np.int64(2), "a": np.zeros(2)})
    assert path.read_text() == "earlier run\n"  # kept until the new file is complete
    lines = outputs.partial_path(path).read_text().splitlines()
    assert json.loads(lines[0]) == {"frame": "000007", "index": 7, "n": 2, "a": [0.0, 0.0]}
    results.close()
    assert len(path.read_text().splitlines()) == 1 and not outputs.partial_path(path).exists()
    with pytest.raises(KittiFormatError, match="unknown video container '.gif'"):
        outputs.AnnotatedVideo(tmp_path / "x.gif", 10)


@pytest.mark.parametrize("suffix, size", [(".mp4", (48, 82)), (".avi", (48, 82))])
def test_odd_picture_sizes(tmp_path, suffix, size):
    """Frames of an odd size are padded to an even one (yuv420p needs it; FFmpeg would cut a
    row and column): an MP4 repeats the last row and column, OpenCV's AVI writer adds black."""
    video = outputs.AnnotatedVideo(tmp_path / f"v{suffix}", 10.0)
    for value in (50, 150):
        video.write(np.full((47, 81, 3), value, np.uint8))
    video.close()
    capture = cv2.VideoCapture(str(tmp_path / f"v{suffix}"))
    ok, bgr = capture.read()
    assert ok and bgr.shape[:2] == size and count_frames(tmp_path / f"v{suffix}") == 2
    assert abs(float(bgr[:47, :81].mean()) - 50) < 8  # lossy


def write_video(path, frames, fps=10.0):
    writer = cv2.VideoWriter(
        str(path), cv2.VideoWriter_fourcc(*"MJPG"), fps, frames[0].shape[1::-1]
    )
    for f in frames:
        writer.write(f)
    writer.release()


def test_sources_check_the_calibration_and_the_input(tmp_path):
    sources.quiet_video_backend()
    frames = [np.full((*SIZE, 3), 10 * i, np.uint8) for i in range(20)]
    write_video(tmp_path / "v.avi", frames, fps=7.0)
    src = sources.VideoSource(tmp_path / "v.avi", P2, "calib.txt")
    assert src.fps == 7.0 and src.expected_frames == 20
    got = []
    while (f := src.read()) is not None:
        got.append(f)
    src.check_complete()
    assert [f.frame_id for f in got] == [f"{i:06d}" for i in range(20)]
    np.testing.assert_allclose([f.image.mean() for f in got], [10 * i for i in range(20)], atol=2)

    data = (tmp_path / "v.avi").read_bytes()
    (tmp_path / "cut.avi").write_bytes(data[: int(len(data) * 0.6)])
    src = sources.VideoSource(tmp_path / "cut.avi", P2, "calib.txt")
    while src.read() is not None:
        pass
    with pytest.raises(KittiFormatError, match=r"cut.avi: truncated or damaged at its end"):
        src.check_complete()  # its last frame is cut short (the header's count is not used)
    (tmp_path / "bad.mp4").write_bytes(b"not a video")
    with pytest.raises(KittiFormatError, match="bad.mp4: cannot be opened as a video"):
        sources.VideoSource(tmp_path / "bad.mp4", P2, "calib.txt")
    kitti_p2 = np.array([[721.5, 0, 609.6, 44.9], [0, 721.5, 172.9, 0.2], [0, 0, 1, 0]])
    with pytest.raises(
        KittiFormatError, match=r"calib.txt: does not fit the 80x48 frames.*outside"
    ):
        sources.VideoSource(tmp_path / "v.avi", kitti_p2, "calib.txt")
    off = P2.copy()
    off[0, 2] = 75  # inside the 80-px frame, but far from its centre
    with pytest.raises(KittiFormatError, match="far from the centre"):
        sources.check_calibration(off, SIZE, "calib.txt", "v.avi")
    with pytest.raises(KittiFormatError, match="camera 99: could not be opened"):
        sources.CameraSource(99, P2, "calib.txt")

    seq = tmp_path / "training" / "image_02" / "0003"
    for i in range(3):
        write_png(seq / f"{i:06d}.png", frames[i][..., ::-1])
    with pytest.raises(KittiFormatError, match="no calibration found"):
        sources.SequenceSource(seq)
    calib = tmp_path / "training" / "calib" / "0003.txt"
    calib.parent.mkdir(parents=True)
    calib.write_text("P2: " + " ".join(str(v) for v in P2.ravel()) + "\n")
    plane = tmp_path / "training" / "planes" / "0003" / "000001.txt"
    plane.parent.mkdir(parents=True)
    plane.write_text("0 -1 0 1.5\n")
    src = sources.SequenceSource(seq)
    got = [src.read() for _ in range(4)]
    assert [f.frame_id for f in got[:3]] == ["000000", "000001", "000002"] and got[3] is None
    assert got[0].plane is None and got[2].plane is None
    np.testing.assert_allclose(got[1].plane, [0, -1, 0, 1.5])
    write_png(seq / "000003.png", np.zeros((50, 80, 3), np.uint8))
    src = sources.SequenceSource(seq)
    with pytest.raises(KittiFormatError, match="000003.png: frame is 80x50 but the first"):
        for _ in range(4):
            src.read()


class StartupSource(ListSource):
    """A source whose frames were all read 5 s before the stream started (a video's first
    frame is decoded when it opens, before the model loads)."""

    def read(self):
        frame = super().read()
        if frame is not None:
            frame.t_read -= 5.0
        return frame


class FailingResults(outputs.KittiResults):
    def __init__(self, folder, fail_at: int):
        super().__init__(folder)
        self.fail_at = fail_at

    def write(self, frame_id, index, objects, record):
        if self.frames == self.fail_at:
            raise OSError(28, "No space left on device", str(self.folder / f"{frame_id}.txt"))
        super().write(frame_id, index, objects, record)


def test_rates_start_with_the_stream_and_a_failed_result_cuts_its_picture(tmp_path):
    """Latency counts from the stream's start for frames read during start-up; a results
    write that fails ends the stream as a write error, and the MP4 holds exactly the frames
    with result files."""
    video = outputs.AnnotatedVideo(tmp_path / "out.mp4", 10.0)
    results = FailingResults(tmp_path / "data", fail_at=4)
    pipeline = StreamPipeline(StartupSource(10), FakeDetector(), video, results, report_every=0)
    report = pipeline.run()
    assert report.rates["latency_p95_ms"] < 4000  # not the 5 s before the start
    assert isinstance(report.write_error, OSError) and report.error is report.write_error
    assert report.written == 4 and not report.interrupted
    assert video.close(complete=False) == tmp_path / "out.incomplete.mp4"
    assert count_frames(tmp_path / "out.incomplete.mp4") == 4
    assert len(list((tmp_path / "data").glob("*.txt"))) == 4
