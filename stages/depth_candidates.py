"""Depth estimators tried as candidates by the leave-one-family-out study
(:mod:`sffscan.stages.depth_study`). They are not methods of scan, replay or stack; the
first two are selectable by name in :func:`sffscan.stages.depth.depth_from_focus`
(:data:`sffscan.stages.depth.CANDIDATE_METHODS`, at the settings below).

Both fit a model over more than the 3 points of ``gauss3``, in a window about the
median-filtered argmax (``centre``, as for SPC and ``adaptive``):

* :func:`gauss_window_fit`: a Gaussian on log values over 2h + 1 levels, each level
  weighted by the square of its height above the curve's minimum (the inverse of the
  variance of a log value under additive noise), so the levels far down the curve's flanks
  count little: the effective window follows the curve's width;
* :func:`window_pc`: phase correlation over a window of P levels about the centre, P set
  per pixel from the curve's measured width (its run of levels above half its height,
  :func:`half_height_run`, median over 11 x 11 px) times a factor: the whole curve's PC
  (SPC) for wide curves, a short one for narrow curves on a noisy floor.

:func:`plane_residual` is the study's ``planar-peak`` candidate's test. The statistics by
which the default method chooses between estimators are in
:mod:`sffscan.stages.depth_choice`.
"""

from __future__ import annotations

import cv2
import numpy as np

__all__ = ["GAUSS_FIT_HALF_WINDOW", "WINDOW_PC_FACTOR", "gauss_window_fit",
           "half_height_count", "half_height_run", "plane_residual", "window_pc"]

GAUSS_FIT_HALF_WINDOW = 3
"""Half window h of ``"gauss_window_fit"`` by name: the study's setting tuned on the training
seeds of all its families (docs/depth-study.md, the pertuz-simu02 row's ``tuned``)."""

WINDOW_PC_FACTOR = 3.0
"""Factor on the curve's width of ``"window_pc"`` by name, tuned as
:data:`GAUSS_FIT_HALF_WINDOW`."""

