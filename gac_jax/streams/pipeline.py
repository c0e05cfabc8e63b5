"""A stream through a detector: reading, the network, post-processing + drawing and writing
overlap on five threads joined by bounded queues.

    read (decode) -> prepare (host transform) -> network -> finish (decode boxes, NMS,
    hill-climbing) + draw -> write (video frame, result file)

Every stage is one thread taking items in order, so frames leave in the order they came. A
file is processed whole; with ``realtime`` (a live camera, or a recording paced as one) the
reader never waits: one-place :class:`LatestSlot` queues before and after the host transform
keep only the newest frame when the detector falls behind (the network always takes the
newest frame there is), and the frames they replaced are counted as dropped.

:meth:`StreamPipeline.stop` (first Ctrl-C) stops reading and lets the frames in flight
finish; :meth:`StreamPipeline.abort` (second Ctrl-C, or a failing stage) drops them. Either
way the caller closes the outputs afterwards, so the video is playable and every finished
frame is written. A failed write of an output (a full disk) ends the stream as an abort does,
with the frames written before it kept (:mod:`gac_jax.streams.outputs`). Always
``delivered == written + dropped_live + dropped_in_flight``.

``detector`` is any object with ``prepare(image, P2, plane)``, ``infer(prepared_list)`` and
``finish(raw, prepared_list) -> detections`` (:class:`gac_jax.api.Detector3D`); a detection
result gives its :class:`~gac_jax.data.kitti.KittiObjects` through ``to_kitti_objects()`` and
its JSON record through ``to_dict()``.
"""

from __future__ import annotations

import dataclasses
import queue
import threading
import time
from collections.abc import Callable

from gac_jax.drawing.detection_pictures import detection_picture
from gac_jax.streams.rates import StreamRates, format_rates
from gac_jax.streams.sources import Frame

END = object()  # the last item of a queue
READ, PREPARE, NETWORK, FINISH, WRITE = range(5)  # the stages, upstream first
STAGE_NAMES = ("read", "prepare", "network", "finish+draw", "write")


class LatestSlot:
    """A one-place queue that never blocks its producer: a ``put`` over an item nobody took
    replaces it, and the frames of the replaced item are counted in :attr:`dropped`. The end
    (``put(END)``) replaces nothing: the last frame is still taken, then ``END`` for good."""

    def __init__(self):
        self._cond = threading.Condition()
        self._item = None
        self._full = False
        self._ended = False
        self.dropped = 0

    def put(self, item) -> None:
        with self._cond:
            if item is END:
                self._ended = True
            else:
                if self._full:
                    self.dropped += len(self._item[0])
                self._item, self._full = item, True
            self._cond.notify()

    def get(self, block: bool = True):
        """The waiting item (``block``: waits for one; else ``queue.Empty`` when none)."""
        with self._cond:
            while block and not (self._full or self._ended):
                self._cond.wait()
            if not self._full:
                if self._ended:
                    return END
                raise queue.Empty
            item, self._item, self._full = self._item, None, False
            return item

    def get_nowait(self):
        return self.get(block=False)


@dataclasses.dataclass
class StreamReport:
    """How a stream ended.

    Attributes:
      delivered: frames the source gave; written: frames whose picture and results were
      written; dropped_live: frames a live source gave while the detector was busy (not
      processed); dropped_in_flight: frames read but dropped by an abort; finished_after_stop:
      frames in flight when reading stopped that were then finished; interrupted: stopped
      before the source ended; rates: :meth:`StreamRates.summary`; error: the first failure
      (a stage's exception, or the source's report of a damaged input), None if none;
      write_error: the failed write of an output that ended the stream (also ``error``), None
      if none; stage_ms: :meth:`StreamPipeline.stage_ms`; damaged: the source's damaged
      frames, skipped (not in ``delivered``; :mod:`gac_jax.streams.damaged_frames`).
    """

    delivered: int
    written: int
    dropped_live: int
    dropped_in_flight: int
    finished_after_stop: int
    interrupted: bool
    rates: dict
    error: BaseException | None = None
    write_error: BaseException | None = None
    stage_ms: dict[str, float] = dataclasses.field(default_factory=dict)
    damaged: int = 0


