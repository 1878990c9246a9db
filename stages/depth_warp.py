"""A level axis warped so that a thin lens' lopsided focus curves become even.

Under a thin lens the blur grows linearly in ``1 / (D + z)`` (``D`` the working distance,
``z`` the height), not in ``z``: where the focus levels are evenly spaced in height, every
focus curve is lopsided in level units (its maximum stays at the height in focus, its flanks
do not). Centroids and the first harmonic (SPC) are then pulled into the longer flank; a
3-point fit is not, but it is noisy. With ``s = c / (N - 1)`` and

    ``g(k) = k / (1 + s k)``  (``c = (N - 1) / D``; ``c = 0``: no warp)

the curve is even in ``g``. Each curve's half-height crossings ``z_l < f < z_r`` about its
peak ``f`` (a 3-point Gaussian) then satisfy ``g(z_l) + g(z_r) = 2 g(f)``:
:func:`lens_asymmetry` finds the ``c`` at which the median over the volume's curves of the
normalised asymmetry ``(g(z_l) + g(z_r) - 2 g(f)) / (g(z_r) - g(z_l))`` crosses zero, and
its standard error by resampling the curves. :func:`warp_volume` resamples the volume onto
N levels evenly spaced in ``g`` (each the curve's mean over the original levels it stands
for), and
:func:`unwarp_levels` maps a depth on that grid back to the original levels.

This is the study's candidate ``"warped_select"``
(:data:`sffscan.stages.depth.CANDIDATE_METHODS`): ``"shape_select"`` on the warped volume
where the warp is clearly needed (``|c| >= WARP_MIN_C`` and ``|c| >= WARP_MIN_Z`` standard
errors), else ``"shape_select"`` itself. Both thresholds were fixed on the training seeds
(0..2) of the synthetic families and not changed after held-out seeds were scored
(docs/depth-method-log.md, 2026-12-05; bench/results/level_warp.md). Where it loses: SPC,
taken on the evened curves, errs on thin-lens pillbox slopes (seeds 60..65, with point
samples for the warped levels: 0.42-0.69 levels RMSE on four stacks against the fallback's
0.26-0.29); and a noisy or quantised floor can make even curves look lopsided (on seeds
54..71 every stack warped without a thin lens had c of -0.54 .. -0.86; one 8-bit flat 1.53x
the best method). Not a method of scan or replay yet: the streaming
depth stage would have to warp each block's stored levels.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from sffscan.stages.depth_peak import three_point_offset

__all__ = ["MAX_CURVES", "WARP_GRID", "WARP_MIN_C", "WARP_MIN_Z", "LevelWarp",
           "half_height_crossings", "lens_asymmetry", "unwarp_levels", "warp_volume"]

WARP_MIN_C = 0.3
"""Smallest ``|c|`` that is warped (a working distance under ~3.3 focus ranges)."""
WARP_MIN_Z = 4.0
"""``|c|`` must also be this many standard errors (bootstrap over the curves)."""
WARP_GRID = np.linspace(-0.9, 6.0, 139)
"""The values of ``c`` searched for the zero crossing (linear between grid points)."""
BOOTSTRAPS = 30
"""Resamples of the curves for the standard error of ``c``."""
SAMPLE_STEP = 2
"""Every ``SAMPLE_STEP``-th row and column's curve is read (more apart where that would be
more than :data:`MAX_CURVES`)."""
WARP_BAND_VALUES = 1 << 21
""":func:`warp_volume` works on bands of rows of about this many values (levels x rows x
columns; float64 work arrays of 16 MiB each)."""
MAX_CURVES = 16384
"""At most about this many curves are read: a 768 x 1024 x 50 volume's 196,608 at every
second pixel took 8.9 s (the 139 medians of every resample), a 256 x 256 stack's 16,384 about
0.3 s."""
MIN_CURVES = 100
"""Fewer usable curves (both crossings, peak within the middle 60 % of the range): no
estimate."""


@dataclass(frozen=True)
class LevelWarp:
    """The warp :func:`lens_asymmetry` found for a volume."""

    c: float
    """``(N - 1) / D``; NaN without an estimate."""
    standard_error: float
    """Of ``c`` (inf where too few resamples gave one)."""
    curves: int
    """Curves that gave both crossings with a peak in the middle of the range."""

    @property
    def applied(self) -> bool:
        """Whether the volume is warped: ``|c| >= WARP_MIN_C`` and ``WARP_MIN_Z`` standard
        errors."""
        c = self.c
        return bool(np.isfinite(c) and abs(c) >= WARP_MIN_C
                    and abs(c) >= WARP_MIN_Z * self.standard_error)


def half_height_crossings(curves: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Peak and half-height crossings of focus curves.

    Parameters
    ----------
    curves : (M, N) ndarray of float
        One curve a row.

    Returns
    -------
    f, z_l, z_r : (m,) ndarray of float64, levels
        For the curves whose first maximum ``p`` is not an end and that fall under half
        height (above their minimum) on both sides: the 3-point Gaussian peak about ``p``
        (:func:`~sffscan.stages.depth_peak.three_point_offset`) and the crossings of half height
        nearest ``p`` on each side, linear between levels.
    """
    y = np.asarray(curves, dtype=np.float64)
    m, n = y.shape
    p = y.argmax(1)
    lo, hi = y.min(1), y.max(1)
    half = lo + 0.5 * (hi - lo)
    idx = np.arange(n)
    below = y < half[:, None]
    left = below & (idx[None, :] < p[:, None])
    right = below & (idx[None, :] > p[:, None])
    il = np.where(left.any(1), n - 1 - np.argmax(left[:, ::-1], 1), -1)
    ir = np.where(right.any(1), np.argmax(right, 1), -1)
    ok = (il >= 0) & (ir >= 0) & (p > 0) & (p < n - 1)
    r = np.arange(m)
    il, ir = np.clip(il, 0, n - 2), np.clip(ir, 1, n - 1)
    a, b = y[r, il], y[r, il + 1]
    zl = il + (half - a) / np.where(b == a, 1.0, b - a)
    a, b = y[r, ir - 1], y[r, ir]
    zr = ir - 1 + (a - half) / np.where(a == b, 1.0, a - b)
    f = p + three_point_offset(np.ascontiguousarray(y.T), p, log=True)
    return f[ok], zl[ok], zr[ok]


