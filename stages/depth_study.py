"""Choosing a depth method by a protocol that cannot overfit: leave one family out.

The families of :mod:`sffscan.stages.sim.families` are rendered with two disjoint sets of
seeds, *training* and *held-out*. For each family F in turn:

1. the tunable candidates (:data:`sffscan.stages.depth_study_grid.CANDIDATES`, each a
   rule with one setting, scored by :func:`sffscan.stages.depth_study_grid.
   candidate_errors`) are tuned on the training seeds of every family
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
from typing import Literal

import cv2
import numpy as np
from sffscan.stages.curve_shape import centroid_departure, curve_width, width_excess
from sffscan.stages.depth import (
    DEFAULT_METHOD,
    DEPTH_METHODS,
    depth_from_focus,
    first_argmax,
    focus_sums,
    shape_select_with_bias,
)
from sffscan.stages.depth_choice import method_bias, method_locking
from sffscan.stages.depth_study_grid import (
    CANDIDATES,
    Setting,
    candidate_errors,
    format_setting,
    score_key,
)
from sffscan.stages.depth_uncertainty import (
    depth_range,
    depth_relief,
    depth_scatter,
    locking_visibility,
)
from sffscan.stages.focus_measure import focus_measure
from sffscan.stages.sim.families import FAMILIES, SimStack, family_stack
from sffscan.stages.uncertainty_fit import (
    UncertaintyConstants,
    fit_uncertainty,
    uncertainty_coverage,
)

__all__ = ["HeldOutTable", "StackSpread", "format_coverage", "format_spread", "format_table",
           "leave_one_family_out", "score_volume", "stack_spread", "uncertainty_sample"]


@dataclass
class _Scores:
    """Sum of squared errors (levels^2) and pixel count per method, one stack; the default
    method's errors, depth scatter and relief and the curves' excess widths of the scored
    pixels (levels, :mod:`sffscan.stages.depth_uncertainty`)."""

    sse: dict[str, float]
    count: int
    error: np.ndarray
    scatter: np.ndarray
    relief: np.ndarray
    excess: np.ndarray
    bias: np.ndarray


def score_volume(volume: np.ndarray, truth_levels: np.ndarray, mask: np.ndarray, *,
                 methods: Sequence[str] = DEPTH_METHODS, median_size: int = 11,
                 spread_size: int = 9) -> _Scores:
    """Squared errors of every method and of the candidate at every threshold."""
    sse: dict[str, float] = {}
    a = first_argmax(np.ascontiguousarray(volume, np.float32))
    default, bias, locking = _default_depth(volume, a, median_size=median_size,
                                            spread_size=spread_size)
    depth = {DEFAULT_METHOD: default}
    for m in dict.fromkeys((*methods, "spc", "adaptive", "adaptive_centroid", "shape_select",
                            "wcentroid", DEFAULT_METHOD)):
        if m not in depth:
            depth[m] = depth_from_focus(volume, method=m, median_size=median_size,
                                        spread_size=spread_size, argmax=a)[0]
        if m in methods:
            sse[m] = float(np.sum((depth[m] - truth_levels)[mask] ** 2))
    width = curve_width(volume)
    sse.update(candidate_errors(volume, truth_levels, mask, depth=depth, argmax=a, width=width,
                                median_size=median_size, spread_size=spread_size))
    return _uncertainty_terms(default, width, truth_levels, mask, sse=sse,
                              window=spread_size, bias=bias, locking=locking)


def _default_depth(volume: np.ndarray, argmax: np.ndarray, *, median_size: int,
                   spread_size: int) -> tuple[np.ndarray, float, float]:
    """The default method's depth (levels), the bias its height uncertainty adds
    (depth_uncertainty's b; ``"shape_select"``'s choice for the stack, from the same pass)
    and its locking (depth_uncertainty's L)."""
    if DEFAULT_METHOD == "shape_select":
        depth, _, bias, locking = shape_select_with_bias(
            volume, argmax=argmax, median_size=median_size, spread_size=spread_size)
        return depth, bias, locking
    return depth_from_focus(volume, method=DEFAULT_METHOD, median_size=median_size,
                            spread_size=spread_size, argmax=argmax)[0], 0.0, 0.0


def _uncertainty_terms(depth: np.ndarray, width: np.ndarray,
                       truth_levels: np.ndarray, mask: np.ndarray, *,
                       sse: dict[str, float], window: int, bias: float,
                       locking: float, pull: np.ndarray | None = None) -> _Scores:
    scatter = depth_scatter(depth, window=window)
    excess = width_excess(width, depth_range(depth, window=window), window=window)
    count = int(mask.sum())
    relief = depth_relief(depth, window=window)
    # b in quadrature with the locking the scatter cannot show, per pixel (depth_uncertainty)
    seen = locking_visibility(cv2.medianBlur(np.ascontiguousarray(depth, np.float32), 5),
                              window=window)[mask]
    b = np.sqrt(np.float32(bias * bias) + (np.float32(locking) * seen) ** 2
                + (0.0 if pull is None else pull[mask] ** 2))
    return _Scores(sse, count, (depth - truth_levels)[mask], scatter[mask], relief[mask],
                   excess[mask], b.astype(np.float32, copy=False))


def uncertainty_sample(volume: np.ndarray, truth_levels: np.ndarray, mask: np.ndarray, *,
                       median_size: int = 11, spread_size: int = 9,
                       method: str = DEFAULT_METHOD) -> _Scores:
    """A method's errors (the default's unless ``method``) and the uncertainty's terms on
    the ``mask`` pixels of one focus volume (levels), for
    :mod:`sffscan.stages.uncertainty_fit` without scoring every method; ``b`` as a stack
    reconstructed with that method adds it
    (:func:`sffscan.stages.depth.shape_select_with_bias`,
    :func:`sffscan.stages.depth_choice.method_bias`)."""
    a = first_argmax(np.ascontiguousarray(volume, np.float32))
    width = curve_width(volume)
    if method == "shape_select":
        d, _, bias, locking = shape_select_with_bias(volume, argmax=a, median_size=median_size,
                                                     spread_size=spread_size)
    else:
        d = depth_from_focus(volume, method=method, median_size=median_size,
                             spread_size=spread_size, argmax=a)[0]
        bias = method_bias(volume, a, method, median_size=median_size, depth=d,
                           margin=spread_size // 2)
        locking = method_locking(volume, a, method, median_size=median_size, width=width,
                                 margin=spread_size // 2)
    # the whole-curve centroid's departure from its curve's phase, per pixel, as a stack's
    # or scan's uncertainty adds it (depth_uncertainty.height_uncertainty_um)
    pull = None
    if method == "centroid":
        sums = focus_sums(np.asarray(volume, np.float32))
        pull = centroid_departure(d, sums[1], sums[2], volume.shape[0])
    return _uncertainty_terms(d, width, truth_levels, mask, sse={},
                              window=spread_size, bias=bias, locking=locking, pull=pull)


@dataclass(frozen=True)
class StackSpread:
    """How much a held-out family's figures rest on its few stacks: a percentile interval
    over resamples of the stacks (with replacement; :func:`stack_spread`)."""

    stacks: int
    """Held-out stacks of the family."""
    ratio: tuple[float, float]
    """The default method's RMSE over the best fixed method's, its interval."""
    coverage: tuple[float, float]
    """The uncertainty's coverage (share of |error| <= 2 sigma), its interval."""


def stack_spread(held: Sequence[_Scores], *, methods: Sequence[str],
                 constants: UncertaintyConstants, default: str = DEFAULT_METHOD,
                 level: float = 0.90, resamples: int = 2000, seed: int = 0) -> StackSpread:
    """The ``level`` percentile interval of a family's held-out figures over its stacks: the
    stacks resampled with replacement ``resamples`` times (a fixed ``seed``: the same
    interval every run), each resample's pixels pooled as the table pools them (the
    default method's RMSE over the least RMSE of ``methods``; the share of pixels with
    |error| <= 2 sigma for ``constants``).

    Three stacks a family move the default's ratio by up to 0.2 between two sets of seeds
    (docs/depth-study.md): the interval says how far a row's figure can be read. It is the
    spread of *these* stacks, not of the family: with few stacks it is too narrow.
    """
    n = len(held)
    if n == 0:
        raise ValueError("no held-out stack")
    count = np.array([x.count for x in held], float)
    sse = np.array([[x.sse[m] for m in (default, *methods)] for x in held])  # (stacks, 1+M)
    covered = np.array([uncertainty_coverage([x], constants) * x.count for x in held])
    pick = np.random.default_rng(seed).integers(0, n, size=(resamples, n))
    weights = np.zeros((resamples, n))
    np.add.at(weights, (np.arange(resamples)[:, None], pick), 1.0)
    total = weights @ count
    rmse = np.sqrt((weights @ sse) / total[:, None])
    ratio = rmse[:, 0] / np.maximum(rmse[:, 1:].min(axis=1), 1e-12)
    share = (weights @ covered) / total
    q = (0.5 - level / 2, 0.5 + level / 2)
    lo_r, hi_r = np.quantile(ratio, q)
    lo_c, hi_c = np.quantile(share, q)
    return StackSpread(n, (float(lo_r), float(hi_r)), (float(lo_c), float(hi_c)))


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
    (a, r, c); ``"all"``: fitted on the training seeds of every family, used for the
    third-party sets, whose coverage is keyed by name).
    """

    rmse: dict[str, dict[str, float]]
    tuned: dict[str, dict[str, Setting]]
    third_party: dict[str, dict[str, float]]
    chosen: str
    worst_ratio: dict[str, float]
    methods: tuple[str, ...]
    coverage: dict[str, float]
    uncertainty_fit: dict[str, UncertaintyConstants]
    spread: dict[str, StackSpread]


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
                         held_out_from: int | None = None,
                         blur_model: Literal["gather", "scatter"] = "gather",
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
    held_out_from : int, optional, keyword-only
        The first held-out seed (default ``seeds``): held out are ``held_out_from ..
        held_out_from + seeds - 1``, a set no earlier run has seen; at least ``seeds``.
    blur_model : {"gather", "scatter"}, keyword-only
        How every stack (training and held out) applies a blur that varies over the image
        (:data:`sffscan.stages.sim.families.BLUR_MODELS`; default ``"gather"``, the
        generator every shipped setting and constant was chosen on).
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
    first = seeds if held_out_from is None else held_out_from
    if first < seeds:
        raise ValueError(f"held-out seeds from {first} would overlap the training seeds "
                         f"0 .. {seeds - 1}")

    def seed(k: int) -> int:  # the k-th seed: training below ``seeds``, held out after
        return k if k < seeds else first + k - seeds

    scores = {(f, s): _stack_scores(family_stack(f, seed(s), size_px=size_px,
                                                 blur_model=blur_model),
                                    operator=operator, window=window, methods=methods)
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
                    c += math.log(max(_rmse(group, score_key(cand, v)), 1e-12) / max(best, 1e-12))
                cost.append(c)
            out[cand] = settings[int(np.argmin(cost))]
        return out

    rmse: dict[str, dict[str, float]] = {}
    tuned: dict[str, dict[str, Setting]] = {}
    coverage: dict[str, float] = {}
    fits: dict[str, UncertaintyConstants] = {}
    spread: dict[str, StackSpread] = {}

    def train_groups(fams: list[str]) -> list[list[_Scores]]:
        return [[scores[g, s] for s in range(seeds)] for g in fams]

    for f in names:
        t = tune([g for g in names if g != f])
        tuned[f] = t
        held = [scores[f, s] for s in range(seeds, 2 * seeds)]
        row = {m: _rmse(held, m) for m in methods}
        row.update({c: _rmse(held, score_key(c, v)) for c, v in t.items()})
        rmse[f] = row
        fits[f] = fit_uncertainty(train_groups([g for g in names if g != f]))
        coverage[f] = uncertainty_coverage(held, fits[f])
        if DEFAULT_METHOD in methods:  # the default's errors are kept only then
            spread[f] = stack_spread(held, methods=methods, constants=fits[f])
    fits["all"] = fit_uncertainty(train_groups(names))
    extra: dict[str, dict[str, float]] = {}
    if third_party:
        t_all = tune(names)
        tuned["all"] = t_all
        for name, (vol, truth, mask) in third_party.items():
            sc = score_volume(vol, truth, mask, methods=methods, spread_size=window)
            row = {m: _rmse([sc], m) for m in methods}
            row.update({c: _rmse([sc], score_key(c, v)) for c, v in t_all.items()})
            extra[name] = row
            coverage[name] = uncertainty_coverage([sc], fits["all"])
    all_methods = (*methods, *CANDIDATES)
    worst = {m: max(r[m] / min(r[k] for k in methods) for r in (*rmse.values(),
                                                                 *extra.values()))
             for m in all_methods}
    chosen = min(all_methods, key=worst.__getitem__)
    return HeldOutTable(rmse, tuned, extra, chosen, worst, all_methods, coverage, fits, spread)


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
             "| r (relief) | c (floor, levels) |", "|---|---:|:---:|---:|---:|---:|"]
    for name, cov in table.coverage.items():
        a, r, c = table.uncertainty_fit.get(name, table.uncertainty_fit["all"])
        ok = "yes" if 0.90 <= cov <= 0.98 else "**no**"
        lines.append(f"| {name} | {cov:.3f} | {ok} | {a:.3f} | {r:.3f} | {c:.4f} |")
    a, r, c = table.uncertainty_fit["all"]
    lines.append(f"| (fit on every family's training seeds) | | | {a:.3f} | {r:.3f} | "
                 f"{c:.4f} |")
    return "\n".join(lines)


def format_spread(table: HeldOutTable) -> str:
    """The default's held-out ratio and the uncertainty's coverage of each family, with their
    90 % intervals over the family's stacks (:func:`stack_spread`), as Markdown."""
    lines = [f"| held out | stacks | {DEFAULT_METHOD} / best | 90 % over stacks | coverage "
             "| 90 % over stacks |", "|---|---:|---:|---|---:|---|"]
    for f, sp in table.spread.items():
        r = table.rmse[f]
        best = min(r[m] for m in table.methods if m in DEPTH_METHODS)
        lines.append(f"| {f} | {sp.stacks} | {r[DEFAULT_METHOD] / best:.2f} | "
                     f"{sp.ratio[0]:.2f} .. {sp.ratio[1]:.2f} | {table.coverage[f]:.3f} | "
                     f"{sp.coverage[0]:.3f} .. {sp.coverage[1]:.3f} |")
    return "\n".join(lines)
