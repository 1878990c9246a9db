"""Choosing a depth method by a protocol that cannot overfit: leave one family out.

The families of :mod:`sffscan.stages.sim.families` are rendered with two disjoint sets of
seeds, *training* and *held-out*. For each family F in turn:

1. the tunable candidates (:func:`width_switch`: its threshold on the curve's width;
   :func:`scatter_select`: its window; :func:`sffscan.stages.depth_candidates.
   gauss_window_fit`: its half window; :func:`sffscan.stages.depth_candidates.window_pc`:
   its window's factor on the curve's width) are tuned on the training seeds of every family
   except F: the setting that minimises the sum over those families of
   ``log(RMSE / best fixed method's RMSE)``;
2. every fixed method and the tuned candidates are scored on F's held-out seeds only.

A third-party stack (pertuz-simu02) is scored with the candidate tuned on the training
seeds of all the families. Errors are in focus levels (RMSE over the scored pixels of all
the held-out seeds of a family pooled), so families with different N compare.

Everything here is pure computation; ``sffscan study --families`` prints and writes it.
"""

from __future__ import annotations

import math
from collections.abc import Iterable, Sequence
from dataclasses import dataclass

import numpy as np
from sffscan.stages.depth import (
    ADAPTIVE_MAX_SPREAD,
    DEFAULT_METHOD,
    DEPTH_METHODS,
    adaptive_peak,
    depth_from_focus,
    first_argmax,
    focus_sums,
    level_spread,
    median_filter_levels,
)
from sffscan.stages.depth_candidates import gauss_window_fit, plane_residual, window_pc
from sffscan.stages.depth_choice import (
    SHAPE_SELECT_LIMITS,
    pull_statistics,
    shape_select,
    shape_statistics,
    spc_departure,
    spc_in_range,
    spc_noise,
    takes_centroid,
    takes_spc,
)
from sffscan.stages.depth_uncertainty import (
    curve_width,
    depth_range,
    depth_scatter,
    floor_share,
    width_excess,
)
from sffscan.stages.focus_measure import focus_measure
from sffscan.stages.sim.families import FAMILIES, SimStack, family_stack
from sffscan.stages.uncertainty_fit import fit_uncertainty, uncertainty_coverage

__all__ = ["CANDIDATES", "SHAPE_GRID", "THRESHOLDS", "HeldOutTable", "curve_width",
           "format_coverage", "format_setting", "format_table", "leave_one_family_out",
           "scatter_select", "score_volume", "uncertainty_sample", "width_switch"]

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
:func:`sffscan.stages.depth_choice.centroid_pull` for which a stack takes the 5-level
centroid at ``adaptive``'s peak pixels (inf: always), or the pull's noise where that is
larger (:func:`sffscan.stages.depth_choice.takes_centroid`)."""

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
(:func:`sffscan.stages.depth_choice.spc_in_range`; 0: everywhere). Largest first:
where settings tie on the training seeds (a stack that takes SPC with no pixel near an end
cannot tell them apart) the tuning takes the first, the widest guard the tie allows, since
a curve cut by the range's end biases SPC whatever the data say about the others."""

SPC_NOISE_RATIOS = (math.inf, 2.83, 2.0, 1.68, 1.41, 1.19, 1.0, 0.84, 0.71)
"""``spc-noise`` settings the protocol tunes over (quarter octaves): the largest ratio of
SPC's predicted noise to the centroid pull's noise
(:func:`sffscan.stages.depth_choice.spc_noise`) of a stack ``shape_select`` (at its
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
(:func:`sffscan.stages.depth_choice.pull_statistics`, levels) above which a stack that does
not take SPC (``shape_select`` at its shipped limits) takes ``wcentroid`` (the whole curve's
weighted centroid) instead of ``shape_select``'s depth (inf: never; first: ties go to it).
Prompted by the crossed family slopes-lens-noisy, where ``wcentroid`` is best."""

LOPSIDED_WCENTROID = tuple((t, p) for t in (math.inf, 0.3, 0.2, 0.15, 0.1)
                           for p in (0.0, 0.05, 0.1, 0.2))
