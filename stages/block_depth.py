"""A block of the focus volume reduced to depth, a band of rows at a time.

:func:`sffscan.stages.volume_reduce.reduce_block` (the core of
:meth:`sffscan.stages.focus_volume.FocusVolume.reduce`) hands each band of rows of a
block to :func:`depth_rows`, then to :func:`block_uncertainty`, as band tasks
(:mod:`sffscan.stages.volume_tasks`, which gather the block's state: the curves' sums or
levels, the running argmax and minimum). Each reads its rows
widened by the filters' reach and returns its own rows only, so the block is bit-identical
whatever the bands (:mod:`sffscan.stages.bands`; tested in ``tests/stages/test_bands.py``).
"""

from __future__ import annotations

from collections.abc import Callable
from typing import NamedTuple

import numpy as np
from sffscan.stages.curve_shape import curve_width
from sffscan.stages.depth import depth_from_focus
from sffscan.stages.depth_adaptive import adaptive_block
from sffscan.stages.depth_choice import fallback_bias, judged_width, peak_locking
from sffscan.stages.depth_floor import GuardFloor, guard_width
from sffscan.stages.depth_harmonics import (
    confidence_from_sums,
    depth_from_harmonics,
    focus_sums,
    magnitude,
    spc_depth,
)
from sffscan.stages.depth_levels import (
    level_spread,
    median_filter_levels,
    median_filter_levels_at,
)
from sffscan.stages.depth_peak import windowed_centroid
from sffscan.stages.depth_spc import spc_bias, spc_in_range, spc_shape, spc_share
from sffscan.stages.depth_statistics import (
    SHAPE_SAMPLE_STEP,
    peak_departure,
    pull_statistics,
    sampled_curves,
    takes_centroid,
)
from sffscan.stages.depth_uncertainty import height_uncertainty_um

__all__ = ["BLOCK_CHOICES", "OWN_LEVEL_METHODS", "SPC_BLOCKS", "BlockChoice", "block_choice",
           "block_departure_bias", "block_method", "block_peak_bias", "block_uncertainty",
           "depth_rows", "judged_centre"]

BLOCK_CHOICES = ("shape_select", "adaptive_centroid")
"""The methods that choose once for each block of columns (:func:`block_method`)."""

OWN_LEVEL_METHODS = ("wcentroid", "adaptive", "adaptive_centroid")
"""The methods that read only the block's own columns' levels (about the filtered argmax);
the other ring methods read the halo's columns too, except the blocks of
:data:`SPC_BLOCKS`, which read their own columns only."""

SPC_BLOCKS = {"spc+centroid": "centroid", "spc+gauss3": "gauss3"}
"""What :func:`block_method` names a ``"shape_select"`` block that takes SPC: SPC averaged
with what ``"adaptive_centroid"`` takes (``adaptive``'s peak refined by the 5-level centroid
or by the 3-point Gaussian) by SPC's share (:func:`sffscan.stages.depth_spc.spc_weight`),
and at its pixels outside the range SPC holds in
(:func:`sffscan.stages.depth_spc.spc_in_range`) that fallback alone."""


class BlockChoice(NamedTuple):
    """What a block takes (:func:`block_choice`)."""

    method: str
    """The block's method (an SPC block is named by :data:`SPC_BLOCKS`)."""
    bias: float
    """The bias the height uncertainty adds in quadrature, levels."""
    floor: GuardFloor | None
    """What SPC's range guard takes from the block's curves; None but for an SPC block."""
    locking: float
    """The 5-level centroid's peak locking the uncertainty adds, levels (0.0 where none)."""
    weight: float = 0.0
    """SPC's share of an SPC block's depth where SPC is in range
    (:func:`sffscan.stages.depth_spc.spc_weight`, 0 to 1); 0.0 for the other blocks."""


def block_method(levels: np.ndarray, argmax: np.ndarray,
                 valid: np.ndarray | None = None, *, method: str = "shape_select",
                 median_size: int = 11) -> str:
    """The method a block takes: :func:`block_choice`'s first element."""
    return block_choice(levels, argmax, valid, method=method, median_size=median_size)[0]


