"""Region reads and writes of local Zarr v3 arrays, chunk by chunk, without zarr's event loop.

Why: the mosaic writer reads and writes a band (four arrays, about five chunks each) for
every 256 px of motion, and its pyramid writes back about 100 chunks per demo scan.
Through zarr 3.1 a chunk costs about 1 ms of CPU, of which encoding is 0.16 ms: the rest is
the asynchronous machinery (a coroutine per chunk, a thread hop per codec call, a round
trip of the event loop per call). Measured on the 2-core VM (``bench/bench_pyramid.py``
and the mosaic stage replayed alone; figures in the README).

What: an array in a local store (a folder), with the regular chunk grid, the default chunk
key encoding and the codecs ``bytes`` (little endian) followed by at most one ``blosc`` or
``zstd`` compressor (what :func:`sffscan.stages.mosaic.mosaic_codecs` makes). Each chunk's
file is encoded and decoded with numcodecs (the library zarr's own codecs call), configured
from the codec's own metadata, so the files are the ones zarr writes (a test compares them
byte for byte), and written as zarr's local store writes them: to a temporary file in the
same folder, then renamed over the chunk (a reader never sees half a chunk). A chunk whose
every element equals the fill value is deleted rather than written (zarr's default,
``write_empty_chunks = False``). Any other array goes through zarr itself.
"""

from __future__ import annotations

import asyncio
import os
import uuid
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import zarr

__all__ = ["read_many", "write_many", "direct_plan"]

Slices = tuple[slice, slice]

_SHUFFLE = {"noshuffle": 0, "shuffle": 1, "bitshuffle": 2}


@dataclass(frozen=True)
class _Plan:
    """How the chunks of one array are found, encoded and decoded."""

    folder: Path  # the array's folder
    chunks: tuple[int, int]
    dtype: np.dtype
    fill: Any
    codec: Any  # a numcodecs codec, or None (no compressor)

    def path(self, arr: zarr.Array, key: tuple[int, int]) -> Path:
        return self.folder / arr.metadata.encode_chunk_key(key)


def _compressor(config: dict[str, Any]) -> Any:
    """The numcodecs codec of a zarr ``blosc`` or ``zstd`` codec's metadata, or raise
    KeyError (anything else)."""
    name, cfg = config["name"], config.get("configuration", {})
    if name == "blosc":
        from numcodecs import Blosc

        return Blosc(cname=cfg["cname"], clevel=cfg["clevel"], shuffle=_SHUFFLE[cfg["shuffle"]],
                     blocksize=cfg.get("blocksize", 0), typesize=cfg.get("typesize"))
    if name == "zstd":
        from numcodecs import Zstd

        return Zstd(level=cfg["level"], checksum=cfg.get("checksum", False))
    raise KeyError(name)


def direct_plan(arr: zarr.Array) -> _Plan | None:
    """How to read and write ``arr``'s chunks directly, or None where zarr must (another
    store, grid, key encoding, byte order or codec; a 1-D or 3-D array)."""
    from zarr.core.chunk_grids import RegularChunkGrid
    from zarr.core.chunk_key_encodings import DefaultChunkKeyEncoding
    from zarr.core.metadata import ArrayV3Metadata
    from zarr.storage import LocalStore

    meta = arr.metadata
    store = arr.store_path.store
    if (not isinstance(meta, ArrayV3Metadata) or not isinstance(store, LocalStore)
            or not isinstance(meta.chunk_grid, RegularChunkGrid)
            or len(arr.shape) != 2 or arr.dtype.byteorder == ">"
            or not isinstance(meta.chunk_key_encoding, DefaultChunkKeyEncoding)
            or meta.chunk_key_encoding.separator != "/"):
        return None
    codecs = [c.to_dict() for c in meta.codecs]
    if not codecs or codecs[0] != {"name": "bytes", "configuration": {"endian": "little"}}:
        return None
    if len(codecs) > 2:
        return None
    try:
        codec = _compressor(codecs[1]) if len(codecs) == 2 else None  # type: ignore[arg-type]
    except KeyError:
        return None
    chunks = tuple(int(c) for c in arr.chunks)
    return _Plan(Path(store.root) / arr.store_path.path, (chunks[0], chunks[1]),
                 np.dtype(arr.dtype), arr.fill_value, codec)


def _load(plan: _Plan, path: Path) -> np.ndarray | None:
    """A chunk's values (a new array), or None where no file is stored."""
    try:
        raw = path.read_bytes()
    except FileNotFoundError:
        return None
    data = plan.codec.decode(raw) if plan.codec is not None else raw
    return np.frombuffer(data, plan.dtype).reshape(plan.chunks).copy()


