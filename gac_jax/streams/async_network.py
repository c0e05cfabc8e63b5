"""The network stage of a stream with several calls in flight.

:class:`AsyncNetworkStage` takes the place of the one-call-at-a-time network stage of
:class:`~gac_jax.streams.pipeline.StreamPipeline` when it runs with ``network_requests`` > 1:
it starts a call (:meth:`gac_jax.api.Detector3D.infer_async`) as soon as a prepared frame is
there and fewer than ``requests`` calls are running, and hands the oldest call's result on
when it cannot start another. So OpenVINO computes frame N+1 (its throughput hint: one stream
per request, the threads shared out) while this thread decodes frame N and the later stages
draw and write it. Results leave in the order the frames came, and are the same values as the
synchronous stage's.

With ``realtime`` the prepared frames come from a one-place slot: a call always starts on the
newest frame there is, as in the synchronous stage.
"""

from __future__ import annotations

import collections
import queue
import time


class AsyncNetworkStage:
    """Runs the network stage of ``pipeline`` (its queues, drop and failure rules; ``end``
    its queues' end marker, ``rank`` the stage's) with up to ``requests`` calls of
    ``pipeline.detector.infer_async`` in flight.

    Wall time (``busy_s``) counts the time this thread spends starting calls and waiting for
    results; CPU time (``cpu_s``) this thread's own (starting, decoding), as the synchronous
    stage's."""

    def __init__(self, pipeline, requests: int, end: object, rank: int):
        if requests < 1:
            raise ValueError(f"requests must be >= 1, got {requests}")
        self.pipeline, self.requests = pipeline, requests
        self.end, self.rank = end, rank  # the pipeline's end marker and the stage's rank
        self._in_flight: collections.deque = collections.deque()  # (frames, prepared, pending)

    def _take(self, block: bool):
        """A batch of items (up to ``batch_size``), the end marker, or None when none waits."""
        p = self.pipeline
        try:
            first = p._prepared_q.get(block=block)
        except queue.Empty:
            return None
        if first is self.end:
            return self.end
        batch = [first]
        while len(batch) < p.batch_size:
            try:
                item = p._prepared_q.get(block=not p.realtime)
            except queue.Empty:
                break
            if item is self.end:
                self._ended = True
                break
            batch.append(item)
        return batch

    def _start(self, batch) -> None:
        p = self.pipeline
        frames = [f for frames, _ in batch for f in frames]
        if p._dropping(self.rank):
            p._drop(frames)
            return
        prepared = [x for _, x in batch]
        t0 = (time.perf_counter(), time.thread_time())
        try:
            pending = p.detector.infer_async(prepared)
        except Exception as e:
            p._drop(frames)
            p._fail(e, self.rank)
            return
        p._busy(self.rank, t0)
        self._in_flight.append((frames, prepared, pending))

    def _hand_on_oldest(self) -> None:
        p = self.pipeline
        frames, prepared, pending = self._in_flight.popleft()
        t0 = (time.perf_counter(), time.thread_time())
        try:
            raw = pending.result()
        except Exception as e:
            p._drop(frames)
            p._fail(e, self.rank)
            return
        p._busy(self.rank, t0)
        if p._dropping(self.rank):
            p._drop(frames)
            return
        p._raw_q.put((frames, (prepared, raw)))

    def run(self) -> None:
        self._ended = False
        try:
            while not self._ended:
                if len(self._in_flight) < self.requests:
                    # wait for a frame only when no call is running
                    batch = self._take(block=not self._in_flight)
                    if batch is self.end:
                        break
                    if batch is not None:
                        self._start(batch)
                        continue
                self._hand_on_oldest()
            while self._in_flight:
                self._hand_on_oldest()
        finally:
            self.pipeline._raw_q.put(self.end)
