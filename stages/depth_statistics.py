"""The statistics of a stack's or a scan block's focus curves by which the default depth
method chooses its estimator (the choices are :mod:`sffscan.stages.depth_choice`'s, SPC's
tests :mod:`sffscan.stages.depth_spc`'s):

* which curves are judged: :func:`sampled_curves` (a scan's block, and the grid of
  :data:`SHAPE_SAMPLE_STEP`), :func:`stack_sample` (a whole stack,
  :data:`SHAPE_STACK_CURVES`), :func:`judged_curves` (those 2 levels or more from the
  range's ends);
* the centroid pull and its noise, :func:`pull_statistics` (:func:`centroid_pull`), and
  the test ``adaptive_centroid`` takes the 5-level centroid by, :func:`takes_centroid`
  (:data:`CENTROID_PULL_LIMIT`);
* the curves' shape, :func:`shape_statistics`: their skewness (:func:`curve_skew`) and the
  ratio of their harmonic width to their extent above half height;
* how far the fallback's wide centroid departs from its peak estimator where the focus
  window sees several heights, :func:`wide_departure` (on :func:`sample_step`'s lattice);
  how far a whole-curve or wide-window method's depth departs from the curves' peaks,
  :func:`peak_departure`;
* robust medians and spreads: :func:`median_spread`, :func:`row_median`.
"""

from __future__ import annotations

import math

import numpy as np
from sffscan.stages.depth_candidates import half_height_count
from sffscan.stages.depth_peak import three_point_offset, windowed_centroid

__all__ = ["CENTROID_PULL_LIMIT", "SHAPE_SAMPLE_STEP", "SHAPE_STACK_CURVES", "centroid_pull",
           "curve_skew", "judged_curves", "median_spread", "peak_departure", "pull_statistics",
           "row_median", "sample_step", "sampled_curves", "shape_statistics", "skew_statistic",
           "stack_sample", "takes_centroid", "wide_departure", "width_ratio_statistic"]


SHAPE_SAMPLE_STEP = (16, 8)
"""The curves' shape is judged on every 16th row and 8th column (:func:`sampled_curves`):
a 1040-row block of 64 columns gives 520 curves, enough to place two medians; judging every
curve would cost a scan's block more than its reduction (bench/results:
bench_depth_default.py)."""


def sampled_curves(levels: np.ndarray, argmax: np.ndarray,
                   valid: np.ndarray | None = None, *, rows_sampled: bool = False
                   ) -> tuple[np.ndarray, np.ndarray, np.ndarray] | None:
    """The curves of :data:`SHAPE_SAMPLE_STEP` a shape is judged on: (N, r, c) float32
    levels, their argmax and the mask of those with data, or None where none has.

    Parameters
    ----------
    levels : (N, rows, columns) ndarray of float
        The curves (a block of a scan, or a whole stack).
    argmax : (rows, columns) ndarray of int
        Their argmax.
    valid : ndarray of bool broadcastable to (rows, columns), optional
        The curves seen at every level (a (columns,) mask: the columns seen at every level;
        a (rows, columns) one: each pixel's); the others are left out, whatever their
        levels hold (a scan's ring keeps earlier columns' values), and so are the curves
        without data (flat: the rows beyond the frames, kept for wobble).
    rows_sampled : bool, keyword-only
        ``levels`` holds only the judged rows already (every ``SHAPE_SAMPLE_STEP[0]``-th
        row of ``argmax``'s, from the first).
    """
    rs, cs = SHAPE_SAMPLE_STEP
    vol = np.ascontiguousarray(levels[:, :, ::cs] if rows_sampled else levels[:, ::rs, ::cs],
                               dtype=np.float32)
    seen = vol.max(axis=0) > vol.min(axis=0)
    if valid is not None:
        seen &= np.broadcast_to(np.asarray(valid, bool), argmax.shape)[::rs, ::cs]
    if not seen.any():
        return None
    return vol, np.asarray(argmax)[::rs, ::cs], seen


SHAPE_STACK_CURVES = 16384
"""A whole stack is judged on an even grid of at least this many of its curves
(:func:`stack_sample`: every s-th row and column, ``s = floor(sqrt(curves / 16384))``),
as a scan's block is on :func:`sampled_curves`: the medians the choice takes are then
those of the whole stack within about 1 % of the curves' spread (a median of n values
has a standard error of about 1.25 sigma / sqrt n). Judging every curve had made
``shape_select`` 4.3-5.6x slower on 512 x 512 stacks, for the same maps
(docs/depth-method-log.md). Stacks of fewer than 4 x 16384 curves (the study's 64 x 64 px
among them) are judged on every curve."""


