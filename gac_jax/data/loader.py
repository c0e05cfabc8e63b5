"""Fixed-shape numpy batches from a source + transforms, with grain workers.

Order and randomness are pure functions of ``(seed, epoch, ...)``:

* epoch ``e`` visits the source in ``permutation(seed, e)`` (or in order when
  ``shuffle=False``), cut into *global* batches of ``batch_size * num_shards``;
  shard ``k`` (one per process of a multi-host run) takes rows
  ``[k * batch_size, (k + 1) * batch_size)`` of every global batch, so shards are
  disjoint and together cover the global batch;
* global step ``s`` is batch ``s % steps_per_epoch`` of epoch
  ``s // steps_per_epoch``, so :meth:`Loader.iterate` can start at any step
  (resume) without reading the data before it;
* each sample gets ``sample['rng'] = np.random.default_rng([seed, epoch, 1, index])``
  for the random transforms, so augmentation does not depend on workers or order.

Detection batch (``M = max_objects``; padding rows have ``gt_mask`` False and
``gt_class`` -1, other fields 0)::

    image (B,H,W,3) f32   P2 (B,3,4) f32   image_transform (B,3,3) f32
    plane (B,4) f32 ground plane (a, b, c, d), camera frame, unit upward normal
    original_size (B,2) i32 (H0, W0)       frame_id (B,) str (host only)
    gt_mask (B,M) bool    gt_class (B,M) i32 index into class_names
    gt_boxes (B,M,4) f32 xyxy              gt_center (B,M,2) f32 projected 3D-box centre
    gt_depth (B,M) f32 homogeneous depth of that centre (z + P2[2,3])
    gt_dims (B,M,3) f32 (h,w,l)  gt_alpha (B,M)  gt_location (B,M,3) bottom centre
    gt_rotation_y (B,M)  gt_truncated (B,M)  gt_occluded (B,M) i32

Depth batch: ``image``, ``P2``, ``plane``, ``depth`` (B,H,W) f32, ``image_transform``,
``original_size``, ``frame_id``.

``plane`` is the sample's (a frame's ``planes/`` file, moved by the transforms) or, for a
frame without one, the level plane ``(0, -1, 0, camera_height)`` of the array converter
(the config's ``model.gac.camera_height``).
"""

from __future__ import annotations

import atexit
import contextlib
import dataclasses
import functools
import gc
import math
import sys
import weakref
from collections.abc import Callable, Iterator, Sequence

import grain
import numpy as np

from gac_jax import geometry
from gac_jax.data.kitti import KittiObjects
from gac_jax.data.worker_lifetime import Owner, grain_worker_init
from gac_jax.geometry import DEFAULT_CAMERA_HEIGHT, level_plane

DETECTION_KEYS = (
    "image",
    "P2",
    "plane",
    "image_transform",
    "original_size",
    "gt_mask",
    "gt_class",
    "gt_boxes",
    "gt_center",
    "gt_depth",
    "gt_dims",
    "gt_alpha",
    "gt_location",
    "gt_rotation_y",
    "gt_truncated",
    "gt_occluded",
    "frame_id",
)
DEPTH_KEYS = ("image", "P2", "plane", "depth", "image_transform", "original_size", "frame_id")


def plane_array(sample: dict, camera_height: float = DEFAULT_CAMERA_HEIGHT) -> np.ndarray:
    """(4,) float32 ground plane of a sample: its ``plane``, else the level one of
    ``camera_height``."""
    plane = sample.get("plane")
    return np.asarray(level_plane(camera_height) if plane is None else plane, np.float32)


def _common_arrays(sample: dict, camera_height: float) -> dict[str, np.ndarray]:
    return {
        "image": np.asarray(sample["image"], np.float32),
        "P2": np.asarray(sample["P2"], np.float32),
        "plane": plane_array(sample, camera_height),
        "image_transform": np.asarray(sample["image_transform"], np.float32),
        "original_size": np.asarray(sample["original_size"], np.int32).reshape(2),
        "frame_id": np.asarray(sample["frame_id"], dtype=str),
    }


