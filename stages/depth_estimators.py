"""The estimators behind the depth methods' names: what each entry of
:data:`sffscan.stages.depth.ESTIMATORS` computes from a volume's checked curves.

:class:`FocusCurves` is what every estimator reads (the curves as
:func:`sffscan.stages.depth.depth_from_focus` checks them, their sums, argmax and window
sizes), :class:`Estimator` an entry of the registry, :data:`CURVE_ESTIMATORS` every entry
but ``"warped_select"`` (which runs :func:`~sffscan.stages.depth.depth_from_focus` on the
warped volume), and :func:`shape_select_parts` the default's depth with what its height
uncertainty adds. The registry itself and the public API
(:func:`~sffscan.stages.depth.depth_from_focus`,
:func:`~sffscan.stages.depth.shape_select_with_bias`) are the sibling
:mod:`sffscan.stages.depth`'s, where the methods are documented.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass
from functools import partial
from typing import NamedTuple

import numpy as np
from sffscan.stages.curve_shape import width_from_sums
from sffscan.stages.depth_adaptive import adaptive_block, adaptive_peak
from sffscan.stages.depth_candidates import (
    GAUSS_FIT_HALF_WINDOW,
    WINDOW_PC_FACTOR,
    gauss_window_fit,
    window_pc,
)
from sffscan.stages.depth_choice import stack_choice, wide_choice
from sffscan.stages.depth_floor import guard_width
from sffscan.stages.depth_harmonics import depth_from_sums, magnitude
from sffscan.stages.depth_levels import level_spread, median_filter_levels
from sffscan.stages.depth_peak import three_point_offset, windowed_centroid
from sffscan.stages.depth_spc import spc_in_range, spc_share
from sffscan.stages.depth_statistics import (
    pull_statistics,
    sample_step,
    stack_sample,
    takes_centroid,
)
from sffscan.stages.depth_window import window_choice

__all__ = ["CURVE_ESTIMATORS", "Estimator", "FocusCurves", "shape_select_parts"]


# ----------------------------------------------------------------------------- the curves


@dataclass(frozen=True)
class FocusCurves:
    """What an estimator of :data:`~sffscan.stages.depth.ESTIMATORS` reads: the checked
    curves and their sums."""

    volume: np.ndarray
    """(N, H, W) float32, finite."""
    moments: np.ndarray
    """(4, H, W) float64: H_0, sum k y, Re H_1, Im H_1
    (:func:`~sffscan.stages.depth_harmonics.curve_moments`)."""
    argmax: np.ndarray | None
    """(H, W) intp, each curve's first maximum; None for a method that does not use it."""
    median_size: int
    spread_size: int

    def centre(self) -> np.ndarray:
        """The argmax median filtered over ``median_size`` x ``median_size`` px (``a_med``)."""
        assert self.argmax is not None
        return median_filter_levels(self.argmax, self.median_size, self.volume.shape[0])


class Estimator(NamedTuple):
    """A depth method: its depth from the curves (float32 fractional levels, (H, W))."""

    depth: Callable[[FocusCurves], np.ndarray]
    uses_argmax: bool = True
    """Reads each curve's argmax (given to :func:`~sffscan.stages.depth.depth_from_focus` or
    computed there)."""
    candidate: bool = False
    """A candidate of the study (:mod:`sffscan.stages.depth_study`): selectable by
    :func:`~sffscan.stages.depth.depth_from_focus`, not by scan, replay or stack."""


# ----------------------------------------------------------------------------- the estimators


def _from_sums(c: FocusCurves, *, method: str) -> np.ndarray:
    h0, hk, re, im = c.moments
    return depth_from_sums(h0, hk, re, im, c.argmax, n_levels=c.volume.shape[0],
                           method=method, median_size=c.median_size)


def _three_point(c: FocusCurves, *, log: bool) -> np.ndarray:
    assert c.argmax is not None
    depth = c.argmax + three_point_offset(c.volume, c.argmax, log=log)
    return depth.astype(np.float32, copy=False)


def _wcentroid(c: FocusCurves) -> np.ndarray:
    return windowed_centroid(c.volume, c.centre())


def _adaptive(c: FocusCurves) -> np.ndarray:
    centre = c.centre()
    return adaptive_peak(c.volume, centre,
                         level_spread(centre, c.spread_size, c.volume.shape[0]))


