"""The live view's pure helpers: the mosaic preview and its point cloud, image scaling.

:class:`MosaicPreview` rebuilds the mosaic at reduced resolution from the depth blocks
with the mosaic stage's own weighted blend (w = max(confidence, 1e-3) for valid pixels),
so that it equals :func:`downsample_mosaic` of the Zarr mosaic whatever the order of the
blocks; :func:`surface_points` turns a reduced mosaic into a point cloud in mm;
:func:`logged_items` selects what the view uses where the stages run in other processes.
Used by :mod:`sffscan.pipeline.viz.sink`; no Rerun here (worker processes import it).
"""

from __future__ import annotations

import math
from collections.abc import Callable
from typing import Any

import cv2
import numpy as np
from sffscan.pipeline.stats import StatsSnapshot
from sffscan.stages.messages import DepthBlock, FocusFrame, RawColumns
from sffscan.stages.protocol import Tapped

MIN_WEIGHT = 1e-3  # as stages.mosaic: weight of a valid contribution = max(confidence, this)


def cell_sums(values: np.ndarray, *, offset: tuple[int, int], factor: int) -> np.ndarray:
    """Sum ``values`` (rows, cols) over ``factor`` x ``factor`` cells of the mosaic grid.

    ``offset`` is the (row, col) of ``values[0, 0]`` on the full-resolution grid; the result
    covers cells ``offset // factor`` onwards, float64, shape (ceil, ceil).
    """
    r0, c0 = offset
    pr, pc = r0 % factor, c0 % factor
    rows, cols = values.shape
    nr, nc = -(-(pr + rows) // factor), -(-(pc + cols) // factor)
    pad = np.zeros((nr * factor, nc * factor), np.float64)
    pad[pr:pr + rows, pc:pc + cols] = values
    return pad.reshape(nr, factor, nc, factor).sum(axis=(1, 3))


def downsample_mosaic(height: np.ndarray, texture: np.ndarray, weight: np.ndarray, *,
                      factor: int) -> tuple[np.ndarray, np.ndarray]:
    """Weighted mean of a mosaic's height and texture over ``factor`` x ``factor`` cells.

    Parameters
    ----------
    height, texture, weight : ndarray, (rows, cols)
        The mosaic arrays (µm, 0..1, blending weight), as in the Zarr group.
    factor : int
        Cell edge, px.

    Returns
    -------
    height, texture : ndarray, float32, (ceil(rows / factor), ceil(cols / factor))
        sum(w * v) / sum(w) per cell; NaN where the cell has no weight.
    """
    w = np.where(np.isfinite(height), weight.astype(np.float64), 0.0)
    sw = cell_sums(w, offset=(0, 0), factor=factor)
    out = []
    for v in (height, texture):
        s = cell_sums(np.where(w > 0, v, 0.0) * w, offset=(0, 0), factor=factor)
        with np.errstate(invalid="ignore", divide="ignore"):
            out.append(np.where(sw > 0, s / sw, np.nan).astype(np.float32))
    return out[0], out[1]


class MosaicPreview:
    """The mosaic at reduced resolution, blended from depth blocks as the mosaic stage does.

    Cell (i, j) holds sum(w * h) / sum(w) over the full-resolution pixels of rows
    [i f, (i + 1) f) and columns [j f, (j + 1) f) of the mosaic (origin ``origin_px``), with
    w = max(confidence, 1e-3) for valid pixels: the same as :func:`downsample_mosaic` of
    the Zarr mosaic, whatever the order of the blocks.
    """

    def __init__(self, *, origin_px: tuple[int, int], shape: tuple[int, int], factor: int,
                 tile: int = 256) -> None:
        self.origin, self.factor, self.tile = origin_px, factor, tile
        n = (-(-shape[0] // factor), -(-shape[1] // factor))
        self.sums = np.zeros((3, *n), np.float64)  # sum w*h, sum w*t, sum w
        self.blocks = 0
        #: tiles (column bands of ``tile`` cells) changed since :meth:`take_dirty`
        self.dirty: set[int] = set()

    @property
    def shape(self) -> tuple[int, int]:
        return self.sums.shape[1], self.sums.shape[2]

    @property
    def tiles(self) -> int:
        return -(-self.sums.shape[2] // self.tile)

    def add(self, block: DepthBlock) -> None:
        h = block.header
        r0, c0 = h.y0_px - self.origin[1], h.x0_px - self.origin[0]
        if r0 < 0 or c0 < 0:
            raise ValueError(f"depth block at world px (x={h.x0_px}, y={h.y0_px}) lies before "
                             f"the mosaic origin {self.origin}")
        valid = np.isfinite(block.height_um)
        w = np.where(valid, np.maximum(block.confidence, MIN_WEIGHT), 0.0)
        parts = [np.where(valid, block.height_um, 0.0) * w,
                 np.where(valid, block.texture, 0.0) * w, w]
        f = self.factor
        cells = [cell_sums(p, offset=(r0, c0), factor=f) for p in parts]
        i0, j0 = r0 // f, c0 // f
        i1, j1 = i0 + cells[0].shape[0], j0 + cells[0].shape[1]
        if i1 > self.sums.shape[1] or j1 > self.sums.shape[2]:  # the mosaic grows too
            if i1 > self.sums.shape[1]:  # every tile gets taller
                self.dirty.update(range(self.tiles))
            grown = np.zeros((3, max(i1, self.sums.shape[1]), max(j1, self.sums.shape[2])))
            grown[:, :self.sums.shape[1], :self.sums.shape[2]] = self.sums
            self.sums = grown
        for k in range(3):
            self.sums[k, i0:i1, j0:j1] += cells[k]
        self.dirty.update(range(j0 // self.tile, (j1 - 1) // self.tile + 1))
        self.blocks += 1

    def take_dirty(self) -> list[int]:
        """The tiles changed since the last call, in order; forgets them."""
        out, self.dirty = sorted(self.dirty), set()
        return out

    def images(self, tile: int | None = None) -> tuple[np.ndarray, np.ndarray]:
        """Height (µm) and texture (0..1), float32, NaN where nothing was measured: of the
        whole preview, or of tile ``tile`` (cell columns [tile T, (tile + 1) T))."""
        sums = self.sums
        if tile is not None:
            sums = sums[:, :, tile * self.tile:(tile + 1) * self.tile]
        sw = sums[2]
        with np.errstate(invalid="ignore", divide="ignore"):
            return tuple(np.where(sw > 0, sums[k] / sw, np.nan).astype(np.float32)
                         for k in (0, 1))  # type: ignore[return-value]


def point_stride(cells: int, max_points: int) -> int:
    """The common row and column stride that leaves at most ``max_points`` of ``cells``."""
    return max(1, math.ceil(math.sqrt(cells / max(max_points, 1))))


def surface_points(height: np.ndarray, texture: np.ndarray, *, pixel_um: float, factor: int,
                   origin_px: tuple[int, int], stride: int) -> tuple[np.ndarray, np.ndarray]:
    """A reduced mosaic as a point cloud: positions (n, 3) in mm, grey colours (n, 3) uint8.

    Cell (i, j) lies at world pixel origin + (j + 0.5, i + 0.5) * factor - 0.5; every
    ``stride``-th cell along rows and columns is kept, NaN cells are left out.
    """
    h, t = height[::stride, ::stride], texture[::stride, ::stride]
    ii, jj = np.nonzero(np.isfinite(h))
    px_mm = pixel_um / 1000.0
    x = (origin_px[0] + (jj * stride + 0.5) * factor - 0.5) * px_mm
    y = (origin_px[1] + (ii * stride + 0.5) * factor - 0.5) * px_mm
    pos = np.stack([x, y, h[ii, jj] / 1000.0], axis=1).astype(np.float32)
    grey = np.clip(np.nan_to_num(t[ii, jj]) * 255.0 + 0.5, 0, 255).astype(np.uint8)
    return pos, np.repeat(grey[:, None], 3, axis=1)


def shown(height_um: np.ndarray) -> np.ndarray:
    """Heights as logged: float32 µm with 0 where invalid (NaN), Rerun's "no depth" value."""
    return np.nan_to_num(height_um.astype(np.float32), nan=0.0)


def to_u8(image: np.ndarray, *, scale: float, reduce: int) -> np.ndarray:
    """An image times ``scale`` as uint8 (clipped, NaN 0), reduced ``reduce`` times by area."""
    img = np.nan_to_num(image.astype(np.float32) * scale)
    if reduce > 1:
        h, w = img.shape
        img = cv2.resize(img, (max(1, w // reduce), max(1, h // reduce)),
                         interpolation=cv2.INTER_AREA)
    return np.clip(img + 0.5, 0, 255).astype(np.uint8)


def logged_items(frame_step: int) -> Callable[[Any], bool]:
    """The live view's selection of tapped items (process mode: run where the stages run,
    before anything is copied for the view): every item but the focus frames the view does
    not log (frame_id not a multiple of ``frame_step``, or no column measured)."""

    def keep(item: Any) -> bool:
        ff = item.item if isinstance(item, Tapped) else item
        if isinstance(ff, FocusFrame):
            return ff.placed.header.frame_id % frame_step == 0 and ff.focus.size > 0
        return not isinstance(ff, RawColumns)  # measured by the band processes: no image

    return keep


def precious_to_view(item: Any) -> bool:
    """The live view's precious items (:attr:`~sffscan.stages.protocol.Sink.precious`):
    the depth blocks, which build its mosaic, and the statistics (one a second; the last
    carry the final counts); the frames make way for them when its queue or channel is
    full."""
    return isinstance(item, StatsSnapshot) or (isinstance(item, Tapped)
                                               and isinstance(item.item, DepthBlock))
