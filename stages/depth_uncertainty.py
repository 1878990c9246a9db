"""Per-pixel height uncertainty (one sigma) of a depth map, measured from the data.

Five terms, added in quadrature (levels; times the local focus step for µm):

``sigma^2 = (a * scatter)^2 + (r * relief)^2 + excess^2 + b^2 + c^2``

* ``scatter``: the depth's RMS about its 5 x 5 median over the focus window (k x k px,
  :func:`depth_scatter`). Noise of the focus curves, stray maxima and a peak fit that locks
  onto the sampling show as pixel-to-pixel scatter; a smooth surface does not.
* ``relief``: the depth's RMS about its own k x k box mean over the focus window
  (:func:`depth_relief`). Neighbouring pixels share most of the focus window, so their
  errors are correlated and smooth over a few pixels: a 5 x 5 median follows them and
  hides them from the scatter (alone, ``a`` had to be ~4 and over-covered smooth maps while
  under-covering rough ones). The box mean leaves a plane alone (a slope has no relief)
  and leaves an error, a bump or an edge of about the window's size in ``relief``.
  Added 2026-12-04 (night): held-out coverage in the band on 10 of 11 sets (the study's
  ten families and pertuz-simu02; 10 before), 13 of 21 with the crossed families (12
  before) and 17 of 21 on twice the seeds (11 before); the sets under the band (the side
  that misleads) 1, 3 and 3 against 1, 4 and 6 (docs/depth-study.md).
* ``excess``: how much wider the pixel's focus curve is than the curves about it
  (:func:`width_excess`, ``sqrt(w^2 - mean_(2k+1)(w)^2)``, levels), at most half the range
  of the depth map about it. A focus window that sees two heights (an edge, a step) has a
  curve with two modes; their variance adds to the curve's: a mix of two heights ``D``
  apart in shares ``p``, ``1 - p`` widens the curve by ``D sqrt(p (1 - p))`` in quadrature
  (at most ``D / 2``). The peak the estimator takes is one mode or the other, and the
  other one (an error of the whole step) about as often as that mode's share: an error of
  standard deviation ``D sqrt(p (1 - p))``, the excess itself, so ``excess`` is one sigma
  (this geometry, not a fitted constant). Until 2026-12-05 the estimate was taken to lie
  anywhere between the two heights, at most ``D / 2`` from its own side, and ``excess / 2``
  was one sigma; the pixels it left uncovered were step pixels whose peak had taken the
  other side (steps-lens-noisy, seeds 3..5: every uncovered pixel within 9 px of a true
  step, their median error 8.9 levels against half the local range 8.4;
  docs/depth-method-log.md). The two heights are
  measured beside the mix, within ``2k + 1`` px: ``D`` is at most the range (max - min) of
  the depth's 5 x 5 median over that square, so the excess is capped at half that range.
  Without the cap a textured continuous surface, whose curves' widths scatter from pixel to
  pixel (about half wider than their neighbours' mean), got 0.5 .. 1 level of sigma from
  that scatter alone (a demo print: a third of a flat part's pixels above a 0.5 level
  tolerance, its error 0.03 level RMS); the cap leaves a mix its full term. Until
  2026-12-05 evening the term was also scaled by ``max(0, 1 - 2 floor share)`` (``N min /
  H_0``, :func:`floor_share`: noisy curves of a weak texture, whose width says more about
  the noise than the heights seen); with the cap it only took the term from noisy step
  edges, whose peaks are taken on the wrong side most often (steps-lens-noisy's uncovered
  pixels had no excess left): dropped (held-out sets under the band 8 -> 0 of 180,
  docs/depth-method-log.md).
* ``b``: a bias of the whole map. SPC's, where ``"shape_select"`` took SPC for the stack or
  scan block: the median departure of SPC from the peaks the fallback would take
  (:attr:`sffscan.stages.depth_choice.StackChoice.bias`, levels). The choice
  takes SPC where that departure is small against the noise (``d^2 + 2 sigma^2 <= s^2``),
  not where it is zero: a lopsided curve's pull on SPC is a bias of the whole map that
  its scatter cannot show. Added as it is (no constant): on the depth study's
  leave-one-family-out tables (2026-12-04) the held-out coverage moved into the band on
  lens-pillbox-noisy (0.869 -> 0.911, seeds 6..11) and toward it on steps-lens-noisy
  (0.825 -> 0.899), no set out of it. Where the depth is a peak instead (the fallback of
  ``"shape_select"``, ``"adaptive"`` and ``"adaptive_centroid"`` by name), ``b`` is the size
  of the curves' centroid pull (:func:`sffscan.stages.depth_choice.fallback_bias`: two peak
  estimators that disagree the same way on every curve), also as it is (2026-12-04, late
  night: the held-out sets under the band 13 -> 7 over five sets of seeds;
  docs/depth-method-log.md). Where it is SPC, PC, the 9-level centroid or the argmax by
  name (:data:`sffscan.stages.depth_choice.DEPARTURE_METHODS`), ``b`` is the size of the
  map's departure from the curves' 3-point peaks (:func:`sffscan.stages.depth_statistics.
  peak_departure`: a whole curve's or a wide window's pull into a lopsided curve's longer
  flank, or the argmax's sub-level offset on a flat), as it is (2026-12-05, night: their
  held-out rows under the band 25 / 58 / 59 -> 1 / 3 / 3 of 140; a streaming scan's SPC, PC
  and argmax judge it on the curves of every 16th row, which they keep for it). Where it is
  the whole-curve centroid, each pixel's departure from its curve's phase
  (:func:`centroid_departure`).
* ``c``: a floor, levels (the estimator's sub-level bias on a perfectly smooth surface).

``a``, ``r`` and ``c`` are fitted on the *training* seeds of the synthetic families
(:mod:`sffscan.stages.sim.families`) by a quantile fit, the 0.94 quantile of
``|error| / (2 sigma)`` equal to 1 (:func:`sffscan.stages.uncertainty_fit.fit_uncertainty`);
``sffscan study --families`` fits them without each family in turn and reports the
coverage (share of |error| <= 2 sigma) on the held-out family (docs/depth-study.md). They
are the default method's; some other methods have their own, fitted the same way on their
own errors (:func:`uncertainty_constants`, since 2026-12-05 evening). Nothing here is
fitted on the repository's data sets.
"""