def _adaptive_centroid(c: FocusCurves, stats: tuple[float, float] | None = None, *,
                       wide_test: bool = True,
                       window_out: np.ndarray | None = None) -> np.ndarray:
    # window_out (with wide_test): the 9-level centroid, from the same gather of the levels
    assert c.argmax is not None
    centre = c.centre()
    pull, noise = pull_statistics(*stack_sample(c.volume, c.argmax)[:2]) if stats is None \
        else stats
    peak = "centroid" if takes_centroid(pull, noise=noise) else "gauss3"
    spread = level_spread(centre, c.spread_size, c.volume.shape[0])
    if not wide_test:
        return adaptive_peak(c.volume, centre, spread, peak=peak)
    # the wide centroid judged on the grid the stack's other statistics take (stack_sample)
    wide_peak = np.empty(spread.shape, np.float32)
    depth = adaptive_block(c.volume, centre, spread, peak=peak, wide_peak_out=wide_peak,
                           window_out=window_out)[0]
    s = sample_step(depth.shape)
    wide_choice(depth, wide_peak, step=(s, s))
    return depth


def _gauss_window_fit(c: FocusCurves) -> np.ndarray:
    return gauss_window_fit(c.volume, c.centre(), _adaptive(c),
                            half_window=GAUSS_FIT_HALF_WINDOW)


def _window_pc(c: FocusCurves) -> np.ndarray:
    return window_pc(c.volume, c.centre(), factor=WINDOW_PC_FACTOR)


def _shape_select(c: FocusCurves) -> np.ndarray:
    return shape_select_parts(c)[0]


def shape_select_parts(c: FocusCurves) -> tuple[np.ndarray, float, float]:
    """``"shape_select"``'s depth, the bias its height uncertainty adds and the locking it
    adds where the scatter cannot show it (levels)."""
    assert c.argmax is not None
    # curve_width's formula from the sums the estimators share: no float64 copy of the
    # volume (4x less time on a 50-level stack; equal to float64 round-off)
    h0, _, re, im = c.moments
    h1, low, n = magnitude(re, im), c.volume.min(axis=0), c.volume.shape[0]
    width = width_from_sums(h0, h1, low, n)
    # judged on a sample of a large stack's curves, as a scan's block is (stack_sample)
    # SPC's mean-square tests inside the focus window's reach (stack_choice's margin)
    choice = stack_choice(c.volume, c.argmax, width, median_size=c.median_size,
                          margin=c.spread_size // 2)
    # a stack that takes SPC keeps the fallback's wide centroid untested, as a scan's SPC
    # block does (the fallback is then read only beyond SPC's range)
    wide = None if choice.spc else np.empty(c.volume.shape[1:], np.float32)
    other = _adaptive_centroid(c, (choice.pull, choice.noise), wide_test=not choice.spc,
                               window_out=wide)
    if wide is not None:
        # the 9-level centroid (adaptive_block's gather, as a scan block's) where its
        # scatter and departure say it errs less
        hidden = window_choice(other, wide, margin=c.spread_size // 2)
        # SPC's map only where the stack takes it
        return (other, choice.bias if hidden is None else math.hypot(choice.bias, hidden),
                choice.locking)
    spc = _from_sums(c, method="spc")
    # the range guard's width from a floor the noise does not lower (depth_floor)
    in_range = spc_in_range(spc, guard_width(h0, h1, low, n, choice.floor), n)
    # SPC and the fallback averaged by the test's estimates of their errors (spc_weight)
    return (np.where(in_range, spc_share(spc, other, choice.weight), other).astype(
        np.float32, copy=False), choice.bias, choice.locking)


CURVE_ESTIMATORS: dict[str, Estimator] = {
    "argmax": Estimator(partial(_from_sums, method="argmax")),
    "gauss3": Estimator(partial(_three_point, log=True)),
    "quadratic3": Estimator(partial(_three_point, log=False)),
    "centroid": Estimator(partial(_from_sums, method="centroid")),
    "pc": Estimator(partial(_from_sums, method="pc"), uses_argmax=False),
    "spc": Estimator(partial(_from_sums, method="spc")),
    "wcentroid": Estimator(_wcentroid),
    "adaptive": Estimator(_adaptive),
    "adaptive_centroid": Estimator(_adaptive_centroid),
    "shape_select": Estimator(_shape_select),
    "gauss_window_fit": Estimator(_gauss_window_fit, candidate=True),
    "window_pc": Estimator(_window_pc, candidate=True),
}
"""The registry's entries that read the curves alone, in its order
(:data:`sffscan.stages.depth.ESTIMATORS` adds ``"warped_select"``)."""
