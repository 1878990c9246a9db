"""Evidence for the default depth method (issue 24, bar: <= 1.05x the best single method on
every held-out family): per-stack selection rules that read the data, on the synthetic
families (:mod:`sffscan.stages.sim.families`), leave one family out.

    python bench/bench_method_rules.py          # writes bench/method_rules_results.md

Rules, each choosing one method per stack:

- ``fixed M``: always M;
- ``min-scatter``: the method of {spc, adaptive, gauss3, wcentroid} whose depth map has the
  smallest median scatter (RMS about the 5 x 5 median over 9 x 9 px,
  :func:`sffscan.stages.depth_uncertainty.depth_scatter`): nothing tuned;
- ``threshold``: ``M1 if feature < t else M2`` with the feature one of the stack's median
  floor share, median curve width (levels, and over N), median depth scatter of adaptive or
  of SPC or their ratio; (feature, t, M1, M2) tuned on the training seeds (0..2) of the
  other families (least sum of log ratio to the best fixed method), scored on the held-out
  seeds (3..5) of the family.

Ratio: held-out RMSE (levels, pixels of the 3 seeds pooled) over that of the best fixed
method of the family. GLVM 9, 64 px. Not a test: nothing here asserts.
"""

from __future__ import annotations

import itertools
import math
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np
from sffscan.stages.curve_shape import curve_width, floor_share
from sffscan.stages.depth import depth_from_focus, first_argmax, focus_sums
from sffscan.stages.depth_uncertainty import depth_scatter
from sffscan.stages.focus_measure import focus_measure
from sffscan.stages.sim.families import FAMILIES, family_stack

OUT = Path(__file__).resolve().parent / "method_rules_results.md"
METHODS = ("spc", "adaptive", "gauss3", "wcentroid", "pc", "centroid")
POOL = ("spc", "adaptive", "gauss3", "wcentroid")
FEATURES = ("floor share", "width", "width / N", "scatter adaptive", "scatter spc",
            "scatter ratio")
Stack = tuple[dict[str, float], int, dict[str, float]]
Choose = Callable[[dict[str, float]], str]


def fixed(method: str) -> Choose:
    return lambda ft: method


def min_scatter(ft: dict[str, float]) -> str:
    return min(POOL, key=lambda m: ft["scatter " + m])


def measure(family: str, seed: int) -> Stack:
    """Squared errors per method, scored pixels, the stack's features."""
    st = family_stack(family, seed)
    vol = focus_measure(st.images, operator="glvm", window=9)
    truth = (st.truth_um - st.focus_um[0]) / (st.focus_um[1] - st.focus_um[0])
    m = np.zeros(truth.shape, bool)
    m[4:-4, 4:-4] = True
    a = first_argmax(np.ascontiguousarray(vol, np.float32))
    sse, feat = {}, {}
    for me in METHODS:
        d = depth_from_focus(vol, method=me, argmax=a)[0]
        sse[me] = float(np.sum((d - truth)[m] ** 2))
        feat["scatter " + me] = float(np.median(depth_scatter(d)[m]))
    sums = focus_sums(np.ascontiguousarray(vol, np.float32))
    feat["floor share"] = float(np.median(floor_share(sums[0], vol.min(axis=0),
                                                      vol.shape[0])[m]))
    feat["width"] = float(np.median(curve_width(vol)[m]))
    feat["width / N"] = feat["width"] / vol.shape[0]
    feat["scatter ratio"] = feat["scatter spc"] / max(feat["scatter adaptive"], 1e-9)
    return sse, int(m.sum()), feat


def main() -> int:
    t0 = time.perf_counter()
    fams = [f.name for f in FAMILIES]
    data = {(f, s): measure(f, s) for f in fams for s in range(6)}

    def rmse(keys: list[tuple[str, int]], choose: Choose) -> float:
        return math.sqrt(sum(data[k][0][choose(data[k][2])] for k in keys)
                         / sum(data[k][1] for k in keys))

    def best(keys: list[tuple[str, int]]) -> float:
        return min(rmse(keys, fixed(m)) for m in METHODS)

    rules = []
    for feat in FEATURES:
        vals = sorted({data[k][2][feat] for k in data})
        for t in [(a + b) / 2 for a, b in itertools.pairwise(vals)][::3]:
            rules += [(feat, t, m1, m2) for m1, m2 in itertools.permutations(POOL, 2)]

    def rule_fn(r: tuple[str, float, str, str]) -> Choose:
        return lambda ft: r[2] if ft[r[0]] < r[1] else r[3]

    def cost(r: tuple[str, float, str, str], train: list[str]) -> float:
        return sum(math.log(rmse(k, rule_fn(r)) / best(k))
                   for k in ([(g, s) for s in range(3)] for g in train))

    cols = [*(f"fixed {m}" for m in POOL), "min-scatter", "threshold"]
    lines = ["| held out | " + " | ".join(cols) + " | threshold rule tuned without it |",
             "|---|" + "---:|" * len(cols) + "---|"]
    worst = dict.fromkeys(cols, 0.0)
    for f in fams:
        keys = [(f, s) for s in range(3, 6)]
        b = best(keys)
        r = min(rules, key=lambda ru: cost(ru, [g for g in fams if g != f]))
        ratios = [rmse(keys, fixed(m)) / b for m in POOL]
        ratios.append(rmse(keys, min_scatter) / b)
        ratios.append(rmse(keys, rule_fn(r)) / b)
        worst = {c: max(worst[c], v) for c, v in zip(cols, ratios, strict=True)}
        lines.append(f"| {f} | " + " | ".join(f"{v:.2f}" for v in ratios)
                     + f" | {r[2]} if {r[0]} < {r[1]:.3g} else {r[3]} |")
    lines.append("| **worst** | " + " | ".join(f"**{worst[c]:.2f}**" for c in cols) + " | |")
    body = "\n".join(lines)
    print(body)
    from bench_pipeline import machine  # torch with it: loaded after the measurements
    OUT.write_text("# Per-stack selection rules for the depth method, held out\n\n"
                   f"Generated by `python bench/bench_method_rules.py` ({machine()}, "
                   f"{time.perf_counter() - t0:.0f} s); see the script's docstring.\n\n"
                   + body + "\n")
    print(f"wrote {OUT}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
