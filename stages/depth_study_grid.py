"""The held-out protocol's tunable candidates: the settings each is tuned over, and each
one's squared errors on one focus volume at every setting.

:mod:`sffscan.stages.depth_study` runs the protocol (leave one family out) over these;
nothing here chooses a setting. Each candidate is a rule over the fixed methods of
:mod:`sffscan.stages.depth` (and :mod:`sffscan.stages.depth_candidates`' estimators) with
one setting a protocol may tune on training data only.
"""

from __future__ import annotations

import math

import numpy as np
from sffscan.stages.depth import (
    ADAPTIVE_MAX_SPREAD,
    adaptive_peak,
    level_spread,
    median_filter_levels,
)
from sffscan.stages.depth_candidates import gauss_window_fit, plane_residual, window_pc
from sffscan.stages.depth_choice import shape_select
from sffscan.stages.depth_floor import guard_floor, guard_width
from sffscan.stages.depth_harmonics import curve_moments, magnitude
from sffscan.stages.depth_spc import (
    SHAPE_SELECT_LIMITS,
    spc_departures,
    spc_in_range,
    spc_noise,
    spc_weight,
    takes_spc,
)
from sffscan.stages.depth_statistics import pull_statistics, shape_statistics, takes_centroid
from sffscan.stages.depth_uncertainty import depth_scatter

__all__ = ["CANDIDATES", "SHAPE_GRID", "THRESHOLDS", "Setting", "candidate_errors",
           "format_setting", "scatter_select", "score_key", "width_switch"]

THRESHOLDS = (2.0, 3.0, 4.0, 5.0, 6.0, 8.0, 12.0, math.inf)
"""``width-switch`` thresholds (levels) the protocol tunes over (inf: never SPC)."""

SCATTER_WINDOWS = (5.0, 9.0, 15.0, 21.0)
"""``scatter-select`` windows (px) the protocol tunes over."""

SHAPE_GRID = tuple((s, r) for s in (0.03, 0.05, 0.08, 0.12, 0.2)
                   for r in (1.5, 2.0, 3.0, 4.0, 6.0, 9.0, math.inf))
"""``shape-select`` settings the protocol tunes over: (largest |median skewness|, largest
median width ratio) for which a stack takes SPC (:func:`sffscan.stages.depth_choice.
shape_select`)."""

GAUSS_FIT_HALF_WINDOWS = (3.0, 5.0, 7.0)
"""``gauss-fit`` half windows (levels) the protocol tunes over."""

WINDOW_PC_FACTORS = (3.0, 4.0, 5.0)
"""``window-pc`` factors on the curve's width the protocol tunes over."""

PULL_LIMITS = (0.03, 0.05, 0.1, 0.2, math.inf)
"""``centroid-pull`` limits (levels) the protocol tunes over: the largest
:func:`sffscan.stages.depth_statistics.centroid_pull` for which a stack takes the 5-level
centroid at ``adaptive``'s peak pixels (inf: always), or the pull's noise where that is
larger (:func:`sffscan.stages.depth_statistics.takes_centroid`)."""

SPC_PULLS = (0.03, 0.05, 0.1, 0.2, math.inf)
"""``spc-pull`` settings the protocol tunes over: the largest centroid pull (levels) of a
stack ``shape_select`` (at its shipped limits and reach) gives to SPC (inf: no limit).
Smallest first: where settings tie on the training seeds the tuning takes the first, the
strictest the tie allows."""

PLANE_LIMITS = (0.0, 0.5, 0.75, 1.0)
"""``planar-peak`` settings the protocol tunes over: for a stack that does not take SPC
(``shape_select``'s rule), at the pixels whose filtered peaks span more than 2 levels over
the focus window (``adaptive``'s centroid pixels) but lie within this RMS (levels) of a
plane over it (:func:`sffscan.stages.depth_candidates.plane_residual`: a slope, not an
edge), the 3-point Gaussian at the filtered peak instead of the 11-level centroid; 0:
never (first: ties go to it)."""

