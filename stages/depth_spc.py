"""Where the default depth method takes SPC: its tests (docs/depth-method.md; the choice as
a whole, per stack or scan block, is :mod:`sffscan.stages.depth_choice`'s), on the curves'
statistics (:mod:`sffscan.stages.depth_statistics`):

* :func:`takes_spc`: SPC for curves that are even (median skewness
  :func:`~sffscan.stages.depth_statistics.curve_skew` near 0: blur even in z) and clean
  (the curves' width from their first harmonic,
  :func:`sffscan.stages.curve_shape.curve_width`, near the width their levels above
  half height give: a noisy floor widens the first, not the second;
  :data:`SHAPE_SELECT_LIMITS`) and whose
  :func:`~sffscan.stages.depth_statistics.centroid_pull` is small (:data:`SPC_PULL_LIMIT`),
  whose SPC is not much noisier than the fallback (:func:`spc_noise`,
  :data:`SPC_NOISE_RATIO`) and does not depart from the curves' peaks by more than their
  spread (:func:`spc_departure`); :func:`spc_bias` runs them on a stack's or a scan block's
  curves;
* SPC's depth only where it lies a reach of curve widths from the range's ends
  (:func:`spc_in_range`, :data:`SPC_END_REACH`).

SPC reads the whole curve, so it holds where wide or ringing curves (pillbox PSFs, coarse
textures) move the 3-point peak; but it is biased by a lopsided curve (a thin lens' blur,
even in 1/z), by a noisy floor under a narrow peak and by a curve cut by an end of the
range.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from typing import NamedTuple

import numpy as np
from sffscan.stages.depth_floor import GuardFloor, curve_noise, guard_floor, guard_width
from sffscan.stages.depth_harmonics import harmonic_table, magnitude, spc_depth
from sffscan.stages.depth_peak import three_point_offset, windowed_centroid
from sffscan.stages.depth_statistics import (
    CENTROID_PULL_LIMIT,
    judged_curves,
    median_spread,
    skew_statistic,
    takes_centroid,
    width_ratio_statistic,
)

__all__ = ["SHAPE_SELECT_LIMITS", "SPC_END_REACH", "SPC_NOISE_RATIO", "SPC_PULL_LIMIT",
           "Departures", "SpcTaken", "spc_bias", "spc_departure", "spc_departures",
           "spc_in_range", "spc_noise", "spc_shape", "spc_share", "spc_weight", "takes_spc"]

SHAPE_SELECT_LIMITS = (0.2, math.inf)
"""(largest |median skewness|, largest median width ratio) of ``"shape_select"`` by name,
tuned as :data:`~sffscan.stages.depth_statistics.CENTROID_PULL_LIMIT` (candidate
``shape-select``, the rule with its other tests as shipped): (0.2, 6) in 9 of the 10
leave-one-family-out folds (0.08 without lens-gauss) and in 20 of 20 over the twenty
families; 0.2 is the grid's largest skewness, and no limit at all (inf) makes the same
choice on every stack of seeds 0..11. (0.08, 6) until 2026-12-04, when the departure test
started to weigh SPC's noise: it measures SPC's bias on lopsided curves directly, and the
skewness, a noisier sign of it, refused thin-lens stacks where SPC errs less
(docs/depth-method-log.md). (0.2, 6) until 2026-12-05, when SPC's noise and the departures'
spread became mean squares (:func:`spc_noise`, :func:`spc_departure`): the width ratio had
stood in for the few curves whose phase wanders (the thesis' chapter 3 with noise, ratio
8.05), and it refused even, noisy stacks just over 6 where SPC errs less (even-noisy,
6.4-7.0); no width limit since."""

SPC_END_REACH = 1.5
"""How many of its widths (sigma, levels) SPC's depth must lie from both ends of the range
for ``"shape_select"`` to keep it (:func:`spc_in_range`), tuned as
:data:`~sffscan.stages.depth_statistics.CENTROID_PULL_LIMIT` (candidate ``spc-reach``)."""


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
    h1 = magnitude(re, im)
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
    where :func:`~sffscan.stages.depth_statistics.takes_centroid`), levels; of those
    differences the median (SPC's *departure*) and their root mean square about it (the
    spread: the robust 1.4826 x median absolute deviation until 2026-12-05, which a mean
    squared error's comparison understates where a few curves' differences are large;
    :func:`spc_noise`). Curves whose centre lies within 2 levels of an end, or whose SPC
    lies out of its range (:func:`spc_in_range` with the
    :func:`~sffscan.stages.depth_floor.guard_width` of the curves' ``floor``: those pixels
    take the other method anyway), are left out; NaN, NaN where none is left.

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
    dep = spc_departures(levels, centre, mask, centroid=centroid, floor=floor)
    return dep.departure, dep.spread


class Departures(NamedTuple):
    """SPC's departure from the fallback's peaks and two spreads of it
    (:func:`spc_departures`), levels."""

    departure: float
    """The median of SPC minus the peak, ``d``."""
    spread: float
    """Their root mean square about ``d``: what :func:`takes_spc`'s test reads."""
    robust: float
    """1.4826 x their median absolute deviation about ``d``: the bulk of the curves, what
    SPC's share reads (:func:`spc_weight`)."""


