"""The default depth method against the best single method per family, pooled over many
held-out seeds and per set of six (issue 24's depth bar: the default <= 1.05x the best
single method on every held-out family).

    python bench/bench_depth_pooled.py --seeds 144 204 --out bench/results/depth_pooled_144

For every stack of the twenty synthetic families (:mod:`sffscan.stages.sim.families`: the
study's ten and the ten crossed from them; 64 px, GLVM 9, the focus window's reach left out
of the scored pixels, as ``sffscan study --families`` scores them) and pertuz-simu02, each
fixed depth method's squared error (levels^2). Per family, the RMSE over the stacks pooled:

- **pooled**: over all the seeds given; the default's RMSE over the best fixed method's
  (the best taken on the same seeds: a minimum over ten methods, with hindsight);
- **per set of six**: the same ratio on each set of six consecutive seeds (the study's
  held-out sets are six seeds a family), the worst set per family, and, as a yardstick of
  how far hindsight alone moves a set's ratio, the worst set of the family's *pooled* best
  method (which no set-size noise favours);
- **per stack**: the default's RMSE over the best single method's on each stack alone (what
  a user with one stack of that kind would see against the best method for it, chosen with
  hindsight): the stacks over 1.10x and the worst stack, with its seed; and, as the
  yardstick, the stacks over 1.10x of the family's pooled best method.

Nothing is tuned here; a seed set is scored once (docs/depth-method-log.md keeps which).
Not a test: nothing asserts; it writes ``<out>.md`` and ``<out>.json`` (the JSON also each
stack's RMSE per method, ``stack_rmse_levels``: two trees' runs on the same seeds compared
stack by stack by ``bench/compare_depth_pooled.py``).
"""

from __future__ import annotations

import json
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from family_scores import (  # noqa: E402
    NAMES,
    PERTUZ,
    ROOT,
    bench_parser,
    machine,
    score_stacks,
    write_table,
)
from sffscan.stages.depth import (  # noqa: E402
    DEFAULT_METHOD,
    DEPTH_METHODS,
    depth_from_focus,
    first_argmax,
)

SET_SIZE = 6
"""Seeds a held-out set of the depth study has per family."""


def method_errors(volume: np.ndarray, truth: np.ndarray, mask: np.ndarray
                  ) -> tuple[list[float], int]:
    """Every fixed method's sum of squared errors over ``mask`` (levels^2), and the count."""
    sse = []
    argmax = first_argmax(np.ascontiguousarray(volume, np.float32))  # once for all methods
    for m in DEPTH_METHODS:
        depth = depth_from_focus(volume, method=m, median_size=11, spread_size=9,
                                 argmax=argmax)[0]
        sse.append(float(np.sum((depth - truth)[mask] ** 2)))
    return sse, int(mask.sum())


def ratios(rows: list[tuple[int, tuple[list[float], int]]], seeds: list[int]
           ) -> np.ndarray:
    """Each method's RMSE over ``seeds`` (levels)."""
    by = dict(rows)
    sse = np.sum([by[s][0] for s in seeds], axis=0)
    return np.sqrt(sse / max(1, sum(by[s][1] for s in seeds)))