class StreamPipeline:
    """Runs ``source`` through ``detector`` into ``video`` and ``results`` (see the module doc).

    Args:
      source: a frame source (:mod:`gac_jax.streams.sources`).
      detector: prepare/infer/finish object (module doc).
      video: :class:`~gac_jax.streams.outputs.AnnotatedVideo` or None (no pictures drawn).
      results: per-frame results writer (``write(frame_id, index, objects, record)``) or None.
      realtime: keep only the newest frame when the detector falls behind (live sources).
      batch_size: frames per network call (realtime: what is waiting, up to this).
      queue_size: frames each queue holds between two stages.
      max_frames: stop reading after this many frames (None: at the source's end).
      report_every: seconds between progress lines (``log``); 0: none.
      log: where progress and notes go (one line each).
      track: a tracking stage (:class:`gac_jax.streams.tracking.TrackingStage`) or None: each
        frame's detections become tracks (in frame order) before drawing and writing.
      network_requests: network calls in flight at once (> 1:
        :class:`~gac_jax.streams.async_network.AsyncNetworkStage`; the detector needs
        ``infer_async``).
      on_first_frame: called (in the write stage) once the first frame's picture and results
        are written (``--overwrite`` deletes the earlier results then).
    """

    def __init__(
        self,
        source,
        detector,
        video=None,
        results=None,
        *,
        realtime: bool = False,
        batch_size: int = 1,
        queue_size: int = 1,
        max_frames: int | None = None,
        report_every: float = 5.0,
        log: Callable[[str], None] = print,
        draw: Callable = detection_picture,
        track=None,
        network_requests: int = 1,
        recorder=None,
        on_first_frame: Callable[[], None] | None = None,
    ):
        self.source, self.detector = source, detector
        self.recorder = recorder
        self.video, self.results = video, results
        self.realtime, self.batch_size = realtime, batch_size
        self.max_frames = max_frames
        self.report_every, self.log, self.draw = report_every, log, draw
        self.track = track
        self.rates = StreamRates()
        self.network_requests = network_requests
        self.on_first_frame = on_first_frame
        self._read_q = LatestSlot() if realtime else queue.Queue(queue_size)
        # live: the network takes the newest prepared frame too (an older one is dropped)
        self._prepared_q = LatestSlot() if realtime else queue.Queue(max(queue_size, batch_size))
        self._raw_q = queue.Queue(2)
        self._drawn_q = queue.Queue(queue_size)
        self._stop = threading.Event()
        self._drop_up_to = -1  # stages of this rank or lower drop what they take
        self._lock = threading.Lock()
        self.delivered = 0
        self.written = 0
        self.dropped_in_flight = 0
        self.written_at_stop: int | None = None
        self._source_ended = False
        self.errors: list[BaseException] = []
        self.write_error: BaseException | None = None  # a failed write of an output
        self.t_start = 0.0  # when run() began: latency and rates count from here
        self.busy_s = [0.0] * len(STAGE_NAMES)  # wall seconds each stage worked
        self.cpu_s = [0.0] * len(STAGE_NAMES)  # CPU seconds of each stage's own thread

    # ------------------------------------------------------------------ control

    def stop(self) -> None:
        """Stop reading; the frames in flight are finished and written."""
        if not self._stop.is_set():
            self.written_at_stop = self.written
            self._stop.set()

    def abort(self) -> None:
        """Stop reading and drop the frames in flight (those already drawn are written)."""
        self._drop_from(FINISH)

    def _drop_from(self, rank: int) -> None:
        self.stop()
        with self._lock:
            self._drop_up_to = max(self._drop_up_to, rank)

    def _dropping(self, rank: int) -> bool:
        return rank <= self._drop_up_to

    @property
    def dropped_live(self) -> int:
        """Frames of a live source replaced by newer ones before the network took them."""
        if not self.realtime:
            return 0
        return self._read_q.dropped + self._prepared_q.dropped

    def _fail(self, error: BaseException, rank: int) -> None:
        """A stage failed: what is upstream of it is dropped, what is past it is finished."""
        with self._lock:
            self.errors.append(error)
        self._drop_from(rank)

    def _busy(self, stage: int, t0: tuple[float, float]) -> None:
        """Adds the wall and thread CPU seconds since ``t0`` to ``stage`` (one thread per
        stage: no lock)."""
        self.busy_s[stage] += time.perf_counter() - t0[0]
        self.cpu_s[stage] += time.thread_time() - t0[1]

    def stage_ms(self, cpu: bool = False) -> dict[str, float]:
        """Milliseconds each stage worked per frame (waits excluded; ``read`` includes a
        paced source's waiting for the next frame): the slowest one sets the rate. ``cpu``:
        CPU time of the stage's thread instead (the network's excludes a runtime's own
        worker threads)."""
        read = max(self.delivered, 1)
        done = max(self.written, 1)
        seconds = self.cpu_s if cpu else self.busy_s
        return {
            name: 1e3 * seconds[i] / (read if i <= PREPARE else done)
            for i, name in enumerate(STAGE_NAMES)
        }

    def _drop(self, frames: list[Frame]) -> None:
        with self._lock:
            self.dropped_in_flight += len(frames)

    # ------------------------------------------------------------------ stages

    def _read(self) -> None:
        try:
            while not self._stop.is_set():
                if self.max_frames is not None and self.delivered >= self.max_frames:
                    self._source_ended = True  # as asked: not an interruption
                    break
                t0 = (time.perf_counter(), time.thread_time())
                frame = self.source.read()
                self._busy(READ, t0)
                if frame is None:
                    self._source_ended = True
                    self.source.check_complete()
                    break
                self.delivered += 1
                self._read_q.put(([frame], None))
        except Exception as e:  # a damaged input: what was read is still finished
            with self._lock:
                self.errors.append(e)
        finally:
            self._read_q.put(END)

    def _stage(self, rank: int, get, put, work) -> None:
        """Takes items ``([frames], payload)`` until the end; ``work(item)`` -> next item."""
        try:
            while (item := get()) is not END:
                if self._dropping(rank):
                    self._drop(item[0])
                    continue
                try:
                    t0 = (time.perf_counter(), time.thread_time())
                    result = work(item)
                    self._busy(rank, t0)
                    put(result)
                except Exception as e:
                    self._drop(item[0])
                    self._fail(e, rank)
        finally:
            put(END)

    def _prepare(self, item):
        (frame,), _ = item
        return [frame], self.detector.prepare(frame.image, frame.P2, frame.plane)

    def _network(self) -> None:
        done = False
        try:
            while not done:
                first = self._prepared_q.get()
                if first is END:
                    break
                batch = [first]
                while len(batch) < self.batch_size:
                    try:
                        item = (
                            self._prepared_q.get_nowait()
                            if self.realtime
                            else (self._prepared_q.get())
                        )
                    except queue.Empty:
                        break
                    if item is END:
                        done = True
                        break
                    batch.append(item)
                frames = [f for frames, _ in batch for f in frames]
                if self._dropping(NETWORK):
                    self._drop(frames)
                    continue
                prepared = [p for _, p in batch]
                try:
                    t0 = (time.perf_counter(), time.thread_time())
                    raw = self.detector.infer(prepared)
                    self._busy(NETWORK, t0)
                except Exception as e:
                    self._drop(frames)
                    self._fail(e, NETWORK)
                    continue
                self._raw_q.put((frames, (prepared, raw)))
        finally:
            self._raw_q.put(END)

    def _finish(self, item):
        frames, (prepared, raw) = item
        detections = self.detector.finish(raw, prepared)
        out = []
        for frame, det in zip(frames, detections, strict=True):
            if self.track is not None:  # tracking hook: detections -> tracks
                det = self.track.update(frame, det)
            objects = det.to_kitti_objects()
            picture = None
            if self.video is not None and self.track is not None:
                picture = self.track.draw(frame, det)
            elif self.video is not None:
                picture = self.draw(frame.image, frame.P2, objects)
            out.append((det, objects, picture))
        return frames, out

    def _write(self) -> None:
        needs_record = getattr(self.results, "needs_record", True)
        failed = False
        while (item := self._drawn_q.get()) is not END:
            frames, drawn = item
            if failed:  # nothing more can be written
                self._drop(frames)
                continue
            for k, (frame, (det, objects, picture)) in enumerate(zip(frames, drawn, strict=True)):
                t0 = (time.perf_counter(), time.thread_time())
                try:
                    self._write_frame(frame, det, objects, picture, needs_record)
                except Exception as e:
                    self._drop(frames[k:])
                    self.write_error = e
                    self._fail(e, WRITE)
                    failed = True
                    break
                self.rates.frame_written(max(frame.t_read, self.t_start))
                self._busy(WRITE, t0)
                with self._lock:
                    self.written += 1
                if self.written == 1 and self.on_first_frame is not None:
                    try:
                        self.on_first_frame()
                    except Exception as e:  # the frames are written; only tell
                        self.log(f"warning: {e}")

    def _write_frame(self, frame: Frame, det, objects, picture, needs_record: bool) -> None:
        """The frame's picture, then its results; when the results fail the picture is cut
        off again where the container allows, so the video holds the frames with results."""
        if self.video is not None:
            self.video.write(picture, frame.time)
        record = {}
        if needs_record and (self.results is not None or self.recorder is not None):
            when = {} if frame.time is None else {"time": round(frame.time, 6)}
            record = {**when, **det.to_dict()}
        if self.results is not None:
            try:
                self.results.write(frame.frame_id, frame.index, objects, record)
            except BaseException:
                if self.video is not None:
                    self.video.drop_last()
                raise
        if self.recorder is not None:
            self.recorder.write_frame(frame, det, record)

    # ------------------------------------------------------------------ run

    def progress_line(self) -> str:
        window = self.rates.summary(last_s=self.report_every)
        line = (
            f"{self.written} frames written: {format_rates(window)} (last {self.report_every:g} s)"
        )
        if self.realtime:
            line += f", {self.dropped_live} dropped"
        return line

    def _network_stage(self) -> Callable[[], None]:
        if self.network_requests == 1:
            return self._network
        from gac_jax.streams.async_network import AsyncNetworkStage

        return AsyncNetworkStage(self, self.network_requests, END, NETWORK).run

    def run(self) -> StreamReport:
        """Runs the stream to its end (or :meth:`stop` / :meth:`abort`); returns the report.
        The outputs are not closed here."""
        stages = [
            ("read", self._read, ()),
            (
                "prepare",
                self._stage,
                (PREPARE, self._read_q.get, self._prepared_q.put, self._prepare),
            ),
            ("network", self._network_stage(), ()),
            ("finish", self._stage, (FINISH, self._raw_q.get, self._drawn_q.put, self._finish)),
            ("write", self._write, ()),
        ]
        threads = [
            threading.Thread(target=fn, args=args, name=f"gac-stream-{name}", daemon=True)
            for name, fn, args in stages
        ]
        self.t_start = time.perf_counter()  # frames read during start-up wait from here
        for t in threads:
            t.start()
        next_report = time.perf_counter() + self.report_every
        while threads[-1].is_alive():
            threads[-1].join(timeout=0.1)
            if self.report_every and time.perf_counter() >= next_report:
                next_report += self.report_every
                self.log(self.progress_line())
        for t in threads:
            t.join()
        interrupted = self._stop.is_set()
        dropped_live = self.dropped_live
        finished = 0 if self.written_at_stop is None else self.written - self.written_at_stop
        return StreamReport(
            delivered=self.delivered,
            written=self.written,
            dropped_live=dropped_live,
            dropped_in_flight=self.dropped_in_flight,
            finished_after_stop=finished,
            interrupted=interrupted and not self._source_ended and self.write_error is None,
            rates=self.rates.summary(),
            error=self.errors[0] if self.errors else None,
            write_error=self.write_error,
            stage_ms=self.stage_ms(),
            damaged=getattr(getattr(self.source, "damaged", None), "count", 0),
        )
