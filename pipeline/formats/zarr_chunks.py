"""Region reads and writes of local Zarr v3 arrays, chunk by chunk, without zarr's event loop.

Why: through zarr 3.1 a chunk costs about 1 ms of CPU beyond its encoding: the
asynchronous machinery (a coroutine per chunk, a thread hop per codec call, a round trip of
the event loop per call). The mosaic writer reads and writes a band (four arrays, about five
chunks each) for every 256 px of motion and its pyramid about 100 chunks per demo scan; the
recorder writes a 2.6 MB frame chunk and a header chunk per frame, where zarr's machinery
cost more CPU than the compression itself. Measured on the 2-core VM
(``bench/bench_pyramid.py``, ``bench/bench_recorder.py``; figures in the README).

What: an N-dimensional array in a local store (a folder), with the regular chunk grid, the
default chunk key encoding with either separator (``c/i/j/…`` or ``c.i.j.…``, the keys made
by the array's own encoding), C order, a numeric data type and the codecs ``bytes`` (little
endian) followed by at most one ``blosc`` or ``zstd`` compressor and at
most one ``crc32c`` after it (what :func:`sffscan.pipeline.mosaic.layout.mosaic_codecs` and the
recorder's :func:`sffscan.pipeline.formats.recording_writer.frame_codecs` make). Which
arrays qualify is
read from zarr's public API only (the array's metadata document, as the Zarr v3
specification defines ``zarr.json``, its :class:`zarr.storage.LocalStore`, order and
config), so a zarr release that reorganises its internals sends the arrays through zarr
rather than breaking the reads and writes. Each chunk's file is encoded
and decoded with numcodecs (the library zarr's own codecs call), configured from the codec's
own metadata; ``crc32c`` appends the CRC-32C of the encoded bytes (google_crc32c, as zarr's
``Crc32cCodec``), little endian, and a chunk whose checksum does not match raises
:class:`ChunkChecksumError` naming its file. So the files are the ones zarr writes (a test
compares them byte for byte), written as zarr's local store writes them: to a temporary
file in the same folder, then renamed over the chunk (a reader never sees half a chunk).
Unless the array's config says ``write_empty_chunks``, a chunk whose every element equals
the fill value is deleted rather than written (zarr's default). A chunk that a region covers
whole is encoded from the region's values without reading the stored one. Any other array
goes through zarr itself (its public ``array[selection]`` reads and writes).

Selections: a tuple of step-1 slices and integers (an integer drops its axis, as in numpy);
missing trailing axes are whole.
"""

from __future__ import annotations

import itertools
import os
import uuid
from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import zarr
from sffscan.pipeline.formats.unbuffered import UnbufferedFiles
from zarr.storage import LocalStore

__all__ = ["ChunkChecksumError", "Plans", "direct_plan", "read_into", "read_many",
           "write_many"]

Selection = Any  # a slice, an int, or a tuple of them

_SHUFFLE = {"noshuffle": 0, "shuffle": 1, "bitshuffle": 2}


class ChunkChecksumError(ValueError):
    """A chunk's stored CRC-32C does not match its bytes (the message names the file)."""


