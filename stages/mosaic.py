"""The mosaic's computation: blending contributions by weight, gathering depth blocks into
chunk-wide column bands, and the resolution pyramid's reduction. Pure numpy: the mosaic
format that stores the results (Zarr group, journal, pyramid chunks, readers) is
:mod:`sffscan.pipeline.mosaic`.

Blending: where passes overlap, height and texture are the weighted mean with
weight = max(confidence, :data:`MIN_WEIGHT`) over valid pixels (:func:`blend`); the
uncertainty is the weighted mean of the contributions' sigmas.

Bands (:class:`BandGatherer`): the blocks of a pass are summed (value * weight) into
chunk-wide column bands; a band is final when the motion has left it, so each chunk is
written once per pass and memory stays bounded.

Pyramid: level k of an array is a function of level 0 only: element (i, j) of level k
reduces the 2^k x 2^k block of level-0 elements (i 2^k .. i 2^k + 2^k - 1, j 2^k .. ) that
exist (blocks at the far edges are cut by the array's end):

- ``height``, ``texture``, ``uncertainty``: NaN-aware mean (mean of the finite values; NaN
  if none);
- ``confidence``: mean (unmeasured pixels count with their fill value 0, so it also says
  how much of the block was measured);
- ``weight``: sum (the total blending weight behind the block).

:func:`downsample` computes every level of a region from level 0 by summing sums (float64)
and counts 2 x 2 at a time, so level k is exactly the 2^k x 2^k reduction, not a mean of
means; each element's value depends on its own block only (the same bits whichever region
it is computed in).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import numpy as np
from sffscan.stages.messages import DepthBlock

#: smallest blending weight of a valid contribution: weight = max(confidence, this)
MIN_WEIGHT = 1e-3
#: reduction of each array from one pyramid level to the next
REDUCTION = {"height": "nanmean", "texture": "nanmean", "confidence": "mean", "weight": "sum",
             "uncertainty": "nanmean"}
#: fewest levels a mosaic gets (level 0 included)
MIN_LEVELS = 4
#: the top level's longest side, px, at most (when more than MIN_LEVELS are needed)
TOP_PX = 1024
#: most levels (a 2^9 = 512 px block per top-level pixel)
MAX_LEVELS = 10

Slices = tuple[slice, slice]


def blend(
    old: dict[str, np.ndarray], new: dict[str, np.ndarray]
) -> dict[str, np.ndarray]:
    """Blend a new contribution into existing mosaic values by weight.

    Parameters
    ----------
    old : dict of ndarray
        Current ``height``, ``texture``, ``confidence``, ``weight`` of a region.
    new : dict of ndarray
        ``height``, ``texture`` as weighted sums (value * weight), ``weight`` and
        ``confidence`` of the new contribution, same shape.

    Returns
    -------
    dict of ndarray, float32
        Updated values of the four arrays.
    """
    # float32 throughout (issue 28: half the memory traffic of float64), as the incremental
    # mean previous + (added - previous * w_new) / w: a pixel's first contribution (previous
    # taken as 0) is added / w and a pixel the contribution does not weigh (w_new = 0,
    # added = 0) keeps previous, both the same bits as float64 arithmetic rounded once (for
    # float32 operands, double rounding of one +, * or / is innocuous: 53 >= 2 * 24 + 2);
    # where both weigh, the result is within float32 round-off of the float64 one
    w_old = np.asarray(old["weight"], np.float32)
    w_new = np.asarray(new["weight"], np.float32)
    w = w_old + w_new
    seen, has = w_old > 0, w > 0  # each used by every array below

    def mean(previous: np.ndarray, added: np.ndarray) -> np.ndarray:
        acc = np.where(seen, previous, np.float32(0.0)).astype(np.float32, copy=False)
        inc = acc * w_new
        np.subtract(added, inc, out=inc, casting="same_kind")
        inc /= w
        acc += inc
        acc[~has] = np.nan
        return acc

    out: dict[str, np.ndarray] = {}
    with np.errstate(invalid="ignore", divide="ignore"):
        for key in ("height", "texture"):
            out[key] = mean(old[key], new[key])
    out["confidence"] = np.maximum(old["confidence"], new["confidence"]).astype(np.float32)
    out["weight"] = w
    if "uncertainty" in old:  # the weighted mean of the contributions' sigmas (errors of
        # overlapping contributions are not independent: no sqrt(n) gain); a contribution
        # without one makes it unknown (NaN), never 0
        su = new.get("uncertainty")
        if su is None:
            su = np.where(w_new > 0, np.float32(np.nan), np.float32(0.0))
        with np.errstate(invalid="ignore", divide="ignore"):
            out["uncertainty"] = mean(old["uncertainty"], su)
    return out


@dataclass
class Band:
    """Weighted sums of one chunk-wide column band of the current pass: world px (x0, y0)
    of its element [0, 0]; sums of height * weight (µm), texture * weight, weight,
    uncertainty * weight (µm; NaN where a contribution had none), and the largest
    confidence, each (rows, chunk)."""

    x0: int
    y0: int
    wh: np.ndarray
    wt: np.ndarray
    w: np.ndarray
    conf: np.ndarray
    wu: np.ndarray

    def sums(self) -> dict[str, np.ndarray]:
        """The band as :func:`blend`'s ``new`` contribution."""
        return {"height": self.wh, "texture": self.wt, "weight": self.w,
                "confidence": self.conf, "uncertainty": self.wu}


