"""The default's 9-level centroid test (stages/depth_window.py) against the rule before it.

    python bench/bench_window_choice.py --seeds 72 78            # bench/results/window_choice.md
    python bench/bench_window_choice.py --seeds 0 72 --set-size 6 \
        --out bench/results/window_choice_seen.md

``shape_select``'s fallback takes, since 2026-12-05, the 9-level centroid (``wcentroid``)
where that map's scatter and its departure from the fallback say it errs less
(:func:`sffscan.stages.depth_window.window_choice`). The rule before it is reconstructed
exactly from the same stack: the default's depth where the stack takes SPC
(:func:`sffscan.stages.depth_choice.stack_choice`), else ``adaptive_centroid``'s (the
fallback before the test; both judge the same sample of curves). For each of the twenty
synthetic families and pertuz-simu02 (``--imdata``): the pooled RMSE (levels) of every
selectable method, the ratios of the default before and after to the best of them, and per
stack what the default took (S: SPC, W: the 9-level centroid, F: the fallback as before).
With ``--set-size K`` the summary also gives the worst ratio per set of K consecutive seeds.

64 px stacks, GLVM 9, the focus window's reach left out of the scored pixels, as the study
scores them. Not a test: nothing here asserts.
"""

from __future__ import annotations

import datetime as dt
import math
import time

import numpy as np
from family_scores import NAMES, ROOT, bench_parser, machine, score_stacks, write_table
from sffscan.stages.depth import DEFAULT_METHOD, DEPTH_METHODS, depth_from_focus, first_argmax
from sffscan.stages.depth_choice import stack_choice

OUT = ROOT / "bench" / "results" / "window_choice.md"
BEFORE = "before"


def score(volume: np.ndarray, truth: np.ndarray, mask: np.ndarray
          ) -> tuple[dict[str, float], int, str]:
    """Sum of squared errors (levels^2) per method and before, pixels scored, what was taken."""
    vol = np.ascontiguousarray(volume, np.float32)
    a = first_argmax(vol)
    depth = {m: depth_from_focus(vol, method=m, median_size=11, spread_size=9,
                                 argmax=a)[0] for m in DEPTH_METHODS}
    spc = stack_choice(vol, a, median_size=11, margin=9 // 2).spc  # as the depth judges
    depth[BEFORE] = depth[DEFAULT_METHOD] if spc else depth["adaptive_centroid"]
    took = "S" if spc else ("F" if np.array_equal(depth[DEFAULT_METHOD], depth[BEFORE])
                            else "W")
    sse = {m: float(np.sum((d - truth)[mask] ** 2)) for m, d in depth.items()}
    return sse, int(mask.sum()), took


def _ratios(group: list[tuple[int, dict[str, float], int, str]]
            ) -> tuple[dict[str, float], float, float]:
    """Pooled RMSE per method, and the ratios before and after to the best selectable method
    of each: the default is one of the selectable methods, so before's best is taken over
    the others and before, after's over all of them."""
    n = sum(r[2] for r in group)
    rmse = {m: math.sqrt(sum(r[1][m] for r in group) / n) for m in (*DEPTH_METHODS, BEFORE)}
    others = min(rmse[m] for m in DEPTH_METHODS if m != DEFAULT_METHOD)
    return (rmse, rmse[BEFORE] / min(others, rmse[BEFORE]),
            rmse[DEFAULT_METHOD] / min(others, rmse[DEFAULT_METHOD]))


def main(argv: list[str] | None = None) -> int:
    p = bench_parser(__doc__ or "", seeds=(72, 78), out=OUT)
    p.add_argument("--set-size", type=int, default=0,
                   help="also the worst ratios per set of this many seeds (0: none)")
    args = p.parse_args(argv)
    if args.seeds[1] <= args.seeds[0] or args.set_size < 0:
        p.error("--seeds FROM TO needs FROM < TO, --set-size >= 0")
    names = NAMES
    seeds = range(*args.seeds)
    t0 = time.perf_counter()
    rows = {name: [(seed, *result) for seed, result in got]
            for name, got in score_stacks(score, seeds, imdata=args.imdata, jobs=args.jobs,
                                          blur_model=args.blur_model).items()}
    wall = time.perf_counter() - t0

    head = ("| family | stacks | " + " | ".join(DEPTH_METHODS) + " | before / best | "
            f"{DEFAULT_METHOD} / best | taken per stack |")
    lines = [head, "|" + "---|" * (len(DEPTH_METHODS) + 5)]
    worst = {BEFORE: (0.0, ""), DEFAULT_METHOD: (0.0, "")}
    over = {BEFORE: 0, DEFAULT_METHOD: 0}
    for name in [*names, "pertuz-simu02"]:
        if name not in rows:
            continue
        group = sorted(rows[name], key=lambda r: r[0])
        rmse, before, after = _ratios(group)
        for m, r in ((BEFORE, before), (DEFAULT_METHOD, after)):
            if r > worst[m][0]:
                worst[m] = (r, name)
            over[m] += round(r, 2) > 1.05
        took = "".join(r[3] for r in group)
        lines.append(f"| {name} | {len(group)} | "
                     + " | ".join(f"{rmse[m]:.3f}" for m in DEPTH_METHODS)
                     + f" | {before:.2f} | {after:.2f} | {took} |")
    sets = []
    if args.set_size:
        sets = ["", f"Per set of {args.set_size} seeds, the worst ratio before -> after "
                "(the family), rows over 1.05x before -> after:", ""]
        for s0 in range(seeds.start, seeds.stop, args.set_size):
            part = range(s0, min(s0 + args.set_size, seeds.stop))
            ratios = {name: _ratios([r for r in rows[name] if r[0] in part])[1:]
                      for name in names}
            wb = max(ratios, key=lambda k: ratios[k][0])
            wa = max(ratios, key=lambda k: ratios[k][1])
            sets.append(f"- seeds {part.start}..{part.stop - 1}: {ratios[wb][0]:.2f}x ({wb}) "
                        f"-> {ratios[wa][1]:.2f}x ({wa}); "
                        f"{sum(round(r[0], 2) > 1.05 for r in ratios.values())} -> "
                        f"{sum(round(r[1], 2) > 1.05 for r in ratios.values())} of {len(names)}")
    text = "\n".join([
        "# The default's 9-level centroid test against the rule before it",
        "",
        f"`python bench/bench_window_choice.py --seeds {args.seeds[0]} {args.seeds[1]}"
        + (f" --set-size {args.set_size}" if args.set_size else "")
        + f"` ({dt.datetime.now():%Y-%m-%d %H:%M}; {machine()}; {wall:.0f} s). Seeds "
        f"{seeds.start}..{seeds.stop - 1} of the twenty families, 64 px stacks, GLVM 9; "
        "pertuz-simu02 in its ROI. RMSE in levels, pooled over a family's stacks; before: "
        "`shape_select` without the test; each ratio to the best selectable method "
        "(`DEPTH_METHODS`) with that default among them. Taken per stack: S SPC, "
        "W the 9-level centroid, F the fallback.",
        "",
        *lines,
        "",
        f"Worst ratio to the best selectable method: before {worst[BEFORE][0]:.2f}x "
        f"({worst[BEFORE][1]}), {DEFAULT_METHOD} {worst[DEFAULT_METHOD][0]:.2f}x "
        f"({worst[DEFAULT_METHOD][1]}); rows over 1.05x: {over[BEFORE]} and "
        f"{over[DEFAULT_METHOD]} of {len(lines) - 2}.",
        *sets,
        "",
    ])
    write_table(args.out, text)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