from __future__ import annotations

import math

import cv2
import numpy as np
from sffscan.stages.depth_harmonics import pc_depth

__all__ = ["DEFAULT_CONSTANTS_METHOD", "FITTED_FOCUS_MEASURE", "FLOOR_LEVELS", "METHOD_CONSTANTS",
           "MIX_SCALE", "OTHER_METHODS", "OTHER_METHODS_CONSTANTS", "RELIEF_SCALE",
           "SCATTER_SCALE", "centroid_departure", "curve_width", "depth_range", "depth_relief",
           "depth_scatter", "depth_uncertainty", "floor_share", "height_uncertainty_um",
           "locking_visibility", "uncalibrated_focus_measure", "uncertainty_constants",
           "uncertainty_um", "width_excess", "width_from_sums"]

SCATTER_SCALE = 0.9841
"""``a`` of the default depth method (``"shape_select"``): fitted on the training seeds 0..5 of
the twenty families (the study's and the ten crossed from them; the ten study families'
seeds 0, 1, 2 until 2026-12-05, night) by
:func:`sffscan.stages.uncertainty_fit.fit_uncertainty` (``sffscan study --families --crossed
--seeds 6``, the row "fit on every family's training seeds": the constants the protocol's
held-out rows are fitted like; docs/depth-study.md), to the errors of the default depth
method (refitted when it became ``adaptive_centroid``: 4.138 and
0.0602 before; and ``shape_select``: 4.197 and 0.0301 before; and when ``adaptive_centroid``
weighed the pull against its noise: 3.970 and 0.0001 before; and when ``shape_select``'s
skewness limit went to 0.2, 2026-12-04: 3.892 and 0.0303 before; and when SPC's bias joined
the model, the same day: 3.833 and 0.0321 before; and when the relief joined it, that night:
3.799 and 0.0334 before; and when a peak method's pull joined ``b``, later that night: 1.569,
1.147 and 0.0477 before; and when ``adaptive_centroid`` began to test its wide centroid,
2026-12-05: 1.598, 1.138 and 0.0402 before; and when SPC's departure began to be measured
about the filtered argmax, the same day: 1.605, 1.136 and 0.0402 before; and when the excess
became one sigma, not a half, that session: 1.606, 1.136 and 0.0401 before; and when the
centroid's peak locking joined ``b``
(:func:`sffscan.stages.depth_choice.centroid_locking`), 2026-12-05 evening: 1.634, 1.116 and
0.0406 before, which the methods without constants of their own keep:
:data:`OTHER_METHODS_CONSTANTS`; and when the locking was added only where the relief cannot
see it, :func:`locking_visibility`, the same evening: 1.5163, 1.1285 and 0.005432 before;
and when the excess width's floor-share discount was dropped, that hour: 1.5462, 1.1334 and
0.005369 before; and when the fit's quantile target went to 0.935 and its training
set to the twenty families' seeds 0..5, 2026-12-05 night: 1.4854, 1.1527 and 0.005383
before)."""

