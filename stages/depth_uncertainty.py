"""Per-pixel height uncertainty (one sigma) of a depth map, measured from the data.

Five terms, added in quadrature (levels; times the local focus step for µm):

``sigma^2 = (a * scatter)^2 + (r * relief)^2 + excess^2 + b^2 + c^2``

* ``scatter``: the depth's RMS about its 5 x 5 median over the focus window (k x k px,
  :func:`depth_scatter`). Noise of the focus curves, stray maxima and a peak fit that locks
  onto the sampling show as pixel-to-pixel scatter; a smooth surface does not.
* ``relief``: the depth's RMS about its own k x k box mean over the focus window
  (:func:`depth_relief`). Neighbouring pixels share most of the focus window, so their
  errors are correlated and smooth over a few pixels: a 5 x 5 median follows them and
  hides them from the scatter. The box mean leaves a plane alone (a slope has no relief)
  and leaves an error, a bump or an edge of about the window's size in ``relief``.
* ``excess``: how much wider the pixel's focus curve is than the curves about it
  (:func:`~sffscan.stages.curve_shape.width_excess`, ``sqrt(w^2 - mean_(2k+1)(w)^2)``,
  levels), at most half the range of the depth map about it. A focus window that sees two
  heights (an edge, a step) has a curve with two modes; a mix of two heights ``D`` apart
  in shares ``p``, ``1 - p`` widens the curve by ``D sqrt(p (1 - p))`` in quadrature. The
  peak the estimator takes is one mode or the other, and the other one (an error of the
  whole step) about as often as that mode's share: an error of standard deviation
  ``D sqrt(p (1 - p))``, the excess itself, so ``excess`` is one sigma (this geometry, not
  a fitted constant: :data:`MIX_SCALE`). ``D`` is measured beside the mix, within
  ``2k + 1`` px: at most the range (max - min) of the depth's 5 x 5 median over that
  square, so the excess is capped at half that range (without the cap a textured surface,
  whose curves' widths scatter from pixel to pixel, got 0.5 .. 1 level of sigma from that
  scatter alone).
* ``b``: a bias of the whole map, which its scatter cannot show. Where ``"shape_select"``
  took SPC for the stack or scan block, SPC's median departure from the peaks the fallback
  would take (:attr:`sffscan.stages.depth_choice.StackChoice.bias`; the choice takes SPC
  where that departure is small against the noise, not where it is zero). Where the depth
  is a peak instead (the fallback of ``"shape_select"``, ``"adaptive"`` and
  ``"adaptive_centroid"``), the size of the curves' centroid pull
  (:func:`sffscan.stages.depth_choice.fallback_bias`: two peak estimators that disagree the
  same way on every curve), with the 5-level centroid's peak locking where the relief
  cannot see it (:func:`locking_visibility`). Where it is SPC, PC, the 9-level centroid or
  the argmax by name (:data:`sffscan.stages.depth_choice.DEPARTURE_METHODS`), the size of
  the map's departure from the curves' 3-point peaks
  (:func:`sffscan.stages.depth_statistics.peak_departure`; a streaming scan's SPC, PC and
  argmax judge it on the curves of every 16th row, which they keep for it). Where it is the
  whole-curve centroid, each pixel's departure from its curve's phase
  (:func:`~sffscan.stages.curve_shape.centroid_departure`). Each added as it is, no
  constant.
* ``c``: a floor, levels (the estimator's sub-level bias on a perfectly smooth surface).

``a``, ``r`` and ``c`` are fitted per depth method on the *training* seeds of the synthetic
families (:mod:`sffscan.stages.fitted_constants`, their home: how, on what, and
:func:`~sffscan.stages.fitted_constants.uncertainty_constants`). Nothing here is fitted on
the repository's data sets. Each term's measured effect when it joined, and the forms tried
before it: docs/depth-method-log.md ("The height uncertainty's model, as its docstring
told it").
"""

from __future__ import annotations

import math

import cv2
import numpy as np
from sffscan.stages.curve_shape import centroid_departure, width_excess
from sffscan.stages.depth_harmonics import magnitude
from sffscan.stages.fitted_constants import (
    FLOOR_LEVELS,
    RELIEF_SCALE,
    SCATTER_SCALE,
    uncertainty_constants,
)

__all__ = ["MIX_SCALE", "depth_range", "depth_relief", "depth_scatter", "depth_uncertainty",
           "height_uncertainty_um", "locking_visibility", "uncertainty_um"]


MIX_SCALE = 1.0
"""The excess width's share of sigma: all of it, from the geometry of a two-height mix whose
peak is taken on either height (not fitted; 0.5 until 2026-12-05)."""


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
    g = magnitude(gx, gy)
    g *= np.float32(window)
    return np.abs(np.sinc(g)).astype(np.float32, copy=False)


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
        Width of each pixel's focus curve, levels
        (:func:`~sffscan.stages.curve_shape.curve_width`).
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
    (:func:`~sffscan.stages.curve_shape.width_from_sums`) from their sums and minima, in µm
    by :func:`uncertainty_um`.

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
        (:func:`~sffscan.stages.fitted_constants.uncertainty_constants`).
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
        The pixels whose curves are whole (:func:`~sffscan.stages.curve_shape.width_excess`):
        the others' sums and minima are not read for their neighbours. Default: every pixel.

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
    ratio = magnitude(re, im)
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