def detection_arrays(
    sample: dict,
    class_names: Sequence[str],
    max_objects: int,
    truncate: bool = False,
    camera_height: float = DEFAULT_CAMERA_HEIGHT,
) -> dict[str, np.ndarray]:
    """One sample's detection arrays (the batch contract without the batch axis).

    Objects whose type is not in ``class_names`` (DontCare, other classes) are
    dropped. More than ``max_objects`` remaining objects is a ValueError naming
    the frame and the count, unless ``truncate``: then the ``max_objects``
    nearest (smallest z) are kept, in label order.
    """
    class_names = list(class_names)
    objects = sample.get("objects")
    if objects is None:
        objects = KittiObjects.empty()
    objects = objects.select(np.isin(objects.type, class_names))
    n = len(objects)
    if n > max_objects:
        if not truncate:
            raise ValueError(
                f"frame {sample['frame_id']} (camera {sample.get('camera', 2)}) has {n} objects of "
                f"classes {class_names}, more than max_objects={max_objects}; raise max_objects "
                "or pass truncate=True"
            )
        nearest = np.argsort(objects.location[:, 2], kind="stable")[:max_objects]
        objects = objects.select(np.sort(nearest))
        n = max_objects
    P2 = np.asarray(sample["P2"], np.float64)
    centre = objects.location - np.stack(
        [np.zeros(n), objects.dimensions[:, 0] / 2.0, np.zeros(n)], axis=1
    )
    uv, w = geometry.project(centre, P2)

    def pad(x, dtype, fill=0):
        x = np.asarray(x)
        out = np.full((max_objects,) + x.shape[1:], fill, dtype)
        out[:n] = x
        return out

    out = _common_arrays(sample, camera_height)
    out.update(
        gt_mask=pad(np.ones(n, bool), bool, False),
        gt_class=pad([class_names.index(t) for t in objects.type], np.int32, -1),
        gt_boxes=pad(objects.bbox.reshape(n, 4), np.float32),
        gt_center=pad(uv.reshape(n, 2), np.float32),
        gt_depth=pad(w.reshape(n), np.float32),
        gt_dims=pad(objects.dimensions.reshape(n, 3), np.float32),
        gt_alpha=pad(objects.alpha, np.float32),
        gt_location=pad(objects.location.reshape(n, 3), np.float32),
        gt_rotation_y=pad(objects.rotation_y, np.float32),
        gt_truncated=pad(objects.truncated, np.float32),
        gt_occluded=pad(objects.occluded, np.int32),
    )
    return out


def depth_arrays(
    sample: dict, camera_height: float = DEFAULT_CAMERA_HEIGHT
) -> dict[str, np.ndarray]:
    """One sample's depth-batch arrays (``sample`` must have ``'depth'``)."""
    if "depth" not in sample:
        raise ValueError(f"frame {sample['frame_id']} has no depth map")
    out = _common_arrays(sample, camera_height)
    out["depth"] = np.asarray(sample["depth"], np.float32)
    return out


@dataclasses.dataclass(frozen=True)
class DetectionArrays:
    """Picklable ``sample -> arrays`` for :class:`Loader` (see :func:`detection_arrays`)."""

    class_names: tuple[str, ...]
    max_objects: int
    truncate: bool = False
    camera_height: float = DEFAULT_CAMERA_HEIGHT  # the plane of frames without one

    def __call__(self, sample: dict) -> dict[str, np.ndarray]:
        return detection_arrays(
            sample, self.class_names, self.max_objects, self.truncate, self.camera_height
        )


@dataclasses.dataclass(frozen=True)
class DepthArrays:
    """Picklable ``sample -> arrays`` for :class:`Loader` (see :func:`depth_arrays`)."""

    camera_height: float = DEFAULT_CAMERA_HEIGHT  # the plane of frames without one

    def __call__(self, sample: dict) -> dict[str, np.ndarray]:
        return depth_arrays(sample, self.camera_height)


def collate(items: Sequence[dict[str, np.ndarray]]) -> dict[str, np.ndarray]:
    """Stacks per-sample arrays along a new batch axis (shapes must agree)."""
    out = {}
    for key in items[0]:
        shapes = {np.shape(it[key]) for it in items}
        if len(shapes) > 1:
            raise ValueError(
                f"samples of one batch have different {key!r} shapes {sorted(shapes)} "
                f"(frames {[str(it.get('frame_id')) for it in items]}); add Resize / "
                "CropOrPadWidth transforms to get a fixed size"
            )
        out[key] = np.stack([it[key] for it in items])
    return out


def _closing(iterator, shared_memory: bool = False) -> Iterator[dict]:
    """Yields from a grain iterator and closes it (stopping its workers) when done or dropped;
    ``shared_memory``: then releases the shared-memory batches it still held."""
    try:
        yield from iterator
    finally:
        iterator.close()
        if shared_memory:
            _release_dropped_batches()