def block_choice(levels: np.ndarray, argmax: np.ndarray,
                 valid: np.ndarray | None = None, *, method: str = "shape_select",
                 median_size: int = 11,
                 centre: Callable[[], np.ndarray] | None = None
                 ) -> BlockChoice:
    """The method a block takes, the bias the height uncertainty adds in quadrature
    (levels: where it takes SPC, the departure ``|d|`` of
    :func:`sffscan.stages.depth_spc.spc_departure` times SPC's share; where it takes a
    peak, the :func:`sffscan.stages.depth_choice.fallback_bias` of its curves) and, where
    it takes SPC, what SPC's range guard takes from its curves
    (:func:`sffscan.stages.depth_floor.guard_floor`; None elsewhere: :func:`depth_rows`'
    ``floor``) and, where the fallback takes the 5-level centroid, that centroid's peak
    locking at the judged curves' median width
    (:func:`sffscan.stages.depth_choice.peak_locking`, levels, times the fallback's share
    of an SPC block; 0.0 elsewhere), and SPC's share of an SPC block
    (:func:`sffscan.stages.depth_spc.spc_weight`; 0.0 elsewhere), judged on the curves of
    :data:`sffscan.stages.depth_statistics.SHAPE_SAMPLE_STEP`
    (:func:`sffscan.stages.depth_statistics.sampled_curves`).

    ``"shape_select"``: SPC where its curves are even and clean
    (:func:`sffscan.stages.depth_choice.shape_select`'s rule at its tuned limits, the
    centroid pull's included), named
    by :data:`SPC_BLOCKS` with what ``"adaptive_centroid"`` takes where SPC is out of range;
    else what ``"adaptive_centroid"`` takes.
    ``"adaptive_centroid"``: itself where a centroid is not pulled from its curves' maxima
    more than their 3-point Gaussians' noise
    (:func:`sffscan.stages.depth_statistics.pull_statistics`,
    :func:`~sffscan.stages.depth_statistics.takes_centroid`), else ``"adaptive"``.

    Parameters
    ----------
    levels : (N, rows, block) ndarray of float32
        The block's curves.
    argmax : (rows, block) ndarray of int
        Their argmax.
    valid : ndarray of bool broadcastable to (rows, block), optional
        The curves seen at every level (a (block,) mask of the columns seen at every level,
        or a (rows, block) one, each pixel's); the others are left out, whatever the ring
        holds there, and so are the curves without data (flat: the rows beyond the frames,
        kept for wobble). A block with no such curve takes ``"adaptive"``.
    method : {"shape_select", "adaptive_centroid"}, keyword-only
    median_size : int, keyword-only
        The argmax's median filter, px (odd), as the block's depth takes it.
    centre : callable, optional, keyword-only
        Gives the filtered argmax the block's depth is taken about, at the judged grid's
        pixels (every ``SHAPE_SAMPLE_STEP[0]``-th row and ``[1]``-th column: the shape of
        :func:`~sffscan.stages.depth_statistics.sampled_curves`' argmax), which SPC's
        departure is measured about (:func:`sffscan.stages.depth_spc.spc_departure`);
        called only where the curves pass SPC's other tests. A scan's block passes one
        that filters with its halo's columns (:func:`judged_centre`); when None,
        ``argmax`` filtered over ``median_size`` px within the block.
    """
    if method not in BLOCK_CHOICES:
        raise ValueError(f"method must be one of {BLOCK_CHOICES}, got {method!r}")
    sample = sampled_curves(levels, argmax, valid)
    if sample is None:
        return BlockChoice("adaptive", 0.0, None, 0.0)
    vol, am, seen = sample
    pull, noise = pull_statistics(vol, am, seen)
    centroid = takes_centroid(pull, noise=noise)
    width = curve_width(vol)
    locking = peak_locking(pull, noise, judged_width(width, am, vol.shape[0], seen))
    if method == "shape_select":
        stats = spc_shape(vol, am, width, seen)
        taken = spc_bias(vol, am, stats, pull, noise, seen,
                         centre=(lambda: judged_centre(argmax, median_size)) if centre is None
                         else centre)
        if taken is not None:
            w = taken.weight
            return BlockChoice("spc+centroid" if centroid else "spc+gauss3",
                               w * taken.departure, taken.floor, (1.0 - w) * locking, w)
    return BlockChoice("adaptive_centroid" if centroid else "adaptive", fallback_bias(pull),
                       None, locking)


