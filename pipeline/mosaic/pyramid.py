"""The mosaic's resolution pyramid in the group: levels 1 .. L-1, each halving the previous
one, as ``pyramid/<k>/<name>`` arrays with 1-D µm coordinate arrays at every level; the
reduction itself is :func:`sffscan.stages.mosaic.downsample`.

Streaming (:class:`PyramidCache`): a band write of the mosaic writer
(:class:`sffscan.pipeline.mosaic.writer.MosaicWriter`) reads its level-0 region widened to
whole 2^(L-1) blocks once (the blend needs it anyway), blends into it and hands it to the
cache, which computes the levels of the region and puts them into the upper-level chunks it
holds in memory. A chunk goes back to the store (``write-back``)

- when a write no longer touches it (the motion has left its columns: a level-k chunk
  spans 2^k chunk-wide bands, so it is encoded once per pass instead of 2^k times),
- at the first band write after it has held unwritten changes for ``lag_s`` seconds
  (default :data:`LAG_S`, 5 s), even if writes still touch it,
- when the writer sets its status (end of scan, complete or failed): every chunk.

So a viewer sees level k lag level 0 by at most the 2^k bands a level-k chunk spans, or
``lag_s`` seconds (checked at band writes), whichever ends first. A chunk is read from the
store only at its write-back, and only if the updates did not set it whole and it may hold
data (a chunk of a new mosaic that the cache has not written holds fill values). On the
demo (45 band writes, 4 levels) that is 100 chunk write-backs and 23 reads, where writing
each band's levels directly read and wrote ~270 (each counting the four arrays once).

Memory: the cache holds only the chunks under the last write: for a write of w x h level-0
px, at most (ceil(h / (c 2^k)) + 1) (ceil(w / (c 2^k)) + 1) chunks of level k (c: the chunk
edge), each the four arrays' c x c float32 and a c x c mask (the demo's 256 x 1040 bands: at
most 6 chunks, 6.4 MiB).

Crash safety: :meth:`PyramidCache.stale` is the level-0 box under the chunks with unwritten
changes; the writer stores it (``pyramid_stale``) with every journal entry it makes anyway
(``writing`` before a band write, ``writes_done`` after it), so it costs no extra metadata
write, and reopening the mosaic recomputes that box from level 0 (:func:`update_pyramid`,
in tiles of :data:`TILE_PX` for bounded memory).
"""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import numpy as np
import zarr
from sffscan.pipeline.formats.zarr_chunks import Plans, read_many, write_many
from sffscan.pipeline.mosaic.ngff import COORDS, level_coords, level_path
from sffscan.stages.mosaic import Slices, aligned, downsample, level_shape

#: longest time, s, an upper-level chunk keeps unwritten changes while writes still touch it
LAG_S = 5.0
#: edge, level-0 px, of the tiles in which a region is recomputed (bounds the memory)
TILE_PX = 1024


def pyramid_arrays(group: zarr.Group, names: tuple[str, ...], levels: int
                   ) -> list[dict[str, zarr.Array]]:
    """The pyramid's arrays: element k-1 maps each name to its level-k array."""
    out = []
    for k in range(1, levels):
        level = {}
        for name in names:
            node = group.get(level_path(name, k))
            if not isinstance(node, zarr.Array):
                raise ValueError(f"{group.store}: mosaic has no pyramid array "
                                 f"'{level_path(name, k)}'")
            level[name] = node
        out.append(level)
    return out


def create_pyramid(group: zarr.Group, *, shape: tuple[int, int], levels: int, chunk_px: int,
                   fill: dict[str, float], units: dict[str, str], compressors: Any) -> None:
    """Create the arrays of levels 1 .. levels-1 (filled with the fill values)."""
    for k in range(1, levels):
        for name, value in fill.items():
            group.create_array(name=level_path(name, k), shape=level_shape(shape, k),
                               chunks=(chunk_px, chunk_px), dtype="float32", fill_value=value,
                               compressors=compressors, dimension_names=("y", "x"),
                               attributes={"units": units[name]})


def resize_pyramid(arrays: list[dict[str, zarr.Array]], shape: tuple[int, int]) -> None:
    """Resize every level to match a level-0 ``shape``."""
    for k, level in enumerate(arrays, start=1):
        want = level_shape(shape, k)
        for arr in level.values():
            if arr.shape != want:
                arr.resize(want)


#: chunk length of the 1-D coordinate arrays, elements
COORD_CHUNK = 4096
CoordArrays = list[tuple[zarr.Array, zarr.Array]]


def create_coords(group: zarr.Group, *, shape: tuple[int, int], levels: int, pixel_um: float,
                  origin_um: tuple[float, float]) -> CoordArrays:
    """Create and write the 1-D coordinate arrays ``y``, ``x`` of levels 0 .. levels-1
    (float64, µm, element centres: :func:`~sffscan.pipeline.mosaic.ngff.level_coords`;
    ``origin_um``: world (x, y) µm of level-0 element [0, 0]). Element k is level k's
    (y, x) pair."""
    out: CoordArrays = []
    for k in range(levels):
        ny, nx = level_shape(shape, k)
        y, x = (group.create_array(name=level_path(name, k), shape=(n,), chunks=(COORD_CHUNK,),
                                   dtype="float64", fill_value=np.nan, dimension_names=(name,),
                                   attributes={"units": "µm"})
                for name, n in zip(COORDS, (ny, nx), strict=True))
        out.append((y, x))
    write_coords(out, shape, pixel_um=pixel_um, origin_um=origin_um, force=True)
    return out