def _own_arrays(batch: dict) -> dict:
    """Copies a worker batch out of grain's shared memory and unlinks each block at once.

    grain 0.2.x unlinks a block when its array is garbage-collected, on a background thread
    whose queue is dropped at exit, and the arrays of the last batches sit in reference
    cycles of grain's iterators that only the cyclic GC frees: a block still linked when
    the program ends makes Python's resource_tracker warn "There appear to be N leaked
    shared_memory objects". Unlinked here (the mapping stays valid until the array is
    closed), it is gone from the tracker whatever happens to the array later.
    """
    out = {}
    for key, value in batch.items():
        out[key] = np.array(value)
        if getattr(value, "_unlink_on_del", False):  # a grain SharedMemoryArray we own
            value._unlink_on_del = False
            value.shm.unlink()
    return out


_OPEN_WORKER_ITERATORS: weakref.WeakSet = weakref.WeakSet()


def _close_at_exit(batches: Iterator[dict]) -> None:
    """Closes ``batches`` at interpreter exit if its owner did not (an exception left the loop):
    before the modules are torn down, so that grain can still stop its workers and unlink the
    shared memory they hold (later, its clean-up fails and the blocks leak)."""
    _register_exit_hook()
    _OPEN_WORKER_ITERATORS.add(batches)


@functools.cache
def _register_exit_hook() -> None:
    atexit.register(_close_open_worker_iterators)


def _close_open_worker_iterators() -> None:
    for batches in list(_OPEN_WORKER_ITERATORS):
        with contextlib.suppress(ValueError):  # still running in another thread
            batches.close()


def _release_dropped_batches() -> None:
    """Frees the shared memory of worker batches that never reached :func:`_own_arrays`
    (buffered when the iterator was closed early): collects grain's reference cycles, then
    waits for grain's one-thread unlink queue to run what that queued (FIFO)."""
    gc.collect()
    from grain._src.python.ipc.shared_memory_array import SharedMemoryArray

    pool = getattr(SharedMemoryArray, "_del_thread_pool", None)
    if pool is not None:
        with contextlib.suppress(ValueError):  # the pool no longer runs (interpreter exit)
            pool.apply(int)


def _grain_worker_flags_workaround() -> None:
    """Lets grain 0.2.x read its worker-profiling flag in programs that never parse absl flags.

    grain's ``mp_prefetch`` reads ``--grain_enable_multiprocess_worker_profiling``
    and absl raises UnparsedFlagAccessError when flags were not parsed (grain
    issue #1355, fixed upstream after 0.2.18). Marking just that flag as
    present keeps its default (False) and touches no other flag.
    """
    from absl import flags

    name = "grain_enable_multiprocess_worker_profiling"
    if not flags.FLAGS.is_parsed() and name in flags.FLAGS:
        flags.FLAGS[name].present = True