def judged_centre(argmax: np.ndarray, median_size: int, *,
                  block: tuple[int, int] | None = None) -> np.ndarray:
    """``argmax`` median filtered over ``median_size`` px at the pixels
    :func:`~sffscan.stages.depth_statistics.sampled_curves` judges: every
    ``SHAPE_SAMPLE_STEP[0]``-th row and ``[1]``-th column of the block, which is the
    columns ``block`` = (first, end) of ``argmax`` (a scan's block with its halo's columns
    about it) or all of them when None."""
    rs, cs = SHAPE_SAMPLE_STEP
    h, w = np.shape(argmax)
    c0, c1 = (0, w) if block is None else block
    return median_filter_levels_at(argmax, median_size, np.arange(0, h, rs),
                                   np.arange(c0, c1, cs))


def block_peak_bias(levels: np.ndarray, argmax: np.ndarray,
                    valid: np.ndarray | None = None) -> float:
    """The height uncertainty's bias of a block reconstructed by ``"adaptive"`` (levels):
    :func:`sffscan.stages.depth_choice.fallback_bias` of the curves :func:`block_choice`
    judges (0.0 where none has data). Parameters as :func:`block_choice`'s."""
    sample = sampled_curves(levels, argmax, valid)
    if sample is None:
        return 0.0
    return fallback_bias(pull_statistics(*sample)[0])


def block_departure_bias(levels: np.ndarray, argmax: np.ndarray, depth: np.ndarray,
                         centre: np.ndarray, valid: np.ndarray | None = None, *,
                         rows_sampled: bool = False) -> float:
    """The height uncertainty's bias of a block reconstructed by a method of
    :data:`sffscan.stages.depth_choice.DEPARTURE_METHODS` (levels): the size of its depth's
    :func:`~sffscan.stages.depth_statistics.peak_departure` at the curves :func:`block_choice`
    judges, as a stack's :func:`sffscan.stages.depth_choice.method_bias` (0.0 where none has
    data).

    Parameters
    ----------
    levels, argmax, valid
        As :func:`block_choice`'s.
    depth : (rows, block) ndarray of float
        The block's depth, levels.
    centre : ndarray of int
        The filtered argmax the block's depth is taken about at the judged grid's pixels
        (:func:`judged_centre`: the shape of
        :func:`~sffscan.stages.depth_statistics.sampled_curves`' argmax).
    rows_sampled : bool, keyword-only
        ``levels`` holds only the judged rows (every ``SHAPE_SAMPLE_STEP[0]``-th, from the
        first: a streaming scan's grid), ``(N, ceil(rows / step), block)``.
    """
    sample = sampled_curves(levels, argmax, valid, rows_sampled=rows_sampled)
    if sample is None:
        return 0.0
    vol, am, seen = sample
    if np.shape(centre) != np.shape(am):
        raise ValueError(f"centre must give the judged curves' {np.shape(am)} pixels, got "
                         f"shape {np.shape(centre)}")
    rs, cs = SHAPE_SAMPLE_STEP
    return fallback_bias(peak_departure(np.asarray(depth)[::rs, ::cs], vol, centre, seen))


