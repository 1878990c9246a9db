"""The shape of each focus curve: its width from its sums and minimum (:func:`curve_width`,
:func:`width_from_sums`), its floor's share of its mass (:func:`floor_share`), its
whole-curve centroid's departure from its first harmonic's phase
(:func:`centroid_departure`) and how much wider it is than the curves about it
(:func:`width_excess`).

The height uncertainty, :mod:`sffscan.stages.depth_uncertainty`, adds the excess width and
the centroid's departure to the depth map's own terms (scatter, relief, locking); the depth
methods' choices read the widths too.
"""

from __future__ import annotations

import math

import cv2
import numpy as np
from sffscan.stages.depth_harmonics import magnitude, pc_depth

__all__ = ["centroid_departure", "curve_width", "floor_share", "width_excess",
           "width_from_sums"]


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
    return width_from_sums(h0, magnitude(re, im), vol.min(axis=0), n)


def width_from_sums(h0: np.ndarray, h1_abs: np.ndarray, minimum: np.ndarray, n: int
                    ) -> np.ndarray:
    """:func:`curve_width` from ``H_0``, ``|H_1|`` and the minimum of each curve."""
    area = np.asarray(h0, np.float64) - n * np.asarray(minimum, np.float64)
    ratio = np.clip(np.asarray(h1_abs, np.float64) / np.where(area > 0, area, 1.0), 1e-9, 1.0)
    return n / (math.pi * math.sqrt(2.0)) * np.sqrt(-np.log(ratio))


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
        The depth's range about each pixel, levels
        (:func:`~sffscan.stages.depth_uncertainty.depth_range`): a mix of two heights ``D``
        apart widens a curve by at most ``D / 2``.
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