def _zero_crossing(f: np.ndarray, zl: np.ndarray, zr: np.ndarray, n: int) -> float:
    vals = np.empty(len(WARP_GRID))
    for i, c in enumerate(WARP_GRID):
        s = c / (n - 1)
        gl, gr, gf = zl / (1 + s * zl), zr / (1 + s * zr), f / (1 + s * f)
        vals[i] = np.median((gl + gr - 2 * gf) / (gr - gl))
    change = np.flatnonzero(np.diff(np.sign(vals)) != 0)
    if change.size == 0:
        return float("nan")
    i = int(change[0])
    step = WARP_GRID[i + 1] - WARP_GRID[i]
    return float(WARP_GRID[i] - vals[i] * step / (vals[i + 1] - vals[i]))


def lens_asymmetry(volume: np.ndarray, *, seed: int = 0) -> LevelWarp:
    """The warp ``c`` that makes a volume's focus curves even (module docstring).

    Parameters
    ----------
    volume : (N, H, W) ndarray of float
        Focus volume, N >= 3 levels.
    seed : int, keyword-only
        Of the resampling for the standard error.

    Returns
    -------
    LevelWarp
        ``c`` NaN where fewer than :data:`MIN_CURVES` curves qualify or the median
        asymmetry does not change sign over :data:`WARP_GRID`.
    """
    n, h, w = volume.shape
    step = max(SAMPLE_STEP, math.ceil(math.sqrt(h * w / MAX_CURVES)))
    curves = volume[:, ::step, ::step].reshape(n, -1).T
    f, zl, zr = half_height_crossings(curves)
    middle = (f > 0.2 * (n - 1)) & (f < 0.8 * (n - 1))  # a curve the range cuts is lopsided
    f, zl, zr = f[middle], zl[middle], zr[middle]
    if f.size < MIN_CURVES:
        return LevelWarp(float("nan"), float("inf"), int(f.size))
    c = _zero_crossing(f, zl, zr, n)
    rng = np.random.default_rng(seed)
    boot = np.empty(BOOTSTRAPS)
    for b in range(BOOTSTRAPS):
        i = rng.integers(0, f.size, f.size)
        boot[b] = _zero_crossing(f[i], zl[i], zr[i], n)
    finite = np.isfinite(boot)
    se = float(np.std(boot[finite])) if finite.sum() > BOOTSTRAPS // 2 else float("inf")
    return LevelWarp(c, se, int(f.size))