"""``lopsided-wcentroid`` settings the protocol tunes over: ``noise-wcentroid``'s rule, and
only for a stack whose curves pull a centroid toward their longer tail by more than the
second value (:func:`sffscan.stages.depth_choice.pull_statistics`' pull, levels: about 0 on
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


def _key(candidate: str, value: Setting) -> str:
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


@dataclass
class _Scores:
    """Sum of squared errors (levels^2) and pixel count per method, one stack; the default
    method's errors, depth scatter and the curves' excess widths of the scored pixels
    (levels, :mod:`sffscan.stages.depth_uncertainty`)."""

    sse: dict[str, float]
    count: int
    error: np.ndarray
    scatter: np.ndarray
    excess: np.ndarray


def score_volume(volume: np.ndarray, truth_levels: np.ndarray, mask: np.ndarray, *,
                 methods: Sequence[str] = DEPTH_METHODS, median_size: int = 11,
                 spread_size: int = 9) -> _Scores:
    """Squared errors of every method and of the candidate at every threshold."""
    sse: dict[str, float] = {}
    depth: dict[str, np.ndarray] = {}
    a = first_argmax(np.ascontiguousarray(volume, np.float32))
    for m in dict.fromkeys((*methods, "spc", "adaptive", "adaptive_centroid", "shape_select",
                            "wcentroid", DEFAULT_METHOD)):
        depth[m] = depth_from_focus(volume, method=m, median_size=median_size,
                                    spread_size=spread_size, argmax=a)[0]
        if m in methods:
            sse[m] = float(np.sum((depth[m] - truth_levels)[mask] ** 2))
    width = curve_width(volume)
    for t in THRESHOLDS:
        d = width_switch(depth["spc"], depth["adaptive"], width, threshold=t)
        sse[_key("width-switch", t)] = float(np.sum((d - truth_levels)[mask] ** 2))
    for k in SCATTER_WINDOWS:
        d = scatter_select(depth["spc"], depth["adaptive"], window=int(k))
        sse[_key("scatter-select", k)] = float(np.sum((d - truth_levels)[mask] ** 2))
    centre = median_filter_levels(a, median_size, volume.shape[0])
    for h in GAUSS_FIT_HALF_WINDOWS:
        d = gauss_window_fit(volume, centre, depth["adaptive"], half_window=int(h))
        sse[_key("gauss-fit", h)] = float(np.sum((d - truth_levels)[mask] ** 2))
    for g in WINDOW_PC_FACTORS:
        d = window_pc(volume, centre, factor=g)
        sse[_key("window-pc", g)] = float(np.sum((d - truth_levels)[mask] ** 2))
    stats = shape_statistics(volume, a, width, mask)
    n = volume.shape[0]
    in_range = spc_in_range(depth["spc"], width, n)
    pull, noise = pull_statistics(volume, a)  # all the curves, as depth_from_focus judges
    spread = level_spread(centre, spread_size, n)
    for pair in SHAPE_GRID:
        d = shape_select(depth["spc"], depth["adaptive_centroid"], stats, max_skew=pair[0],
                         max_ratio=pair[1], in_range=in_range, pull=pull)
        sse[_key("shape-select", pair)] = float(np.sum((d - truth_levels)[mask] ** 2))
    max_skew, max_ratio = SHAPE_SELECT_LIMITS
    spc, other = depth["spc"], depth["adaptive_centroid"]
    for k in SPC_REACHES:
        d = shape_select(spc, other, stats, max_skew=max_skew, max_ratio=max_ratio,
                         in_range=spc_in_range(spc, width, n, reach=k), pull=pull)
        sse[_key("spc-reach", k)] = float(np.sum((d - truth_levels)[mask] ** 2))
    for t in SPC_PULLS:
        d = shape_select(spc, other, stats, max_skew=max_skew, max_ratio=max_ratio,
                         in_range=in_range, pull=pull, max_pull=t)
        sse[_key("spc-pull", t)] = float(np.sum((d - truth_levels)[mask] ** 2))
    noises = (spc_noise(volume), noise)
    departure = spc_departure(volume, a)
    for t in SPC_NOISE_RATIOS:
        d = shape_select(spc, other, stats, max_skew=max_skew, max_ratio=max_ratio,
                         in_range=in_range, pull=pull, noise=noises, max_noise_ratio=t,
                         departure=departure)
        sse[_key("spc-noise", t)] = float(np.sum((d - truth_levels)[mask] ** 2))
    took_spc = takes_spc(stats, max_skew=max_skew, max_ratio=max_ratio, pull=pull,
                         noise=noises, departure=departure)
    for t in NOISE_WCENTROID:
        d = depth["wcentroid"] if not took_spc and noise > t else depth["shape_select"]
        sse[_key("noise-wcentroid", t)] = float(np.sum((d - truth_levels)[mask] ** 2))
    for t, p in LOPSIDED_WCENTROID:
        d = (depth["wcentroid"] if not took_spc and noise > t and pull > p
             else depth["shape_select"])
        sse[_key("lopsided-wcentroid", (t, p))] = float(np.sum((d - truth_levels)[mask] ** 2))
    if took_spc:
        planar: dict[float, np.ndarray] = dict.fromkeys(PLANE_LIMITS, depth["shape_select"])
    else:
        blend = spread > ADAPTIVE_MAX_SPREAD  # adaptive's centroid pixels
        residual = plane_residual(centre, window=spread_size)
        at_peak = adaptive_peak(volume, centre, np.zeros_like(centre))  # gauss3 at the peak
        planar = {t: np.where(blend & (residual < t), at_peak, depth["adaptive_centroid"])
                  for t in PLANE_LIMITS}
    for t, d in planar.items():
        sse[_key("planar-peak", t)] = float(np.sum((d - truth_levels)[mask] ** 2))
    peak_centroid = adaptive_peak(volume, centre, spread, peak="centroid")
    for t in PULL_LIMITS:
        d = peak_centroid if takes_centroid(pull, noise=noise, limit=t) else depth["adaptive"]
        sse[_key("centroid-pull", t)] = float(np.sum((d - truth_levels)[mask] ** 2))
    wide: dict[tuple[float, float], np.ndarray] = {}
    for t, ms, h in WIDE_GRID:
        centroid = takes_centroid(pull, noise=noise, limit=t)
        if centroid and (ms, h) not in wide:
            wide[ms, h] = adaptive_peak(volume, centre, spread, max_spread=int(ms),
                                        half_window=int(h), peak="centroid")
        d = wide[ms, h] if centroid else depth["adaptive"]
        sse[_key("wide-centroid", (t, ms, h))] = float(np.sum((d - truth_levels)[mask] ** 2))
    return _uncertainty_terms(volume, depth[DEFAULT_METHOD], width, truth_levels, mask, sse=sse,
                              window=spread_size)


def _uncertainty_terms(volume: np.ndarray, depth: np.ndarray, width: np.ndarray,
                       truth_levels: np.ndarray, mask: np.ndarray, *,
                       sse: dict[str, float], window: int) -> _Scores:
    scatter = depth_scatter(depth, window=window)
    sums = focus_sums(np.ascontiguousarray(volume, np.float32))
    share = floor_share(sums[0], np.min(volume, axis=0), volume.shape[0])
    excess = width_excess(width, share, depth_range(depth, window=window), window=window)
    return _Scores(sse, int(mask.sum()), (depth - truth_levels)[mask], scatter[mask],
                   excess[mask])


def uncertainty_sample(volume: np.ndarray, truth_levels: np.ndarray, mask: np.ndarray, *,
                       median_size: int = 11, spread_size: int = 9) -> _Scores:
    """The default method's errors and the uncertainty's terms on the ``mask`` pixels of
    one focus volume (levels), for :mod:`sffscan.stages.uncertainty_fit`
    without scoring every method."""
    d = depth_from_focus(volume, method=DEFAULT_METHOD, median_size=median_size,
                         spread_size=spread_size)[0]
    return _uncertainty_terms(volume, d, curve_width(volume), truth_levels, mask, sse={},
                              window=spread_size)


@dataclass(frozen=True)
class HeldOutTable:
    """The protocol's result.

    ``rmse[family][method]``: held-out RMSE (levels) of each fixed method and of each
    candidate of :data:`CANDIDATES` tuned without that family; ``tuned[family]`` the
    settings chosen for it (``tuned["all"]``: on every family, for the third-party sets);
    ``third_party[name][method]`` the same for third-party stacks; ``chosen`` the method
    whose worst ratio to the best fixed method over the held-out families and third-party
    stacks is the smallest, ``worst_ratio`` that ratio per method; ``coverage[family]``:
    share of the held-out pixels whose default-method error is within 2 sigma of the
    uncertainty fitted without the family (``uncertainty_fit[family]``: the constants
    (a, c); ``"all"``: fitted on the training seeds of every family, used for the
    third-party sets, whose coverage is keyed by name).
    """

    rmse: dict[str, dict[str, float]]
    tuned: dict[str, dict[str, Setting]]
    third_party: dict[str, dict[str, float]]
    chosen: str
    worst_ratio: dict[str, float]
    methods: tuple[str, ...]
    coverage: dict[str, float]
    uncertainty_fit: dict[str, tuple[float, float]]


def _stack_scores(stack: SimStack, *, operator: str, window: int,
                  methods: Sequence[str]) -> _Scores:
    vol = focus_measure(stack.images, operator=operator, window=window)
    m = window // 2
    mask = np.zeros(stack.truth_um.shape, bool)
    mask[m:-m, m:-m] = True
    truth = (stack.truth_um - stack.focus_um[0]) / (stack.focus_um[1] - stack.focus_um[0])
    return score_volume(vol, truth, mask, methods=methods, spread_size=window)


def _rmse(scores: Iterable[_Scores], key: str) -> float:
    s = list(scores)
    return math.sqrt(sum(x.sse[key] for x in s) / max(1, sum(x.count for x in s)))


def leave_one_family_out(*, families: Sequence[str] | None = None, seeds: int = 3,
                         size_px: int = 64, operator: str = "glvm", window: int = 9,
                         methods: Sequence[str] = DEPTH_METHODS,
                         third_party: dict[str, tuple[np.ndarray, np.ndarray, np.ndarray]]
                         | None = None) -> HeldOutTable:
    """Run the protocol.

    Parameters
    ----------
    families : sequence of str, optional
        Names from :data:`sffscan.stages.sim.families.FAMILIES` (default: all).
    seeds : int, keyword-only
        Seeds per family for training (0 .. seeds-1) and as many held out
        (seeds .. 2 seeds - 1).
    size_px, operator, window : keyword-only
        Image size, focus measure operator and window.
    methods : sequence of str, keyword-only
        Fixed methods compared (default: every method).
    third_party : dict, optional, keyword-only
        ``name -> (volume (N, H, W), truth in levels (H, W), scored mask (H, W))``.

    Returns
    -------
    HeldOutTable
    """
    names = list(families) if families else [f.name for f in FAMILIES]
    if len(names) < 2:
        raise ValueError("leave-one-family-out needs at least 2 families")
    scores = {(f, s): _stack_scores(family_stack(f, s, size_px=size_px), operator=operator,
                                    window=window, methods=methods)
              for f in names for s in range(2 * seeds)}
    def tune(train: list[str]) -> dict[str, Setting]:
        """Each candidate's setting: the least sum over the training families of
        log(RMSE / the family's best fixed method's RMSE)."""
        out = {}
        for cand, settings in CANDIDATES.items():
            cost = []
            for v in settings:
                c = 0.0
                for f in train:
                    group = [scores[f, s] for s in range(seeds)]
                    best = min(_rmse(group, m) for m in methods)
                    c += math.log(max(_rmse(group, _key(cand, v)), 1e-12) / max(best, 1e-12))
                cost.append(c)
            out[cand] = settings[int(np.argmin(cost))]
        return out

    rmse: dict[str, dict[str, float]] = {}
    tuned: dict[str, dict[str, Setting]] = {}
    coverage: dict[str, float] = {}
    fits: dict[str, tuple[float, float]] = {}

    def train_groups(fams: list[str]) -> list[list[_Scores]]:
        return [[scores[g, s] for s in range(seeds)] for g in fams]

    for f in names:
        t = tune([g for g in names if g != f])
        tuned[f] = t
        held = [scores[f, s] for s in range(seeds, 2 * seeds)]
        row = {m: _rmse(held, m) for m in methods}
        row.update({c: _rmse(held, _key(c, v)) for c, v in t.items()})
        rmse[f] = row
        fits[f] = fit_uncertainty(train_groups([g for g in names if g != f]))
        coverage[f] = uncertainty_coverage(held, *fits[f])
    fits["all"] = fit_uncertainty(train_groups(names))
    extra: dict[str, dict[str, float]] = {}
    if third_party:
        t_all = tune(names)
        tuned["all"] = t_all
        for name, (vol, truth, mask) in third_party.items():
            sc = score_volume(vol, truth, mask, methods=methods, spread_size=window)
            row = {m: _rmse([sc], m) for m in methods}
            row.update({c: _rmse([sc], _key(c, v)) for c, v in t_all.items()})
            extra[name] = row
            coverage[name] = uncertainty_coverage([sc], *fits["all"])
    all_methods = (*methods, *CANDIDATES)
    worst = {m: max(r[m] / min(r[k] for k in methods) for r in (*rmse.values(),
                                                                 *extra.values()))
             for m in all_methods}
    chosen = min(all_methods, key=worst.__getitem__)
    return HeldOutTable(rmse, tuned, extra, chosen, worst, all_methods, coverage, fits)


def format_table(table: HeldOutTable) -> str:
    """The held-out table as Markdown: RMSE (levels) and, in brackets, the ratio to the best
    fixed method of the row; the last row the worst ratio of each method; the last column
    the candidates' settings tuned without the row's family."""
    methods = table.methods
    lines = ["| held out | " + " | ".join(methods) + " | tuned |",
             "|---|" + "---:|" * (len(methods) + 1)]
    def settings(key: str) -> str:
        return ", ".join(format_setting(v) for v in table.tuned.get(key, {}).values())

    rows = [(f, r, settings(f)) for f, r in table.rmse.items()]
    rows += [(f"{n} (third party)", r, settings("all")) for n, r in
             table.third_party.items()]
    fixed = [m for m in methods if m in DEPTH_METHODS]
    for name, r, t in rows:
        best = min(r[m] for m in fixed)
        cells = " | ".join(f"{r[m]:.3f} ({r[m] / best:.2f})" for m in methods)
        lines.append(f"| {name} | {cells} | {t} |")
    lines.append("| **worst ratio** | " + " | ".join(f"**{table.worst_ratio[m]:.2f}**"
                                                      for m in methods) + " | |")
    return "\n".join(lines)


def format_coverage(table: HeldOutTable) -> str:
    """The uncertainty's held-out coverage as Markdown (share of |error| <= 2 sigma)."""
    lines = ["| held out | share of abs(error) <= 2 sigma | in 0.90 .. 0.98 | a (scatter) "
             "| c (floor, levels) |", "|---|---:|:---:|---:|---:|"]
    for name, cov in table.coverage.items():
        a, c = table.uncertainty_fit.get(name, table.uncertainty_fit["all"])
        ok = "yes" if 0.90 <= cov <= 0.98 else "**no**"
        lines.append(f"| {name} | {cov:.3f} | {ok} | {a:.3f} | {c:.4f} |")
    a, c = table.uncertainty_fit["all"]
    lines.append(f"| (fit on every family's training seeds) | | | {a:.3f} | {c:.4f} |")
    return "\n".join(lines)
