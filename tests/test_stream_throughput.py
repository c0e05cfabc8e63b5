"""A stream at the network's speed: calls in flight give the synchronous detections, the
thread budget is what the libraries run with inside the stream, ``--no-video`` writes results
only, ``--video-scale`` a smaller annotated frame.

The tiny trained detector on a 5-frame generated clip, per exported runtime installed.
"""

from __future__ import annotations

import importlib.util
import shutil
import threading
import time

import cv2
import numpy as np
import pytest

from gac_jax.api import Detector3D
from gac_jax.cli import predict
from gac_jax.data.kitti import KittiObjects
from gac_jax.streams import sources, thread_budget
from gac_jax.streams.pipeline import StreamPipeline

RUNTIMES = [r for r in ("onnxruntime", "openvino") if importlib.util.find_spec(r) is not None]


@pytest.fixture(scope="module")
def workdir(tiny_detect3d_workdir, tmp_path_factory):
    """A copy of the tiny run (the runtimes export into it)."""
    wd = tmp_path_factory.mktemp("throughput") / "wd"
    shutil.copytree(tiny_detect3d_workdir, wd, ignore=shutil.ignore_patterns("eval", "results"))
    return wd


@pytest.fixture(scope="module")
def clip(tmp_path_factory):
    """``--clip``: a 1-sequence, 5-frame generated set in a temporary cache."""
    from gac_jax.cli import stream_start

    with pytest.MonkeyPatch.context() as mp:
        mp.setenv("GAC_JAX_CACHE", str(tmp_path_factory.mktemp("cache")))
        mp.setattr(stream_start, "CLIP_SEQUENCES", 1)
        mp.setattr(stream_start, "CLIP_FRAMES", 5)
        return stream_start.clip_sequence(0)


def stream(workdir, clip, out, capsys, *extra) -> str:
    argv = ["--workdir", workdir, "--sequence", clip, "--out", out, "--jsonl", *extra]
    code = predict.main([str(a) for a in argv])
    stdout, err = capsys.readouterr()
    assert code == 0, err
    return stdout


@pytest.mark.parametrize("runtime", RUNTIMES)
def test_two_calls_in_flight_give_the_synchronous_detections(
    workdir, clip, tmp_path, capsys, monkeypatch, runtime
):
    """``--network-requests 2`` (OpenVINO: two streams of one thread each on two cores) writes
    the same detections, frame by frame, as one call at a time; inside the stream OpenCV and
    BLAS run one thread per stage and the compiled network has the budget's threads and
    streams."""
    seen = []
    finish = Detector3D.finish

    def finish_and_look(self, raw, prepared):
        network = getattr(self._predict, "network", None)
        seen.append((threading.current_thread().name, thread_budget.thread_settings(network)))
        return finish(self, raw, prepared)

    monkeypatch.setattr(Detector3D, "finish", finish_and_look)
    common = ["--runtime", runtime, "--threads", 2, "--no-video"]
    sync = stream(workdir, clip, tmp_path / "sync", capsys, *common)
    seen_sync = [s for name, s in seen if name == "gac-stream-finish"]
    seen.clear()
    out = stream(workdir, clip, tmp_path / "async", capsys, *common, "--network-requests", 2)
    seen_async = [s for name, s in seen if name == "gac-stream-finish"]
    a = (tmp_path / "sync" / "detections.jsonl").read_text().splitlines()
    b = (tmp_path / "async" / "detections.jsonl").read_text().splitlines()
    assert len(a) == 5 and a == b
    assert sum('"score"' in line for line in a) >= 5  # detections to compare (threshold 0)
    assert "threads: network 2" in sync and "in 2 streams" in out
    assert len(seen_sync) == len(seen_async) == 5
    for settings in seen_sync + seen_async:
        assert settings["opencv"] == 1
        assert settings["blas"] in (None, [1])
    if runtime == "openvino":
        assert {(s["openvino_threads"], s["openvino_streams"]) for s in seen_sync} == {(2, 1)}
        assert {(s["openvino_threads"], s["openvino_streams"]) for s in seen_async} == {(2, 2)}
    # --no-video: the results only
    assert sorted(p.name for p in (tmp_path / "async").iterdir()) == ["detections.jsonl"]


def test_the_video_decoder_runs_in_the_budget(workdir, clip, tmp_path, capsys, monkeypatch):
    """A video stream decodes with the budget's one FFmpeg thread (read inside the stream's
    read stage); the parameter reaches FFmpeg (2 asked: 2 reported)."""
    images = sorted(clip.glob("*.png"))[:3]
    first = cv2.imread(str(images[0]))
    h, w = first.shape[:2]
    video = tmp_path / "clip.mp4"
    writer = cv2.VideoWriter(str(video), cv2.VideoWriter_fourcc(*"mp4v"), 10.0, (w, h))
    for path in images:
        writer.write(cv2.imread(str(path)))
    writer.release()
    calib = clip.parents[1] / "calib" / f"{clip.name}.txt"
    P2 = sources.load_projection(calib)
    asked = sources.VideoSource(video, P2, str(calib), decode_threads=2)
    assert thread_budget.thread_settings(source=asked)["decoder"] == 2
    asked.close()
    seen = []
    read = sources.VideoSource.read

    def read_and_look(self):
        seen.append((threading.current_thread().name, thread_budget.thread_settings(source=self)))
        return read(self)

    monkeypatch.setattr(sources.VideoSource, "read", read_and_look)
    argv = ["--workdir", workdir, "--video", video, "--calib", calib, "--out", tmp_path / "o"]
    code = predict.main([str(a) for a in [*argv, "--no-video"]])
    out, err = capsys.readouterr()
    assert code == 0, err
    assert "decoder 1 per stage" in out
    in_stream = [s for name, s in seen if name == "gac-stream-read"]
    assert len(in_stream) == 4  # 3 frames and the end
    assert {s["decoder"] for s in in_stream} == {1}