def stack_sample(volume: np.ndarray, argmax: np.ndarray, width: np.ndarray | None = None
                 ) -> tuple[np.ndarray, np.ndarray, np.ndarray | None]:
    """The curves of a whole stack its shape is judged on (:data:`SHAPE_STACK_CURVES`).

    Parameters
    ----------
    volume : (N, H, W) ndarray of float
        The stack's focus curves.
    argmax : (H, W) ndarray of int
        Their argmax.
    width : (H, W) ndarray of float, optional
        Their widths (:func:`sffscan.stages.curve_shape.curve_width`).

    Returns
    -------
    volume, argmax, width
        Every s-th row and column of each (the inputs themselves where s = 1; the volume a
        contiguous copy otherwise; width None where not given).
    """
    s = sample_step(np.shape(argmax))
    if s == 1:
        return volume, argmax, width
    return (np.ascontiguousarray(volume[:, ::s, ::s]), np.asarray(argmax)[::s, ::s],
            None if width is None else np.asarray(width)[::s, ::s])


def sample_step(shape: tuple[int, ...]) -> int:
    """The step s of :func:`stack_sample`'s grid for a stack of ``(H, W)`` pixels:
    ``floor(sqrt(H W / SHAPE_STACK_CURVES))``, at least 1."""
    h, w = shape
    return max(1, math.isqrt(h * w // SHAPE_STACK_CURVES))


def wide_departure(wide_depth: np.ndarray, peak_depth: np.ndarray) -> tuple[float, float]:
    """How far the wide centroid departs from the peak estimator, and how noisy that
    comparison is: over the judged pixels (those where the focus window sees several
    heights, on a sample's grid), the median of ``wide_depth - peak_depth`` (the
    *departure*) and its robust spread (:func:`median_spread`); NaN, NaN where no pixel is
    judged, which :func:`~sffscan.stages.depth_choice.takes_wide_centroid` takes as no
    departure.

    Parameters
    ----------
    wide_depth : ndarray of float
        Depth of the judged pixels by the baseline-free centroid of the 11 levels about the
        filtered argmax (what ``"adaptive"`` takes where the spread of the filtered peaks
        in the focus window exceeds :data:`~sffscan.stages.depth_adaptive.ADAPTIVE_MAX_SPREAD`),
        levels.
    peak_depth : ndarray of float
        Depth of the same pixels by the peak estimator (the 3-point Gaussian or the 5-level
        centroid at the filtered argmax), levels; same shape.
    """
    diff = np.asarray(wide_depth, np.float64) - np.asarray(peak_depth, np.float64)
    if diff.size == 0:
        return math.nan, math.nan
    return median_spread(diff.reshape(-1))


def peak_departure(depth: np.ndarray, levels: np.ndarray, centre: np.ndarray,
                   mask: np.ndarray | None = None) -> float:
    """How far a depth map departs from the curves' peaks: the median over the judged
    pixels (:func:`judged_curves` of ``centre``, the ``mask`` ones, finite ``depth``) of
    ``depth`` minus the 3-point Gaussian at ``centre``, levels; NaN where none is judged.

    On even curves a method that reads the whole curve (SPC, PC) or a wide window of it
    (the 9-level centroid) finds the peak, and the median is about 0 whatever the noise; on
    lopsided or flat-topped curves (a thin lens, a pillbox) it is pulled into the longer
    flank the same way on every curve: a bias of the map that its scatter does not show
    (SPC's departure in ``"shape_select"``'s test, :func:`~sffscan.stages.depth_spc.
    spc_departure`, is this against the fallback's peak).

    Parameters
    ----------
    depth : (H, W) ndarray of float
        The method's depth at the judged pixels, levels.
    levels : (N, H, W) ndarray of float
        Their focus curves.
    centre : (H, W) ndarray of int
        The filtered argmax the peak is read about (the depth's own).
    mask : (H, W) ndarray of bool, optional
        The pixels judged (all when None).
    """
    am, ok = judged_curves(centre, np.shape(levels)[0], mask)
    d = np.asarray(depth, np.float32)
    ok &= np.isfinite(d)
    if not ok.any():
        return math.nan
    cur = np.ascontiguousarray(np.asarray(levels, np.float32)[:, ok])  # (N, curves)
    a = am[ok]
    peak = a + three_point_offset(cur[:, None, :], a[None, :], log=True)[0]
    return float(np.median(d[ok].astype(np.float64) - peak))


def pull_statistics(levels: np.ndarray, argmax: np.ndarray, mask: np.ndarray | None = None
                    ) -> tuple[float, float]:
    """How far a centroid is pulled from the curves' maximum, and how noisy that comparison
    is: over the ``mask`` curves (all when None), the baseline-free centroid of the 5 levels
    about each curve's argmax minus its 3-point Gaussian (levels; curves whose argmax lies
    within 2 levels of an end of the range left out), and of those differences the median
    (the *pull*) and the robust standard deviation (1.4826 x their median absolute
    deviation about it: the *noise*). NaN, NaN where no curve is left, which
    :func:`takes_centroid` refuses.

    The pull is about 0 on even curves, whatever their noise (the median of many curves);
    positive where the curves' tails run to higher levels (a thin lens' blur, even in 1/z):
    measured 0.14 on pertuz-simu02, 0.22 on Gaussians whose upper flank is twice as wide.
    The noise is mostly the 3-point Gaussian's (three samples against the centroid's five).

    Parameters
    ----------
    levels : (N, H, W) ndarray of float
        The curves.
    argmax : (H, W) ndarray of int
        Their argmax.
    mask : (H, W) ndarray of bool, optional
        The curves judged.
    """
    am, ok = judged_curves(argmax, levels.shape[0], mask)
    if not ok.any():
        return math.nan, math.nan
    vol = np.ascontiguousarray(levels, dtype=np.float32)
    diff = (windowed_centroid(vol, am, half_window=2)
            - (am + three_point_offset(vol, am, log=True)))[ok]
    return median_spread(diff)


CENTROID_PULL_LIMIT = 0.03
"""Largest :func:`~sffscan.stages.depth_statistics.centroid_pull` (levels) for which
``"adaptive_centroid"`` takes the 5-level centroid, tuned by the study on the training seeds of all
its families (as :data:`~sffscan.stages.depth_candidates.GAUSS_FIT_HALF_WINDOW`;
docs/depth-study.md)."""


def takes_centroid(pull: float, *, noise: float = 0.0,
                   limit: float = CENTROID_PULL_LIMIT) -> bool:
    """Whether ``adaptive_centroid`` takes the 5-level centroid for curves of this pull and
    noise (:func:`~sffscan.stages.depth_statistics.pull_statistics`): ``abs(pull) < max(limit,
    noise)`` (``limit`` default :data:`CENTROID_PULL_LIMIT`); not for a NaN pull (no curve judged).

    The noise term is a bias-variance comparison, no tuned constant: at a curve's peak the
    centroid's error is about the pull (a bias) and the 3-point Gaussian's about its own
    noise, whose spread the differences show; where the pull is smaller than that spread
    the centroid errs less, even on lopsided curves. Measured with the leave-one-family-out
    protocol (docs/depth-study.md; the default's held-out RMSE, levels, before -> after):
    slopes 0.258 -> 0.238 (1.13x -> 1.04x the best fixed method), flat-fine-8bit 0.098 ->
    0.076, lens-pillbox-noisy 1.036 -> 1.013, the other families and pertuz-simu02 within
    0.3 %; on ten families crossed from the study's (not in it), noisy slopes under a thin
    lens' blur 0.508 -> 0.318 (2.02x -> 1.26x), a thin lens' flat 12-bit plate 0.133 ->
    0.127, the other eight unchanged.
    """
    return bool(abs(pull) < max(limit, 0.0 if math.isnan(noise) else noise))


def judged_curves(argmax: np.ndarray, n: int, mask: np.ndarray | None
            ) -> tuple[np.ndarray, np.ndarray]:
    """The argmax as intp, and the curves judged: the ``mask`` ones (all when None) whose
    argmax lies 2 levels or more from both ends of the N levels."""
    am = np.asarray(argmax).astype(np.intp)
    ok = (am >= 2) & (am <= n - 3)
    if mask is not None:
        ok &= np.asarray(mask, bool)
    return am, ok


def median_spread(diff: np.ndarray) -> tuple[float, float]:
    """The median of ``diff`` and 1.4826 x its median absolute deviation about it."""
    m = float(np.median(diff))
    return m, 1.4826 * float(np.median(np.abs(diff - m)))


def row_median(x: np.ndarray) -> np.ndarray:
    """Median of each row of a 2-D array (np.median's with axis=1, bit for bit, where no row
    holds a NaN, which sorts last here), by sorting each row. np.median took 0.37 ms on a
    block's (520, 48) second differences; a partition at the middle one or two places 0.06
    ms on random values but 0.54 ms on a scan block's (1008, 48) second differences (their
    many ties and tails), against 0.08 ms sorted (numpy's vectorised sort of short rows;
    measured 2026-12-06, docs/performance-log.md). The choice of a block takes three of
    these."""
    m = x.shape[1]
    h = m // 2
    rows = np.sort(x, axis=1)
    return rows[:, h] if m % 2 else 0.5 * (rows[:, h - 1] + rows[:, h])


def centroid_pull(levels: np.ndarray, argmax: np.ndarray, mask: np.ndarray | None = None
                  ) -> float:
    """The pull of :func:`pull_statistics` alone (levels; NaN where no curve is judged)."""
    return pull_statistics(levels, argmax, mask)[0]


def curve_skew(volume: np.ndarray, peak: np.ndarray, width: np.ndarray) -> np.ndarray:
    """Skewness of each focus curve: the third standardised moment of its values above its
    minimum over the levels within ``max(3, ceil(2.5 width))`` of ``peak``.

    Parameters
    ----------
    volume : (N, H, W) ndarray of float
        Focus volume.
    peak : (H, W) ndarray of int
        Each curve's argmax, levels (where the window is centred).
    width : (H, W) ndarray of float
        Curve width, levels (:func:`sffscan.stages.curve_shape.curve_width`).

    Returns
    -------
    (H, W) ndarray of float64
        About 0 for an even curve; positive when the curve's tail runs to higher levels.
    """
    vol = np.asarray(volume, np.float64)
    n = vol.shape[0]
    v = vol - vol.min(axis=0)
    reach = np.clip(np.ceil(2.5 * np.maximum(width, 1.0)), 3, n)
    d = np.arange(n, dtype=np.float64)[:, None, None] - np.asarray(peak, np.float64)[None]
    w = np.where(np.abs(d) <= reach[None], v, 0.0)
    # the moments about the peak, then about their mean: one product per power (the
    # two-pass form took 3x the time; d spans a few tens of levels, no cancellation)
    m0 = w.sum(axis=0) + 1e-300
    w *= d
    m1 = w.sum(axis=0) / m0
    w *= d
    m2 = w.sum(axis=0) / m0
    w *= d
    m3 = w.sum(axis=0) / m0
    var = m2 - m1 * m1
    third = m3 - 3.0 * m1 * m2 + 2.0 * m1**3
    return third / np.maximum(var, 1e-12) ** 1.5


def shape_statistics(volume: np.ndarray, peak: np.ndarray, width: np.ndarray,
                     mask: np.ndarray | None = None) -> tuple[float, float]:
    """The two numbers :func:`~sffscan.stages.depth_choice.shape_select` decides by, over the
    ``mask`` pixels (all when None): ``abs(median skewness)`` (:func:`curve_skew` about each curve's
    argmax ``peak``) and the median ratio of the harmonic width ``width`` to the sigma of the levels
    above half height (:func:`~sffscan.stages.depth_candidates.half_height_count` / 2.355, a
    Gaussian's FWHM / sigma).

    Counted, not the contiguous run through the maximum
    (:func:`~sffscan.stages.depth_candidates.half_height_run`, until 2026-12-05): on noisy
    even curves a level dipping under half height cuts the run, the ratio rises past the
    limit of 6 and SPC, the better method there, is refused. Measured with the study
    (twenty crossed families, docs/depth-method-log.md): the default's ratio to the best
    single method on even-noisy 1.21x -> 1.07x on seeds 6..11 (where the cut runs were
    found) and 1.38x -> 1.27x on seeds 24..29 (scored after the change was fixed), every
    other family the same on seeds 3..5, 12..17, 18..23 and 24..29."""
    return (skew_statistic(volume, peak, width, mask),
            width_ratio_statistic(volume, peak, width, mask))


def _selected(peak: np.ndarray, mask: np.ndarray | None) -> np.ndarray:
    """The ``mask`` pixels, all where None (not :func:`judged_curves`, which also leaves
    out the curves whose argmax lies near an end)."""
    return np.ones(np.shape(peak), bool) if mask is None else np.asarray(mask, bool)


def skew_statistic(volume: np.ndarray, peak: np.ndarray, width: np.ndarray,
                   mask: np.ndarray | None = None) -> float:
    """:func:`shape_statistics`' first number: ``abs(median skewness)`` over the ``mask``
    pixels (all when None)."""
    return abs(float(np.median(curve_skew(volume, peak, width)[_selected(peak, mask)])))


def width_ratio_statistic(volume: np.ndarray, peak: np.ndarray, width: np.ndarray,
                          mask: np.ndarray | None = None) -> float:
    """:func:`shape_statistics`' second number: the median ratio of ``width`` to the sigma
    of the levels above half height over the ``mask`` pixels (all when None)."""
    above = half_height_count(volume, peak).astype(np.float64)
    ratio = np.asarray(width, np.float64) / (above / 2.355)
    return float(np.median(ratio[_selected(peak, mask)]))