RELIEF_SCALE = 1.1683
"""``r`` of the default depth method: fitted with :data:`SCATTER_SCALE`."""

FLOOR_LEVELS = 0.006291
"""``c`` of the default depth method, levels: fitted with :data:`SCATTER_SCALE`."""

DEFAULT_CONSTANTS_METHOD = "shape_select"
"""The depth method :data:`SCATTER_SCALE`, :data:`RELIEF_SCALE` and :data:`FLOOR_LEVELS` are
fitted to: the default (``sffscan.stages.depth.DEFAULT_METHOD``; a test holds them equal)."""

OTHER_METHODS_CONSTANTS = (1.634, 1.116, 0.0406)
"""``(a, r, c)`` of the depth methods without constants of their own
(:data:`METHOD_CONSTANTS`): the default's before its centroid's peak locking joined ``b``
(fitted on the default's errors, not on each method's own; ``"pc"``, ``"spc"``,
``"wcentroid"`` and ``"adaptive"``). With the locking term the default's refitted floor fell
from 0.0406 to 0.0054 levels (the locking now carries what the floor did on the flat
families), which left the 3-point peak of ``"adaptive"`` under-covered on a textured flat
(0.882 within 2 sigma, tests/stages/test_uncertainty_scan.py); its own fit over-covers that
flat (its 75th percentile 3.05 x the error's RMS)."""

METHOD_CONSTANTS: dict[str, tuple[float, float, float]] = {
    "argmax": (0.3666, 0.909, 0.1335),
    "gauss3": (0.6347, 0.9797, 0.07076),
    "quadratic3": (0.62, 0.9612, 0.08809),
    "centroid": (4.621, 0.02828, 0.5208),
    "adaptive_centroid": (1.379, 1.161, 0.0001),
}
"""``(a, r, c)`` fitted on each method's own errors, as the default's are on its own (the
twenty families' training seeds 0..5, the ten's 0, 1, 2 until 2026-12-05 night; ``python
bench/bench_method_constants.py``, bench/results/method_constants_before.md), for the
methods whose own constants (refitted without each family in turn) put at least as many
held-out (seed set, family) rows in the 90-98 % band and no more under it than
:data:`OTHER_METHODS_CONSTANTS`, on seeds 6..47 (the rule stated after that table,
2026-12-05 evening; on the clean seeds 102..107, in / under / over of 20: argmax 1 / 4 / 15
-> 17 / 0 / 3, gauss3 6 / 1 / 13 -> 19 / 1 / 0, quadratic3 4 / 3 / 13 -> 17 / 1 / 2,
centroid 4 / 16 / 0 -> 4 / 4 / 12, adaptive_centroid 13 / 0 / 7 -> 12 / 0 / 8;
bench/results/method_constants_102.md, docs/depth-method-log.md; ``"adaptive_centroid"``'s
refitted, 2.191, 1.083 and 0.0001 before, when its locking was added only where the relief
cannot see it: :func:`locking_visibility`; all five refitted when the excess width's
floor-share discount was dropped: argmax 0.3999, 0.936, 0.1822, gauss3 0.9689, 0.9202,
0.075, quadratic3 0.7191, 0.9607, 0.0979, centroid 20.63, 0.001, 0.0001, adaptive_centroid
2.172, 1.101, 0.0001 before).
All five refitted with the default's when the fit's quantile target went to 0.935 and its
training set to the twenty families' seeds 0..5 (2026-12-05, night): argmax 0.4788,
0.9277, 0.1804, gauss3 0.6999, 0.9859, 0.0733, quadratic3 0.721, 0.9695, 0.09508, centroid
19.98, 0.001, 0.0001, adaptive_centroid 2.308, 1.085, 0.0001 before.
``"argmax"``'s refitted when its departure from the curves' peaks joined ``b``
(:data:`sffscan.stages.depth_choice.DEPARTURE_METHODS`, 2026-12-05 night: 0.3489, 0.8799,
0.1928 before). ``"centroid"``'s refitted when its departure from its curves' phase joined
``b`` per pixel
(:func:`centroid_departure`, 2026-12-05 night: 20.25, 0.001, 0.0001 before, a fit on the
bounds of r and c that made the scatter carry the floor's pull). On seeds 6..47, refitted
per fold, in / under / over 27 / 31 / 82 -> 42 / 18 / 80; with
:data:`OTHER_METHODS_CONSTANTS` and the departure 66 / 45 / 29 (more in the band, but more
under it, the side that misleads: kept its own)."""