def spc_departures(levels: np.ndarray, centre: np.ndarray, mask: np.ndarray | None = None,
                   *, centroid: bool = False, floor: GuardFloor | None = None) -> Departures:
    """:func:`spc_departure`'s ``(d, s)`` and the differences' robust spread beside them
    (1.4826 x their median absolute deviation about ``d``), from one pass; NaN, NaN, NaN
    where no curve is left. Parameters as :func:`spc_departure`'s."""
    n = levels.shape[0]
    am, ok = judged_curves(centre, n, mask)
    if not ok.any():
        return Departures(math.nan, math.nan, math.nan)
    cur = np.ascontiguousarray(np.asarray(levels, np.float32)[:, ok])  # (N, curves)
    a = am[ok]
    h0, _, re, im = harmonic_table(n).astype(np.float32) @ cur
    spc = spc_depth(re, im, a, n_levels=n)
    width = guard_width(h0, magnitude(re, im), cur.min(axis=0), n, floor)
    keep = spc_in_range(spc, width, n)
    if not keep.any():
        return Departures(math.nan, math.nan, math.nan)
    if centroid:
        peak = windowed_centroid(cur[:, None, :], a[None, :], half_window=2)[0]
    else:
        peak = a + three_point_offset(cur[:, None, :], a[None, :], log=True)[0]
    diff = (spc - peak)[keep].astype(np.float64)
    d, robust = median_spread(diff)
    return Departures(d, math.sqrt(float(np.mean((diff - d) ** 2))), robust)


def spc_shape(volume: np.ndarray, peak: np.ndarray, width: np.ndarray,
              mask: np.ndarray | None = None) -> tuple[float, float | None]:
    """The :func:`~sffscan.stages.depth_statistics.shape_statistics` that :func:`takes_spc`
    reads at :data:`SHAPE_SELECT_LIMITS`: the width ratio only where its limit is finite,
    else None (not measured). Finite curves have finite widths
    (:func:`~sffscan.stages.curve_shape.width_from_sums` clips its ratio), so their
    width ratio is always under an infinite limit; counting the levels above half height
    for it cost a scan block's choice 0.45-0.5 ms (3.30-3.49 against 2.85-2.98 ms,
    2026-12-06, docs/performance-log.md). Parameters as
    :func:`~sffscan.stages.depth_statistics.shape_statistics`'."""
    ratio = (None if math.isinf(SHAPE_SELECT_LIMITS[1])
             else width_ratio_statistic(volume, peak, width, mask))
    return skew_statistic(volume, peak, width, mask), ratio