@dataclass(frozen=True)
class _Plan:
    """How the chunks of one array are found, encoded and decoded."""

    folder: Path  # the array's folder
    chunks: tuple[int, ...]
    dtype: np.dtype
    fill: Any
    codec: Any  # a numcodecs codec, or None (no compressor)
    crc: bool  # a crc32c codec after the compressor
    write_empty: bool  # the array's config: store chunks equal to the fill value too
    encode: Callable[[tuple[int, ...]], str]  # the array's own chunk key encoding

    def path(self, key: tuple[int, ...]) -> Path:
        return self.folder / self.encode(key)


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
    store, zarr format, grid, key encoding, order, data type, byte order or codec).

    Read from zarr's public API only: the array's metadata document (``zarr.json``, as the
    Zarr v3 specification defines it), its store (:class:`zarr.storage.LocalStore`), path,
    order and config. Anything this cannot read the way it expects (a zarr release that
    moved one of them) makes the array go through zarr itself."""
    try:
        store, path, order = arr.store, arr.path, arr.order
        write_empty = arr.async_array.config.write_empty_chunks
        doc: dict[str, Any] = dict(arr.metadata.to_dict())
    except AttributeError:
        return None
    if (not isinstance(store, LocalStore) or doc.get("zarr_format") != 3 or order != "C"
            or doc.get("storage_transformers") or not isinstance(write_empty, bool)):
        return None
    dtype = np.dtype(arr.dtype)
    shape = tuple(int(n) for n in arr.shape)
    grid, keys = doc.get("chunk_grid"), doc.get("chunk_key_encoding")
    if (not isinstance(grid, dict) or grid.get("name") != "regular" or len(shape) == 0
            or dtype.kind not in "biuf" or dtype.byteorder == ">"
            or not isinstance(keys, dict) or keys.get("name") != "default"):
        return None
    chunks = tuple(int(c) for c in (grid.get("configuration") or {}).get("chunk_shape", ()))
    separator = (keys.get("configuration") or {}).get("separator", "/")
    if len(chunks) != len(shape) or separator not in ("/", "."):
        return None
    codecs = [dict(c) for c in doc.get("codecs") or ()]
    if not codecs or codecs[0].get("name") != "bytes":
        return None
    endian = (codecs[0].get("configuration") or {}).get("endian")
    if not (endian == "little" or (endian is None and dtype.itemsize == 1)):
        return None
    rest = codecs[1:]
    crc = bool(rest) and rest[-1].get("name") == "crc32c" and not rest[-1].get("configuration")
    if crc:
        rest = rest[:-1]
    if len(rest) > 1:
        return None
    try:
        codec = _compressor(rest[0]) if rest else None
    except KeyError:
        return None
    return _Plan(Path(store.root) / path, chunks, dtype, arr.fill_value, codec, crc,
                 write_empty, _key_encoding(separator))


class Plans:
    """The :func:`direct_plan` of each array an owner reads or writes again and again (a
    mosaic writer's arrays, a recording's), worked out once per array.

    Why: :func:`direct_plan` reads the array's whole metadata document through zarr, about
    0.2 ms of CPU; the mosaic writer asked for it for every array of every read and write
    (``bench/bench_mosaic.py``). A plan does not depend on the array's shape, so an array
    resized in place keeps its plan; an array object not seen before gets a new one. The
    cache holds its arrays (so their ids stay theirs) for as long as its owner lives.
    """

    def __init__(self) -> None:
        self._plans: dict[int, tuple[zarr.Array, _Plan | None]] = {}

    def of(self, arr: zarr.Array) -> _Plan | None:
        """``direct_plan(arr)``, from the cache where ``arr`` was seen before."""
        hit = self._plans.get(id(arr))
        if hit is None or hit[0] is not arr:
            hit = (arr, direct_plan(arr))
            self._plans[id(arr)] = hit
        return hit[1]


def _key_encoding(separator: str) -> Callable[[tuple[int, ...]], str]:
    """The Zarr v3 ``default`` chunk key encoding: ``c`` and the chunk's indices, joined by
    ``separator``."""

    def encode(key: tuple[int, ...]) -> str:
        return separator.join(["c", *map(str, key)])

    return encode


def _crc32c(data: Any) -> bytes:
    import google_crc32c

    # google_crc32c's C function takes bytes or a numpy array, not a memoryview (no copy)
    return int(google_crc32c.value(np.frombuffer(data, np.uint8))).to_bytes(4, "little")


def _stored_bytes(plan: _Plan, path: Path) -> Any:
    """A chunk file's encoded bytes, its CRC-32C checked and cut off; None where no file is
    stored."""
    try:
        raw: Any = path.read_bytes()
    except FileNotFoundError:
        return None
    if plan.crc:
        view = memoryview(raw)
        if len(raw) < 4 or _crc32c(view[:-4]) != bytes(view[-4:]):
            raise ChunkChecksumError(f"{path}: stored and computed CRC-32C do not match "
                                     "(the chunk is corrupt)")
        raw = view[:-4]
    return raw


def _load(plan: _Plan, path: Path, *, copy: bool = True) -> np.ndarray | None:
    """A chunk's values (``copy``: a new, writable array; else possibly a read-only view of
    the decoded bytes), or None where no file is stored."""
    raw = _stored_bytes(plan, path)
    if raw is None:
        return None
    if plan.codec is not None:
        raw = plan.codec.decode(raw)
    data = np.frombuffer(raw, plan.dtype)
    if data.size != int(np.prod(plan.chunks)):
        raise ValueError(f"{path}: {data.size} elements decoded, a chunk of {plan.chunks} "
                         f"holds {int(np.prod(plan.chunks))}")
    data = data.reshape(plan.chunks)
    return data.copy() if copy else data


def _load_into(plan: _Plan, path: Path, into: np.ndarray) -> bool:
    """Decode a whole chunk straight into ``into`` (C-contiguous, the chunk's shape and
    dtype); False where no file is stored (``into`` untouched)."""
    raw = _stored_bytes(plan, path)
    if raw is None:
        return False
    if plan.codec is None:
        if len(raw) != into.nbytes:
            raise ValueError(f"{path}: {len(raw)} bytes stored, a chunk of {plan.chunks} "
                             f"holds {into.nbytes}")
        np.copyto(into, np.frombuffer(raw, plan.dtype).reshape(plan.chunks))
        return True
    try:
        got = plan.codec.decode(raw, out=into)
    except Exception as exc:  # noqa: BLE001 - a codec's own error (truncated, corrupt)
        raise ValueError(f"{path}: cannot be decoded ({type(exc).__name__}: {exc})") from exc
    if np.asarray(got).nbytes != into.nbytes:
        raise ValueError(f"{path}: decoded to {np.asarray(got).nbytes} bytes, a chunk of "
                         f"{plan.chunks} holds {into.nbytes}")
    return True


def _is_fill(plan: _Plan, data: np.ndarray) -> bool:
    fill = plan.fill
    if isinstance(fill, float | np.floating) and np.isnan(fill):
        return bool(np.isnan(data).all())
    return bool((data == fill).all())


def _store(plan: _Plan, path: Path, data: np.ndarray,
           unbuffered: UnbufferedFiles | None = None) -> None:
    """Write a whole chunk atomically, or delete it if it holds only the fill value (unless
    the array writes empty chunks); past the page cache where ``unbuffered`` takes it."""
    if not plan.write_empty and _is_fill(plan, data):
        path.unlink(missing_ok=True)
        return
    raw: Any = np.ascontiguousarray(data, plan.dtype).data.cast("B")
    if plan.codec is not None:
        raw = plan.codec.encode(raw)
    tail = _crc32c(raw) if plan.crc else b""
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_suffix(f".{uuid.uuid4().hex}.partial")  # as zarr's local store names it
    try:
        if unbuffered is None or not unbuffered.write(tmp, (raw, tail)):
            with open(tmp, "wb") as fh:
                fh.write(raw)
                if tail:
                    fh.write(tail)
        os.replace(tmp, path)
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise


@dataclass(frozen=True)
class _Region:
    """A selection resolved against an array's shape."""

    start: tuple[int, ...]
    stop: tuple[int, ...]
    dropped: tuple[int, ...]  # axes indexed by an integer

    @property
    def shape(self) -> tuple[int, ...]:
        return tuple(b - a for a, b in zip(self.start, self.stop, strict=True))

    @property
    def value_shape(self) -> tuple[int, ...]:
        return tuple(n for k, n in enumerate(self.shape) if k not in self.dropped)