def test_a_smaller_annotated_video(workdir, clip, tmp_path, capsys):
    """``--video-scale 0.5``: the annotated frames are half the clip's size (camera view and
    the bird's-eye view of that height)."""
    stream(workdir, clip, tmp_path / "half", capsys, "--video-scale", 0.5, "--max-frames", 2)
    full = cv2.imread(str(next(clip.glob("*.png"))))
    capture = cv2.VideoCapture(str(tmp_path / "half" / "annotated.mp4"))
    ok, frame = capture.read()
    assert ok and capture.get(cv2.CAP_PROP_FRAME_COUNT) == 2
    h = round(full.shape[0] / 2)
    assert frame.shape[0] in (h, h + 1)  # the encoder pads an odd height
    assert round(full.shape[1] / 2) < frame.shape[1] < full.shape[1]


class SlowAsyncDetector:
    """prepare/infer_async/finish: each call takes ``infer_s`` on a thread of its own; counts
    the calls in flight. A result is the frame's index (its image value)."""

    def __init__(self, infer_s: float, fail_at: int | None = None):
        self.infer_s, self.fail_at = infer_s, fail_at
        self.running = self.most = self.calls = 0
        self._lock = threading.Lock()

    def prepare(self, image, P2, plane):
        return int(image[0, 0, 0])

    def infer_async(self, prepared):
        from concurrent.futures import ThreadPoolExecutor

        with self._lock:
            self.calls += 1
            if self.fail_at is not None and self.calls > self.fail_at:
                raise RuntimeError("network failed")
            self.running += 1
            self.most = max(self.most, self.running)

        def work():
            time.sleep(self.infer_s)
            with self._lock:
                self.running -= 1
            return list(prepared)

        return ThreadPoolExecutor(1).submit(work)

    def finish(self, raw, prepared):
        return [FakeResult(v) for v in raw]


class FakeResult:
    def __init__(self, value):
        self.value = value

    def to_kitti_objects(self):
        return KittiObjects.from_arrays(type=["Car"], score=[self.value / 100])

    def to_dict(self):
        return {"value": self.value}


class Frames:
    live = False

    def __init__(self, n, delay=0.0):
        self.n, self.i, self.delay = n, 0, delay

    def read(self):
        if self.i >= self.n:
            return None
        time.sleep(self.delay)
        i, self.i = self.i, self.i + 1
        image = np.full((8, 8, 3), i, np.uint8)
        return sources.Frame(i, f"{i:06d}", image, np.eye(3, 4), None, time.perf_counter())

    def check_complete(self):
        pass


class Collect:
    needs_record = True

    def __init__(self):
        self.values = []

    def write(self, frame_id, index, objects, record):
        self.values.append((index, record["value"]))


@pytest.mark.parametrize("requests", [2, 3])
def test_calls_in_flight_keep_the_frames_in_order(requests):
    detector, results = SlowAsyncDetector(0.02), Collect()
    pipeline = StreamPipeline(
        Frames(12), detector, None, results, report_every=0, network_requests=requests
    )
    report = pipeline.run()
    assert report.error is None and report.written == 12
    assert results.values == [(i, i) for i in range(12)]
    assert detector.most == requests  # never more calls in flight than asked, and that many


def test_calls_in_flight_live_and_failing():
    """``realtime``: the newest frames are taken, written + dropped == delivered and the last
    frame is written; a failing call is reported and the stream ends."""
    detector, results = SlowAsyncDetector(0.05), Collect()
    pipeline = StreamPipeline(
        Frames(30, delay=0.005),
        detector,
        None,
        results,
        realtime=True,
        report_every=0,
        network_requests=2,
    )
    report = pipeline.run()
    assert report.error is None and report.dropped_live > 0
    assert report.written + report.dropped_live == report.delivered == 30
    assert results.values[-1] == (29, 29)
    assert [i for i, _ in results.values] == sorted(i for i, _ in results.values)
    failing = StreamPipeline(
        Frames(10),
        SlowAsyncDetector(0.0, fail_at=3),
        None,
        Collect(),
        report_every=0,
        network_requests=2,
    )
    report = failing.run()
    assert isinstance(report.error, RuntimeError) and report.written <= 3
    assert report.written + report.dropped_in_flight <= report.delivered
