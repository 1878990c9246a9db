"""How the default depth method chooses its estimator, per stack or per scan block, from
the curves' statistics (:mod:`sffscan.stages.depth_statistics`; SFF_NOTES.md section 3;
docs/depth-method.md):

* :func:`shape_select`: SPC for a stack whose focus curves are even (median skewness
  :func:`~sffscan.stages.depth_statistics.curve_skew` near 0: blur even in z) and clean
  (the curves' width from their first harmonic,
  :func:`sffscan.stages.depth_uncertainty.curve_width`, near the width their levels above
  half height give: a noisy floor widens the first, not the second) and whose
  :func:`~sffscan.stages.depth_statistics.centroid_pull` is small, whose SPC is not much
  noisier than the fallback (:func:`spc_noise`) and does not depart from the curves' peaks
  by more than their spread (:func:`spc_departure`), else ``adaptive_centroid``; SPC's
  depth only where it lies a reach of curve widths from the range's ends
  (:func:`spc_in_range`). SPC reads the whole curve, so it holds where wide or ringing
  curves (pillbox PSFs, coarse textures) move the 3-point peak; but it is biased by a
  lopsided curve (a thin lens' blur, even in 1/z), by a noisy floor under a narrow peak
  and by a curve cut by an end of the range. The default of scan, replay and stack since
  2026-12-02.
* ``adaptive_centroid``'s statistic,
  :func:`~sffscan.stages.depth_statistics.centroid_pull`: how far the 5-level centroid
  about each curve's argmax lies from its 3-point Gaussian, the median over the curves;
  :func:`takes_centroid` below :data:`CENTROID_PULL_LIMIT` or the pull's own noise;
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
from collections.abc import Callable
from typing import NamedTuple

import numpy as np
from sffscan.stages.depth_floor import GuardFloor, curve_noise, guard_floor, guard_width
from sffscan.stages.depth_harmonics import harmonic_table, spc_depth
from sffscan.stages.depth_levels import median_filter_levels_at
from sffscan.stages.depth_peak import three_point_offset, windowed_centroid
from sffscan.stages.depth_statistics import (
    judged_curves,
    peak_departure,
    pull_statistics,
    sample_step,
    shape_statistics,
    stack_sample,
    wide_departure,
)
from sffscan.stages.depth_uncertainty import curve_width

__all__ = ["CENTROID_PULL_LIMIT", "DEPARTURE_METHODS", "PEAK_METHODS", "SHAPE_SELECT_LIMITS",
           "SPC_END_REACH", "SPC_NOISE_RATIO", "SPC_PULL_LIMIT", "StackChoice", "centroid_locking",
           "fallback_bias", "judged_width", "method_bias", "method_locking", "peak_locking",
           "shape_select", "spc_bias", "spc_departure", "spc_in_range", "spc_noise",
           "stack_choice", "takes_centroid", "takes_spc", "takes_wide_centroid", "wide_choice"]

CENTROID_PULL_LIMIT = 0.03
"""Largest :func:`~sffscan.stages.depth_statistics.centroid_pull` (levels) for which
``"adaptive_centroid"`` takes the 5-level centroid, tuned by the study on the training seeds of all
its families (as :data:`~sffscan.stages.depth_candidates.GAUSS_FIT_HALF_WINDOW`;
docs/depth-study.md)."""

SHAPE_SELECT_LIMITS = (0.2, math.inf)
"""(largest |median skewness|, largest median width ratio) of ``"shape_select"`` by name,
tuned as :data:`CENTROID_PULL_LIMIT` (candidate ``shape-select``, the rule with its other
tests as shipped): (0.2, 6) in 9 of the 10 leave-one-family-out folds (0.08 without
lens-gauss) and in 20 of 20 over the twenty families; 0.2 is the grid's largest skewness,
and no limit at all (inf) makes the same choice on every stack of seeds 0..11. (0.08, 6)
until 2026-12-04, when the departure test started to weigh SPC's noise: it measures SPC's
bias on lopsided curves directly, and the skewness, a noisier sign of it, refused thin-lens
stacks where SPC errs less (docs/depth-method-log.md). (0.2, 6) until 2026-12-05, when
SPC's noise and the departures' spread became mean squares (:func:`spc_noise`,
:func:`spc_departure`): the width ratio had stood in for the few curves whose phase wanders
(the thesis' chapter 3 with noise, ratio 8.05), and it refused even, noisy stacks just over
6 where SPC errs less (even-noisy, 6.4-7.0); no width limit since."""

SPC_END_REACH = 1.5
"""How many of its widths (sigma, levels) SPC's depth must lie from both ends of the range
for ``"shape_select"`` to keep it (:func:`spc_in_range`), tuned as
:data:`CENTROID_PULL_LIMIT` (candidate ``spc-reach``)."""

SPC_PULL_LIMIT = 0.1
"""Largest :func:`~sffscan.stages.depth_statistics.centroid_pull` (levels) of curves
``"shape_select"`` gives to SPC: the skewness of
:func:`~sffscan.stages.depth_statistics.shape_statistics` is a noisy judge of evenness (heavy
additive noise brings a lopsided stack's median skewness under its limit: measured 0.076 at noise
0.1, where SPC's error was 2.35 x adaptive's), the pull of a centroid a steady one (> 0.15 levels on
the same curves). Tuned by the protocol (candidate ``spc-pull``; limits that tie on the training
seeds go to the smallest) over all twenty families of ``sffscan study --families --crossed``, as
:data:`SPC_NOISE_RATIO` is: 0.1 in 19 of 20 leave-one-out folds and on every family's training
seeds (0.05, the ten families' tuning, until 2026-12-05; only the thin-lens sinusoid's stacks
tell the two apart in training). Measured (docs/depth-method-log.md): on seeds 36..41, set aside
before it was scored, the default's worst ratio to the best single method 1.46x -> 1.32x
(pillbox 1.46x -> 1.00x, even-gauss 1.22x -> 1.00x, even-noisy 1.34x -> 1.32x, no row worse);
on the seeds seen before, sinus-lens-light 1.04-1.33x -> 1.00x and clean-coarse 1.26x -> 1.02x
(30..35), steps-lens-noisy 1.03x -> 1.07x (24..29) and 1.00x -> 1.02x (12..17)."""

SPC_NOISE_RATIO = math.inf
"""Largest ratio of SPC's predicted noise to the pull's noise (:func:`spc_noise` over
:func:`~sffscan.stages.depth_statistics.pull_statistics`' second number) of curves
``"shape_select"`` gives to SPC; inf: no such test. Tuned by the protocol over all twenty families
of ``sffscan study --families --crossed`` (candidate ``spc-noise``): 1.19 in 19 of 20 leave-one-out
folds until 2026-12-04, when the departure test started to weigh SPC's predicted noise itself
(:func:`takes_spc`); since then no training stack tells the settings apart in any fold and
the tie goes to inf (docs/depth-study.md). Noisy, even-looking curves (noisy slopes: SPC's
error 1.7-2.1x the fallback's) are refused by the departure test now."""


def spc_noise(levels: np.ndarray, mask: np.ndarray | None = None) -> float:
    """SPC's predicted noise (levels, one sigma), the root mean square over the ``mask``
    curves (all when None) of each curve's, which is at most ``N / sqrt 12`` (a phase
    anywhere on the circle); NaN where none is judged.

    SPC reads the phase of the curve's first harmonic H_1: white noise of sigma s on each
    of the N levels gives its real and imaginary parts a variance of s^2 N / 2 each, so the
    phase a sigma of about ``s sqrt(N / 2) / |H_1|`` radians and the depth
    ``N / (2 pi)`` times that. The curve's s is taken from its second differences
    (``1.4826 MAD / sqrt 6``: robust to the few levels of the peak, whose curvature is
    signal). Over the curves, the mean square, not the median (until 2026-12-05): the
    comparison it enters (:func:`takes_spc`) is one of mean squared errors, which the few
    curves whose first harmonic is weak, and whose phase wanders, dominate (the thesis'
    chapter 3 with noise: median 0.56, RMS 1.12 levels; SPC's RMSE there 1.43 levels against
    the fallback's 0.74). A number to weigh against the other estimator's noise, not a calibrated
    uncertainty (that is :mod:`sffscan.stages.depth_uncertainty`'s). It assumes noise
    independent from level to level: noise correlated along the levels (a texture's focus
    measure changing smoothly through focus) moves the first harmonic more than its second
    differences show (a thin-lens slope under noise, ``slopes-lens-noisy`` seed 12: SPC's
    scatter 1.14 levels against 0.28 predicted; docs/depth-method-log.md).

    Parameters
    ----------
    levels : (N, H, W) ndarray of float
        The curves; NaN for N < 5 (too few second differences for a spread).
    mask : (H, W) ndarray of bool, optional
        The curves judged.
    """
    vol = np.asarray(levels, np.float32)
    n = vol.shape[0]
    curves = vol.reshape(n, -1) if mask is None else vol[:, np.asarray(mask, bool)]
    if curves.shape[1] == 0 or n < 5:  # under 3 second differences: no spread to take
        return math.nan
    cur = np.ascontiguousarray(curves.T)  # (curves, N): the medians along rows, in cache
    s = curve_noise(cur)
    re, im = (cur @ harmonic_table(n)[2:].T.astype(np.float32)).T
    h1 = np.hypot(re, im)
    sigma = n / (2.0 * np.pi) * math.sqrt(n / 2.0) * s / np.maximum(h1, np.float32(1e-30))
    # a phase error is at most a uniform one on the circle: N / sqrt(12) levels
    sigma = np.minimum(sigma, np.float32(n / math.sqrt(12.0))).astype(np.float64)
    return math.sqrt(float(np.mean(sigma * sigma)))


def spc_departure(levels: np.ndarray, centre: np.ndarray, mask: np.ndarray | None = None,
                  *, centroid: bool = False, floor: GuardFloor | None = None
                  ) -> tuple[float, float]:
    """How far SPC lies from the curves' own peaks: over the ``mask`` curves (all when
    None), SPC's depth (each curve's first-harmonic phase, wrapped about ``centre``) minus
    the fallback's peak about ``centre`` (the 3-point Gaussian; with ``centroid`` the
    baseline-free centroid of the 5 levels about it, what ``"adaptive_centroid"`` takes
    where :func:`takes_centroid`), levels; of those differences the median (SPC's
    *departure*) and their root mean square about it (the spread: the robust 1.4826 x
    median absolute deviation until 2026-12-05, which a mean squared error's comparison
    understates where a few curves' differences are large; :func:`spc_noise`). Curves
    whose centre lies within 2 levels of an end, or whose SPC lies out of its range
    (:func:`spc_in_range` with the :func:`~sffscan.stages.depth_floor.guard_width` of the
    curves' ``floor``: those pixels take the other method anyway), are left out; NaN, NaN
    where none is left.

    ``centre`` is the argmax median filtered as both methods take it (``a_med``,
    :func:`sffscan.stages.depth_levels.median_filter_levels`): the spread then holds the
    noise of the peak the fallback takes. About each curve's own argmax (until 2026-12-05)
    noise that moved the argmax to a stray maximum made the peaks there far noisier than the
    fallback's, the spread large and a biased SPC pass: ``slopes-lens-noisy`` seed 12, SPC's
    departure 1.56 levels against a spread of 1.67 about the argmax and 1.25 about ``a_med``,
    where SPC's error was 2.3 times the fallback's (docs/depth-method-log.md).

    SPC reads the whole curve, the 3-point Gaussian the three levels at its peak. On even
    curves both find the peak and the departure is about 0 whatever the noise (the median
    of many curves); flanks that are lopsided far from the peak (a thin lens' blur over the
    whole range) pull SPC, not the peak: measured +0.4 to +1.2 levels on thin-lens stacks
    of 21 levels, where SPC's error was 1.8 to 8.9 times the fallback's.

    Parameters
    ----------
    levels : (N, H, W) ndarray of float
        The curves (N >= 5).
    centre : (H, W) ndarray of int
        The levels SPC is wrapped about and the peaks taken about: the filtered argmax.
    mask : (H, W) ndarray of bool, optional
        The curves judged.
    centroid : bool, keyword-only
        The fallback's peak is the 5-level centroid, not the 3-point Gaussian.
    floor : GuardFloor, optional, keyword-only
        What the range guard's widths take (:func:`~sffscan.stages.depth_floor.guard_floor`
        of the same curves); None: the curves' minima as their floor.
    """
    n = levels.shape[0]
    am, ok = judged_curves(centre, n, mask)
    if not ok.any():
        return math.nan, math.nan
    cur = np.ascontiguousarray(np.asarray(levels, np.float32)[:, ok])  # (N, curves)
    a = am[ok]
    h0, _, re, im = harmonic_table(n).astype(np.float32) @ cur
    spc = spc_depth(re, im, a, n_levels=n)
    width = guard_width(h0, np.hypot(re, im), cur.min(axis=0), n, floor)
    keep = spc_in_range(spc, width, n)
    if not keep.any():
        return math.nan, math.nan
    if centroid:
        peak = windowed_centroid(cur[:, None, :], a[None, :], half_window=2)[0]
    else:
        peak = a + three_point_offset(cur[:, None, :], a[None, :], log=True)[0]
    diff = (spc - peak)[keep].astype(np.float64)
    d = float(np.median(diff))
    return d, math.sqrt(float(np.mean((diff - d) ** 2)))


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


def takes_wide_centroid(departure: tuple[float, float]) -> bool:
    """Whether ``adaptive_centroid`` (and ``"shape_select"``'s fallback) keeps the wide
    centroid where the focus window sees several heights, given its
    :func:`~sffscan.stages.depth_statistics.wide_departure` ``(d, s)``: ``|d| <= s``; also
    for NaN (no such pixel judged). Else the peak estimator (:func:`takes_centroid`'s) is
    taken at every pixel.

    ``"adaptive"`` takes, where the filtered peaks in the focus window span more than
    :data:`~sffscan.stages.depth_peak.ADAPTIVE_MAX_SPREAD` levels (a slope, an edge, a
    rough or noisy surface), the baseline-free centroid of 11 levels: the middle of a blend
    of peaks, and less noisy than a peak where noise moved the argmax. On a smooth slope the
    blend is even about the pixel's own height, so its peak is not biased, while the
    11-level window reaches into the curves' tails and the centroid is pulled (by a median
    +0.18 levels against the 3-point Gaussian on the study's ``slopes`` family, whose
    differences spread 0.14). The test is a bias-variance comparison with no tuned
    constant, as :func:`takes_spc`'s departure test: a departure larger than the spread is
    a bias of the wide centroid larger than the noise it saves.
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
        The fallback's depth (:func:`sffscan.stages.depth_peak.adaptive_block`), levels;
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


def takes_spc(statistics: tuple[float, float], *, max_skew: float = SHAPE_SELECT_LIMITS[0],
              max_ratio: float = SHAPE_SELECT_LIMITS[1], pull: float | None = None,
              max_pull: float = SPC_PULL_LIMIT, noise: tuple[float, float] | None = None,
              max_noise_ratio: float = SPC_NOISE_RATIO,
              departure: tuple[float, float] | None = None) -> bool:
    """Whether curves with these :func:`~sffscan.stages.depth_statistics.shape_statistics` are even
    and clean enough for SPC: both below their limits (default :data:`SHAPE_SELECT_LIMITS`), and,
    where their :func:`~sffscan.stages.depth_statistics.centroid_pull` is given, its size below
    ``max_pull`` (not for NaN: no curve judged), and where ``noise`` is given (SPC's predicted
    noise, :func:`spc_noise`, and the pull's noise,
    :func:`~sffscan.stages.depth_statistics.pull_statistics`), the first at most ``max_noise_ratio``
    times the second or under :data:`CENTROID_PULL_LIMIT` (an error the study's choices treat as
    negligible: noise-free curves' second differences are their shape, not noise), and where
    ``departure`` is given (:func:`spc_departure`, ``(d, s)``), SPC's mean squared error predicted
    no larger than the fallback's: ``d^2 + 2 sigma^2 <= max(CENTROID_PULL_LIMIT, s)^2``, ``sigma``
    SPC's predicted noise (``noise``'s first number; 0 where ``noise`` is None or it is under
    :data:`CENTROID_PULL_LIMIT`, which leaves ``|d| <= s``); not for NaN.

    The departure test is a bias-variance comparison with no tuned constant, as
    :func:`takes_centroid`'s. Per curve, SPC minus the fallback's peak has the median
    ``d`` (SPC's bias, the fallback's peak taken as the reference: it reads the 3 or 5
    levels at the maximum, which a lopsided flank far from it does not move) and the
    spread ``s``, with ``s^2 = sigma^2 + sigma_f^2`` for independent noises. SPC errs
    less where ``d^2 + sigma^2 <= sigma_f^2 = s^2 - sigma^2``. Until 2026-12-04 the test
    was ``|d| <= s`` against the 3-point Gaussian, whatever the fallback took: on noisy
    thin-lens curves the 3-point peak's noise made ``s`` large (1.46 levels) and a
    departure of 1.21 levels passed, where SPC's error was 2.2x the fallback's (the
    held-out seed 8 of ``slopes-lens-noisy``). Measured (2026-12-04, the twenty families,
    seeds 0..11, and pertuz-simu02; docs/depth-method-log.md): one stack of the training
    seeds 0..2 refused (steps-lens-noisy seed 1: 1.006x -> 1.002x), none of the held-out
    seeds 3..5; on seeds 6..11 two refused (the default's worst ratio to the best single
    method 1.655x -> 1.324x, with :data:`SPC_NOISE_RATIO` then inf). It
    refuses a breathing thin-lens stack that took SPC once aligned
    (``bench/bench_align_families.py``: 1.90x its twin's error)."""
    if pull is not None and not abs(pull) < max_pull:
        return False
    if departure is not None:
        dep, spread = departure
        # SPC's noise, where given, counts twice: once as its own error, once inside the
        # spread of the differences (the fallback's noise is spread^2 - sigma^2); under
        # CENTROID_PULL_LIMIT it is negligible, as for the noise test (noise-free curves'
        # second differences are their shape)
        sigma = 0.0 if noise is None or noise[0] < CENTROID_PULL_LIMIT else noise[0]
        if not dep * dep + 2.0 * sigma * sigma <= max(CENTROID_PULL_LIMIT, spread) ** 2:
            return False  # NaN: not shown small
    if noise is not None and not math.isinf(max_noise_ratio):
        sigma, pull_noise = noise
        bound = max_noise_ratio * pull_noise
        if not (sigma < CENTROID_PULL_LIMIT or sigma <= bound):  # NaN: not shown small
            return False
    skew, ratio = statistics
    return skew < max_skew and ratio < max_ratio


def spc_in_range(spc: np.ndarray, width: np.ndarray, n_levels: int, *,
                 reach: float = SPC_END_REACH) -> np.ndarray:
    """Where SPC's depth (levels) lies at least ``reach`` of the curve's widths (sigma,
    levels: :func:`sffscan.stages.depth_floor.guard_width`, the width from a floor that
    noise does not lower, since 2026-12-05; :func:`sffscan.stages.depth_uncertainty.
    curve_width`'s before) from both ends of the range, 0 and N - 1.

    SPC reads the phase of the curve's first harmonic over the whole range, as if the
    curve were periodic: a curve whose peak lies within about its width of an end has its
    tail cut there (or, in the harmonic's eyes, wrapped to the other end), and the phase is
    pulled towards the middle. Measured on the repository's plate scan (its base 2-4 levels
    above the range's start): SPC +86 um off where the default is within 6 um, while SPC is
    the better of the two on the relief (levels 8-30). NaN widths or depths are out of
    range; an infinite width is, but for ``reach`` 0 (everywhere).
    """
    if reach == 0.0:
        margin = np.zeros(np.shape(width), np.float32)
    else:
        margin = reach * np.asarray(width, np.float32)
    return (spc >= margin) & (spc <= np.float32(n_levels - 1) - margin)


def shape_select(spc: np.ndarray, other: np.ndarray, statistics: tuple[float, float], *,
                 max_skew: float, max_ratio: float, in_range: np.ndarray | None = None,
                 pull: float | None = None, max_pull: float = SPC_PULL_LIMIT,
                 noise: tuple[float, float] | None = None,
                 max_noise_ratio: float = SPC_NOISE_RATIO,
                 departure: tuple[float, float] | None = None) -> np.ndarray:
    """SPC's depth map where the stack's curves are even and clean (:func:`takes_spc`), else
    ``other`` (``adaptive_centroid``'s depth map in ``"shape_select"``);
    float32 levels. One choice for the whole stack (the streaming depth stage chooses per
    block: :func:`sffscan.stages.block_depth.block_method`); where SPC is taken, ``other``
    still stands at the pixels outside ``in_range`` (:func:`spc_in_range`; all inside
    when None). ``pull``, ``max_pull``, ``noise``, ``max_noise_ratio``, ``departure``: as
    for :func:`takes_spc`."""
    use_spc = takes_spc(statistics, max_skew=max_skew, max_ratio=max_ratio, pull=pull,
                        max_pull=max_pull, noise=noise,
                        max_noise_ratio=max_noise_ratio, departure=departure)
    if not use_spc:
        return np.asarray(other, np.float32)
    if in_range is None:
        return np.asarray(spc, np.float32)
    return np.where(in_range, spc, other).astype(np.float32, copy=False)


class StackChoice(NamedTuple):
    """``"shape_select"``'s choice for a stack (:func:`stack_choice`)."""

    spc: bool
    """The stack takes SPC (where it is in range)."""
    bias: float
    """A bias of the depth that its scatter does not show, which the height uncertainty
    adds in quadrature (:mod:`sffscan.stages.depth_uncertainty`), levels: SPC's departure
    from the fallback's peaks, ``|d|`` of :func:`spc_departure`, where the stack takes SPC;
    elsewhere the fallback's own, :func:`fallback_bias`."""
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
    scatter cannot show it (:func:`sffscan.stages.depth_uncertainty.locking_visibility`);
    0.0 elsewhere."""


def stack_choice(volume: np.ndarray, argmax: np.ndarray, width: np.ndarray | None = None,
                 *, median_size: int = 11) -> StackChoice:
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
        Their widths (:func:`sffscan.stages.depth_uncertainty.curve_width`; computed when
        None).
    median_size : int, keyword-only
        The argmax's median filter, px (odd), as the depth's: SPC's departure is measured
        about the filtered argmax (:func:`spc_departure`).
    """
    if width is None:
        width = curve_width(volume)
    vol, peak, wid = stack_sample(volume, argmax, width)
    assert wid is not None
    s = sample_step(np.shape(argmax))
    h, w = np.shape(argmax)
    pull, noise = pull_statistics(vol, peak)
    taken = spc_bias(vol, peak, shape_statistics(vol, peak, wid), pull, noise,
                     centre=lambda: median_filter_levels_at(argmax, median_size,
                                                            np.arange(0, h, s),
                                                            np.arange(0, w, s)))
    if taken is None:
        locking = peak_locking(pull, noise, judged_width(wid, peak, volume.shape[0]))
        return StackChoice(False, fallback_bias(pull), pull, noise, None, locking)
    return StackChoice(True, taken[0], pull, noise, taken[1])


DEPARTURE_METHODS = ("pc", "spc", "wcentroid", "argmax")
"""The methods that read the whole curve (PC, SPC) or a wide window of it (the 9-level
centroid) and keep the constants fitted to the default's errors
(:data:`sffscan.stages.depth_uncertainty.OTHER_METHODS_CONSTANTS`), and the argmax, whose
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
    (:func:`takes_centroid`), else 0.0 (the 3-point Gaussian is exact on a Gaussian
    curve)."""
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
                depth: np.ndarray | None = None) -> float:
    """The bias (levels) the height uncertainty of a whole stack reconstructed with
    ``method`` adds: ``"shape_select"``'s :attr:`StackChoice.bias`, a peak method's
    :func:`fallback_bias` on :func:`~sffscan.stages.depth_statistics.stack_sample`'s curves, a
    method of :data:`DEPARTURE_METHODS` the size of its :func:`~sffscan.stages.
    depth_statistics.peak_departure` there (its ``depth`` needed), 0.0 for the other
    methods. ``volume``, ``argmax``, ``width`` and ``median_size`` as
    :func:`stack_choice`'s (``width`` from the curves' sums, as the depth's choice takes it,
    saves its float64 :func:`~sffscan.stages.depth_uncertainty.curve_width`); ``method`` the
    depth method. For ``"shape_select"`` this is its choice's bias before the
    fallback's 9-level centroid is weighed (that needs the depth maps):
    :func:`sffscan.stages.depth.shape_select_with_bias` gives the whole of it with the
    depth, and is what a stack's reconstruction takes."""
    if method == "shape_select":
        return stack_choice(volume, argmax, width, median_size=median_size).bias
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
                   median_size: int = 11, width: np.ndarray | None = None) -> float:
    """The peak locking (levels) of a whole stack reconstructed with ``method``, which the
    height uncertainty adds where its scatter cannot show it
    (:func:`sffscan.stages.depth_uncertainty.locking_visibility`): ``"shape_select"``'s
    :attr:`StackChoice.locking`, ``"adaptive_centroid"``'s :func:`peak_locking` on
    :func:`~sffscan.stages.depth_statistics.stack_sample`'s curves, 0.0 for the other
    methods (``"adaptive"``'s 3-point Gaussian is exact on a Gaussian curve). ``width``: the
    curves' widths from their sums, as the depth's choice takes them (computed when None)."""
    if method == "shape_select":
        return stack_choice(volume, argmax, width, median_size=median_size).locking
    if method == "adaptive_centroid":
        vol, peak, wid = stack_sample(volume, argmax, width)
        if wid is None:
            wid = curve_width(vol)
        pull, noise = pull_statistics(vol, peak)
        return peak_locking(pull, noise, judged_width(wid, peak, volume.shape[0]))
    return 0.0


def spc_bias(levels: np.ndarray, argmax: np.ndarray, statistics: tuple[float, float],
             pull: float, noise: float, mask: np.ndarray | None = None, *,
             centre: Callable[[], np.ndarray]) -> tuple[float, GuardFloor] | None:
    """``"shape_select"``'s tests on curves of these
    :func:`~sffscan.stages.depth_statistics.shape_statistics` and
    :func:`~sffscan.stages.depth_statistics.pull_statistics`: where they take SPC, SPC's
    departure ``|d|`` (:func:`spc_departure` against the peak the fallback takes; levels) and
    what its range guard takes from them (:func:`~sffscan.stages.depth_floor.guard_floor`);
    None where they do not. SPC's noise and departure are
    measured only for curves that pass the rest (they cost about as much as the rest). One
    home for the choice of a stack (:func:`stack_choice`) and of a scan block
    (:func:`sffscan.stages.block_depth.block_choice`).

    Parameters
    ----------
    levels : (N, H, W) ndarray of float
        The curves judged (a stack's sample or a block's).
    argmax : (H, W) ndarray of int
        Their argmax.
    statistics : (float, float)
        Their :func:`~sffscan.stages.depth_statistics.shape_statistics`.
    pull, noise : float
        Their :func:`~sffscan.stages.depth_statistics.pull_statistics`.
    mask : (H, W) ndarray of bool, optional
        The curves judged (all when None).
    centre : callable, keyword-only
        Gives their argmax median filtered as the depth takes it, (H, W) on the same grid:
        what SPC's departure is measured about (:func:`spc_departure`); called only where
        the curves pass the other tests.
    """
    if not takes_spc(statistics, pull=pull):
        return None
    grid = centre()
    if np.shape(grid) != np.shape(argmax):
        raise ValueError(f"centre must give the judged curves' {np.shape(argmax)} pixels, "
                         f"got shape {np.shape(grid)}")
    noises = (spc_noise(levels, mask), noise)
    if not takes_spc(statistics, pull=pull, noise=noises):
        return None
    floor = guard_floor(levels, grid, mask)
    departure = spc_departure(levels, grid, mask, centroid=takes_centroid(pull, noise=noise),
                              floor=floor)
    if not takes_spc(statistics, pull=pull, noise=noises, departure=departure):
        return None
    return abs(departure[0]), floor
