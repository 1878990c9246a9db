"""How the default depth method chooses its estimator, per stack or per scan block, from
the curves' statistics (:mod:`sffscan.stages.depth_statistics`; SFF_NOTES.md section 3;
docs/depth-method.md):

* :func:`shape_select`: SPC for a stack whose focus curves pass SPC's tests (even, clean,
  a small centroid pull, SPC not much noisier than the fallback and not departing from the
  curves' peaks by more than their spread: :func:`~sffscan.stages.depth_spc.takes_spc`;
  the tests, their limits and why are :mod:`sffscan.stages.depth_spc`'s), else
  ``adaptive_centroid``; SPC's depth only where it lies a reach of curve widths from the
  range's ends (:func:`~sffscan.stages.depth_spc.spc_in_range`). The default of scan,
  replay and stack since 2026-12-02.
* ``adaptive_centroid``'s statistic,
  :func:`~sffscan.stages.depth_statistics.centroid_pull`: how far the 5-level centroid
  about each curve's argmax lies from its 3-point Gaussian, the median over the curves;
  :func:`~sffscan.stages.depth_statistics.takes_centroid` below
  :data:`~sffscan.stages.depth_statistics.CENTROID_PULL_LIMIT` or the pull's own noise;
  and where the focus window sees several heights, the 11-level centroid that ``adaptive``
  takes there only where it does not depart from the peak estimator by more than their
  differences' spread (:func:`takes_wide_centroid`,
  :func:`~sffscan.stages.depth_statistics.wide_departure`).

A scan's block is judged on its :func:`~sffscan.stages.depth_statistics.sampled_curves`
(:func:`sffscan.stages.block_depth.block_method`). The thresholds are the
leave-one-family-out protocol's (:mod:`sffscan.stages.depth_study`); the estimators the
study tried beside them are in :mod:`sffscan.stages.depth_candidates`.
"""

from __future__ import annotations

import math
from typing import NamedTuple

import numpy as np
from sffscan.stages.curve_shape import curve_width
from sffscan.stages.depth_floor import GuardFloor
from sffscan.stages.depth_levels import median_filter_levels_at
from sffscan.stages.depth_spc import (
    SPC_NOISE_RATIO,
    SPC_PULL_LIMIT,
    spc_bias,
    spc_shape,
    spc_share,
    takes_spc,
)
from sffscan.stages.depth_statistics import (
    judged_curves,
    peak_departure,
    pull_statistics,
    sample_step,
    stack_sample,
    takes_centroid,
    wide_departure,
)

__all__ = ["DEPARTURE_METHODS", "PEAK_METHODS", "StackChoice", "centroid_locking",
           "fallback_bias", "judged_width", "method_bias", "method_locking", "peak_locking",
           "shape_select", "stack_choice", "takes_wide_centroid", "wide_choice"]


def takes_wide_centroid(departure: tuple[float, float]) -> bool:
    """Whether ``adaptive_centroid`` (and ``"shape_select"``'s fallback) keeps the wide
    centroid where the focus window sees several heights, given its
    :func:`~sffscan.stages.depth_statistics.wide_departure` ``(d, s)``: ``|d| <= s``; also
    for NaN (no such pixel judged). Else the peak estimator
    (:func:`~sffscan.stages.depth_statistics.takes_centroid`'s) is taken at every pixel.

    ``"adaptive"`` takes, where the filtered peaks in the focus window span more than
    :data:`~sffscan.stages.depth_adaptive.ADAPTIVE_MAX_SPREAD` levels (a slope, an edge, a
    rough or noisy surface), the baseline-free centroid of 11 levels: the middle of a blend
    of peaks, and less noisy than a peak where noise moved the argmax. On a smooth slope the
    blend is even about the pixel's own height, so its peak is not biased, while the
    11-level window reaches into the curves' tails and the centroid is pulled (by a median
    +0.18 levels against the 3-point Gaussian on the study's ``slopes`` family, whose
    differences spread 0.14). The test is a bias-variance comparison with no tuned
    constant, as :func:`~sffscan.stages.depth_spc.takes_spc`'s departure test: a departure
    larger than the spread is a bias of the wide centroid larger than the noise it saves.
    Measured with the leave-one-family-out protocol (the twenty families; docs/depth-study.md,
    docs/depth-method-log.md), the default's ratio to the best single method on ``slopes``
    1.04x -> 1.00x (held out, seeds 3..5), 1.10x -> 1.00x (6..11), 1.24x -> 1.00x (24..29),
    ``slopes-lens-pillbox`` 1.05-1.08x -> 1.00-1.05x; on seeds 30..35, set aside before
    the test was written, ``slopes-lens-pillbox`` 1.11x -> 1.07x and ``slopes-lens-noisy``
    1.06x -> 1.05x; no row worse by more than 1.1 % (``flat-lens-12bit``, seeds 12..17,
    1.488x -> 1.504x).
    """
    d, s = departure
    return not abs(d) > s


