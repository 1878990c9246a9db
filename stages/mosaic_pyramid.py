"""The mosaic's resolution pyramid: levels 1 .. L-1, each halving the previous one.

Level k of an array is a function of level 0 only: element (i, j) of level k reduces the
2^k x 2^k block of level-0 elements (i 2^k .. i 2^k + 2^k - 1, j 2^k .. ) that exist
(blocks at the far edges are cut by the array's end):

- ``height``, ``texture``: NaN-aware mean (mean of the finite values; NaN if none);
- ``confidence``: mean (unmeasured pixels count with their fill value 0, so it also says
  how much of the block was measured);
- ``weight``: sum (the total blending weight behind the block).

:func:`downsample` computes every level of a region from level 0 by summing sums and
counts 2 x 2 at a time (float64), so level k is exactly the 2^k x 2^k reduction, not a mean
of means. The writer (:class:`sffscan.stages.mosaic.MosaicWriter`) calls
:func:`update_pyramid` after each band write, for the blocks that the write touched: the
pyramid is current whenever a band completes, and a crash inside the update is covered by
the write's journal entry (the resume recomputes the box). A band write reads its level-0
region widened to whole blocks once, blends into it, and computes the levels from it
(:func:`write_levels`), so the pyramid costs no second read.
"""

from __future__ import annotations

import asyncio
import math
from collections.abc import Sequence
from typing import Any

import numpy as np
import zarr
from sffscan.pipeline.formats.ngff import level_path

#: fewest levels a mosaic gets (level 0 included)
MIN_LEVELS = 4
#: the top level's longest side, px, at most (when more than MIN_LEVELS are needed)
TOP_PX = 1024
#: most levels (a 2^9 = 512 px block per top-level pixel)
MAX_LEVELS = 10

Slices = tuple[slice, slice]


def default_levels(shape: tuple[int, int]) -> int:
    """Levels for a mosaic of ``shape``: enough that the top level's longest side is at most
    :data:`TOP_PX`, at least :data:`MIN_LEVELS`, at most :data:`MAX_LEVELS`.

    Each level costs a read-modify-write of its chunks at every band write
    (``bench/bench_pyramid.py``), so there are no more levels than a viewer needs for an
    overview: a 10^9-pixel mosaic (31623 px square) gets 6, the demo (1908 x 7304) 4.
    """
    longest = max(1, *shape)
    need = 1 + math.ceil(math.log2(longest / TOP_PX)) if longest > TOP_PX else 1
    return int(min(MAX_LEVELS, max(MIN_LEVELS, need)))


def level_shape(shape: tuple[int, int], level: int) -> tuple[int, int]:
    """Shape of level ``level`` of a level-0 array of ``shape``."""
    f = 2 ** level
    return -(-shape[0] // f), -(-shape[1] // f)


def downsample(values: dict[str, np.ndarray], levels: int) -> list[dict[str, np.ndarray]]:
    """Levels 1 .. levels-1 of a level-0 region.

    Parameters
    ----------
    values : dict of ndarray, float32, (rows, cols)
        ``height``, ``texture``, ``confidence``, ``weight`` of a level-0 region whose first
        row and column are multiples of 2^(levels-1) in the array, and whose end is either
        such a multiple or the array's end.
    levels : int
        Number of levels, level 0 included.

    Returns
    -------
    list of dict of ndarray, float32
        Element k-1 is level k: each array (ceil(rows / 2^k), ceil(cols / 2^k)).
    """
    rows, cols = values["height"].shape
    f = 2 ** (levels - 1)
    pr, pc = -(-rows // f) * f, -(-cols // f) * f

    def padded(a: np.ndarray, dtype: type, where: np.ndarray | None = None) -> np.ndarray:
        out = np.zeros((pr, pc), dtype)
        np.copyto(out[:rows, :cols], a, where=True if where is None else where)
        return out

    def halve(a: np.ndarray) -> np.ndarray:  # 2 x 2 block sums (slices: ~5x a 4-D sum)
        return (a[0::2, 0::2] + a[1::2, 0::2]) + (a[0::2, 1::2] + a[1::2, 1::2])

    sums: dict[str, np.ndarray] = {}
    counts: dict[str, np.ndarray] = {}
    for name in ("height", "texture"):
        valid = np.isfinite(values[name])
        sums[name] = padded(values[name], np.float64, valid)
        counts[name] = padded(valid, np.float32)  # exact: at most 4^9 per element
    sums["confidence"] = padded(values["confidence"], np.float64)
    sums["weight"] = padded(values["weight"], np.float64)
    # elements of the array (not padding) under each block: rows x columns present
    rp = np.zeros(pr, np.float64)
    cp = np.zeros(pc, np.float64)
    rp[:rows], cp[:cols] = 1.0, 1.0

    out = []
    for k in range(1, levels):
        sums = {n: halve(a) for n, a in sums.items()}
        counts = {n: halve(a) for n, a in counts.items()}
        rp, cp = rp[0::2] + rp[1::2], cp[0::2] + cp[1::2]
        r, c = level_shape((rows, cols), k)
        level: dict[str, np.ndarray] = {}
        with np.errstate(invalid="ignore", divide="ignore"):
            for name in ("height", "texture"):
                n = counts[name][:r, :c]
                level[name] = np.where(n > 0, sums[name][:r, :c] / n, np.nan).astype(np.float32)
            present = np.outer(rp[:r], cp[:c])
            level["confidence"] = (sums["confidence"][:r, :c] / present).astype(np.float32)
        level["weight"] = sums["weight"][:r, :c].astype(np.float32)
        out.append(level)
    return out


def read_many(items: Sequence[tuple[zarr.Array, Slices]]) -> list[np.ndarray]:
    """Read several array regions in one round trip of zarr's event loop (concurrently)."""
    from zarr.core.sync import sync

    async def run() -> list[Any]:
        return list(await asyncio.gather(*(a.async_array.getitem(sel) for a, sel in items)))

    return [np.asarray(v) for v in sync(run())]


def write_many(items: Sequence[tuple[zarr.Array, Slices, np.ndarray]]) -> None:
    """Write several array regions in one round trip of zarr's event loop (concurrently)."""
    from zarr.core.sync import sync

    async def run() -> None:
        await asyncio.gather(*(a.async_array.setitem(sel, v) for a, sel, v in items))

    sync(run())


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


def aligned(sel: Slices, shape: tuple[int, int], levels: int) -> Slices:
    """The level-0 region of whole 2^(levels-1) blocks (cut at the array's end) around
    ``sel``."""
    f = 2 ** (levels - 1)
    rs, cs = sel
    r0, c0 = (rs.start // f) * f, (cs.start // f) * f
    r1 = min(shape[0], -(-rs.stop // f) * f)
    c1 = min(shape[1], -(-cs.stop // f) * f)
    return slice(r0, r1), slice(c0, c1)


def update_pyramid(level0: dict[str, zarr.Array], arrays: list[dict[str, zarr.Array]],
                   sel: Slices) -> None:
    """Recompute every level over the blocks that the level-0 region ``sel`` touches."""
    if not arrays:
        return
    levels = len(arrays) + 1
    shape = level0["height"].shape
    region = aligned(sel, (int(shape[0]), int(shape[1])), levels)
    if region[0].stop <= region[0].start or region[1].stop <= region[1].start:
        return
    names = list(level0)
    values = dict(zip(names, read_many([(level0[n], region) for n in names]), strict=True))
    write_levels(arrays, region, values)


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