def _window(volume: np.ndarray, centre: np.ndarray, h: int
            ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Levels centre - h .. centre + h (float64, (2h + 1, H, W)), the mask of those in the
    range, and the offsets j (column vector)."""
    n = volume.shape[0]
    j = np.arange(-h, h + 1)[:, None, None]
    k = np.asarray(centre)[None] + j
    inside = (k >= 0) & (k < n)
    vals = np.take_along_axis(volume, np.clip(k, 0, n - 1), axis=0).astype(np.float64)
    return vals, inside, j.astype(np.float64)


def gauss_window_fit(volume: np.ndarray, centre: np.ndarray, fallback: np.ndarray, *,
                     half_window: int) -> np.ndarray:
    """Weighted least-squares Gaussian (a parabola on log values) over 2h + 1 levels.

    Parameters
    ----------
    volume : (N, H, W) ndarray of float
        Focus volume.
    centre : (H, W) ndarray of int
        Window centres (median-filtered argmax), levels.
    fallback : (H, W) ndarray of float
        Depth where the fit fails (no maximum in the window, a singular system).
    half_window : int, keyword-only
        h >= 1.

    Returns
    -------
    (H, W) ndarray of float32
        Depth in fractional levels.
    """
    vals, inside, j = _window(volume, centre, half_window)
    floor = np.asarray(volume, np.float64).min(axis=0)
    w = np.where(inside, np.maximum(vals - floor[None], 0.0), 0.0)
    q = w * w
    y = np.log(np.maximum(w, 1e-30))
    s = [np.sum(q * j**p, axis=0) for p in range(5)]
    t = [np.sum(q * y * j**p, axis=0) for p in range(3)]
    m = np.stack([np.stack([s[0], s[1], s[2]]), np.stack([s[1], s[2], s[3]]),
                  np.stack([s[2], s[3], s[4]])])
    m = np.moveaxis(m, (0, 1), (-2, -1))
    det = np.linalg.det(m)
    ok = np.abs(det) > 1e-9 * np.maximum(s[0], 1e-30) ** 3
    coef = np.linalg.solve(np.where(ok[..., None, None], m, np.eye(3)),
                           np.moveaxis(np.stack(t), 0, -1)[..., None])[..., 0]
    b, c = coef[..., 1], coef[..., 2]
    ok &= c < 0
    off = np.where(ok, -b / (2.0 * np.where(ok, c, -1.0)), 0.0)
    ok &= np.abs(off) <= half_window
    return np.where(ok, np.asarray(centre) + off, fallback).astype(np.float32)


def _above_half(volume: np.ndarray, centre: np.ndarray, reach: int
                ) -> tuple[np.ndarray, np.ndarray]:
    """The levels within ``reach`` of ``centre`` above half the curve's height over its
    minimum ((2 reach + 1, H, W) bool), and the window's values (-inf outside the range)."""
    vals, inside, _ = _window(volume, centre, reach)
    top = np.where(inside, vals, -np.inf)
    half = 0.5 * (top.max(axis=0) + np.asarray(volume, np.float64).min(axis=0))
    return inside & (vals > half[None]), top


def half_height_run(volume: np.ndarray, centre: np.ndarray, *, reach: int = 15) -> np.ndarray:
    """Levels in the run above half the curve's height (over its minimum) through the
    window's maximum, within ``reach`` levels of ``centre``; (H, W) int."""
    above, top = _above_half(volume, centre, reach)
    at = top.argmax(axis=0)
    # the run ends at the first level below half height on either side of the maximum
    # (or the window's end): one search per side over the window's 2 reach + 1 levels
    j = np.arange(2 * reach + 1).reshape(-1, *([1] * at.ndim))
    after = ~above & (j > at)
    end = np.where(after.any(axis=0), after.argmax(axis=0), 2 * reach + 1)
    before = (~above & (j < at))[::-1]
    start = np.where(before.any(axis=0), 2 * reach - before.argmax(axis=0), -1)
    return (end - start - 1).astype(np.int64)


def half_height_count(volume: np.ndarray, centre: np.ndarray, *, reach: int = 15
                      ) -> np.ndarray:
    """Levels above half the curve's height (over its minimum) within ``reach`` levels of
    ``centre``, wherever they lie, at least 1 (the maximum itself: a flat curve has no level
    above its half height); (H, W) int. The same as :func:`half_height_run` on a
    curve with one peak and no noise; on a noisy one a level dipping under half height
    inside the peak cuts the run but not the count (the width ratio of
    :func:`sffscan.stages.depth_statistics.shape_statistics` reads this one).

    Parameters
    ----------
    volume : (N, H, W) ndarray of float
        Focus curves.
    centre : (H, W) ndarray of int
        Window centres, levels.
    reach : int, keyword-only
        Half width of the window read, levels.
    """
    return np.maximum(_above_half(volume, centre, reach)[0].sum(axis=0), 1).astype(np.int64)


def window_pc(volume: np.ndarray, centre: np.ndarray, *, factor: float) -> np.ndarray:
    """Phase correlation over P levels about ``centre``, P = factor x the curve's width
    (:func:`half_height_run`, median over 11 x 11 px), odd, 5 .. N (kept inside the range).

    Returns
    -------
    (H, W) ndarray of float32
        Depth in fractional levels.
    """
    n = volume.shape[0]
    run = half_height_run(volume, centre)
    pooled = cv2.medianBlur(np.clip(run, 0, 255).astype(np.uint8), 11).astype(np.int64)
    top = n if n % 2 else n - 1
    period = np.clip(np.round(factor * pooled).astype(np.int64) // 2 * 2 + 1, 5, top)
    h = int(period.max()) // 2
    c = np.asarray(centre).astype(np.int64)
    shift = np.clip(period // 2 - c, 0, None) - np.clip(c + period // 2 - (n - 1), 0, None)
    vals, inside, j = _window(volume, c + shift, h)
    use = inside & (np.abs(j) <= (period // 2)[None])
    theta = 2.0 * np.pi * (j + shift[None]) / period[None]
    v = np.where(use, vals, 0.0)
    re = np.sum(v * np.cos(theta), axis=0)
    im = np.sum(v * np.sin(theta), axis=0)
    return (c + np.arctan2(im, re) * period / (2.0 * np.pi)).astype(np.float32)


def plane_residual(centre: np.ndarray, *, window: int) -> np.ndarray:
    """RMS (levels) of the filtered peaks ``centre`` about their least-squares plane over
    the ``window`` x ``window`` square about each pixel (edges reflected): about 0 where
    the window sees a plane (a slope: the curve blends heights evenly about the pixel's
    own), large where it sees an edge or a step (float64, ``centre``'s shape)."""
    z = np.asarray(centre, np.float64)
    r = window // 2
    x = np.tile(np.arange(-r, r + 1, dtype=np.float64), (window, 1))
    n, sxx = window * window, float((x * x).mean())
    border = cv2.BORDER_REFLECT
    ez = cv2.boxFilter(z, -1, (window, window), normalize=True, borderType=border)
    ez2 = cv2.boxFilter(z * z, -1, (window, window), normalize=True, borderType=border)
    exz = cv2.filter2D(z, -1, x / n, borderType=border)
    eyz = cv2.filter2D(z, -1, x.T / n, borderType=border)
    return np.sqrt(np.maximum(ez2 - ez * ez - (exz * exz + eyz * eyz) / sxx, 0.0))