OTHER_METHODS = ("pc", "spc", "wcentroid", "adaptive")
"""The depth methods that take :data:`OTHER_METHODS_CONSTANTS`. With
:data:`DEFAULT_CONSTANTS_METHOD` and :data:`METHOD_CONSTANTS`' keys, every one of
``sffscan.stages.depth.DEPTH_METHODS`` (which this module cannot import: depth imports it;
a test holds the lists equal)."""


FITTED_FOCUS_MEASURE = ("glvm", 9)
"""The focus measure (operator, window k) every constant here was fitted with: the synthetic
families' stacks are measured with GLVM 9 (:func:`sffscan.stages.depth_study.uncertainty_sample`
's callers, ``bench/bench_method_constants.py``)."""


def uncalibrated_focus_measure(operator: str, window: int) -> str | None:
    """None for the focus measure the uncertainty was fitted with
    (:data:`FITTED_FOCUS_MEASURE`), else why its uncertainty is not calibrated, for a
    warning: measured on pertuz-simu02 (``sffscan study``, 2026-12-05), LAPM 5 and 9 put
    0.75-0.92 of the pixels within 2 sigma for most methods, GLVM 5 0.86 for the default."""
    op, k = FITTED_FOCUS_MEASURE
    if operator.lower() == op and window == k:
        return None
    return (f"the height uncertainty's constants were fitted with the focus measure "
            f"{op.upper()} k={k}; with {operator.upper()} k={window} it is not calibrated "
            "(on pertuz-simu02 LAPM put 0.75-0.92 of the pixels within 2 sigma, GLVM 5 "
            "0.86): check it on a surface you know with 'sffscan study'")


def uncertainty_constants(method: str) -> tuple[float, float, float]:
    """The constants ``(a, r, c)`` of the height uncertainty of a depth taken by ``method``:
    the default method's own fit, another method's own (:data:`METHOD_CONSTANTS`), or
    :data:`OTHER_METHODS_CONSTANTS` (:data:`OTHER_METHODS`).

    Raises
    ------
    ValueError
        For a name none of those lists holds (a study's candidate method, a typo): its
        uncertainty was never fitted, and no constants are given in its place.
    """
    if method == DEFAULT_CONSTANTS_METHOD:
        return SCATTER_SCALE, RELIEF_SCALE, FLOOR_LEVELS
    if method in METHOD_CONSTANTS:
        return METHOD_CONSTANTS[method]
    if method in OTHER_METHODS:
        return OTHER_METHODS_CONSTANTS
    known = sorted((DEFAULT_CONSTANTS_METHOD, *METHOD_CONSTANTS, *OTHER_METHODS))
    raise ValueError(f"method {method!r}: no height uncertainty constants for it; "
                     f"depth methods with them: {', '.join(known)}")


MIX_SCALE = 1.0
"""The excess width's share of sigma: all of it, from the geometry of a two-height mix whose
peak is taken on either height (not fitted; 0.5 until 2026-12-05)."""


def curve_width(volume: np.ndarray) -> np.ndarray:
    """Each focus curve's width (levels, one sigma) from its sums and minimum.

    A Gaussian peak of area A and sigma s on a floor b has ``H_0 = N b + A`` and
    ``|H_1| = A exp(-2 pi^2 s^2 / N^2)``; with b the curve's minimum,
    ``s = N / (pi sqrt 2) sqrt(-ln(|H_1| / (H_0 - N b)))``. Noise lowers the minimum,
    which widens the estimate.

    Parameters
    ----------
    volume : (N, H, W) ndarray of float
        Focus volume.

    Returns
    -------
    (H, W) ndarray of float64
        Width in levels (0 for a single-level spike, large for a flat curve).
    """
    vol = np.asarray(volume, dtype=np.float64)
    n = vol.shape[0]
    k = np.arange(n, dtype=np.float64)
    h0 = vol.sum(axis=0)
    re = np.tensordot(np.cos(2 * np.pi * k / n), vol, axes=1)
    im = np.tensordot(np.sin(2 * np.pi * k / n), vol, axes=1)
    return width_from_sums(h0, np.hypot(re, im), vol.min(axis=0), n)


