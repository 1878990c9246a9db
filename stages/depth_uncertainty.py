"""Per-pixel height uncertainty (one sigma) of a depth map, measured from the data.

Two measured terms, added in quadrature:

* the *scatter* of the depth about its local median: ``r = d - median_5x5(d)``, averaged
  as ``r^2`` over the focus window (k x k px). A noisy focus curve, a stray maximum or a
  peak fit that locks onto the sampling shows as pixel-to-pixel scatter; a smooth surface
  does not;
* the focus curve's *width* (levels, :func:`curve_width`): the wider the curve, the more a
  windowed estimator's result depends on what the window cuts off, the more a blend of
  heights inside the focus window spreads the curve.

``sigma^2 = (a * scatter)^2 + (b * width)^2`` in levels, times the local focus step for µm.
The two constants are fitted on the *training* seeds of the synthetic families
(:mod:`sffscan.stages.sim.families`) so that |error| <= 2 sigma holds for 90 .. 98 % of the
pixels of as many training families as the grid allows
(:func:`sffscan.stages.depth_study.fit_uncertainty`); ``sffscan study --families`` reports
the coverage on the held-out family of each fold (leave one family out): in the band for
6 of the 10 families, below on steps (0.90) and a coarse clean texture (0.86), above on
flat and end-of-range surfaces (0.99 .. 1.00), 0.97 on pertuz-simu02 (docs/depth-study.md).
"""

from __future__ import annotations

import math

import cv2
import numpy as np

__all__ = ["SCATTER_SCALE", "WIDTH_SCALE", "curve_width", "depth_scatter",
           "depth_uncertainty", "height_uncertainty_um", "uncertainty_um", "width_from_sums"]

SCATTER_SCALE = 5.0
"""``a``: fitted on the training seeds (0, 1, 2) of all families by
:func:`sffscan.stages.depth_study.fit_uncertainty` (``sffscan study --families``, the row
"fit on every family's training seeds"; docs/depth-study.md)."""

WIDTH_SCALE = 0.05
"""``b``: fitted with :data:`SCATTER_SCALE`."""


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
    r = d - cv2.medianBlur(d, 5)
    mean = cv2.blur(r * r, (window, window), borderType=cv2.BORDER_REPLICATE)
    return np.sqrt(np.maximum(mean, 0.0)).astype(np.float32)


def depth_uncertainty(depth_levels: np.ndarray, width_levels: np.ndarray, *,
                      window: int = 9, scatter_scale: float = SCATTER_SCALE,
                      width_scale: float = WIDTH_SCALE) -> np.ndarray:
    """One-sigma uncertainty of a depth map, in levels.

    Parameters
    ----------
    depth_levels : (H, W) ndarray of float
        Depth map, fractional levels, finite.
    width_levels : (H, W) ndarray of float
        Width of each pixel's focus curve, levels (:func:`curve_width`).
    window : int, keyword-only
        Focus measure window, px (the scatter's averaging window).
    scatter_scale, width_scale : float, keyword-only
        The constants ``a`` and ``b`` (defaults: fitted on the training families).

    Returns
    -------
    (H, W) ndarray of float32
        ``sqrt((a scatter)^2 + (b width)^2)``, levels.
    """
    s = depth_scatter(depth_levels, window=window).astype(np.float64)
    w = np.asarray(width_levels, np.float64)
    return np.sqrt((scatter_scale * s) ** 2 + (width_scale * w) ** 2).astype(np.float32)


def uncertainty_um(sigma_levels: np.ndarray, depth_levels: np.ndarray, *,
                   focus_heights_um: np.ndarray) -> np.ndarray:
    """Levels to µm: ``sigma`` times the focus table's step at each pixel's depth."""
    table = np.asarray(focus_heights_um, dtype=np.float64)
    step = np.abs(np.diff(table))
    d = np.nan_to_num(np.asarray(depth_levels, np.float64), nan=0.0)
    i = np.clip(np.floor(d), 0, step.size - 1).astype(np.intp)
    return (np.asarray(sigma_levels, np.float64) * step[i]).astype(np.float32)


def height_uncertainty_um(depth_levels: np.ndarray, sums: np.ndarray, minimum: np.ndarray,
                          *, n_levels: int, focus_heights_um: np.ndarray, window: int = 9
                          ) -> np.ndarray:
    """The height uncertainty, µm, one sigma, from a depth map and its curves' sums.

    What the streaming depth stage computes per block (and a whole-field stack per field):
    :func:`depth_uncertainty` of ``depth_levels`` with the curves' widths from
    :func:`width_from_sums`, in µm by :func:`uncertainty_um`.

    Parameters
    ----------
    depth_levels : (H, W) ndarray of float
        Depth, fractional levels; non-finite values count as 0 for the scatter (mark those
        pixels invalid afterwards).
    sums : (3, H, W) ndarray of float
        H_0, Re H_1, Im H_1 of every curve (:func:`sffscan.stages.depth.focus_sums`).
    minimum : (H, W) ndarray of float
        Each curve's smallest value.
    n_levels : int, keyword-only
        N.
    focus_heights_um : (N,) array_like, keyword-only
        Height in focus at each level, µm.
    window : int, keyword-only
        The focus measure's window, px (the scatter's window).

    Returns
    -------
    (H, W) ndarray of float32
        µm.
    """
    d = np.nan_to_num(np.asarray(depth_levels, np.float32), nan=0.0, posinf=0.0,
                      neginf=0.0)
    # float32 throughout (a block of 1000 x 64 px per few frames of a scan)
    h0, re, im = (np.asarray(v, np.float32) for v in sums)
    area = h0 - np.float32(n_levels) * np.asarray(minimum, np.float32)
    ratio = np.hypot(re, im)
    np.divide(ratio, area, out=ratio, where=area > 0)
    ratio[area <= 0] = 1.0
    np.clip(ratio, np.float32(1e-9), np.float32(1.0), out=ratio)
    w2 = np.log(ratio)
    w2 *= np.float32(-(n_levels / math.pi) ** 2 / 2.0)  # width^2, levels^2
    s = depth_scatter(d, window=window)
    var = s * s
    var *= np.float32(SCATTER_SCALE**2)
    var += np.float32(WIDTH_SCALE**2) * w2
    sigma = np.sqrt(var)
    table = np.asarray(focus_heights_um, dtype=np.float64)
    step = np.abs(np.diff(table)).astype(np.float32)
    if np.all(step == step[0]):
        return sigma * step[0]
    i = np.clip(d.astype(np.intp), 0, step.size - 1)  # d >= 0 here: floor
    return sigma * step[i]