class BandGatherer:
    """Sums the depth blocks of a pass into chunk-wide column bands (see the module).

    Parameters
    ----------
    chunk_px : int
        Band width (the mosaic's chunk edge), px.
    origin_x_px : int
        World x pixel of the mosaic's column 0 (band k starts at origin + k * chunk_px).
    """

    def __init__(self, *, chunk_px: int, origin_x_px: int) -> None:
        self.chunk = chunk_px
        self.origin_x = origin_x_px
        self.bands: dict[int, Band] = {}

    def _band_for(self, cx: int, y0: int, rows: int) -> Band:
        band = self.bands.get(cx)
        if band is None:
            c = self.chunk
            x0 = self.origin_x + cx * c
            z = np.zeros((rows, c), np.float32)
            band = Band(x0, y0, z.copy(), z.copy(), z.copy(), z.copy(), z.copy())
            self.bands[cx] = band
        return band

    def add(self, item: DepthBlock) -> list[int]:
        """Add a block of the current pass; returns the bands (keys for :meth:`take`) the
        motion has left behind, final for this pass, in the order they were opened."""
        h = item.header
        valid = np.isfinite(item.height_um)
        weight = np.where(valid, np.maximum(item.confidence, MIN_WEIGHT), 0.0)
        # the block's weighted values once (float32, as the products were), then each band
        # takes its columns of them
        wh = np.where(valid, item.height_um, 0.0) * weight
        wt = np.where(valid, item.texture, 0.0) * weight
        if item.uncertainty_um is None:  # unknown: NaN where this block contributes
            wu = np.where(weight > 0, np.nan, 0.0)
        else:
            wu = np.where(valid, item.uncertainty_um, 0.0) * weight
        c, ox = self.chunk, self.origin_x
        first = (h.x0_px - ox) // c
        last = (h.x0_px + h.width_px - 1 - ox) // c
        rows = item.height_um.shape[0]
        for cx in range(first, last + 1):
            band = self._band_for(cx, h.y0_px, rows)
            a = max(h.x0_px, band.x0)
            e = min(h.x0_px + h.width_px, band.x0 + c)
            src = slice(a - h.x0_px, e - h.x0_px)
            dst = slice(a - band.x0, e - band.x0)
            band.w[:, dst] += weight[:, src]
            band.wh[:, dst] += wh[:, src]
            band.wt[:, dst] += wt[:, src]
            np.maximum(band.conf[:, dst], item.confidence[:, src], out=band.conf[:, dst])
            band.wu[:, dst] += wu[:, src]
        return [k for k in self.bands if k < first or k > last]

    def open_bands(self) -> list[int]:
        """The bands still gathering, left to right."""
        return sorted(self.bands)

    def take(self, cx: int) -> Band | None:
        """Remove band ``cx``; None if nothing valid landed in it."""
        band = self.bands.pop(cx)
        return band if (band.w > 0).any() else None


def default_levels(shape: tuple[int, int]) -> int:
    """Levels for a mosaic of ``shape``: enough that the top level's longest side is at most
    :data:`TOP_PX`, at least :data:`MIN_LEVELS`, at most :data:`MAX_LEVELS`.

    A 10^9-pixel mosaic (31623 px square) gets 6, the demo (1908 x 7304) 4.
    """
    longest = max(1, *shape)
    need = 1 + math.ceil(math.log2(longest / TOP_PX)) if longest > TOP_PX else 1
    return int(min(MAX_LEVELS, max(MIN_LEVELS, need)))