def width_from_sums(h0: np.ndarray, h1_abs: np.ndarray, minimum: np.ndarray, n: int
                    ) -> np.ndarray:
    """:func:`curve_width` from ``H_0``, ``|H_1|`` and the minimum of each curve."""
    area = np.asarray(h0, np.float64) - n * np.asarray(minimum, np.float64)
    ratio = np.clip(np.asarray(h1_abs, np.float64) / np.where(area > 0, area, 1.0), 1e-9, 1.0)
    return n / (math.pi * math.sqrt(2.0)) * np.sqrt(-np.log(ratio))


def depth_scatter(depth_levels: np.ndarray, *, window: int = 9) -> np.ndarray:
    """RMS of the depth about its 5 x 5 median over ``window`` x ``window`` px (levels).

    Parameters
    ----------
    depth_levels : (H, W) ndarray of float
        Depth map, fractional levels, finite.
    window : int, keyword-only
        Odd averaging window, px (the focus measure's window). Default 9.

    Returns
    -------
    (H, W) ndarray of float32
    """
    d = np.ascontiguousarray(depth_levels, dtype=np.float32)
    return _scatter(d, cv2.medianBlur(d, 5), window)


def depth_relief(depth_levels: np.ndarray, *, window: int = 9) -> np.ndarray:
    """RMS of the depth about its own ``window`` x ``window`` box mean over ``window`` x
    ``window`` px (levels): zero on a plane, an error, bump or edge of about the focus
    window's size in full.

    Parameters
    ----------
    depth_levels : (H, W) ndarray of float
        Depth map, fractional levels, finite.
    window : int, keyword-only
        Odd window, px (the focus measure's window). Default 9.

    Returns
    -------
    (H, W) ndarray of float32
        Levels; borders replicated.
    """
    return _relief(np.ascontiguousarray(depth_levels, dtype=np.float32), window)


def _relief(d: np.ndarray, window: int) -> np.ndarray:
    # the scatter's RMS over the window, about the box mean instead of the 5 x 5 median
    mean = cv2.blur(d, (window, window), borderType=cv2.BORDER_REPLICATE)
    return _scatter(d, mean, window)


def _scatter(d: np.ndarray, median: np.ndarray, window: int) -> np.ndarray:
    r = d - median
    mean = cv2.blur(r * r, (window, window), borderType=cv2.BORDER_REPLICATE)
    return np.sqrt(np.maximum(mean, 0.0)).astype(np.float32)


def depth_range(depth_levels: np.ndarray, *, window: int = 9) -> np.ndarray:
    """Range (max - min) of the depth's 5 x 5 median over ``2 window + 1`` px square, levels.

    The heights a focus window of ``window`` px about a pixel can see, as measured beside
    it (replicated borders; the median drops isolated stray maxima).

    Parameters
    ----------
    depth_levels : (H, W) ndarray of float
        Depth map, fractional levels, finite.
    window : int, keyword-only
        The focus measure's window, px. Default 9.

    Returns
    -------
    (H, W) ndarray of float32
    """
    d = np.ascontiguousarray(depth_levels, dtype=np.float32)
    return _range(cv2.medianBlur(d, 5), window)


def _range(median: np.ndarray, window: int) -> np.ndarray:
    k = 2 * int(window) + 1
    kernel = np.ones((k, k), np.uint8)
    hi = cv2.dilate(median, kernel, borderType=cv2.BORDER_REPLICATE)
    lo = cv2.erode(median, kernel, borderType=cv2.BORDER_REPLICATE)
    return np.asarray(cv2.subtract(hi, lo), np.float32)


def locking_visibility(median_levels: np.ndarray, *, window: int = 9) -> np.ndarray:
    """The share of a peak estimator's locking that the scatter and relief do not show:
    ``|sinc(k |grad m|)|`` (``sinc(x) = sin(pi x) / (pi x)``), ``m`` the depth's 5 x 5 median
    (levels), its gradient in levels a px (central differences), ``k`` the focus window, px.

    The locking is a function of the true height's fraction of a level, periodic in it: on
    a surface whose height runs through a level every ``P`` px it is a ripple of that period,
    whose mean over the k-px box that the relief subtracts keeps ``sinc(k / P)`` of its
    amplitude, the part the relief cannot see (a flat part: all of it; a slope through a
    level every k px or faster: next to none). The geometry of the box filter; no fitted
    constant. Added 2026-12-05 evening (docs/depth-method-log.md).

    Parameters
    ----------
    median_levels : (H, W) ndarray of float32
        The depth's 5 x 5 median, levels.
    window : int, keyword-only
        The focus measure's window, px (the relief's box).

    Returns
    -------
    (H, W) ndarray of float32
        0 .. 1.
    """
    m = np.asarray(median_levels, np.float32)
    if min(m.shape) < 2:
        return np.ones(m.shape, np.float32)
    gy, gx = np.gradient(m)
    g = np.hypot(gx, gy)
    g *= np.float32(window)
    return np.abs(np.sinc(g)).astype(np.float32, copy=False)


