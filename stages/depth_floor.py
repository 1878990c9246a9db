"""A focus curve's noise, and its width from a floor that noise does not lower.

A curve's width from its sums (:func:`sffscan.stages.curve_shape.width_from_sums`)
takes the curve's minimum as its floor: the area above the floor and the first harmonic
give a Gaussian's sigma. Under noise the minimum of N levels lies below the floor the curve
sits on by about the largest of N draws of that noise, and the area above it grows by N
times that: the width comes out too large. On the twenty families' even, noisy stacks
(``even-noisy``, seeds 60..65) the widths from the minimum were 2.8-6.3x those from the
ratio of the first two harmonics, which no floor enters (1.00-1.39x on clean ones); on
Gaussian curves of sigma 2.5 levels in 50, 1.6x at noise 0.005 of the peak, 4.3x at 0.08.

SPC's range guard (:func:`sffscan.stages.depth_spc.spc_in_range`) keeps SPC where it lies
a reach of widths from the range's ends: with widths that large it sent 30-50 % of an even,
noisy stack's pixels to the fallback far from any end (levels 13..58 of 72), where SPC erred
1.9 against the fallback's 3.0 levels (docs/depth-method-log.md, 2026-12-05). The guard now
takes its widths from the minimum raised by the expected extreme of the curves' noise
(:func:`guard_width`): no tuned constant, the noise measured on the floors of the curves the
choice judges (:func:`guard_floor`), the extreme of a normal sample
(:func:`expected_extreme`). Where a curve's area above that floor does not exceed its first
harmonic (its noise, or half a peak cut by an end) the width is the typical one of the
judged curves. Other uses of the width (the uncertainty's, the shape statistics) keep the
minimum: their models were calibrated with it.
"""

from __future__ import annotations

import math
from statistics import NormalDist
from typing import NamedTuple

import numpy as np
from sffscan.stages.curve_shape import width_from_sums
from sffscan.stages.depth_harmonics import harmonic_table, magnitude
from sffscan.stages.depth_statistics import judged_curves, row_median

__all__ = ["GuardFloor", "curve_noise", "expected_extreme", "guard_floor", "guard_width",
           "level_noise"]


def curve_noise(cur: np.ndarray) -> np.ndarray:
    """Each curve's noise sigma (rows of ``cur``, (curves, N) float32, N >= 5) from its
    second differences: ``1.4826 MAD / sqrt 6``, robust to the few levels of the peak, whose
    curvature is signal."""
    d2 = cur[:, :-2] - 2.0 * cur[:, 1:-1] + cur[:, 2:]
    d2 -= row_median(d2)[:, None]
    return np.float32(1.4826 / math.sqrt(6.0)) * row_median(np.abs(d2))


def level_noise(levels: np.ndarray, centre: np.ndarray, mask: np.ndarray | None = None
                ) -> float:
    """The noise sigma of the judged curves' floors (the focus measure's units): ``1.4826
    MAD / sqrt 6`` of the second differences, pooled over the curves, at the levels k whose
    neighbours k - 2 and k + 2 average at most the curve's median (its floor: about half of
    its levels or more), where a peak's curvature, which is signal, does not enter (over
    every level a clean Gaussian curve of sigma 2.5 levels in 30 read 2.2x its noise); NaN
    where none is judged or N < 5.

    Parameters
    ----------
    levels : (N, H, W) ndarray of float
        The curves (a stack's sample or a block's).
    centre : (H, W) ndarray of int
        Their filtered argmax: curves whose centre lies within 2 levels of an end are left
        out, as SPC's departure leaves them
        (:func:`~sffscan.stages.depth_statistics.judged_curves`).
    mask : (H, W) ndarray of bool, optional
        The curves judged (all when None).
    """
    cur = _judged(levels, centre, mask)
    return math.nan if cur is None else _floor_noise(cur)


def _judged(levels: np.ndarray, centre: np.ndarray, mask: np.ndarray | None
            ) -> np.ndarray | None:
    """The judged curves, (curves, N) float32; None where none is judged or N < 5."""
    n = levels.shape[0]
    if n < 5:
        return None
    _, ok = judged_curves(centre, n, mask)
    if not ok.any():
        return None
    return np.ascontiguousarray(np.asarray(levels, np.float32)[:, ok].T)