def depth_rows(src: np.ndarray, argmax: np.ndarray, low_src: np.ndarray | None,
               rows: tuple[int, int], own: slice, inner: slice, sums: np.ndarray,
               low: np.ndarray, *, method: str, n_levels: int, median_size: int,
               spread_size: int, streaming: bool, keep_low: bool,
               wide_peak: np.ndarray | None = None,
               window_out: np.ndarray | None = None,
               floor: GuardFloor | None = None,
               spc_weight: float = 1.0) -> tuple[np.ndarray, np.ndarray]:
    """Depth (levels) and confidence of rows [r0, r1) of a block.

    Parameters
    ----------
    src : ndarray of float32
        Rows of the block, every row or those of ``argmax`` (``rows`` index it): for the
        accumulating methods (``streaming``) the sums
        (S, rows, halo + block + halo columns); for wcentroid, adaptive, adaptive_centroid
        and the :data:`SPC_BLOCKS` the levels of the block's columns (N, rows, block); for
        the other methods the levels of the block and its halo (N, rows, halo + block +
        halo).
    argmax : ndarray of int, (R, halo + block + halo)
        The running argmax of rows [r0, r1) widened by the filters' reach (R rows).
    low_src : ndarray of float32 or None
        The accumulating methods' running minimum of ``src``'s rows, (rows, block), or None.
    rows : (int, int)
        The band [r0, r1), rows of ``src``.
    own : slice
        Rows [r0, r1) within ``argmax``'s R rows.
    inner : slice
        The block's columns within the halo.
    sums, low : ndarray of float32, (3, r1 - r0, block) and (r1 - r0, block)
        Outputs (the band's rows of the block's arrays): the curves' H_0, Re H_1, Im H_1
        and minimum (``low`` written where ``keep_low`` or the method reads the levels).
    method : str, keyword-only
        The depth method.
    n_levels, median_size, spread_size : int, keyword-only
        N, the SPC median's size and adaptive's spread window, px.
    streaming, keep_low : bool, keyword-only
        Whether ``src`` holds sums; whether the minimum is wanted.
    wide_peak : ndarray of float32, (r1 - r0, block), optional, keyword-only
        For ``"adaptive"`` and ``"adaptive_centroid"`` blocks: receives the peak
        estimator's depth where they took the wide centroid, NaN elsewhere
        (:func:`~sffscan.stages.depth_adaptive.adaptive_block`'s ``wide_peak_out``, for
        :func:`~sffscan.stages.depth_choice.wide_choice` over the whole block); NaN
        everywhere for the other methods.
    window_out : ndarray of float32, (r1 - r0, block), optional, keyword-only
        For ``"adaptive"`` and ``"adaptive_centroid"`` blocks of ``"shape_select"``:
        receives the 9-level centroid about the same filtered argmax
        (:func:`~sffscan.stages.depth_peak.windowed_centroid`, for
        :func:`sffscan.stages.depth_window.window_choice` over the whole block).
    floor : GuardFloor, optional, keyword-only
        For the :data:`SPC_BLOCKS`: what SPC's range guard takes from the block's judged
        curves (:func:`block_choice`'s third element, for
        :func:`sffscan.stages.depth_floor.guard_width`; one for the whole block, whatever
        its bands); None: the curves' minima as their floor.
    spc_weight : float, keyword-only
        For the :data:`SPC_BLOCKS`: SPC's share of the depth where it is in range
        (:func:`block_choice`'s ``weight``; :func:`sffscan.stages.depth_spc.spc_share`), the
        fallback's the rest; 1.0: SPC alone.

    Returns
    -------
    depth, confidence : ndarray of float32, (r1 - r0, block)
    """
    r0, r1 = rows
    wide = slice(r0 - own.start, r1 + (argmax.shape[0] - own.stop))  # argmax's rows
    if wide_peak is not None:
        wide_peak.fill(np.nan)  # adaptive_block overwrites it where it is asked to
    if streaming:
        planes = src[:, wide]
        full = np.zeros((4, *planes.shape[1:]), np.float32)
        full[0], full[2], full[3] = planes[0], planes[1], planes[2]
        if planes.shape[0] == 4:  # only the centroid uses sum k y
            full[1] = planes[3]
        depth, conf = depth_from_harmonics(full, argmax, n_levels=n_levels, method=method,
                                           median_size=median_size)
        sums[:] = full[[0, 2, 3]][:, own, inner]
        if keep_low and low_src is not None:
            low[:] = low_src[r0:r1]
        return depth[own, inner], conf[own, inner]
    if method in OWN_LEVEL_METHODS or method in SPC_BLOCKS:  # about the filtered argmax
        centre = median_filter_levels(argmax, median_size, n_levels)
        levels = src[:, r0:r1]
        if method == "wcentroid":
            depth = windowed_centroid(levels, centre[own, inner])
            sums[:] = focus_sums(levels)
            low[:] = levels.min(axis=0)
            return depth, confidence_from_sums(*sums)
        # depth and confidence in one pass over the levels
        spc_block = method in SPC_BLOCKS
        spread = level_spread(centre, spread_size, n_levels)
        peak = SPC_BLOCKS[method] if spc_block else (
            "centroid" if method == "adaptive_centroid" else "gauss3")
        depth, conf = adaptive_block(levels, centre[own, inner], spread[own, inner],
                                     peak=peak, sums_out=sums,
                                     min_out=low if keep_low or spc_block else None,
                                     wide_peak_out=None if spc_block else wide_peak,
                                     window_out=None if spc_block else window_out)
        if not spc_block:
            return depth, conf
        # SPC from that pass's float32 sums (the block's own columns) and filtered argmax,
        # not depth_from_focus's float64 sums over the halo's columns too and its own
        # median (the depths differ by float32 round-off); averaged with
        # adaptive_centroid's depth by SPC's share, which stands alone where SPC is out of
        # its range
        spc = spc_depth(sums[1], sums[2], centre[own, inner], n_levels=n_levels)
        width = guard_width(sums[0], magnitude(sums[1], sums[2]), low, n_levels, floor)
        keep = spc_in_range(spc, width, n_levels)
        return (np.where(keep, spc_share(spc, depth, spc_weight), depth).astype(
            np.float32, copy=False), conf)
    vol = src[:, wide]
    depth, conf = depth_from_focus(vol, method=method, median_size=median_size, argmax=argmax)
    sums[:] = focus_sums(vol[:, own, inner])
    low[:] = vol[:, own, inner].min(axis=0)
    return depth[own, inner], conf[own, inner]