def floor_share(h0: np.ndarray, minimum: np.ndarray, n_levels: int) -> np.ndarray:
    """Share of each focus curve's mass that is its floor: ``N min / H_0`` (0 .. 1).

    Parameters
    ----------
    h0 : (H, W) ndarray of float
        Sum of each curve, ``H_0``.
    minimum : (H, W) ndarray of float
        Each curve's smallest value.
    n_levels : int
        N.

    Returns
    -------
    (H, W) ndarray of float32
        0 for a curve on a zero floor, 1 for a flat curve (and where ``H_0 <= 0``).
    """
    h = np.asarray(h0, np.float32)
    out = np.float32(n_levels) * np.asarray(minimum, np.float32)
    np.divide(out, h, out=out, where=h > 0)
    out[~(h > 0)] = 1.0
    return np.clip(out, 0.0, 1.0)


def centroid_departure(depth_levels: np.ndarray, re: np.ndarray, im: np.ndarray,
                       n_levels: int) -> np.ndarray:
    """How far each pixel's whole-curve centroid (the depth method ``"centroid"``) lies from
    the phase of its curve's first harmonic (PC's depth,
    :func:`sffscan.stages.depth_harmonics.pc_depth`), levels, on the circle of N levels.

    A curve's floor pulls its centroid towards the middle of the range by ``|m - c| s /
    (1 - s)`` (``s`` the floor's share, ``m`` the middle), a bias of each pixel that moves
    with the height, smoothly, so that the map's scatter does not show it; a constant floor
    adds nothing to the first harmonic, so the phase does not move with it. The departure
    also holds the phase's own noise: an upper bound rather than a lower one. The
    uncertainty adds it in quadrature, no constant. Measured against the floor's pull
    computed from the curve's smallest value instead, which a noisy floor lies above
    (docs/depth-method-log.md): held-out (set, family) rows of seeds 6..47, with the
    constants refitted per fold, in / under / over the band 27 / 31 / 82 of 140 without
    either, 34 / 41 / 65 with that pull, 42 / 18 / 80 with this departure.

    Parameters
    ----------
    depth_levels : (H, W) ndarray of float
        The centroid, levels (non-finite values: no departure).
    re, im : (H, W) ndarray of float
        Re H_1 and Im H_1 of each curve (:func:`sffscan.stages.depth.focus_sums`' last
        two).
    n_levels : int
        N.

    Returns
    -------
    (H, W) ndarray of float32
        Levels, 0 .. N / 2.
    """
    c = np.asarray(depth_levels, np.float32)
    d = np.abs(c - pc_depth(np.asarray(re, np.float32), np.asarray(im, np.float32),
                            n_levels=n_levels))
    np.minimum(d, np.float32(n_levels) - d, out=d)
    d[~np.isfinite(c)] = 0.0
    return d.astype(np.float32, copy=False)


def width_excess(width_levels: np.ndarray, depth_range_levels: np.ndarray, *,
                 window: int = 9, valid: np.ndarray | None = None) -> np.ndarray:
    """How much wider each curve is than the curves about it, levels, at most half the
    depth's range about it.

    ``min(sqrt(max(w^2 - m^2, 0)), R / 2)``, ``m`` the mean width over ``2 window + 1`` px
    square (replicated borders), ``R`` the depth's range there.

    Parameters
    ----------
    width_levels : (H, W) ndarray of float
        Each curve's width, levels (:func:`curve_width`, :func:`width_from_sums`).
    depth_range_levels : (H, W) ndarray of float
        The depth's range about each pixel, levels (:func:`depth_range`): a mix of two
        heights ``D`` apart widens a curve by at most ``D / 2``.
    window : int, keyword-only
        The focus measure's window, px.
    valid : (H, W) ndarray of bool, optional, keyword-only
        The pixels whose curves count: the mean width is taken over these only (a curve
        that lacks levels, whatever its sums hold, widens nobody's reference); where a
        square holds none, the pixel's own width. Default: every pixel.

    Returns
    -------
    (H, W) ndarray of float32
    """
    w = np.ascontiguousarray(width_levels, dtype=np.float32)
    k = 2 * int(window) + 1
    mean = _mean_width(w, k, valid)
    ex = np.asarray(cv2.subtract(cv2.multiply(w, w), cv2.multiply(mean, mean)), np.float32)
    np.maximum(ex, np.float32(0.0), out=ex)
    np.sqrt(ex, out=ex)
    np.minimum(ex, np.float32(0.5) * np.asarray(depth_range_levels, np.float32), out=ex)
    return ex