def wide_choice(depth: np.ndarray, wide_peak: np.ndarray, *, step: tuple[int, int],
                valid: np.ndarray | None = None) -> bool:
    """``adaptive_centroid``'s choice of the wide centroid for a stack or a block, in place:
    where :func:`takes_wide_centroid` refuses it, ``depth`` takes ``wide_peak`` at every
    pixel where that is finite.

    Parameters
    ----------
    depth : (H, W) ndarray of float32
        The fallback's depth (:func:`sffscan.stages.depth_adaptive.adaptive_block`), levels;
        changed in place.
    wide_peak : (H, W) ndarray of float32
        The peak estimator's depth where the wide centroid was taken, NaN elsewhere
        (``adaptive_block``'s ``wide_peak_out``).
    step : (int, int), keyword-only
        The grid the pixels are judged on, every ``step[0]``-th row and ``step[1]``-th
        column (:func:`~sffscan.stages.depth_statistics.sample_step` for a stack,
        :data:`~sffscan.stages.depth_statistics.SHAPE_SAMPLE_STEP` for a scan's block).
    valid : (H, W) ndarray of bool, optional, keyword-only
        The pixels judged (a block's whole curves); all when None.

    Returns
    -------
    bool
        True if the peak estimator was taken.
    """
    rs, cs = step
    w = wide_peak[::rs, ::cs]
    judged = np.isfinite(w)
    if valid is not None:
        judged &= np.asarray(valid, bool)[::rs, ::cs]
    if takes_wide_centroid(wide_departure(depth[::rs, ::cs][judged], w[judged])):
        return False
    np.copyto(depth, wide_peak, where=np.isfinite(wide_peak))
    return True


def shape_select(spc: np.ndarray, other: np.ndarray, statistics: tuple[float, float], *,
                 max_skew: float, max_ratio: float, in_range: np.ndarray | None = None,
                 pull: float | None = None, max_pull: float = SPC_PULL_LIMIT,
                 noise: tuple[float, float] | None = None,
                 max_noise_ratio: float = SPC_NOISE_RATIO,
                 departure: tuple[float, float] | None = None,
                 weight: float = 1.0) -> np.ndarray:
    """SPC's depth map where the stack's curves are even and clean
    (:func:`~sffscan.stages.depth_spc.takes_spc`), averaged with ``other`` by SPC's share
    ``weight`` (:func:`~sffscan.stages.depth_spc.spc_weight`; 1: SPC alone), else ``other``
    (``adaptive_centroid``'s depth map in ``"shape_select"``); float32 levels. One choice
    for the whole stack (the streaming depth stage chooses per block:
    :func:`sffscan.stages.block_depth.block_method`); where SPC is taken, ``other`` still
    stands alone at the pixels outside ``in_range``
    (:func:`~sffscan.stages.depth_spc.spc_in_range`; all inside when None). ``pull``,
    ``max_pull``, ``noise``, ``max_noise_ratio``, ``departure``: as for
    :func:`~sffscan.stages.depth_spc.takes_spc`."""
    use_spc = takes_spc(statistics, max_skew=max_skew, max_ratio=max_ratio, pull=pull,
                        max_pull=max_pull, noise=noise,
                        max_noise_ratio=max_noise_ratio, departure=departure)
    if not use_spc:
        return np.asarray(other, np.float32)
    mixed = spc_share(spc, other, weight)
    if in_range is None:
        return mixed
    return np.where(in_range, mixed, other).astype(np.float32, copy=False)