def _is_fill(plan: _Plan, data: np.ndarray) -> bool:
    fill = plan.fill
    if isinstance(fill, float | np.floating) and np.isnan(fill):
        return bool(np.isnan(data).all())
    return bool((data == fill).all())


def _store(plan: _Plan, path: Path, data: np.ndarray) -> None:
    """Write a whole chunk atomically, or delete it if it holds only the fill value."""
    if _is_fill(plan, data):
        path.unlink(missing_ok=True)
        return
    raw = np.ascontiguousarray(data, plan.dtype).tobytes()
    if plan.codec is not None:
        raw = plan.codec.encode(raw)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_suffix(f".{uuid.uuid4().hex}.partial")  # as zarr's local store names it
    try:
        with open(tmp, "wb") as fh:
            fh.write(raw)
        os.replace(tmp, path)
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise


def _overlaps(plan: _Plan, shape: tuple[int, ...], sel: Slices):  # noqa: ANN202
    """(chunk key, slice of the chunk, slice of the region, whole) for every chunk under
    ``sel``; ``whole``: the region covers all of the chunk that lies inside the array."""
    (r0, r1, _), (c0, c1, _) = sel[0].indices(shape[0]), sel[1].indices(shape[1])
    ch, cw = plan.chunks
    for i in range(r0 // ch, -(-r1 // ch)):
        a0, a1 = max(r0, i * ch), min(r1, (i + 1) * ch)
        for j in range(c0 // cw, -(-c1 // cw)):
            b0, b1 = max(c0, j * cw), min(c1, (j + 1) * cw)
            whole = (a0 == i * ch and a1 == min((i + 1) * ch, shape[0])
                     and b0 == j * cw and b1 == min((j + 1) * cw, shape[1]))
            yield ((i, j), (slice(a0 - i * ch, a1 - i * ch), slice(b0 - j * cw, b1 - j * cw)),
                   (slice(a0 - r0, a1 - r0), slice(b0 - c0, b1 - c0)), whole)


def _region_shape(shape: tuple[int, ...], sel: Slices) -> tuple[int, int]:
    (r0, r1, _), (c0, c1, _) = sel[0].indices(shape[0]), sel[1].indices(shape[1])
    return max(0, r1 - r0), max(0, c1 - c0)


def read_many(items: Sequence[tuple[zarr.Array, Slices]]) -> list[np.ndarray]:
    """Several array regions (step-1 slices), each a new array: directly where
    :func:`direct_plan` allows, the others in one round trip of zarr's event loop."""
    out: list[np.ndarray | None] = []
    rest: list[tuple[int, zarr.Array, Slices]] = []
    for n, (arr, sel) in enumerate(items):
        plan = direct_plan(arr)
        if plan is None:
            out.append(None)
            rest.append((n, arr, sel))
            continue
        region = np.empty(_region_shape(arr.shape, sel), plan.dtype)
        for key, inner, part, _ in _overlaps(plan, arr.shape, sel):
            chunk = _load(plan, plan.path(arr, key))
            region[part] = plan.fill if chunk is None else chunk[inner]
        out.append(region)
    if rest:
        from zarr.core.sync import sync

        async def run() -> list[Any]:
            return list(await asyncio.gather(*(a.async_array.getitem(s) for _, a, s in rest)))

        for (n, _, _), value in zip(rest, sync(run()), strict=True):
            out[n] = np.asarray(value)
    return [v for v in out if v is not None]


def write_many(items: Sequence[tuple[zarr.Array, Slices, np.ndarray]]) -> None:
    """Write several array regions (step-1 slices; a chunk partly under a region is read,
    patched and written whole): directly where :func:`direct_plan` allows, the others in one
    round trip of zarr's event loop."""
    rest = []
    for arr, sel, value in items:
        plan = direct_plan(arr)
        if plan is None:
            rest.append((arr, sel, value))
            continue
        value = np.asarray(value)
        if value.shape != _region_shape(arr.shape, sel):
            raise ValueError(f"{plan.folder}: a region of {_region_shape(arr.shape, sel)} "
                             f"cannot take values of shape {value.shape}")
        for key, inner, part, whole in _overlaps(plan, arr.shape, sel):
            path = plan.path(arr, key)
            chunk = None if whole else _load(plan, path)
            if chunk is None:
                chunk = np.full(plan.chunks, plan.fill, plan.dtype)
            chunk[inner] = value[part]
            _store(plan, path, chunk)
    if rest:
        from zarr.core.sync import sync

        async def run() -> None:
            await asyncio.gather(*(a.async_array.setitem(s, v) for a, s, v in rest))

        sync(run())