def _mean_width(w: np.ndarray, k: int, valid: np.ndarray | None) -> np.ndarray:
    """Mean of ``w`` over k x k px (replicated borders), over the ``valid`` pixels only."""
    if valid is None:
        return np.asarray(cv2.blur(w, (k, k), borderType=cv2.BORDER_REPLICATE), np.float32)
    box = (k, k)
    # the invalid pixels' widths as 0.0 (whatever they hold: NaN too), then / the share
    num = cv2.blur(np.where(valid, w, np.float32(0.0)), box, borderType=cv2.BORDER_REPLICATE)
    den = cv2.blur(np.asarray(valid, np.float32), box, borderType=cv2.BORDER_REPLICATE)
    # a box mean of 0/1 is a multiple of 1 / k^2 up to round-off: below half of it, none
    some = den > np.float32(0.5 / (k * k))
    np.divide(num, den, out=num, where=some)
    np.copyto(num, w, where=~some)
    return np.asarray(num, np.float32)


def depth_uncertainty(depth_levels: np.ndarray, width_levels: np.ndarray, *,
                      window: int = 9,
                      scatter_scale: float = SCATTER_SCALE,
                      relief_scale: float = RELIEF_SCALE,
                      floor_levels: float = FLOOR_LEVELS, bias_levels: float = 0.0,
                      locking_levels: float = 0.0) -> np.ndarray:
    """One-sigma uncertainty of a depth map, in levels.

    Parameters
    ----------
    depth_levels : (H, W) ndarray of float
        Depth map, fractional levels, finite.
    width_levels : (H, W) ndarray of float
        Width of each pixel's focus curve, levels (:func:`curve_width`).
    window : int, keyword-only
        Focus measure window, px (the scatter's averaging window; the excess width's
        reference and the depth's range are over ``2 window + 1`` px).
    scatter_scale, relief_scale, floor_levels : float, keyword-only
        The constants ``a``, ``r`` and ``c`` (defaults: fitted on the training families).
    bias_levels : float, keyword-only
        ``b``: a bias of the whole map that its scatter does not show, levels (SPC's
        departure where ``"shape_select"`` took SPC, a peak method's centroid pull:
        :func:`sffscan.stages.depth_choice.method_bias`); default 0.
    locking_levels : float, keyword-only
        ``L``: the peak estimator's locking, levels
        (:func:`sffscan.stages.depth_choice.peak_locking`), added in quadrature at each
        pixel times :func:`locking_visibility`; default 0.

    Returns
    -------
    (H, W) ndarray of float32
        ``sqrt((a scatter)^2 + (r relief)^2 + excess^2 + c^2 + b^2 + (L v)^2)``, levels.
    """
    d = np.ascontiguousarray(depth_levels, dtype=np.float32)
    med = cv2.medianBlur(d, 5)
    x = width_excess(width_levels, _range(med, window), window=window)
    return _combine(_scatter(d, med, window), _relief(d, window), x, scatter_scale,
                    relief_scale, floor_levels, bias_levels,
                    _locking(med, window, locking_levels))


def _locking(median: np.ndarray, window: int, locking: float) -> np.ndarray | None:
    """``L v`` at each pixel (levels), None where ``L`` is 0."""
    if not locking:
        return None
    v = locking_visibility(median, window=window)
    v *= np.float32(locking)
    return v


def _combine(scatter: np.ndarray, relief: np.ndarray, excess: np.ndarray, a: float,
             r: float, c: float, bias: float = 0.0,
             locking: np.ndarray | None = None,
             pull: np.ndarray | None = None) -> np.ndarray:
    var = scatter * scatter
    var *= np.float32(a * a)
    q = relief * relief
    q *= np.float32(r * r)
    var += q
    x = excess * np.float32(MIX_SCALE)
    var += x * x
    var += np.float32(c * c + bias * bias)
    if locking is not None:
        var += locking * locking
    if pull is not None:
        var += pull * pull
    return np.sqrt(var).astype(np.float32, copy=False)