class StackChoice(NamedTuple):
    """``"shape_select"``'s choice for a stack (:func:`stack_choice`)."""

    spc: bool
    """The stack takes SPC (where it is in range)."""
    bias: float
    """A bias of the depth that its scatter does not show, which the height uncertainty
    adds in quadrature (:mod:`sffscan.stages.depth_uncertainty`), levels: where the stack
    takes SPC, SPC's departure from the fallback's peaks, ``|d|`` of
    :func:`~sffscan.stages.depth_spc.spc_departure`, times SPC's share of the depth
    (:attr:`weight`: the average departs from the peaks by that much); elsewhere the
    fallback's own, :func:`fallback_bias`."""
    pull: float
    """The curves' centroid pull (:func:`~sffscan.stages.depth_statistics.pull_statistics`),
    levels."""
    noise: float
    """The pull's noise (:func:`~sffscan.stages.depth_statistics.pull_statistics`), levels."""
    floor: GuardFloor | None = None
    """Where the stack takes SPC, what its range guard's widths take from the judged curves
    (:func:`~sffscan.stages.depth_floor.guard_floor`, for
    :func:`~sffscan.stages.depth_floor.guard_width`); None elsewhere."""
    locking: float = 0.0
    """Where the fallback takes the 5-level centroid, its peak locking at the judged curves'
    median width (:func:`peak_locking`, levels), which the height uncertainty adds where the
    scatter cannot show it (:func:`sffscan.stages.depth_uncertainty.locking_visibility`),
    times the fallback's share of the depth (``1 - weight``); 0.0 elsewhere."""
    weight: float = 0.0
    """SPC's share of the depth where the stack takes SPC and SPC is in range
    (:func:`~sffscan.stages.depth_spc.spc_weight`, 0 to 1), the fallback's the rest; 0.0
    where the stack takes the fallback."""


def stack_choice(volume: np.ndarray, argmax: np.ndarray, width: np.ndarray | None = None,
                 *, median_size: int = 11, margin: int = 0) -> StackChoice:
    """``"shape_select"``'s choice for a whole stack, judged on
    :func:`~sffscan.stages.depth_statistics.stack_sample`'s curves as
    :func:`sffscan.stages.depth.depth_from_focus` judges it (a scan's block is judged by
    :func:`sffscan.stages.block_depth.block_choice`).

    Parameters
    ----------
    volume : (N, H, W) ndarray of float
        The focus curves.
    argmax : (H, W) ndarray of int
        Their argmax.
    width : (H, W) ndarray of float, optional
        Their widths (:func:`sffscan.stages.curve_shape.curve_width`; computed when
        None).
    median_size : int, keyword-only
        The argmax's median filter, px (odd), as the depth's: SPC's departure is measured
        about the filtered argmax (:func:`~sffscan.stages.depth_spc.spc_departure`).
    margin : int, keyword-only
        SPC's mean-square tests (its noise, its range guard's floor and its departure:
        :func:`~sffscan.stages.depth_spc.spc_bias`' ``mask``) leave out the curves within
        this many px of the image's edges: a stack's is the focus window's reach
        (``spread_size // 2`` of :func:`sffscan.stages.depth.depth_from_focus`, which a
        stack's reconstruction sets to its focus window), where the focus measure reads the
        image's padding (a scan's frames leave it out of every curve already:
        :func:`sffscan.stages.volume_columns.new_columns`' ``margin``). A mean square is
        carried by a few wild curves, the medians of the skewness and the centroid pull are
        not, and they keep every curve. Since 2026-12-06: on the study's 64 px stacks the
        border is 23 % of the curves; on ``slopes-lens-noisy`` seed 219 the spread of SPC
        minus the peaks was 1.16 levels inside, 3.86 on the border, and the stack took SPC
        at 2.2x the fallback's error (docs/depth-method-log.md). 0 judges every curve; a
        stack of at most ``2 margin`` px a side leaves none for them and takes the fallback.
    """
    if width is None:
        width = curve_width(volume)
    vol, peak, wid = stack_sample(volume, argmax, width)
    assert wid is not None
    s = sample_step(np.shape(argmax))
    h, w = np.shape(argmax)
    rows, cols = np.arange(0, h, s), np.arange(0, w, s)
    inner = (None if margin <= 0 else
             ((rows >= margin) & (rows < h - margin))[:, None]
             & ((cols >= margin) & (cols < w - margin))[None, :])
    pull, noise = pull_statistics(vol, peak)
    taken = spc_bias(vol, peak, spc_shape(vol, peak, wid), pull, noise, inner,
                     centre=lambda: median_filter_levels_at(argmax, median_size, rows, cols))
    locking = peak_locking(pull, noise, judged_width(wid, peak, volume.shape[0]))
    if taken is None:
        return StackChoice(False, fallback_bias(pull), pull, noise, None, locking)
    w = taken.weight
    return StackChoice(True, w * taken.departure, pull, noise, taken.floor,
                       (1.0 - w) * locking, w)


