"""A stack's own focus curve as a matched filter (issue 24: "a model fit over more than 3
points"), held out: leave one family out, and pertuz-simu02.

    python bench/bench_template_match.py     # writes bench/results/template_match.md

Estimator (:func:`template_match`; stated 2026-12-03, before it was scored; its numbers are
not tuned): every focus curve scaled to 0..1 (its minimum and maximum); the stack's
template is the median over the pixels of the curves sampled at ``d + t`` (a start depth
``d``, ``t`` on a 0.25-level grid over +-R, R = ceil(3 x the median curve width, one
sigma), at least 2; pixels whose window leaves the range are left out of the median); the
template's peak by a parabola through its three highest samples. Each pixel's depth is the
shift, on a 0.05-level grid within 2 levels of ``d``, that maximises the normalised cross
correlation of its curve with the template over the levels the template reaches; then the
template is rebuilt from those depths and the search made once more. Unlike the 3-point
peak or SPC it uses the whole peak and the stack's own curve shape (a thin lens' lopsided
curve included), and it has no spatial filter of its own.

Candidates scored: ``template`` (start: ``adaptive_centroid``), and ``fallback-template``:
the default (``shape_select``) where it took SPC, else the template match started from the
default, kept at a pixel where it moves the depth by less than L levels; L in 0.5, 1, 1.5,
inf is chosen for each held-out family on the training seeds (0..5) of the others (the
study's rule: least sum of log(RMSE / the best fixed method's RMSE)), scored on seeds
6..11 (the depth study's last table), and for pertuz-simu02 chosen on every family.

The synthetic families are :mod:`sffscan.stages.sim.families` (the ten and the ten
crossed, 64 px, GLVM 9); pertuz-simu02 is ../shared/datasets/pertuz-simu02 (BSD-3-Clause,
read in place). Not a test: nothing here asserts.
"""

from __future__ import annotations

import argparse
import math
import sys
import time
from pathlib import Path

import numpy as np
from sffscan.stages.curve_shape import curve_width
from sffscan.stages.depth import DEPTH_METHODS, depth_from_focus, first_argmax
from sffscan.stages.sim.families import family_names

ROOT = Path(__file__).resolve().parents[1]
OUT = ROOT / "bench" / "results" / "template_match.md"
LIMITS = (0.5, 1.0, 1.5, math.inf)
SEEDS = 6  # training 0..5, held out 6..11


def _sample(curves: np.ndarray, pos: np.ndarray) -> np.ndarray:
    """curves (N, P) at the fractional levels pos (P, T), linearly; NaN outside 0..N-1."""
    n = curves.shape[0]
    i0 = np.clip(np.floor(pos).astype(np.intp), 0, n - 2)
    f = np.clip(pos - i0, 0.0, 1.0)
    p = np.arange(curves.shape[1])[:, None]
    v = curves[i0, p] * (1 - f) + curves[i0 + 1, p] * f
    return np.where((pos >= 0) & (pos <= n - 1), v, np.nan)


def template_match(volume: np.ndarray, start: np.ndarray, *, rounds: int = 2,
                   reach: float = 2.0, step: float = 0.05) -> np.ndarray:
    """Depth (levels, (H, W)) by the stack template's normalised cross-correlation."""
    n = volume.shape[0]
    c = volume.reshape(n, -1).astype(np.float64)
    lo, hi = c.min(axis=0), c.max(axis=0)
    c = (c - lo) / np.where(hi > lo, hi - lo, 1.0)
    r = max(2, math.ceil(3 * float(np.median(curve_width(volume)))))
    grid = np.arange(-r, r + 1e-9, 0.25)
    z = np.arange(n, dtype=np.float64)
    d = start.reshape(-1).astype(np.float64)
    for _ in range(rounds):
        aligned = _sample(c, d[:, None] + grid[None, :])
        whole = ~np.isnan(aligned).any(axis=1)
        template = (np.median(aligned[whole], axis=0) if whole.any()
                    else np.nanmedian(aligned, axis=0))
        j = min(max(int(np.nanargmax(template)), 1), grid.size - 2)
        y0, y1, y2 = template[j - 1:j + 2]
        den = y0 - 2 * y1 + y2
        peak = grid[j] + (0.5 * (y0 - y2) / den * 0.25 if den != 0 else 0.0)
        best = np.full(d.shape, -np.inf)
        found = d.copy()
        for s in np.arange(-reach, reach + 1e-9, step):
            at = d + s
            tv = np.interp(z[None, :] - at[:, None] + peak, grid, template,
                           left=np.nan, right=np.nan)
            seen = ~np.isnan(tv)
            count = np.maximum(seen.sum(axis=1), 1)
            tv0 = np.where(seen, tv, 0.0)
            cv = np.where(seen, c.T, 0.0)
            a = np.where(seen, tv0 - (tv0.sum(axis=1) / count)[:, None], 0.0)
            b = np.where(seen, cv - (cv.sum(axis=1) / count)[:, None], 0.0)
            ncc = (a * b).sum(axis=1) / np.sqrt((a * a).sum(axis=1) * (b * b).sum(axis=1)
                                                + 1e-30)
            ncc = np.where(seen.sum(axis=1) >= 3, ncc, -np.inf)
            better = ncc > best
            best = np.where(better, ncc, best)
            found = np.where(better, at, found)
        d = found
    return d.reshape(start.shape)


