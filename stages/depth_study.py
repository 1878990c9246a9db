"""Choosing a depth method by a protocol that cannot overfit: leave one family out.

The families of :mod:`sffscan.stages.sim.families` are rendered with two disjoint sets of
seeds, *training* and *held-out*. For each family F in turn:

1. the tunable candidate (:func:`width_switch`, its threshold) is tuned on the training
   seeds of every family except F: the threshold that minimises the mean over those
   families of ``log(RMSE / best fixed method's RMSE)``;
2. every fixed method and the tuned candidate are scored on F's held-out seeds only.

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
    DEPTH_METHODS,
    _argmax,
    depth_from_focus,
)
from sffscan.stages.focus_measure import focus_measure
from sffscan.stages.sim.families import FAMILIES, SimStack, family_stack

__all__ = ["CANDIDATE", "THRESHOLDS", "HeldOutTable", "curve_width", "leave_one_family_out",
           "format_table", "score_volume", "width_switch"]

CANDIDATE = "width-switch"
"""Name of the tunable candidate in the tables."""

THRESHOLDS = (2.0, 3.0, 4.0, 5.0, 6.0, 8.0, 12.0, math.inf)
"""Candidate thresholds (levels) the protocol tunes over (inf: never SPC = adaptive)."""


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
    area = h0 - n * vol.min(axis=0)
    ratio = np.clip(np.hypot(re, im) / np.where(area > 0, area, 1.0), 1e-9, 1.0)
    return n / (math.pi * math.sqrt(2.0)) * np.sqrt(-np.log(ratio))


def width_switch(spc: np.ndarray, adaptive: np.ndarray, width: np.ndarray, *,
                 threshold: float) -> np.ndarray:
    """SPC where the curve is wider than ``threshold`` levels (the centroid window and the
    peak fit see only part of it), else ``adaptive``; float32 levels."""
    return np.where(width > threshold, spc, adaptive).astype(np.float32)


@dataclass
class _Scores:
    """Sum of squared errors (levels^2) and pixel count per method, one stack."""

    sse: dict[str, float]
    count: int


def score_volume(volume: np.ndarray, truth_levels: np.ndarray, mask: np.ndarray, *,
                 methods: Sequence[str] = DEPTH_METHODS, median_size: int = 11,
                 spread_size: int = 9) -> _Scores:
    """Squared errors of every method and of the candidate at every threshold."""
    sse: dict[str, float] = {}
    depth: dict[str, np.ndarray] = {}
    a = _argmax(np.ascontiguousarray(volume, np.float32))
    for m in dict.fromkeys((*methods, "spc", "adaptive")):
        depth[m] = depth_from_focus(volume, method=m, median_size=median_size,
                                    spread_size=spread_size, argmax=a)[0]
        if m in methods:
            sse[m] = float(np.sum((depth[m] - truth_levels)[mask] ** 2))
    width = curve_width(volume)
    for t in THRESHOLDS:
        d = width_switch(depth["spc"], depth["adaptive"], width, threshold=t)
        sse[f"{CANDIDATE}@{t:g}"] = float(np.sum((d - truth_levels)[mask] ** 2))
    return _Scores(sse, int(mask.sum()))


@dataclass(frozen=True)
class HeldOutTable:
    """The protocol's result.

    ``rmse[family][method]``: held-out RMSE (levels) of each fixed method and of the
    candidate tuned without that family (key :data:`CANDIDATE`); ``tuned[family]`` the
    threshold chosen for it; ``third_party`` the same for third-party stacks (candidate
    tuned on all families); ``chosen`` the method whose worst ratio to the best fixed
    method over the held-out families and third-party stacks is the smallest, and
    ``worst_ratio`` that ratio per method.
    """

    rmse: dict[str, dict[str, float]]
    tuned: dict[str, float]
    third_party: dict[str, dict[str, float]]
    chosen: str
    worst_ratio: dict[str, float]
    methods: tuple[str, ...]


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
    cand_keys = [f"{CANDIDATE}@{t:g}" for t in THRESHOLDS]

    def tune(train: list[str]) -> float:
        cost = []
        for key in cand_keys:
            c = 0.0
            for f in train:
                group = [scores[f, s] for s in range(seeds)]
                best = min(_rmse(group, m) for m in methods)
                c += math.log(max(_rmse(group, key), 1e-12) / max(best, 1e-12))
            cost.append(c)
        return THRESHOLDS[int(np.argmin(cost))]

    rmse: dict[str, dict[str, float]] = {}
    tuned: dict[str, float] = {}
    for f in names:
        t = tune([g for g in names if g != f])
        tuned[f] = t
        held = [scores[f, s] for s in range(seeds, 2 * seeds)]
        row = {m: _rmse(held, m) for m in methods}
        row[CANDIDATE] = _rmse(held, f"{CANDIDATE}@{t:g}")
        rmse[f] = row
    extra: dict[str, dict[str, float]] = {}
    if third_party:
        t_all = tune(names)
        for name, (vol, truth, mask) in third_party.items():
            sc = score_volume(vol, truth, mask, methods=methods, spread_size=window)
            row = {m: _rmse([sc], m) for m in methods}
            row[CANDIDATE] = _rmse([sc], f"{CANDIDATE}@{t_all:g}")
            extra[name] = row
    all_methods = (*methods, CANDIDATE)
    worst = {m: max(r[m] / min(r[k] for k in methods) for r in (*rmse.values(),
                                                                 *extra.values()))
             for m in all_methods}
    chosen = min(all_methods, key=worst.__getitem__)
    return HeldOutTable(rmse, tuned, extra, chosen, worst, all_methods)


def format_table(table: HeldOutTable) -> str:
    """The held-out table as Markdown: RMSE (levels) and, in brackets, the ratio to the best
    fixed method of the row; the last row the worst ratio of each method."""
    methods = table.methods
    lines = ["| held out | " + " | ".join(methods) + " | tuned |",
             "|---|" + "---:|" * (len(methods) + 1)]
    rows = [(f, r, f"{table.tuned[f]:g}") for f, r in table.rmse.items()]
    rows += [(f"{n} (third party)", r, "all") for n, r in table.third_party.items()]
    fixed = [m for m in methods if m in DEPTH_METHODS]
    for name, r, t in rows:
        best = min(r[m] for m in fixed)
        cells = " | ".join(f"{r[m]:.3f} ({r[m] / best:.2f})" for m in methods)
        lines.append(f"| {name} | {cells} | {t} |")
    lines.append("| **worst ratio** | " + " | ".join(f"**{table.worst_ratio[m]:.2f}**"
                                                      for m in methods) + " | |")
    return "\n".join(lines)