def takes_spc(statistics: tuple[float, float | None], *,
              max_skew: float = SHAPE_SELECT_LIMITS[0],
              max_ratio: float = SHAPE_SELECT_LIMITS[1], pull: float | None = None,
              max_pull: float = SPC_PULL_LIMIT, noise: tuple[float, float] | None = None,
              max_noise_ratio: float = SPC_NOISE_RATIO,
              departure: tuple[float, float] | None = None) -> bool:
    """Whether curves with these :func:`~sffscan.stages.depth_statistics.shape_statistics` are
    even and clean enough for SPC: both below their limits (default
    :data:`SHAPE_SELECT_LIMITS`), and, where their
    :func:`~sffscan.stages.depth_statistics.centroid_pull` is given, its size below ``max_pull``
    (not for NaN: no curve judged), and where ``noise`` is given (SPC's predicted noise,
    :func:`spc_noise`, and the pull's noise,
    :func:`~sffscan.stages.depth_statistics.pull_statistics`), the first at most
    ``max_noise_ratio`` times the second or under
    :data:`~sffscan.stages.depth_statistics.CENTROID_PULL_LIMIT` (an error the study's choices
    treat as negligible: noise-free curves' second differences are their shape, not noise), and
    where ``departure`` is given (:func:`spc_departure`, ``(d, s)``), SPC's mean squared error
    predicted no larger than the fallback's: ``d^2 + 2 sigma^2 <= max(CENTROID_PULL_LIMIT,
    s)^2``, ``sigma`` SPC's predicted noise (``noise``'s first number; 0 where ``noise`` is None
    or it is under :data:`~sffscan.stages.depth_statistics.CENTROID_PULL_LIMIT`, which leaves
    ``|d| <= s``); not for NaN.

    The departure test is a bias-variance comparison with no tuned constant, as
    :func:`~sffscan.stages.depth_statistics.takes_centroid`'s. Per curve, SPC minus the
    fallback's peak has the median ``d`` (SPC's bias, the fallback's peak taken as the
    reference: it reads the 3 or 5 levels at the maximum, which a lopsided flank far from it
    does not move) and the spread ``s``, with ``s^2 = sigma^2 + sigma_f^2`` for independent
    noises. SPC errs less where ``d^2 + sigma^2 <= sigma_f^2 = s^2 - sigma^2``. Until
    2026-12-04 the test was ``|d| <= s`` against the 3-point Gaussian, whatever the fallback
    took: on noisy thin-lens curves the 3-point peak's noise made ``s`` large (1.46 levels)
    and a departure of 1.21 levels passed, where SPC's error was 2.2x the fallback's (the
    held-out seed 8 of ``slopes-lens-noisy``). Measured (2026-12-04, the twenty families,
    seeds 0..11, and pertuz-simu02; docs/depth-method-log.md): one stack of the training
    seeds 0..2 refused (steps-lens-noisy seed 1: 1.006x -> 1.002x), none of the held-out
    seeds 3..5; on seeds 6..11 two refused (the default's worst ratio to the best single
    method 1.655x -> 1.324x, with :data:`SPC_NOISE_RATIO` then inf). It refuses a breathing
    thin-lens stack that took SPC once aligned (``bench/bench_align_families.py``: 1.90x its
    twin's error)."""
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
    if ratio is None:  # not measured (spc_shape): no finite limit to pass
        if not math.isinf(max_ratio):
            raise ValueError(f"a width ratio limit of {max_ratio} needs the width ratio "
                             "measured (statistics' second number is None)")
        return skew < max_skew
    return skew < max_skew and ratio < max_ratio


def spc_weight(departure: tuple[float, float], noise: float) -> float:
    """SPC's share of the depth where :func:`takes_spc` takes it: the weight of the least
    mean squared error average of SPC and the fallback (independent errors), ``w = E_f /
    (E_f + E_spc)``, with ``E_spc = d^2 + sigma^2`` (SPC's departure and predicted noise, as
    the test takes them) and ``E_f = max(0, max(CENTROID_PULL_LIMIT, s)^2 - sigma^2)``, ``s``
    the departures' *robust* spread (:attr:`Departures.robust`, 1.4826 x their median
    absolute deviation): the fallback's noise over the bulk of the curves. 0 to 1; ``sigma``
    0 under :data:`~sffscan.stages.depth_statistics.CENTROID_PULL_LIMIT`, as in the test;
    NaN for a NaN statistic.

    Why not SPC alone (until 2026-12-06): the test is a cliff where the two estimators
    differ several-fold, and its mean-square spread carries, as if they were the fallback's
    noise, the few curves where SPC errs far (a thin lens' lopsided flanks under heavy
    noise, step edges where SPC reads the blend of two heights): ``slopes-lens-noisy`` and
    ``steps-lens-noisy`` stacks took SPC at 1.5-2.9x the fallback's error. The share from
    the same mean squares (w of 1/2 to 1) was adopted first (worst held-out family 1.066x ->
    1.025x on seeds 585..704); from the robust spread, the same day (steps-lens-noisy's
    stacks over 1.10x their best method 92 -> 38 on seen seeds; adopted by the rule declared
    before seeds 1008..1127; docs/depth-method-log.md). Where the test refuses SPC the
    fallback stands alone: there any share would add SPC's bias where the fallback errs less
    than the test's spread says (measured: stacks over 1.10x 873 -> 1319)."""
    d, s = departure
    sigma = 0.0 if noise < CENTROID_PULL_LIMIT else noise  # NaN stays NaN
    e_spc = d * d + sigma * sigma
    e_f = max(0.0, max(CENTROID_PULL_LIMIT, s) ** 2 - sigma * sigma)
    if math.isnan(e_spc) or math.isnan(e_f):
        return math.nan
    return 1.0 if e_f + e_spc == 0.0 else e_f / (e_f + e_spc)