def stack_errors(volume: np.ndarray, truth: np.ndarray, mask: np.ndarray
                 ) -> tuple[dict[str, float], int]:
    """Sum of squared errors (levels^2) of every fixed method and candidate; pixel count."""
    a = first_argmax(np.ascontiguousarray(volume, np.float32))
    depth = {m: depth_from_focus(volume, method=m, median_size=11, spread_size=9,
                                 argmax=a)[0] for m in DEPTH_METHODS}
    default = depth["shape_select"]
    depth["template"] = template_match(volume, depth["adaptive_centroid"])
    matched = template_match(volume, default)
    fallback = default == depth["adaptive_centroid"]  # the stack (or pixel) did not take SPC
    for lim in LIMITS:
        depth[f"fallback-template {lim:g}"] = np.where(
            fallback & (np.abs(matched - default) < lim), matched, default)
    return {k: float(np.sum((v - truth)[mask] ** 2)) for k, v in depth.items()}, int(mask.sum())


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--out", type=Path, default=OUT)
    args = ap.parse_args(argv)
    sys.path.insert(0, str(ROOT / "bench"))
    from bench_pipeline import machine
    from study_stacks import family_volume, pertuz_volume

    t0 = time.perf_counter()
    names = family_names(crossed=True)
    errs = {}
    for f in names:
        for s in range(2 * SEEDS):
            errs[f, s] = stack_errors(*family_volume(f, s))
        print(f"{f}: {time.perf_counter() - t0:.0f} s", file=sys.stderr, flush=True)
    third = stack_errors(*pertuz_volume())

    def rmse(groups: list[tuple[dict[str, float], int]], key: str) -> float:
        return math.sqrt(sum(g[0][key] for g in groups) / sum(g[1] for g in groups))

    def ratio(groups: list[tuple[dict[str, float], int]], key: str) -> float:
        return rmse(groups, key) / min(rmse(groups, m) for m in DEPTH_METHODS)

    keys = [f"fallback-template {lim:g}" for lim in LIMITS]

    def tuned(train: list[str]) -> str:
        cost = {k: sum(math.log(ratio([errs[g, s] for s in range(SEEDS)], k)) for g in train)
                for k in keys}
        return min(keys, key=lambda k: (cost[k], -keys.index(k)))  # ties: the largest L

    rows = ["| held out | best fixed (levels) | shape_select (default) | wcentroid | template "
            "| fallback-template, tuned | its L | every L (0.5 / 1 / 1.5 / inf) |",
            "|---|---:|---:|---:|---:|---:|---:|---|"]
    worst = dict.fromkeys(("shape_select", "wcentroid", "template", "tuned"), 0.0)
    groups = {f: [errs[f, s] for s in range(SEEDS, 2 * SEEDS)] for f in names}
    groups["pertuz-simu02 (third party)"] = [third]
    for f, held in groups.items():
        k = tuned([g for g in names if g != f])
        r = {m: ratio(held, m) for m in ("shape_select", "wcentroid", "template")}
        r["tuned"] = ratio(held, k)
        worst = {m: max(worst[m], r[m]) for m in worst}
        best = min(rmse(held, m) for m in DEPTH_METHODS)
        rows.append(f"| {f} | {best:.3f} | {r['shape_select']:.2f} | {r['wcentroid']:.2f} | "
                    f"{r['template']:.2f} | {r['tuned']:.2f} | {k.split()[-1]} | "
                    + " / ".join(f"{ratio(held, x):.2f}" for x in keys) + " |")
    rows.append(f"| **worst** | | **{worst['shape_select']:.2f}** | **{worst['wcentroid']:.2f}**"
                f" | **{worst['template']:.2f}** | **{worst['tuned']:.2f}** | | |")
    parts = ["# The stack's focus curve as a matched filter, held out", "",
             f"`python bench/bench_template_match.py` ({machine()}; "
             f"{time.strftime('%Y-%m-%d %H:%M')}). RMSE over the held-out seeds (6..11) of "
             "each family, as a ratio to the best fixed depth method of the row; "
             "pertuz-simu02 with L chosen on every family. Estimator and protocol: the "
             "script's docstring.", "", *rows, "",
             f"Whole run {time.perf_counter() - t0:.0f} s.", ""]
    args.out.write_text("\n".join(parts))
    print("\n".join(parts))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