DEPARTURE_METHODS = ("pc", "spc", "wcentroid", "argmax")
"""The methods that read the whole curve (PC, SPC) or a wide window of it (the 9-level
centroid) and keep the constants fitted to the default's errors
(:data:`sffscan.stages.fitted_constants.OTHER_METHODS_CONSTANTS`), and the argmax, whose
depth is the peak's level without its sub-level offset (a flat's whole quantisation error,
the same on every pixel, which its scatter does not show): the height uncertainty adds the
size of their :func:`~sffscan.stages.depth_statistics.peak_departure` as their bias
(:func:`method_bias`), as ``"shape_select"`` adds SPC's where it takes SPC. Added 2026-12-05
(night; seeds 6..47, 140 (seed set, family) rows each, under the 90-98 % band / in it:
wcentroid 25 -> 1 / 105 -> 107, spc 58 -> 3 / 77 -> 89, pc 59 -> 3 / 76 -> 88;
docs/depth-method-log.md); the argmax later that night (its constants refitted with it, per
fold: in / under / over 116 / 6 / 18 -> 135 / 3 / 2)."""

PEAK_METHODS = ("adaptive", "adaptive_centroid")
"""The methods whose depth is a peak about each curve's filtered argmax (the 3-point
Gaussian or the 5-level centroid), as ``"shape_select"``'s fallback's is: the height
uncertainty adds their :func:`fallback_bias`."""


def centroid_locking(width: float, *, half_window: int = 2, fractions: int = 64) -> float:
    """The peak locking of the baseline-free centroid over ``2 half_window + 1`` levels
    (:func:`~sffscan.stages.depth_peak.windowed_centroid`) on noise-free Gaussian curves of
    sigma ``width`` levels: the RMS of its error over the true peak's fraction of a level
    (``fractions`` evenly spaced fractions in -0.5 .. 0.5), levels; 0.0 for a NaN width (no
    curve judged).

    The centroid subtracts its window's minimum, the far end's level, so its weights are
    lopsided wherever the peak lies off a level: it errs away from the level, by a sine of
    the fraction (measured against the estimator itself, docs/depth-method-log.md: RMS
    0.018 / 0.039 / 0.049 / 0.056 / 0.062 levels at sigma 1 / 1.5 / 2 / 3 / 10 with 5 levels).
    Not a noise and the same on every curve of one width and fraction: a flat surface whose
    curves share one fraction errs by it everywhere, which neither the scatter nor the relief
    shows. The geometry of the estimator; no fitted constant.
    """
    if not math.isfinite(width):
        return 0.0
    t = (np.arange(fractions) + 0.5) / fractions - 0.5
    j = np.arange(-half_window, half_window + 1, dtype=np.float64)
    w = max(float(width), 1e-3)
    f = np.exp(-((j[None, :] - t[:, None]) ** 2) / (2.0 * w * w))
    f -= f.min(axis=1, keepdims=True)
    s0 = f.sum(axis=1)
    offset = np.divide(f @ j, s0, out=np.zeros_like(s0), where=s0 > 0)
    return float(np.sqrt(np.mean((offset - t) ** 2)))


def judged_width(width: np.ndarray, argmax: np.ndarray, n: int,
                 mask: np.ndarray | None = None) -> float:
    """The median width (levels) of the curves :func:`~sffscan.stages.depth_statistics.
    pull_statistics` judges (the ``mask`` ones whose argmax lies 2 levels or more from both
    ends of the N levels; finite widths); NaN where none is left."""
    _, ok = judged_curves(argmax, n, mask)
    w = np.asarray(width)[ok]
    w = w[np.isfinite(w)]
    return float(np.median(w)) if w.size else math.nan


def peak_locking(pull: float, noise: float, width: float) -> float:
    """The locking (levels) of the peak a peak method takes for curves of this pull and noise
    (:func:`~sffscan.stages.depth_statistics.pull_statistics`) and median ``width``
    (levels): :func:`centroid_locking` where it takes the 5-level centroid
    (:func:`~sffscan.stages.depth_statistics.takes_centroid`), else 0.0 (the 3-point
    Gaussian is exact on a Gaussian curve)."""
    if math.isnan(pull) or not takes_centroid(pull, noise=noise):
        return 0.0
    return centroid_locking(width)