def spc_share(spc: np.ndarray, other: np.ndarray, weight: float) -> np.ndarray:
    """``weight * spc + (1 - weight) * other`` in float32 (levels; SPC itself for a weight of
    1): the default's depth where it takes SPC, ``weight`` from :func:`spc_weight`."""
    spc = np.asarray(spc, np.float32)
    if weight >= 1.0:
        return spc
    return np.float32(weight) * spc + np.float32(1.0 - weight) * np.asarray(other, np.float32)


def spc_in_range(spc: np.ndarray, width: np.ndarray, n_levels: int, *,
                 reach: float = SPC_END_REACH) -> np.ndarray:
    """Where SPC's depth (levels) lies at least ``reach`` of the curve's widths (sigma,
    levels: :func:`sffscan.stages.depth_floor.guard_width`, the width from a floor that
    noise does not lower, since 2026-12-05; :func:`sffscan.stages.curve_shape.
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


class SpcTaken(NamedTuple):
    """What :func:`spc_bias` gives where the curves take SPC."""

    departure: float
    """SPC's departure ``|d|`` from the fallback's peaks (:func:`spc_departure`), levels."""
    floor: GuardFloor
    """What SPC's range guard takes from the curves
    (:func:`~sffscan.stages.depth_floor.guard_floor`)."""
    weight: float
    """SPC's share of the depth where it is in range (:func:`spc_weight` of the departure's
    robust spread), 0 to 1; the fallback's is ``1 - weight``."""


def spc_bias(levels: np.ndarray, argmax: np.ndarray,
             statistics: tuple[float, float | None],
             pull: float, noise: float, mask: np.ndarray | None = None, *,
             centre: Callable[[], np.ndarray]) -> SpcTaken | None:
    """``"shape_select"``'s tests on curves of these
    :func:`~sffscan.stages.depth_statistics.shape_statistics` and
    :func:`~sffscan.stages.depth_statistics.pull_statistics`: where they take SPC, SPC's
    departure ``|d|`` (:func:`spc_departure` against the peak the fallback takes; levels),
    what its range guard takes from them (:func:`~sffscan.stages.depth_floor.guard_floor`)
    and SPC's share of the depth (:func:`spc_weight`); None where they do not. SPC's noise
    and departure are measured only for curves that pass the rest (they cost about as much
    as the rest). One home for the choice of a stack
    (:func:`sffscan.stages.depth_choice.stack_choice`) and of a scan block
    (:func:`sffscan.stages.block_depth.block_choice`).

    Parameters
    ----------
    levels : (N, H, W) ndarray of float
        The curves judged (a stack's sample or a block's).
    argmax : (H, W) ndarray of int
        Their argmax.
    statistics : (float, float or None)
        Their :func:`~sffscan.stages.depth_statistics.shape_statistics` (:func:`spc_shape`:
        the width ratio None where its limit is infinite).
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
    dep = spc_departures(levels, grid, mask, centroid=takes_centroid(pull, noise=noise),
                         floor=floor)
    if not takes_spc(statistics, pull=pull, noise=noises, departure=dep[:2]):
        return None
    return SpcTaken(abs(dep.departure), floor,
                    spc_weight((dep.departure, dep.robust), noises[0]))