def warp_volume(volume: np.ndarray, c: float) -> np.ndarray:
    """The volume resampled onto N levels evenly spaced in ``g`` (module docstring).

    Parameters
    ----------
    volume : (N, H, W) ndarray of float
    c : float
        ``(N - 1) / D``, > -1.

    Returns
    -------
    (N, H, W) ndarray of float32
        Level j: the mean of the curve (linear between levels) over the original levels
        that warped level j stands for, ``k(g_j - dg / 2) .. k(g_j + dg / 2)`` with
        ``g_j = j / (1 + c)`` and ``k(g) = g / (1 - s g)`` (cut at the range's ends; the
        value at ``k(g_j)`` where the cut leaves no width). Where the warped levels are
        coarser than the original ones (the far end for ``c > 0``) this averages the
        levels in between instead of skipping them, as a point sample would (an aliased
        pillbox curve's ringing took SPC off: training seeds 0..2, slopes-lens-pillbox
        1.31x -> 1.25x the best selectable method, pertuz-simu02 0.95x -> 0.72x); where they
        are finer it is the linear interpolation to within the curve's curvature.
    """
    n = volume.shape[0]
    s = c / (n - 1)
    g = np.linspace(0.0, (n - 1) / (1 + c), n)
    dg = g[1] - g[0]
    edges = np.concatenate([[g[0] - dg / 2], (g[:-1] + g[1:]) / 2, [g[-1] + dg / 2]])
    ke = np.clip(edges / (1 - s * edges), 0, n - 1)
    i0 = np.clip(np.floor(ke).astype(np.intp), 0, n - 2)
    t = (ke - i0)[:, None, None]
    width = np.diff(ke)[:, None, None]
    k = np.clip(g / (1 - s * g), 0, n - 1)
    j0 = np.clip(np.floor(k).astype(np.intp), 0, n - 2)
    u = (k - j0)[:, None, None]
    out = np.empty(volume.shape, np.float32)
    # in bands of rows: the float64 work arrays of a whole stack (a camera's 2048 x 1536 x
    # 50) would be several GB
    rows = max(1, WARP_BAND_VALUES // max(1, n * volume.shape[2]))
    for r0 in range(0, volume.shape[1], rows):
        v = volume[:, r0:r0 + rows].astype(np.float64)
        # the curve's integral from level 0: trapezoids up to each level, then the part of
        # the next trapezoid up to the edge (the curve linear between levels)
        cum = np.concatenate([np.zeros((1, *v.shape[1:])),
                              np.cumsum((v[1:] + v[:-1]) / 2, 0)])
        integral = cum[i0] + t * v[i0] + 0.5 * t * t * (v[i0 + 1] - v[i0])
        mean = (integral[1:] - integral[:-1]) / np.where(width > 0, width, 1.0)
        point = (1 - u) * v[j0] + u * v[j0 + 1]
        out[:, r0:r0 + rows] = np.where(width > 1e-9, mean, point)
    return out


def unwarp_levels(depth: np.ndarray, c: float, n_levels: int) -> np.ndarray:
    """A depth on :func:`warp_volume`'s grid (fractional warped levels) as original levels.

    Parameters
    ----------
    depth : ndarray of float
        Fractional levels of the warped volume.
    c : float
        The warp's ``c``.
    n_levels : int
        N.

    Returns
    -------
    ndarray of float32, ``depth``'s shape
        ``k = g / (1 - s g)`` with ``g = depth / (1 + c)``; NaN where ``1 - s g <= 0``
        (beyond the lens' focal point: not a height).
    """
    s = c / (n_levels - 1)
    g = np.asarray(depth, dtype=np.float64) / (1 + c)
    den = 1 - s * g
    with np.errstate(divide="ignore", invalid="ignore"):
        k = np.where(den > 0, g / den, np.nan)
    return k.astype(np.float32)