class Loader:
    """Deterministic, shardable, resumable batches (see module docstring).

    Args:
      source: random-access source (``len``, ``[i] -> sample``); must be picklable
        when ``worker_count > 0``.
      transform: ``sample -> sample`` (e.g. :class:`gac_jax.data.transforms.Compose`).
      to_arrays: ``sample -> dict of arrays`` (:class:`DetectionArrays`, :class:`DepthArrays`).
      batch_size: per-shard (per-process) batch size.
      seed: base seed of the order and of the per-sample generators.
      shuffle: permute each epoch (else source order).
      drop_remainder: drop the last incomplete global batch of an epoch. When
        False the last step of an epoch is a smaller batch (split over shards as
        evenly as possible; a shard whose part is empty yields nothing for it).
      shard_index, num_shards: this process's shard of every global batch.
      num_epochs: stop after this many epochs (None: never).
      worker_count: grain worker processes (0: load in this process).
      num_threads: threads per process loading batches concurrently (0: none).
      prefetch: batches buffered per process (and per worker).
    """

    def __init__(
        self,
        source,
        transform: Callable[[dict], dict] | None,
        to_arrays: Callable[[dict], dict[str, np.ndarray]],
        *,
        batch_size: int,
        seed: int = 0,
        shuffle: bool = True,
        drop_remainder: bool = True,
        shard_index: int = 0,
        num_shards: int = 1,
        num_epochs: int | None = None,
        worker_count: int = 0,
        num_threads: int = 0,
        prefetch: int = 2,
    ):
        if batch_size < 1:
            raise ValueError(f"batch_size must be >= 1, got {batch_size}")
        if not 0 <= shard_index < num_shards:
            raise ValueError(f"need 0 <= shard_index < num_shards, got {shard_index}, {num_shards}")
        self.source = source
        self.transform = transform
        self.to_arrays = to_arrays
        self.batch_size = batch_size
        self.seed = int(seed)
        self.shuffle = shuffle
        self.drop_remainder = drop_remainder
        self.shard_index = shard_index
        self.num_shards = num_shards
        self.num_epochs = num_epochs
        self.worker_count = worker_count
        self.num_threads = num_threads
        self.prefetch = prefetch
        self.num_records = len(source)
        g = self.global_batch_size
        if drop_remainder:
            self.steps_per_epoch = self.num_records // g
        else:
            self.steps_per_epoch = math.ceil(self.num_records / g)
        if self.steps_per_epoch == 0:
            raise ValueError(
                f"source has {self.num_records} records, fewer than one global batch of {g}"
            )
        self._order: tuple[int, np.ndarray] | None = None

    @property
    def global_batch_size(self) -> int:
        return self.batch_size * self.num_shards

    def epoch_order(self, epoch: int) -> np.ndarray:
        """(num_records,) source indices in the order epoch ``epoch`` visits them."""
        cached = self._order
        if cached is not None and cached[0] == epoch:
            return cached[1]
        if self.shuffle:
            order = np.random.default_rng([self.seed, epoch, 0]).permutation(self.num_records)
        else:
            order = np.arange(self.num_records)
        self._order = (epoch, order)
        return order

    def step_indices(self, step: int) -> tuple[int, np.ndarray]:
        """(epoch, this shard's source indices) of global step ``step``."""
        epoch, j = divmod(int(step), self.steps_per_epoch)
        g = self.global_batch_size
        rows = self.epoch_order(epoch)[j * g : (j + 1) * g]
        if len(rows) == g:
            part = rows[
                self.shard_index * self.batch_size : (self.shard_index + 1) * self.batch_size
            ]
        else:
            part = np.array_split(rows, self.num_shards)[self.shard_index]
        return epoch, part

    def load_sample(self, index: int, epoch: int) -> dict[str, np.ndarray]:
        """Source record ``index`` through the transforms, as arrays (as seen in ``epoch``)."""
        sample = dict(self.source[int(index)])
        sample["rng"] = np.random.default_rng([self.seed, epoch, 1, int(index)])
        if self.transform is not None:
            sample = self.transform(sample)
        sample.pop("rng", None)
        return self.to_arrays(sample)

    def load_batch(self, step: int) -> dict[str, np.ndarray] | None:
        """This shard's batch of global step ``step`` (None when its part is empty)."""
        epoch, indices = self.step_indices(step)
        if not len(indices):
            return None
        return collate([self.load_sample(i, epoch) for i in indices])

    def _stop_step(self) -> int:
        if self.num_epochs is None:
            return sys.maxsize // 2
        return self.num_epochs * self.steps_per_epoch

    def iterate(self, start_step: int = 0, num_steps: int | None = None) -> Iterator[dict]:
        """Batches of global steps ``start_step, start_step + 1, ...`` (grain pipeline).

        Args:
          start_step: first global step (a resumed run passes its step count).
          num_steps: how many steps (default: until ``num_epochs`` ends, or forever).
        """
        stop = self._stop_step()
        if num_steps is not None:
            stop = min(stop, start_step + num_steps)
        if start_step >= stop:
            return iter(())
        ds = grain.MapDataset.range(start_step, stop).map(self.load_batch)
        read = grain.ReadOptions(
            num_threads=self.num_threads,
            prefetch_buffer_size=max(self.prefetch, self.num_threads) if self.num_threads else 0,
        )
        it_ds = ds.to_iter_dataset(read)
        if self.worker_count > 0:
            _grain_worker_flags_workaround()
            it_ds = it_ds.mp_prefetch(
                grain.MultiprocessingOptions(
                    num_workers=self.worker_count, per_worker_buffer_size=self.prefetch
                ),
                # Workers end when this process dies by any signal (SIGKILL included).
                worker_init_fn=functools.partial(grain_worker_init, owner=Owner.current().token()),
            )
            # Batches arrive as shared-memory arrays; copying them into ordinary
            # arrays lets grain free the shared memory right away.
            it_ds = it_ds.map(_own_arrays)
        if self.worker_count == 0:
            return _closing(iter(it_ds))
        batches = _closing(iter(it_ds), shared_memory=True)
        _close_at_exit(batches)
        return batches

    def epoch(self, epoch: int) -> Iterator[dict]:
        """The batches of one epoch."""
        return self.iterate(epoch * self.steps_per_epoch, self.steps_per_epoch)

    def __iter__(self) -> Iterator[dict]:
        return self.iterate()

    def __len__(self) -> int:
        """Steps per epoch."""
        return self.steps_per_epoch
