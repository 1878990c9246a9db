"""Reading a recording's per-frame metadata and repairing what is damaged
(:mod:`sffscan.pipeline.formats.recording`): :func:`read_frame_metadata`, the step of
:func:`~sffscan.pipeline.formats.recording_reader.open_recording` that reads the per-frame
arrays chunk by chunk, bounds them by the chunk files present, marks the entries of lost
or corrupt chunks and rebuilds what it can from the header copies beside the frames
(version 2)."""

from __future__ import annotations

from typing import Any

import numpy as np
import zarr
from sffscan.pipeline.formats.recording import (
    BASE_COLUMNS,
    GROW,
    HEADER_COLUMNS,
    PER_FRAME,
    RecordingAttrs,
    RecordingReport,
    _array,
    _chunk_keys,
    _first_indexes,
    _stored,
)
from sffscan.pipeline.formats.recording_checks import stored_extent


def read_frame_metadata(group: zarr.Group, frames: zarr.Array, arrays: dict[str, zarr.Array],
                        frame_keys: set[str], n: int, *, attrs: RecordingAttrs, where: str,
                        report: RecordingReport) -> tuple[int, dict[str, np.ndarray], set[int]]:
    """Read the per-frame metadata of the first ``n`` entries (``arrays``: the per-frame
    arrays present; ``frame_keys``: the chunk keys of ``frames``), repairing what it can;
    returns ``n`` (cut to the entries the chunk files present hold), the metadata by name
    and the indexes of the entries whose metadata is unreadable (``bad``). Notes go to
    ``report``."""
    bad: set[int] = set()
    meta: dict[str, np.ndarray] = {}
    v2 = attrs.format_version >= 2
    headers = _array(group, "headers", where) if v2 else None
    # the lengths the zarr.json files claim, against the chunk files present: entries past
    # the last stored chunk of every array hold no data (and 2**40 of them no memory)
    present = max([stored_extent(_first_indexes(frames, frame_keys), _stored(frames)[0])]
                  + [stored_extent(_first_indexes(a, _chunk_keys(a)), _stored(a)[0])
                     for a in arrays.values()])
    if n > present:
        if n > present + GROW:  # more than the recorder's growth step: not its doing
            report.claimed_entries = n
            report.notes.append(f"the arrays' zarr.json claim {n} entries, the chunk files "
                                f"present hold at most {present}: entries beyond are not "
                                "read (metadata edited or chunks lost?)")
        n = present
    extent = 0
    if v2:
        # the frames written whole: a frame chunk and its header copy (written after it); a
        # frame chunk alone is a write a crash cut short, not a lost frame
        stored = _first_indexes(frames, frame_keys)
        if headers is None:
            report.notes.append("no 'headers' array: a lost metadata chunk cannot be rebuilt")
        else:
            stored &= _first_indexes(headers, _chunk_keys(headers))
        extent = min(n, max(stored) + 1) if stored else 0
    for name, (dtype, fill, _) in PER_FRAME.items():
        if name in arrays:
            meta[name] = _read_per_frame(arrays[name], n, fill, bad, extent=extent,
                                         required=PER_FRAME[name][2]).astype(dtype)
        else:
            meta[name] = np.full(n, 0 if name == "pass_index" else fill, dtype)
    if headers is not None:
        rebuilt = _rebuild_from_headers(headers, meta, bad, extent)
        if rebuilt:
            report.notes.append(f"{rebuilt} entries rebuilt from the header copies beside "
                                "their frames (metadata lost, corrupt or not yet flushed)")
    return n, meta, bad


def _same_fill(arr: zarr.Array, fill: Any) -> bool:
    a = arr.fill_value
    if isinstance(fill, float) and np.isnan(fill):
        return bool(np.isnan(a)) if np.asarray(a).dtype.kind == "f" else False
    return bool(a == fill)


