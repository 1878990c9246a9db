"""The reduction of a focus volume's completed columns to depth, block by block.

:func:`reduce_block` is the core of :meth:`sffscan.stages.focus_volume.FocusVolume.reduce`
(which applies the volume's deferred writes first and releases the columns left behind
after): the block's valid pixels, the depth method chosen once for the block on their
curves, each band of rows' depth and confidence as band tasks
(:mod:`sffscan.stages.volume_tasks`, by the volume's band workers where it has some), then
the height, texture and confidence of the block. :class:`BlockSource` is what it reads of
the volume (:mod:`sffscan.stages.focus_volume`); the volume's column geometry is
:mod:`sffscan.stages.volume_columns`'s.

Every block also carries the height's uncertainty (µm, one sigma,
:mod:`sffscan.stages.depth_uncertainty`): from the block's depth (its scatter about its
local median) and each curve's width (its sums and its minimum: from the stored levels at
the reduction, or for the accumulating methods a running minimum kept like the maximum).
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass
from typing import NamedTuple

import numpy as np
from sffscan.stages import block_depth as blocks
from sffscan.stages.depth_choice import DEPARTURE_METHODS, wide_choice
from sffscan.stages.depth_levels import levels_to_height
from sffscan.stages.depth_statistics import SHAPE_SAMPLE_STEP
from sffscan.stages.depth_window import WINDOW_STRIPS, window_choice
from sffscan.stages.volume_tasks import gather, scratch

__all__ = ["BlockResult", "BlockSource", "reduce_block"]


class BlockResult(NamedTuple):
    """A reduced block of world columns (see
    :meth:`~sffscan.stages.focus_volume.FocusVolume.reduce`)."""

    x0: int
    y0: int
    height_um: np.ndarray
    texture: np.ndarray
    confidence: np.ndarray
    complete: int
    uncertainty_um: np.ndarray | None
    bias_levels: float = 0.0
    """The bias the block's uncertainty holds (levels, ``b`` of
    :func:`sffscan.stages.depth_uncertainty.depth_uncertainty`: SPC's departure or a peak's
    centroid pull, one value for the block)."""


@dataclass(frozen=True)
class BlockSource:
    """What the reduction of a block reads of a focus volume
    (:class:`~sffscan.stages.focus_volume.FocusVolume`'s attributes of the same names, as
    they are at the reduction): its ring of columns, its parameters, and its band tasks."""

    count: np.ndarray
    row_lo: np.ndarray
    row_hi: np.ndarray
    argmax: np.ndarray
    tex: np.ndarray
    fv: np.ndarray | None
    grid: np.ndarray | None
    arrays: dict[str, np.ndarray]
    """The arrays the band tasks read and write, the block's scratch among them."""
    run_task: Callable[[str, dict[str, object]], None]
    """Runs a band task (:mod:`sffscan.stages.volume_tasks`) on :attr:`arrays`, band by band."""
    heights: np.ndarray
    n: int
    rows: int
    ring: int
    halo: int
    first_u: int
    end_u: int
    y0: int
    direction: int
    method: str
    median_size: int
    spread_size: int
    uncertainty: bool
    window_test: bool


def reduce_block(src: BlockSource, u0: int, u1: int) -> BlockResult:
    """Depth of a volume's internal columns [u0, u1) (its deferred writes applied before).

    Returns
    -------
    BlockResult
        ``x0``, ``y0``: world position of the block's first column and row, px;
        ``height_um``, ``texture``, ``confidence``: float32 (rows, u1 - u0), NaN height
        and texture and zero confidence where a pixel's curve lacks levels;
        ``complete``: columns seen at all N levels; ``uncertainty_um``: the height's
        uncertainty, µm, one sigma, NaN where invalid
        (:func:`sffscan.stages.depth_uncertainty.height_uncertainty_um`; the depth's
        scatter measured within the block, replicated at its edges). New arrays: the
        volume may release the block's columns once it has them.
    """
    complete = gather(src.count, u0, u1, src.ring) == src.n  # columns seen at every level
    lo = gather(src.row_lo, u0, u1, src.ring).max(axis=0)
    hi = gather(src.row_hi, u0, u1, src.ring).min(axis=0)
    rows = np.arange(src.rows)[:, None]
    valid = complete[None, :] & (rows >= lo[None, :]) & (rows < hi[None, :])
    depth, conf, _, _, bias, locking = _depth(src, u0, u1, valid)
    invalid = ~valid
    height = levels_to_height(depth, focus_heights_um=src.heights)  # float32, new
    np.copyto(height, np.float32(np.nan), where=invalid)
    unc: np.ndarray | None = None
    if src.uncertainty:
        # invalid pixels (curves that lack levels) take the block's mean depth, so
        # that their values do not count as scatter of their valid neighbours
        fill = float(depth[valid].mean()) if valid.any() else 0.0
        unc = _uncertainty(src, depth, valid, fill, bias, locking)
        np.copyto(unc, np.nan, where=invalid)
    conf = np.where(valid, conf, 0.0).astype(np.float32, copy=False)
    tex = np.where(valid, gather(src.tex, u0, u1, src.ring), np.nan).astype(np.float32,
                                                                            copy=False)
    if src.direction == -1:
        height, tex, conf = height[:, ::-1], tex[:, ::-1], conf[:, ::-1]
        unc = None if unc is None else unc[:, ::-1]
    x0 = u0 if src.direction == 1 else -(u1 - 1)  # world x of the block's first column
    return BlockResult(x0, src.y0, height, tex, conf, int(complete.sum()), unc, bias)