def block_uncertainty(depth: np.ndarray, sums: np.ndarray, low: np.ndarray,
                      rows: tuple[int, int], *, method: str, n_levels: int,
                      focus_heights_um: np.ndarray, window: int, bias_levels: float = 0.0,
                      locking_levels: float = 0.0,
                      valid: np.ndarray | None = None) -> np.ndarray:
    """:func:`~sffscan.stages.depth_uncertainty.height_uncertainty_um` of rows [r0, r1)
    of a block, from the rows within its filters' reach (a 5 x 5 median, then ranges and
    means over ``2 window + 1`` px: 2 + ``window`` rows; one more is read).

    ``depth`` (levels, invalid pixels filled), ``sums`` (3, rows, block) and ``low`` hold
    every row of the block; ``method``: the scan's depth method (its constants:
    :func:`~sffscan.stages.fitted_constants.uncertainty_constants`); ``bias_levels``: the
    block's bias and ``locking_levels`` its locking (:func:`block_choice`);
    ``valid``: the block's pixels whose curves are whole (the others' sums and minima, left
    from earlier columns in the ring, are not read for their neighbours); returns float32
    (r1 - r0, block), µm.
    """
    r0, r1 = rows
    reach = 3 + window
    a0, a1 = max(r0 - reach, 0), min(r1 + reach, depth.shape[0])
    u = height_uncertainty_um(depth[a0:a1], sums[:, a0:a1], low[a0:a1], method=method,
                              n_levels=n_levels,
                              focus_heights_um=focus_heights_um, window=window,
                              bias_levels=bias_levels, locking_levels=locking_levels,
                              valid=None if valid is None else valid[a0:a1])
    return u[r0 - a0:r1 - a0]
