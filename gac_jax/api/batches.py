"""How the API's ``infer`` stages batch prepared images: fixed-size chunks, the last padded."""

from __future__ import annotations

from collections.abc import Iterator, Sequence

from gac_jax.api.inputs import InputError


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