def main(argv: list[str] | None = None) -> int:
    out = ROOT / "bench" / "results" / "depth_pooled"
    ap = bench_parser(__doc__, seeds=(144, 204), out=out)
    args = ap.parse_args(argv)
    first, end = args.seeds
    if end - first < SET_SIZE:
        ap.error(f"--seeds: at least {SET_SIZE} seeds, got {first} .. {end - 1}")
    t0 = time.time()
    scores = score_stacks(method_errors, range(first, end), imdata=args.imdata, jobs=args.jobs,
                          blur_model=args.blur_model)
    wall = time.time() - t0
    methods = list(DEPTH_METHODS)
    d = methods.index(DEFAULT_METHOD)
    seeds = list(range(first, end))
    sets = [seeds[a:a + SET_SIZE] for a in range(0, len(seeds) - SET_SIZE + 1, SET_SIZE)]
    rows: list[dict[str, Any]] = []
    for name in (*NAMES, *([PERTUZ] if PERTUZ in scores else [])):
        own = [0] if name == PERTUZ else seeds
        rmse = ratios(scores[name], own)
        best = int(np.argmin(rmse))
        row = {"family": name, "seeds": len(own),
               "rmse_levels": dict(zip(methods, rmse.tolist(), strict=True)),
               "default_over_best": float(rmse[d] / rmse[best]), "best": methods[best]}
        if name != PERTUZ:
            per_set = [ratios(scores[name], ss) for ss in sets]
            row["worst_set"] = max(float(x[d] / x.min()) for x in per_set)
            row["sets_over_1_05"] = sum(float(x[d] / x.min()) > 1.05 for x in per_set)
            row["pooled_best_worst_set"] = max(float(x[best] / x.min()) for x in per_set)
            per_stack = [ratios(scores[name], [s]) for s in seeds]
            of = [(float(x[d] / x.min()), s) for s, x in zip(seeds, per_stack, strict=True)]
            row["stacks_over_1_10"] = sum(r > 1.10 for r, _ in of)
            row["worst_stack"], row["worst_stack_seed"] = max(of)
            row["pooled_best_stacks_over_1_10"] = sum(float(x[best] / x.min()) > 1.10
                                                      for x in per_stack)
            # each stack's RMSE per method (JSON only): two trees' runs compared stack by
            # stack, which choices flipped and which way, without scoring them again
            row["stack_rmse_levels"] = {
                str(s): dict(zip(methods, x.tolist(), strict=True))
                for s, x in zip(seeds, per_stack, strict=True)}
        rows.append(row)
    command = "python bench/bench_depth_pooled.py " + " ".join(
        sys.argv[1:] if argv is None else argv)
    fam = [r for r in rows if r["family"] != PERTUZ]
    lines = [f"# The default depth method against the best single method, pooled "
             f"({time.strftime('%Y-%m-%d %H:%M')})", "",
             f"`{command}` ({machine()}; {wall:.0f} s)", "",
             f"Default `{DEFAULT_METHOD}`; the families' stacks rendered with the "
             f"`{args.blur_model}` blur model; seeds {first}..{end - 1} ({len(seeds)} a family, "
             f"{len(sets)} sets of {SET_SIZE}); RMSE in levels over the stacks pooled. "
             "'pooled best's worst set': the family's pooled best method on its worst set of "
             "six, against that set's best (how far hindsight alone moves a set's ratio).", "",
             "| family | default RMSE | best (pooled) | default / best, pooled | worst set of "
             "six | sets over 1.05x | pooled best's worst set | stacks over 1.10x | worst "
             "stack (seed) | pooled best's stacks over 1.10x |",
             "|---|---:|---|---:|---:|---:|---:|---:|---:|---:|"]
    for r in rows:
        tail = ("| - | - | - | - | - | - |" if r["family"] == PERTUZ else
                f"| {r['worst_set']:.3f}x | {r['sets_over_1_05']} of {len(sets)} | "
                f"{r['pooled_best_worst_set']:.3f}x | {r['stacks_over_1_10']} of {len(seeds)} "
                f"| {r['worst_stack']:.3f}x ({r['worst_stack_seed']}) | "
                f"{r['pooled_best_stacks_over_1_10']} of {len(seeds)} |")
        lines.append(f"| {r['family']} | {r['rmse_levels'][DEFAULT_METHOD]:.4f} | {r['best']} | "
                     f"{r['default_over_best']:.3f}x " + tail)
    lines += ["", f"Worst family pooled: {max(r['default_over_best'] for r in fam):.3f}x; "
              f"worst set of six: {max(r['worst_set'] for r in fam):.3f}x; (set, family) rows "
              f"over 1.05x: {sum(r['sets_over_1_05'] for r in fam)} of {len(sets) * len(fam)}; "
              "the pooled best methods' own worst set: "
              f"{max(r['pooled_best_worst_set'] for r in fam):.3f}x; stacks over 1.10x the "
              f"best method for each alone: {sum(r['stacks_over_1_10'] for r in fam)} of "
              f"{len(seeds) * len(fam)}, the worst "
              f"{max(r['worst_stack'] for r in fam):.3f}x (the pooled best methods': "
              f"{sum(r['pooled_best_stacks_over_1_10'] for r in fam)})."]
    write_table(args.out.with_suffix(".md"), "\n".join(lines) + "\n")
    args.out.with_suffix(".json").write_text(json.dumps(
        {"command": command, "machine": machine(), "seeds": [first, end - 1],
         "blur_model": args.blur_model,
         "default": DEFAULT_METHOD, "rows": rows}, indent=1) + "\n")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