def coord_arrays(group: zarr.Group, levels: int) -> CoordArrays | None:
    """The coordinate arrays of every level, or None if the mosaic has none (format
    version 2 or older)."""
    out: CoordArrays = []
    for k in range(levels):
        pair = [group.get(level_path(name, k)) for name in COORDS]
        if not all(isinstance(a, zarr.Array) for a in pair):
            return None
        out.append((pair[0], pair[1]))  # type: ignore[arg-type]
    return out


def write_coords(coords: CoordArrays, shape: tuple[int, int], *, pixel_um: float,
                 origin_um: tuple[float, float], force: bool = False) -> None:
    """Resize the coordinate arrays to a level-0 ``shape`` and write the ones resized (all
    with ``force``)."""
    for k, (y, x) in enumerate(coords):
        for arr, n, o in zip((y, x), level_shape(shape, k), (origin_um[1], origin_um[0]),
                             strict=True):
            if arr.shape != (n,) or force:
                arr.resize((n,))
                arr[:] = level_coords(n, level=k, pixel_um=pixel_um, origin_um=o)


def update_pyramid(level0: dict[str, zarr.Array], arrays: list[dict[str, zarr.Array]],
                   sel: Slices, *, tile_px: int = TILE_PX) -> None:
    """Recompute every level over the blocks that the level-0 region ``sel`` touches, in
    tiles of about ``tile_px`` x ``tile_px`` level-0 px (whole blocks), written directly."""
    if not arrays:
        return
    levels = len(arrays) + 1
    shape = level0["height"].shape
    region = aligned(sel, (int(shape[0]), int(shape[1])), levels)
    step = max(tile_px // 2 ** (levels - 1), 1) * 2 ** (levels - 1)
    names = list(level0)
    for r in range(region[0].start, region[0].stop, step):
        for c in range(region[1].start, region[1].stop, step):
            tile = (slice(r, min(r + step, region[0].stop)),
                    slice(c, min(c + step, region[1].stop)))
            values = dict(zip(names, read_many([(level0[n], tile) for n in names]),
                              strict=True))
            write_levels(arrays, tile, values)


def write_levels(arrays: list[dict[str, zarr.Array]], region: Slices,
                 values: dict[str, np.ndarray]) -> None:
    """Write every level over ``region``, a level-0 region of whole blocks (:func:`aligned`)
    whose current level-0 ``values`` are given."""
    levels = len(arrays) + 1
    writes = []
    for k, (level, arrs) in enumerate(zip(downsample(values, levels), arrays, strict=True),
                                      start=1):
        f = 2 ** k
        r0, c0 = region[0].start // f, region[1].start // f
        for name, arr in arrs.items():
            v = level[name]
            writes.append((arr, (slice(r0, r0 + v.shape[0]), slice(c0, c0 + v.shape[1])), v))
    write_many(writes)


@dataclass
class _Chunk:
    """One cached upper-level chunk of every array (float32, chunk x chunk)."""

    data: dict[str, np.ndarray]
    #: the elements set by updates while cached; None: every element is current
    covered: np.ndarray | None
    touched: int  # the update that last changed it
    dirty_since: float | None  # when its first unwritten change was made; None: clean


class PyramidCache:
    """Write-back cache of the upper-level chunks under the latest writes (see the module).

    A chunk is not read when a write first touches it: the cache records which elements
    the updates set, and reads the chunk (to keep the others) only when it writes it back
    and the updates did not set it whole, or never if it is known to be empty.

    Parameters
    ----------
    arrays : list of dict of zarr.Array
        The pyramid (:func:`pyramid_arrays`): element k-1 maps each name to level k.
    lag_s : float
        A chunk that still has unwritten changes this many seconds after its first one is
        written at the next :meth:`write_back` even if writes still touch it (0: every
        change is written at the next write-back, as without a cache).
    empty : bool
        The arrays were just created: a chunk this cache has not written holds fill values
        (no read needed); False for a reopened mosaic.
    clock : callable
        Monotonic time, s.
    plans : Plans, optional
        The owner's cache of the arrays' chunk plans (its own when not given).
    """

    def __init__(self, arrays: list[dict[str, zarr.Array]], *, lag_s: float = LAG_S,
                 empty: bool = False, clock: Callable[[], float] = time.monotonic,
                 plans: Plans | None = None) -> None:
        self.arrays = arrays
        self.plans = Plans() if plans is None else plans
        self.levels = len(arrays) + 1
        self.lag_s = lag_s
        self.clock = clock
        self.empty = empty
        first = next(iter(arrays[0].values())) if arrays else None
        self.chunk = int(first.chunks[0]) if first is not None else 0
        self.cached: dict[tuple[int, int, int], _Chunk] = {}  # (level, chunk row, chunk col)
        self.written: set[tuple[int, int, int]] = set()  # chunks written (when empty)
        self.updates = 0
        self.chunks_written = 0  # chunk write-backs (the four arrays of a chunk count once)
        self.chunks_read = 0  # chunk reads before a write-back (likewise)

    def _sel(self, key: tuple[int, int, int]) -> Slices:
        k, i, j = key
        rows, cols = next(iter(self.arrays[k - 1].values())).shape
        c = self.chunk
        return slice(i * c, min((i + 1) * c, rows)), slice(j * c, min((j + 1) * c, cols))

    def update(self, region: Slices, values: dict[str, np.ndarray]) -> None:
        """Put the levels of ``region`` (level-0 region of whole blocks, :func:`aligned`)
        whose level-0 ``values`` are given into the cached chunks."""
        self.updates += 1
        now = self.clock()
        c = self.chunk
        for k, level in enumerate(downsample(values, self.levels), start=1):
            f = 2 ** k
            r0, c0 = region[0].start // f, region[1].start // f
            r1, c1 = r0 + level["height"].shape[0], c0 + level["height"].shape[1]
            for i in range(r0 // c, -(-r1 // c)):
                for j in range(c0 // c, -(-c1 // c)):
                    a0, b0 = max(r0, i * c), max(c0, j * c)
                    a1, b1 = min(r1, (i + 1) * c), min(c1, (j + 1) * c)
                    dst = slice(a0 - i * c, a1 - i * c), slice(b0 - j * c, b1 - j * c)
                    src = slice(a0 - r0, a1 - r0), slice(b0 - c0, b1 - c0)
                    self._place((k, i, j), dst, level, src, now)

    def _place(self, key: tuple[int, int, int], dst: Slices, level: dict[str, np.ndarray],
               src: Slices, now: float) -> None:
        chunk = self.cached.get(key)
        if chunk is None:
            c = self.chunk
            known = self.empty and key not in self.written  # all fill values
            chunk = _Chunk({name: np.full((c, c), arr.fill_value, np.float32)
                            for name, arr in self.arrays[key[0] - 1].items()},
                           None if known else np.zeros((c, c), bool), self.updates, None)
            self.cached[key] = chunk
        for name, block in chunk.data.items():
            block[dst] = level[name][src]
        if chunk.covered is not None:
            chunk.covered[dst] = True
        chunk.touched = self.updates
        if chunk.dirty_since is None:
            chunk.dirty_since = now

    def _whole(self, key: tuple[int, int, int]) -> bool:
        """Whether every element of a cached chunk inside the array is current."""
        covered = self.cached[key].covered
        if covered is None:
            return True
        sel = self._sel(key)
        return bool(covered[:sel[0].stop - sel[0].start, :sel[1].stop - sel[1].start].all())

    def write_back(self, *, everything: bool = False
                   ) -> list[tuple[zarr.Array, Slices, np.ndarray]]:
        """Take the chunks due (see the module; ``everything``: all) out of the cache.

        Returns the writes to make (:func:`write_many`), so that the caller can make them
        together with its own. Chunks the last update did not touch leave the cache.
        """
        now = self.clock()
        due = [key for key, chunk in self.cached.items() if chunk.dirty_since is not None and (
            everything or chunk.touched < self.updates or now - chunk.dirty_since >= self.lag_s)]
        # the elements no update set, read from the store for the chunks not set whole
        partial = [key for key in due if not self._whole(key)]
        reads = [(arr, self._sel(key)) for key in partial
                 for arr in self.arrays[key[0] - 1].values()]
        stored = iter(read_many(reads, plans=self.plans))
        for key in partial:
            chunk = self.cached[key]
            keep = ~chunk.covered  # type: ignore[operator]
            for block in chunk.data.values():
                part = next(stored)
                np.copyto(block[:part.shape[0], :part.shape[1]], part,
                          where=keep[:part.shape[0], :part.shape[1]])
            self.chunks_read += 1
        writes = []
        for key in due:
            chunk = self.cached[key]
            sel = self._sel(key)
            rows, cols = sel[0].stop - sel[0].start, sel[1].stop - sel[1].start
            for name, arr in self.arrays[key[0] - 1].items():
                writes.append((arr, sel, chunk.data[name][:rows, :cols].copy()))
            chunk.covered, chunk.dirty_since = None, None
            self.written.add(key)
            self.chunks_written += 1
        for key in [key for key, chunk in self.cached.items()
                    if everything or chunk.touched < self.updates]:
            del self.cached[key]
        return writes

    def stale(self) -> Slices | None:
        """The level-0 region (array px) under the chunks with unwritten changes, or None."""
        boxes = []
        for (k, i, j), chunk in self.cached.items():
            if chunk.dirty_since is not None:
                e = self.chunk * 2 ** k
                boxes.append((i * e, j * e, (i + 1) * e, (j + 1) * e))
        if not boxes:
            return None
        return (slice(min(b[0] for b in boxes), max(b[2] for b in boxes)),
                slice(min(b[1] for b in boxes), max(b[3] for b in boxes)))