SPC_REACHES = (3.0, 2.0, 1.5, 1.0, 0.0)
"""``spc-reach`` settings the protocol tunes over: how many of its widths SPC's depth must lie
from the range's ends for ``shape_select`` (at its shipped limits) to keep SPC at a pixel
(:func:`sffscan.stages.depth_spc.spc_in_range`; 0: everywhere). Largest first:
where settings tie on the training seeds (a stack that takes SPC with no pixel near an end
cannot tell them apart) the tuning takes the first, the widest guard the tie allows, since
a curve cut by the range's end biases SPC whatever the data say about the others."""

SPC_NOISE_RATIOS = (math.inf, 2.83, 2.0, 1.68, 1.41, 1.19, 1.0, 0.84, 0.71)
"""``spc-noise`` settings the protocol tunes over (quarter octaves): the largest ratio of
SPC's predicted noise to the centroid pull's noise
(:func:`sffscan.stages.depth_spc.spc_noise`) of a stack ``shape_select`` (at its
shipped limits, reach and pull limit) gives to SPC (inf: no limit). Largest first: where
settings tie on the training seeds the tuning takes the first, the loosest the tie allows,
so the limit changes only what training stacks show."""

WIDE_GRID = tuple((t, ms, h) for t in (0.03, 0.05, 0.1) for ms in (2.0, 4.0)
                  for h in (5.0, 8.0, 12.0, 15.0))
"""``wide-centroid`` settings the protocol tunes over: (largest centroid pull, levels; largest
span of the filtered peaks for the peak estimator, levels; the centroid's half window h)
with which a stack whose curves pull a centroid less than the limit takes ``adaptive``'s
rule with the 5-level centroid at its peak pixels, the span limit and a centroid of
2h + 1 levels elsewhere; the other stacks ``adaptive`` (span 2, h = 5, 3-point Gaussian)."""

NOISE_WCENTROID = (math.inf, 0.5, 0.3, 0.2, 0.15, 0.1, 0.05)
"""``noise-wcentroid`` settings the protocol tunes over: the pull's noise
(:func:`sffscan.stages.depth_statistics.pull_statistics`, levels) above which a stack that does
not take SPC (``shape_select`` at its shipped limits) takes ``wcentroid`` (the whole curve's
weighted centroid) instead of ``shape_select``'s depth (inf: never; first: ties go to it).
Prompted by the crossed family slopes-lens-noisy, where ``wcentroid`` is best."""

LOPSIDED_WCENTROID = tuple((t, p) for t in (math.inf, 0.3, 0.2, 0.15, 0.1)
                           for p in (0.0, 0.05, 0.1, 0.2))
"""``lopsided-wcentroid`` settings the protocol tunes over: ``noise-wcentroid``'s rule, and
only for a stack whose curves pull a centroid toward their longer tail by more than the
second value (:func:`sffscan.stages.depth_statistics.pull_statistics`' pull, levels: about 0 on
even curves, positive on a thin lens' lopsided ones); (inf, 0) first: never."""

Setting = float | tuple[float, ...]

CANDIDATES: dict[str, tuple[Setting, ...]] = {"width-switch": THRESHOLDS,
                                              "scatter-select": SCATTER_WINDOWS,
                                              "gauss-fit": GAUSS_FIT_HALF_WINDOWS,
                                              "window-pc": WINDOW_PC_FACTORS,
                                              "shape-select": SHAPE_GRID,
                                              "spc-reach": SPC_REACHES,
                                              "spc-pull": SPC_PULLS,
                                              "spc-noise": SPC_NOISE_RATIOS,
                                              "planar-peak": PLANE_LIMITS,
                                              "centroid-pull": PULL_LIMITS,
                                              "wide-centroid": WIDE_GRID,
                                              "noise-wcentroid": NOISE_WCENTROID,
                                              "lopsided-wcentroid": LOPSIDED_WCENTROID}
"""The tunable candidates and the settings each is tuned over (on training data only)."""


def format_setting(value: Setting) -> str:
    """A candidate's setting as the table and the score keys write it (``0.08/6`` for a
    pair)."""
    if isinstance(value, tuple):
        return "/".join(f"{v:g}" for v in value)
    return f"{value:g}"


def score_key(candidate: str, value: Setting) -> str:
    """The key of a candidate at a setting in a stack's scores (``width-switch@3``)."""
    return f"{candidate}@{format_setting(value)}"