def fallback_bias(pull: float) -> float:
    """The bias of a peak method's depth the height uncertainty adds in quadrature (levels):
    the size of the curves' centroid pull (:func:`~sffscan.stages.depth_statistics.pull_statistics`:
    the median over the curves of the 5-level centroid minus the 3-point Gaussian about each
    argmax); 0.0 where no curve was judged (NaN).

    Two peak estimators that agree on even curves disagree by that much, the same way on
    every curve, where the curves are lopsided or flat-topped (a thin lens, a pillbox): a
    bias of the map of about that size, which its scatter cannot show, as SPC's departure
    is where SPC is taken; added as it is (no constant). For ``"shape_select"``'s fallback
    (:attr:`StackChoice.bias`, a scan block's :func:`sffscan.stages.block_depth.
    block_choice`) and the :data:`PEAK_METHODS` by name. Added 2026-12-04 (late night):
    held-out sets under the uncertainty's band (the side that misleads) 1 -> 0 of 11 (seeds
    3..5), 3 -> 2 of 21 (crossed families), 3 -> 2 (seeds 6..11), 3 -> 1 (seeds 12..17),
    3 -> 2 (seeds 18..23, scored once, after the others); pertuz-simu02 0.836 -> 0.991, over
    the band (docs/depth-method-log.md)."""
    return abs(pull) if math.isfinite(pull) else 0.0


def method_bias(volume: np.ndarray, argmax: np.ndarray, method: str, *,
                median_size: int = 11, width: np.ndarray | None = None,
                depth: np.ndarray | None = None, margin: int = 0) -> float:
    """The bias (levels) the height uncertainty of a whole stack reconstructed with
    ``method`` adds: ``"shape_select"``'s :attr:`StackChoice.bias`, a peak method's
    :func:`fallback_bias` on :func:`~sffscan.stages.depth_statistics.stack_sample`'s curves, a
    method of :data:`DEPARTURE_METHODS` the size of its :func:`~sffscan.stages.
    depth_statistics.peak_departure` there (its ``depth`` needed), 0.0 for the other
    methods. ``volume``, ``argmax``, ``width``, ``median_size`` and ``margin`` (for
    ``"shape_select"``: the depth's ``spread_size // 2``) as :func:`stack_choice`'s
    (``width`` from the curves' sums, as the depth's choice takes it, saves its float64
    :func:`~sffscan.stages.curve_shape.curve_width`); ``method`` the depth method. For
    ``"shape_select"`` this is its choice's bias before the fallback's 9-level centroid is
    weighed (that needs the depth maps):
    :func:`sffscan.stages.depth.shape_select_with_bias` gives the whole of it with the
    depth, and is what a stack's reconstruction takes."""
    if method == "shape_select":
        return stack_choice(volume, argmax, width, median_size=median_size,
                            margin=margin).bias
    if method in PEAK_METHODS:
        vol, peak, _ = stack_sample(volume, argmax)
        return fallback_bias(pull_statistics(vol, peak)[0])
    if method in DEPARTURE_METHODS:
        if depth is None:
            raise ValueError(f"method {method!r}: its bias is its depth's departure from the "
                             "curves' peaks: give the depth")
        s = sample_step(np.shape(argmax))
        h, w = np.shape(argmax)
        centre = median_filter_levels_at(argmax, median_size, np.arange(0, h, s),
                                         np.arange(0, w, s))
        vol = stack_sample(volume, argmax)[0]
        return fallback_bias(peak_departure(np.asarray(depth)[::s, ::s], vol, centre))
    return 0.0


def method_locking(volume: np.ndarray, argmax: np.ndarray, method: str, *,
                   median_size: int = 11, width: np.ndarray | None = None,
                   margin: int = 0) -> float:
    """The peak locking (levels) of a whole stack reconstructed with ``method``, which the
    height uncertainty adds where its scatter cannot show it
    (:func:`sffscan.stages.depth_uncertainty.locking_visibility`): ``"shape_select"``'s
    :attr:`StackChoice.locking`, ``"adaptive_centroid"``'s :func:`peak_locking` on
    :func:`~sffscan.stages.depth_statistics.stack_sample`'s curves, 0.0 for the other
    methods (``"adaptive"``'s 3-point Gaussian is exact on a Gaussian curve). ``width``: the
    curves' widths from their sums, as the depth's choice takes them (computed when None);
    ``margin`` as :func:`stack_choice`'s."""
    if method == "shape_select":
        return stack_choice(volume, argmax, width, median_size=median_size,
                            margin=margin).locking
    if method == "adaptive_centroid":
        vol, peak, wid = stack_sample(volume, argmax, width)
        if wid is None:
            wid = curve_width(vol)
        pull, noise = pull_statistics(vol, peak)
        return peak_locking(pull, noise, judged_width(wid, peak, volume.shape[0]))
    return 0.0

