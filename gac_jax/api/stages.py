"""The three stages every API model is made of, and how ``infer`` batches.

A model (:class:`~gac_jax.api.Detector3D`, :class:`~gac_jax.api.DepthPredictor`) defines
``prepare(image, P2, plane) -> prepared`` (host, thread-safe), ``infer([prepared, ...]) ->
raw`` (the network, serialised) and ``finish(raw, [prepared, ...]) -> [result, ...]`` (host,
thread-safe); :class:`StagedModel` gives it ``predict`` and ``predict_batch`` on top.
"""

from __future__ import annotations

import abc
from collections.abc import Iterator, Sequence
from typing import Any

import numpy as np

from gac_jax.api.inputs import InputError, prepare_batch


def checked_prepared(prepared: Sequence, kind: type, made_by: str) -> list:
    """``prepared`` as a list, or :class:`InputError` (``prepared``) when it is empty or holds
    anything but ``kind`` (what ``made_by`` returns)."""
    prepared = list(prepared)
    if not prepared or not all(isinstance(p, kind) for p in prepared):
        raise InputError("prepared", f"expected a non-empty list of {made_by} results")
    return prepared


def padded_chunks(items: list, batch_size: int) -> Iterator[tuple[list, int]]:
    """``(chunk, n)``: consecutive chunks of ``batch_size`` items, the last one padded by
    repeating its last item (one compiled batch shape), with ``n`` its real items."""
    for start in range(0, len(items), batch_size):
        part = items[start : start + batch_size]
        yield part + [part[-1]] * (batch_size - len(part)), len(part)


class StagedModel(abc.ABC):
    """``predict`` and ``predict_batch`` of a model with ``prepare`` / ``infer`` / ``finish``."""

    batch_size: int = 1
    input_size: tuple[int, int]
    min_image_rows: int

    def warmup(self) -> float:
        """Runs a black image of the network's input size through all three stages once (the
        jax runtime compiles here instead of in the first real call); returns the seconds."""
        import time

        h, w = self.input_size
        image = np.zeros((self.min_image_rows - 1 + h, w, 3), np.uint8)
        P2 = np.array([[w, 0.0, w / 2, 0.0], [0.0, w, h / 2, 0.0], [0.0, 0.0, 1.0, 0.0]])
        t0 = time.perf_counter()
        self.predict(image, P2)
        return time.perf_counter() - t0

    def predict(self, image: np.ndarray, P2: Any, plane: Any = None):
        """The result of one image (Detector3D: :class:`~gac_jax.api.Detections`;
        DepthPredictor: (H, W) float32 depth in metres at the image's size).

        Args:
          image: (H, W, 3) uint8 RGB, any size.
          P2: (3, 4) projection of ``image`` (camera frame x right, y down, z forward).
          plane: (4,) ground plane ``a x + b y + c z + d = 0`` with a unit normal pointing up
            (``d``: camera height), or None: the config's level camera
            (``model.gac.camera_height``).

        Raises:
          InputError: naming ``image``, ``P2`` or ``plane``.
        """
        prepared = [self.prepare(image, P2, plane)]
        return self.finish(self.infer(prepared), prepared)[0]

    def predict_batch(
        self, images: Sequence[np.ndarray], P2s: Sequence[Any], planes: Sequence[Any] | None = None
    ) -> list:
        """:meth:`predict` of several images (any sizes; ``planes`` None: no plane for any),
        run through the network in chunks of ``batch_size``; one result per image, the same as
        :meth:`predict` image by image. Errors name the item: ``images[3]: ...``."""
        prepared = prepare_batch(self.prepare, images, P2s, planes)
        return self.finish(self.infer(prepared), prepared) if prepared else []

    @abc.abstractmethod
    def prepare(self, image: np.ndarray, P2: Any, plane: Any = None):
        """One image checked and transformed for the network (host; thread-safe)."""

    @abc.abstractmethod
    def infer(self, prepared: Sequence):
        """The network on prepared images (calls serialised)."""

    @abc.abstractmethod
    def finish(self, raw, prepared: Sequence) -> list:
        """One result per prepared image from ``raw`` (host; thread-safe)."""

    def _describe(self) -> str:
        h, w = self.input_size
        return f"input {h}x{w}; {self.runtime} {self.precision}, batch {self.batch_size}"