def width_switch(spc: np.ndarray, adaptive: np.ndarray, width: np.ndarray, *,
                 threshold: float) -> np.ndarray:
    """SPC where the curve is wider than ``threshold`` levels (the centroid window and the
    peak fit see only part of it), else ``adaptive``; float32 levels."""
    return np.where(width > threshold, spc, adaptive).astype(np.float32)


def scatter_select(spc: np.ndarray, adaptive: np.ndarray, *, window: int) -> np.ndarray:
    """Per pixel the estimate whose measured scatter (RMS about its 5 x 5 median over
    ``window`` x ``window`` px, :func:`depth_scatter`) is the smaller: SPC where its map is
    locally smoother than ``adaptive``'s, else ``adaptive``; float32 levels."""
    smoother = depth_scatter(spc, window=window) < depth_scatter(adaptive, window=window)
    return np.where(smoother, spc, adaptive).astype(np.float32)


def candidate_errors(volume: np.ndarray, truth_levels: np.ndarray, mask: np.ndarray, *,
                     depth: dict[str, np.ndarray], argmax: np.ndarray, width: np.ndarray,
                     median_size: int = 11, spread_size: int = 9) -> dict[str, float]:
    """Sum of squared errors (levels^2) over ``mask`` of every candidate at every setting.

    Parameters
    ----------
    volume : (N, H, W) ndarray of float
        Focus volume.
    truth_levels : (H, W) ndarray of float
        True depth, focus levels.
    mask : (H, W) ndarray of bool
        Scored pixels.
    depth : dict of str to (H, W) ndarray, keyword-only
        The fixed methods' depths (levels) the candidates choose between: ``spc``,
        ``adaptive``, ``adaptive_centroid``, ``shape_select`` and ``wcentroid``.
    argmax : (H, W) ndarray of int, keyword-only
        Each curve's first argmax.
    width : (H, W) ndarray of float, keyword-only
        Each curve's width (levels, :func:`sffscan.stages.curve_shape.curve_width`).
    median_size, spread_size : int, keyword-only
        The argmax median's and the peaks' spread window (px), as the fixed methods took.

    Returns
    -------
    dict of str to float
        Keyed by :func:`score_key`.
    """
    sse: dict[str, float] = {}
    for t in THRESHOLDS:
        d = width_switch(depth["spc"], depth["adaptive"], width, threshold=t)
        sse[score_key("width-switch", t)] = float(np.sum((d - truth_levels)[mask] ** 2))
    for k in SCATTER_WINDOWS:
        d = scatter_select(depth["spc"], depth["adaptive"], window=int(k))
        sse[score_key("scatter-select", k)] = float(np.sum((d - truth_levels)[mask] ** 2))
    centre = median_filter_levels(argmax, median_size, volume.shape[0])
    for h in GAUSS_FIT_HALF_WINDOWS:
        d = gauss_window_fit(volume, centre, depth["adaptive"], half_window=int(h))
        sse[score_key("gauss-fit", h)] = float(np.sum((d - truth_levels)[mask] ** 2))
    for g in WINDOW_PC_FACTORS:
        d = window_pc(volume, centre, factor=g)
        sse[score_key("window-pc", g)] = float(np.sum((d - truth_levels)[mask] ** 2))
    stats = shape_statistics(volume, argmax, width, mask)
    n = volume.shape[0]
    # SPC's range guard as the default takes it: widths from a floor the noise does not
    # lower, the noise of the curves judged (depth_floor)
    floor = guard_floor(volume, centre)
    h0, _, re, im = curve_moments(volume)
    guard = guard_width(h0, magnitude(re, im), volume.min(axis=0), n, floor)
    in_range = spc_in_range(depth["spc"], guard, n)
    pull, noise = pull_statistics(volume, argmax)  # all the curves, as depth_from_focus judges
    spread = level_spread(centre, spread_size, n)
    # every candidate below is the shipped rule with one setting varied: the pull, SPC's
    # noise and its departure tested as the default tests them (docs/depth-method-log.md,
    # 2026-12-04: before, shape-select, spc-reach and spc-pull left the last two out)
    noises = (spc_noise(volume), noise)
    deps = spc_departures(volume, centre, centroid=takes_centroid(pull, noise=noise),
                          floor=floor)
    departure = (deps.departure, deps.spread)
    # SPC's share where it is taken, as the default's (spc_weight: the robust spread)
    share = spc_weight((deps.departure, deps.robust), noises[0])
    for pair in SHAPE_GRID:
        d = shape_select(depth["spc"], depth["adaptive_centroid"], stats, max_skew=pair[0],
                         max_ratio=pair[1], in_range=in_range, pull=pull, noise=noises,
                         departure=departure, weight=share)
        sse[score_key("shape-select", pair)] = float(np.sum((d - truth_levels)[mask] ** 2))
    max_skew, max_ratio = SHAPE_SELECT_LIMITS
    spc, other = depth["spc"], depth["adaptive_centroid"]
    for k in SPC_REACHES:
        d = shape_select(spc, other, stats, max_skew=max_skew, max_ratio=max_ratio,
                         in_range=spc_in_range(spc, guard, n, reach=k), pull=pull,
                         noise=noises, departure=departure, weight=share)
        sse[score_key("spc-reach", k)] = float(np.sum((d - truth_levels)[mask] ** 2))
    for t in SPC_PULLS:
        d = shape_select(spc, other, stats, max_skew=max_skew, max_ratio=max_ratio,
                         in_range=in_range, pull=pull, max_pull=t, noise=noises,
                         departure=departure, weight=share)
        sse[score_key("spc-pull", t)] = float(np.sum((d - truth_levels)[mask] ** 2))
    for t in SPC_NOISE_RATIOS:
        d = shape_select(spc, other, stats, max_skew=max_skew, max_ratio=max_ratio,
                         in_range=in_range, pull=pull, noise=noises, max_noise_ratio=t,
                         departure=departure, weight=share)
        sse[score_key("spc-noise", t)] = float(np.sum((d - truth_levels)[mask] ** 2))
    took_spc = takes_spc(stats, max_skew=max_skew, max_ratio=max_ratio, pull=pull,
                         noise=noises, departure=departure)
    for t in NOISE_WCENTROID:
        d = depth["wcentroid"] if not took_spc and noise > t else depth["shape_select"]
        sse[score_key("noise-wcentroid", t)] = float(np.sum((d - truth_levels)[mask] ** 2))
    for t, p in LOPSIDED_WCENTROID:
        d = (depth["wcentroid"] if not took_spc and noise > t and pull > p
             else depth["shape_select"])
        sse[score_key("lopsided-wcentroid", (t, p))] = float(np.sum((d - truth_levels)[mask] ** 2))
    if took_spc:
        planar: dict[float, np.ndarray] = dict.fromkeys(PLANE_LIMITS, depth["shape_select"])
    else:
        blend = spread > ADAPTIVE_MAX_SPREAD  # adaptive's centroid pixels
        residual = plane_residual(centre, window=spread_size)
        at_peak = adaptive_peak(volume, centre, np.zeros_like(centre))  # gauss3 at the peak
        planar = {t: np.where(blend & (residual < t), at_peak, depth["adaptive_centroid"])
                  for t in PLANE_LIMITS}
    for t, d in planar.items():
        sse[score_key("planar-peak", t)] = float(np.sum((d - truth_levels)[mask] ** 2))
    peak_centroid = adaptive_peak(volume, centre, spread, peak="centroid")
    for t in PULL_LIMITS:
        d = peak_centroid if takes_centroid(pull, noise=noise, limit=t) else depth["adaptive"]
        sse[score_key("centroid-pull", t)] = float(np.sum((d - truth_levels)[mask] ** 2))
    wide: dict[tuple[float, float], np.ndarray] = {}
    for t, ms, h in WIDE_GRID:
        centroid = takes_centroid(pull, noise=noise, limit=t)
        if centroid and (ms, h) not in wide:
            wide[ms, h] = adaptive_peak(volume, centre, spread, max_spread=int(ms),
                                        half_window=int(h), peak="centroid")
        d = wide[ms, h] if centroid else depth["adaptive"]
        sse[score_key("wide-centroid", (t, ms, h))] = float(np.sum((d - truth_levels)[mask] ** 2))
    return sse