def level_shape(shape: tuple[int, int], level: int) -> tuple[int, int]:
    """Shape of level ``level`` of a level-0 array of ``shape``."""
    f = 2 ** level
    return -(-shape[0] // f), -(-shape[1] // f)


def _quarters(a: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    return a[0::2, 0::2], a[1::2, 0::2], a[0::2, 1::2], a[1::2, 1::2]


def _halve(a: np.ndarray, dtype: Any = None) -> np.ndarray:
    """2 x 2 block sums ((a + b) + c) + d, in ``dtype`` (default: a's); strided slices are
    ~5x faster than a 4-D sum, and the in-place adds spare two temporaries."""
    p, q, r, s = _quarters(a)
    out = np.add(p, q, dtype=dtype or a.dtype)
    out += r
    out += s
    return out


def downsample(values: dict[str, np.ndarray], levels: int) -> list[dict[str, np.ndarray]]:
    """Levels 1 .. levels-1 of a level-0 region.

    Parameters
    ----------
    values : dict of ndarray, float32, (rows, cols)
        The mosaic arrays (``height``, ``texture``, ``confidence``, ``weight``, and any
        other) of a level-0 region whose first row and column are multiples of
        2^(levels-1) in the array, and whose end is either such a multiple or the array's
        end. Each is reduced as :data:`REDUCTION` says
        (``nanmean`` for a name it does not list).
    levels : int
        Number of levels, level 0 included.

    Returns
    -------
    list of dict of ndarray, float32
        Element k-1 is level k: each array (ceil(rows / 2^k), ceil(cols / 2^k)).
    """
    rows, cols = next(iter(values.values())).shape
    f = 2 ** (levels - 1)
    pr, pc = -(-rows // f) * f, -(-cols // f) * f

    def padded(a: np.ndarray) -> np.ndarray:  # zeros beyond the region (the array's end)
        if (pr, pc) == a.shape:
            return a
        out = np.zeros((pr, pc), a.dtype)
        out[:rows, :cols] = a
        return out

    # level 1 straight from float32 (NaN set to 0) into float64 sums; counts of the finite
    # values in float32 (exact: at most 4^9 per element)
    how = {name: REDUCTION.get(name, "nanmean") for name in values}
    sums: dict[str, np.ndarray] = {}
    counts: dict[str, np.ndarray] = {}
    for name, v in values.items():
        if how[name] == "nanmean":
            valid = np.isfinite(v)
            sums[name] = _halve(padded(np.where(valid, v, np.float32(0))), np.float64)
            counts[name] = _halve(padded(valid).view(np.uint8), np.float32)
        else:
            sums[name] = _halve(padded(v), np.float64)
    # elements of the array (not padding) under each block: rows x columns present
    rp = np.zeros(pr, np.float64)
    cp = np.zeros(pc, np.float64)
    rp[:rows], cp[:cols] = 1.0, 1.0

    out = []
    for k in range(1, levels):
        if k > 1:
            sums = {n: _halve(a) for n, a in sums.items()}
            counts = {n: _halve(a) for n, a in counts.items()}
        rp, cp = rp[0::2] + rp[1::2], cp[0::2] + cp[1::2]
        r, c = level_shape((rows, cols), k)
        level: dict[str, np.ndarray] = {}
        with np.errstate(invalid="ignore", divide="ignore"):
            for name in values:
                if how[name] == "sum":
                    level[name] = sums[name][:r, :c].astype(np.float32)
                    continue
                # nanmean: a block without finite values is 0 / 0 = NaN; mean: over the
                # elements present
                den = counts[name][:r, :c] if how[name] == "nanmean" else np.outer(rp[:r],
                                                                                     cp[:c])
                level[name] = np.empty((r, c), np.float32)
                np.divide(sums[name][:r, :c], den, out=level[name], casting="same_kind")
        out.append(level)
    return out


def aligned(sel: Slices, shape: tuple[int, int], levels: int) -> Slices:
    """The level-0 region of whole 2^(levels-1) blocks (cut at the array's end) around
    ``sel``."""
    f = 2 ** (levels - 1)
    rs, cs = sel
    r0, c0 = (rs.start // f) * f, (cs.start // f) * f
    r1 = min(shape[0], -(-rs.stop // f) * f)
    c1 = min(shape[1], -(-cs.stop // f) * f)
    return slice(r0, r1), slice(c0, c1)