def _read_per_frame(arr: zarr.Array, n: int, fill: Any, bad: set[int], *,
                    required: bool, extent: int = 0) -> np.ndarray:
    """Read entries [0, n) chunk by chunk; entries of an unreadable chunk become ``fill``
    and their indexes go to ``bad``.

    Zarr stores no chunk equal to the array's fill value and reads an absent chunk as that
    value, so a lost chunk cannot be told from one that was all fill. For a required array
    whose fill value is not the documented one (-1, "not written"), an absent chunk would
    read as real metadata (focus level 0, time stamp 0): its entries go to ``bad`` instead.
    Version 2 writes every chunk, so any chunk absent below ``extent`` (the frames
    written) was lost: its entries go to ``bad``.
    """
    chunk = _stored(arr)[0]
    keys = _chunk_keys(arr)
    enc = arr.metadata.encode_chunk_key  # type: ignore[union-attr]
    doubt_absent = required and not _same_fill(arr, fill)
    out = np.full(n, fill, dtype=arr.dtype)
    for a in range(0, n, chunk):
        b = min(n, a + chunk)
        if doubt_absent and enc((a // chunk,)) not in keys:
            bad.update(range(a, b))
            continue
        if a < extent and enc((a // chunk,)) not in keys:
            bad.update(range(a, min(b, extent)))
            continue
        try:
            out[a:b] = np.asarray(arr[a:b])
        except Exception:  # noqa: BLE001 - any decode failure is a corrupt chunk
            bad.update(range(a, b))
    return out


def _rebuild_from_headers(headers: zarr.Array, meta: dict[str, np.ndarray], bad: set[int],
                          extent: int) -> int:
    """Fill the entries below ``extent`` whose metadata is unreadable or unwritten from the
    copy of the header beside their frame (version 2); returns how many were rebuilt. A
    version-4 copy whose stored index is not its own (a swapped or copied header chunk) is
    not used."""
    if headers.ndim != 2 or headers.shape[1] not in (BASE_COLUMNS, len(HEADER_COLUMNS)):
        return 0
    written = ((meta["frame_id"] >= 0) & (meta["timestamp_ns"] >= 0)
               & (meta["focus_index"] >= 0) & (meta["pass_index"] >= 0))
    todo = sorted({i for i in bad if i < extent}
                  | {int(i) for i in np.flatnonzero(~written[:extent])})
    if not todo:
        return 0
    keys = _chunk_keys(headers)
    enc = headers.metadata.encode_chunk_key  # type: ignore[union-attr]
    rebuilt = 0
    for i in todo:
        if i >= headers.shape[0] or enc((i, 0)) not in keys:
            continue
        try:
            row = np.asarray(headers[i], dtype=np.int64)
        except Exception:  # noqa: BLE001 - a corrupt header chunk: the entry stays lost
            continue
        if row[0] < 0 or row[1] < 0 or row[2] < 0 or row[5] < 0:
            continue
        if row.size > BASE_COLUMNS and row[BASE_COLUMNS] != i:
            continue
        pos = row[3:5].view(np.float64)
        values = dict(zip(HEADER_COLUMNS[:BASE_COLUMNS],
                          (row[0], row[1], row[2], pos[0], pos[1], row[5]), strict=True))
        if not all(_fits(meta[name].dtype, v) for name, v in values.items()):
            continue  # a value the metadata's column cannot hold: the entry stays lost
        for name, value in values.items():
            meta[name][i] = value
        bad.discard(i)
        rebuilt += 1
    return rebuilt


def _fits(dtype: np.dtype, value: np.integer | np.floating) -> bool:
    """Whether a header copy's ``value`` fits a metadata column of ``dtype`` (an int32
    column cannot take a 64-bit copy's 3e9, whatever corrupted it)."""
    if np.issubdtype(dtype, np.integer):
        info = np.iinfo(dtype)
        return bool(info.min <= int(value) <= info.max)
    return True
