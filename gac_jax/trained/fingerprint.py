"""The identity of trained weights: a sha256 over every array of a variables tree.

An export (``export.json``), an accuracy-guard verdict (``guard.json``) and a resumable result
folder (``run.json``) record :func:`weights_sha256` of the weights they were made from, so a
model retrained to the same step, or a checkpoint replaced in place, is never taken for the
one they describe: the step number names a checkpoint, the hash names its contents.

The hash covers, for every leaf in sorted path order, the path (``params/backbone/conv1/
kernel``), dtype, shape and the little-endian bytes of the array; it does not depend on
where the weights live (host or device), on the dict order, or on the compute dtype the
model runs in (parameters are kept in float32 whatever that is).
"""

from __future__ import annotations

import hashlib
from collections.abc import Iterator, Mapping
from typing import Any

import numpy as np


def _leaves(tree: Any, path: tuple[str, ...] = ()) -> Iterator[tuple[str, np.ndarray]]:
    if isinstance(tree, Mapping):
        for key in sorted(tree, key=str):
            yield from _leaves(tree[key], (*path, str(key)))
    elif isinstance(tree, list | tuple):
        for i, item in enumerate(tree):
            yield from _leaves(item, (*path, str(i)))
    elif tree is not None:
        yield "/".join(path), np.asarray(tree)


def weights_sha256(variables: Mapping[str, Any]) -> str:
    """Hex sha256 of a (nested dict) variables tree, e.g. ``{'params', 'batch_stats'}`` of
    numpy or jax arrays; equal trees give equal hashes, any changed value, shape, dtype or
    name another."""
    digest = hashlib.sha256()
    for name, array in _leaves(variables):
        array = np.ascontiguousarray(array)
        little = array.dtype.newbyteorder("<") if array.dtype.byteorder == ">" else array.dtype
        digest.update(f"{name}\0{little.str}\0{array.shape}\0".encode())
        digest.update(array.astype(little, copy=False).tobytes())
    return digest.hexdigest()


def short(sha256: str | None) -> str:
    """The first 12 hex digits, for messages (``None`` -> ``'none'``)."""
    return sha256[:12] if sha256 else "none"