def _depth(src: BlockSource, u0: int, u1: int, valid: np.ndarray
           ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, float, float]:
    """Depth (levels) and confidence of columns [u0, u1), their curves' sums (H_0,
    Re H_1, Im H_1) and minima (views of the block's scratch arrays), and the bias the
    uncertainty adds (levels: SPC's where the block took it, a peak method's
    :func:`~sffscan.stages.block_depth.block_choice` or
    :func:`~sffscan.stages.block_depth.block_peak_bias`, ``"wcentroid"``'s
    :func:`~sffscan.stages.block_depth.block_departure_bias`; else 0.0) and the locking it adds
    where the scatter cannot show it (:func:`~sffscan.stages.block_depth.block_choice`'s;
    else 0.0): the method chosen
    once for the block on its ``valid`` pixels' curves (rows, u1 - u0), then
    :func:`sffscan.stages.volume_tasks.depth` on each band of rows."""
    method, bias, floor, locking, weight = src.method, 0.0, None, 0.0, 1.0
    own = method in blocks.OWN_LEVEL_METHODS or method in blocks.BLOCK_CHOICES
    if src.fv is not None and method in blocks.BLOCK_CHOICES:
        # one choice for the block, whatever its bands
        method, bias, floor, locking, weight = blocks.block_choice(
            gather(src.fv, u0, u1, src.ring), gather(src.argmax, u0, u1, src.ring), valid,
            method=method, centre=lambda: _centre(src, u0, u1))
    elif src.fv is not None and method == "adaptive" and src.uncertainty:
        bias = blocks.block_peak_bias(gather(src.fv, u0, u1, src.ring),
                                      gather(src.argmax, u0, u1, src.ring), valid)
    # the fallback's wide centroid judged on the whole block, whatever its bands
    wide_test = (src.fv is not None and src.method in blocks.BLOCK_CHOICES
                 and method not in blocks.SPC_BLOCKS)
    # and the default's 9-level centroid (depth_window), as a stack's
    window_test = wide_test and src.window_test
    src.run_task("depth", {
        "u0": u0, "u1": u1, "a0": max(u0 - src.halo, src.first_u),
        "a1": min(u1 + src.halo, src.end_u), "ring": src.ring, "rows": src.rows,
        "halo": src.halo, "own": own, "method": method, "n_levels": src.n,
        "median_size": src.median_size, "spread_size": src.spread_size,
        "uncertainty": src.uncertainty, "wide_test": wide_test,
        "window_test": window_test,
        # SPC's range guard (depth_floor): a list of two floats or None, as JSON takes
        # it to band processes (NaN written as null)
        "floor": None if floor is None else [None if math.isnan(v) else v for v in floor],
        # an SPC block's share of SPC (spc_weight), the fallback's the rest
        "spc_weight": weight})
    a, shape = src.arrays, (src.rows, u1 - u0)
    if wide_test:
        wide_choice(scratch(a, "b_depth", shape), scratch(a, "b_peak", shape),
                    step=SHAPE_SAMPLE_STEP, valid=valid)
    if window_test:
        hidden = window_choice(scratch(a, "b_depth", shape), scratch(a, "b_window", shape),
                               valid=valid, strips=WINDOW_STRIPS)
        if hidden is not None:  # the centroid's bias, beside the fallback's
            bias = math.hypot(bias, hidden)
    # a wide window's pull into lopsided curves' longer flank, a truncated curve's near
    # an end of the range, the argmax's sub-level offset: judged on the ring's curves, or
    # a streaming scan's SPC, PC or argmax on the judged rows it keeps (the grid)
    curves = src.fv if src.fv is not None else src.grid
    if method in DEPARTURE_METHODS and src.uncertainty and curves is not None:
        bias = blocks.block_departure_bias(
            gather(curves, u0, u1, src.ring), gather(src.argmax, u0, u1, src.ring),
            scratch(a, "b_depth", shape), _centre(src, u0, u1), valid,
            rows_sampled=src.fv is None)
    return (scratch(a, "b_depth", shape), scratch(a, "b_conf", shape),
            scratch(a, "b_sums", (3, *shape)), scratch(a, "b_low", shape), bias, locking)


def _centre(src: BlockSource, u0: int, u1: int) -> np.ndarray:
    """The filtered argmax of columns [u0, u1) as the depth task takes it (the median
    over ``median_size`` px of the argmax with the halo's columns), at the pixels the
    block's choice judges (every ``SHAPE_SAMPLE_STEP``-th row and column)."""
    a0, a1 = max(u0 - src.halo, src.first_u), min(u1 + src.halo, src.end_u)
    return blocks.judged_centre(gather(src.argmax, a0, a1, src.ring), src.median_size,
                                block=(u0 - a0, u1 - a0))


def _uncertainty(src: BlockSource, depth: np.ndarray, valid: np.ndarray, fill: float,
                 bias: float, locking: float) -> np.ndarray:
    """The block's height uncertainty, µm (a new array), its invalid pixels' depth
    taken as ``fill`` (:func:`sffscan.stages.volume_tasks.uncertainty` on each band,
    from the block's scratch arrays that :func:`_depth` filled)."""
    a, shape = src.arrays, depth.shape
    np.copyto(scratch(a, "b_filled", shape), np.where(valid, depth, fill))
    np.copyto(scratch(a, "b_valid", shape), valid)
    src.run_task("uncertainty", {
        "rows": shape[0], "width": shape[1], "n_levels": src.n, "method": src.method,
        "window": src.spread_size, "bias": bias, "locking": locking})
    return scratch(a, "b_unc", shape).copy()