def uncertainty_um(sigma_levels: np.ndarray, depth_levels: np.ndarray, *,
                   focus_heights_um: np.ndarray) -> np.ndarray:
    """Levels to µm: ``sigma`` times the focus table's step at each pixel's depth."""
    table = np.asarray(focus_heights_um, dtype=np.float64)
    step = np.abs(np.diff(table))
    d = np.nan_to_num(np.asarray(depth_levels, np.float64), nan=0.0)
    i = np.clip(np.floor(d), 0, step.size - 1).astype(np.intp)
    return (np.asarray(sigma_levels, np.float64) * step[i]).astype(np.float32)


def height_uncertainty_um(depth_levels: np.ndarray, sums: np.ndarray, minimum: np.ndarray,
                          *, method: str, n_levels: int, focus_heights_um: np.ndarray,
                          window: int = 9, bias_levels: float = 0.0,
                          locking_levels: float = 0.0, valid: np.ndarray | None = None
                          ) -> np.ndarray:
    """The height uncertainty, µm, one sigma, from a depth map and its curves' sums.

    What the streaming depth stage computes per block (and a whole-field stack per field):
    :func:`depth_uncertainty` of ``depth_levels`` with the curves' widths
    (:func:`width_from_sums`) from their sums and minima, in µm by :func:`uncertainty_um`.

    Parameters
    ----------
    depth_levels : (H, W) ndarray of float
        Depth, fractional levels; non-finite values count as 0 for the scatter (mark those
        pixels invalid afterwards).
    sums : (3, H, W) ndarray of float
        H_0, Re H_1, Im H_1 of every curve (:func:`sffscan.stages.depth.focus_sums`).
    minimum : (H, W) ndarray of float
        Each curve's smallest value.
    method : str, keyword-only
        The depth method that took ``depth_levels``: its constants
        (:func:`uncertainty_constants`).
    n_levels : int, keyword-only
        N.
    focus_heights_um : (N,) array_like, keyword-only
        Height in focus at each level, µm.
    window : int, keyword-only
        The focus measure's window, px (the scatter's window).
    bias_levels : float, keyword-only
        ``b`` of :func:`depth_uncertainty`, levels; default 0.
    locking_levels : float, keyword-only
        ``L`` of :func:`depth_uncertainty`, levels; default 0.
    valid : (H, W) ndarray of bool, optional, keyword-only
        The pixels whose curves are whole (:func:`width_excess`): the others' sums and
        minima are not read for their neighbours. Default: every pixel.

    Returns
    -------
    (H, W) ndarray of float32
        µm.
    """
    d = np.nan_to_num(np.asarray(depth_levels, np.float32), nan=0.0, posinf=0.0,
                      neginf=0.0)
    # float32 throughout (a block of 1000 x 64 px per few frames of a scan)
    h0, re, im = (np.asarray(v, np.float32) for v in sums)
    low = np.asarray(minimum, np.float32)
    area = h0 - np.float32(n_levels) * low
    ratio = np.hypot(re, im)
    np.divide(ratio, area, out=ratio, where=area > 0)
    ratio[area <= 0] = 1.0
    np.clip(ratio, np.float32(1e-9), np.float32(1.0), out=ratio)
    w = np.log(ratio)
    w *= np.float32(-(n_levels / math.pi) ** 2 / 2.0)  # width^2, levels^2
    np.sqrt(w, out=w)
    med = cv2.medianBlur(d, 5)
    x = width_excess(w, _range(med, window), window=window, valid=valid)
    # the whole-curve centroid's departure from the first harmonic's phase, per pixel
    pull = centroid_departure(d, re, im, n_levels) if method == "centroid" else None
    sigma = _combine(_scatter(d, med, window), _relief(d, window), x,
                     *uncertainty_constants(method), bias_levels,
                     _locking(med, window, locking_levels), pull)
    table = np.asarray(focus_heights_um, dtype=np.float64)
    step = np.abs(np.diff(table)).astype(np.float32)
    if np.all(step == step[0]):
        return sigma * step[0]
    i = np.clip(d.astype(np.intp), 0, step.size - 1)  # d >= 0 here: floor
    return sigma * step[i]