def _region(where: object, shape: tuple[int, ...], sel: Selection) -> _Region:
    items = sel if isinstance(sel, tuple) else (sel,)
    if len(items) > len(shape):
        raise IndexError(f"{where}: {len(items)} indices for an array of {len(shape)} axes")
    start, stop, dropped = [], [], []
    for axis, n in enumerate(shape):
        s = items[axis] if axis < len(items) else slice(None)
        if isinstance(s, slice):
            a, b, step = s.indices(n)
            if step != 1:
                raise IndexError(f"{where}: axis {axis}: only step-1 slices, not {s}")
            start.append(a)
            stop.append(max(a, b))
        elif isinstance(s, int | np.integer):
            k = int(s) + n if s < 0 else int(s)
            if not 0 <= k < n:
                raise IndexError(f"{where}: index {int(s)} is out of bounds for axis {axis} "
                                 f"of length {n}")
            start.append(k)
            stop.append(k + 1)
            dropped.append(axis)
        else:
            raise IndexError(f"{where}: axis {axis}: a slice or an integer, not {s!r}")
    return _Region(tuple(start), tuple(stop), tuple(dropped))


def _overlaps(plan: _Plan, shape: tuple[int, ...], reg: _Region) -> Iterator[
        tuple[tuple[int, ...], tuple[slice, ...], tuple[slice, ...], bool]]:
    """(chunk key, slice of the chunk, slice of the region, whole) for every chunk under the
    region; ``whole``: the region covers all of the chunk that lies inside the array."""
    per_axis = []
    for r0, r1, c, n in zip(reg.start, reg.stop, plan.chunks, shape, strict=True):
        axis = []
        for i in range(r0 // c, -(-r1 // c)):
            a0, a1 = max(r0, i * c), min(r1, (i + 1) * c)
            axis.append((i, slice(a0 - i * c, a1 - i * c), slice(a0 - r0, a1 - r0),
                         a0 == i * c and a1 == min((i + 1) * c, n)))
        per_axis.append(axis)
    for combo in itertools.product(*per_axis):
        yield (tuple(x[0] for x in combo), tuple(x[1] for x in combo),
               tuple(x[2] for x in combo), all(x[3] for x in combo))


def read_many(items: Sequence[tuple[zarr.Array, Selection]], *,
              plans: Plans | None = None) -> list[np.ndarray]:
    """Several array regions, each a new array: directly where :func:`direct_plan` allows,
    the others through zarr (``array[selection]``). A stored chunk whose checksum does
    not match raises :class:`ChunkChecksumError`. ``plans``: the caller's cache of the
    arrays' plans (:class:`Plans`; worked out afresh without one)."""
    out: list[np.ndarray | None] = []
    rest: list[tuple[int, zarr.Array, Selection]] = []
    for n, (arr, sel) in enumerate(items):
        plan = direct_plan(arr) if plans is None else plans.of(arr)
        if plan is None:
            out.append(None)
            rest.append((n, arr, sel))
            continue
        reg = _region(plan.folder, arr.shape, sel)
        region = np.empty(reg.shape, plan.dtype)
        for key, inner, part, _ in _overlaps(plan, arr.shape, reg):
            chunk = _load(plan, plan.path(key), copy=False)  # copied into the region
            region[part] = plan.fill if chunk is None else chunk[inner]
        out.append(region.reshape(reg.value_shape))
    for n, arr, sel in rest:
        out[n] = np.asarray(arr[sel])
    return [v for v in out if v is not None]


def read_into(arr: zarr.Array, sel: Selection, out: np.ndarray, *,
              plans: Plans | None = None) -> np.ndarray:
    """One array region, written into ``out`` (the region's shape and the array's dtype);
    returns ``out``. Where the region is one whole chunk and ``out`` is C-contiguous, the
    chunk is decoded straight into it (no intermediate array: a replayed frame decoded into
    the process placement's frame ring, :class:`sffscan.stages.frame_source.FrameBuffers`);
    otherwise as :func:`read_many`, then copied. Errors as :func:`read_many`'s."""
    plan = direct_plan(arr) if plans is None else plans.of(arr)
    if plan is None:
        out[...] = np.asarray(arr[sel])
        return out
    reg = _region(plan.folder, arr.shape, sel)
    if out.shape != reg.value_shape or out.dtype != plan.dtype:
        raise ValueError(f"{plan.folder}: a region of {reg.value_shape} {plan.dtype} cannot be "
                         f"read into {out.shape} {out.dtype}")
    parts = list(_overlaps(plan, arr.shape, reg))
    if (len(parts) == 1 and parts[0][3] and reg.shape == plan.chunks
            and out.flags.c_contiguous):
        key = parts[0][0]
        if not _load_into(plan, plan.path(key), out.reshape(plan.chunks)):
            out[...] = plan.fill
        return out
    np.copyto(out, read_many([(arr, sel)], plans=plans)[0])
    return out


def write_many(items: Sequence[tuple[zarr.Array, Selection, np.ndarray]], *,
               plans: Plans | None = None, unbuffered: UnbufferedFiles | None = None) -> None:
    """Write several array regions (a chunk partly under a region is read, patched and
    written whole; a chunk under it whole is not read): directly where :func:`direct_plan`
    allows, the others through zarr (``array[selection] = value``). ``value`` has the region's
    shape, without the axes indexed by integers. ``plans`` as for :func:`read_many`;
    ``unbuffered``: the chunk files it takes are written past the page cache
    (:class:`~sffscan.pipeline.formats.unbuffered.UnbufferedFiles`; the same bytes)."""
    rest = []
    for arr, sel, value in items:
        plan = direct_plan(arr) if plans is None else plans.of(arr)
        if plan is None:
            rest.append((arr, sel, value))
            continue
        value = np.asarray(value)
        reg = _region(plan.folder, arr.shape, sel)
        if value.shape != reg.value_shape:
            raise ValueError(f"{plan.folder}: a region of {reg.value_shape} cannot take "
                             f"values of shape {value.shape}")
        value = value.reshape(reg.shape)
        for key, inner, part, whole in _overlaps(plan, arr.shape, reg):
            path = plan.path(key)
            if whole and value[part].shape == plan.chunks:  # the chunk is the value itself
                _store(plan, path, value[part], unbuffered)
                continue
            chunk = None if whole else _load(plan, path)
            if chunk is None:
                chunk = np.full(plan.chunks, plan.fill, plan.dtype)
            chunk[inner] = value[part]
            _store(plan, path, chunk, unbuffered)
    for arr, sel, value in rest:
        arr[sel] = value