def _floor_noise(cur: np.ndarray) -> float:
    """:func:`level_noise` of the curves ``cur`` (curves, N)."""
    # the floor judged from levels k - 2 and k + 2, which the second difference at k does
    # not read: judged from level k itself it kept the levels whose own noise was low, and
    # read the noise 16-19 % low (measured)
    d2 = cur[:, 1:-3] - 2.0 * cur[:, 2:-2] + cur[:, 3:-1]
    floor = cur[:, :-4] + cur[:, 4:] <= 2.0 * row_median(cur)[:, None]
    d = d2[floor].astype(np.float64)
    if d.size == 0:
        return math.nan
    return 1.4826 / math.sqrt(6.0) * float(np.median(np.abs(d - np.median(d))))


def expected_extreme(n: int) -> float:
    """The expected largest of ``n`` independent standard normal draws, Blom's
    approximation ``Phi^-1((n - 0.375) / (n + 0.25))`` (1.868, 2.243, 2.499 for n = 20, 50,
    100; by numerical integration 1.868, 2.249, 2.508); 0 for n < 2."""
    if n < 2:
        return 0.0
    return NormalDist().inv_cdf((n - 0.375) / (n + 0.25))


class GuardFloor(NamedTuple):
    """What SPC's range guard takes from the curves a stack's or block's choice judges
    (:func:`guard_floor`): one pair for the whole stack or block, whatever its bands."""

    noise: float
    """The floors' noise sigma (:func:`level_noise`), the focus measure's units."""
    width: float
    """The judged curves' median :func:`guard_width` (sigma, levels) where it is defined:
    the width of a curve whose own is not."""


def _lift(n_levels: int, noise: float) -> float:
    return expected_extreme(n_levels // 2) * noise if math.isfinite(noise) and noise > 0 \
        else 0.0


def _raised(h0: np.ndarray, h1_abs: np.ndarray, minimum: np.ndarray, n_levels: int,
            lift: float) -> tuple[np.ndarray, np.ndarray]:
    """The widths from the raised floor, and where they are defined."""
    floor = np.asarray(minimum, np.float64) + lift
    width = width_from_sums(h0, h1_abs, floor, n_levels)
    area = np.asarray(h0, np.float64) - n_levels * floor
    return width, area > np.asarray(h1_abs, np.float64)


def guard_floor(levels: np.ndarray, centre: np.ndarray, mask: np.ndarray | None = None
                ) -> GuardFloor:
    """:class:`GuardFloor` of the judged curves: their floors' :func:`level_noise` and their
    median guard width where defined (the median of the widths from their minima where
    none is; NaN, NaN where no curve is judged).

    Parameters
    ----------
    levels, centre, mask
        As :func:`level_noise`'s.
    """
    cur = _judged(levels, centre, mask)
    if cur is None:
        return GuardFloor(math.nan, math.nan)
    noise = _floor_noise(cur)
    n = cur.shape[1]
    h0, _, re, im = harmonic_table(n) @ cur.T  # float64 sums of the float32 curves
    h1, low = magnitude(re, im), cur.min(axis=1)
    width, defined = _raised(h0, h1, low, n, _lift(n, noise))
    if defined.any():
        return GuardFloor(noise, float(np.median(width[defined])))
    return GuardFloor(noise, float(np.median(width_from_sums(h0, h1, low, n))))


def guard_width(h0: np.ndarray, h1_abs: np.ndarray, minimum: np.ndarray, n_levels: int,
                floor: GuardFloor | None) -> np.ndarray:
    """Each curve's width (sigma, levels) for SPC's range guard: :func:`width_from_sums`
    with the floor at the curve's minimum raised by ``expected_extreme(N // 2)`` times the
    noise of ``floor`` (the minimum lies among the floor's levels, at least half of them by
    :func:`level_noise`'s count: the smaller lift, so the guard errs towards the wider
    width it had); ``floor.width`` where the curve's area above that floor does not exceed
    ``|H_1|`` (a Gaussian's ratio is below 1: noise about a narrow peak, or half a peak cut
    by an end, whose width 0 let SPC in, 34 % of a cut strip's pixels pulled 1-2.6 levels
    inwards, measured). ``floor`` None or its noise NaN: the minimum, as before 2026-12-05.

    Parameters
    ----------
    h0, h1_abs, minimum : (H, W) ndarray of float
        Each curve's H_0, ``|H_1|`` and smallest level.
    n_levels : int
        N.
    floor : GuardFloor or None
        The judged curves' (:func:`guard_floor`).
    """
    lift = 0.0 if floor is None else _lift(n_levels, floor.noise)
    if lift == 0.0:
        return width_from_sums(h0, h1_abs, minimum, n_levels)
    width, defined = _raised(h0, h1_abs, minimum, n_levels, lift)
    assert floor is not None
    width[~defined] = floor.width
    return width
