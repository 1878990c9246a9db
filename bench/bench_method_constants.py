"""Each depth method's own height-uncertainty constants, against the constants it has in
this tree, on the held-out coverage bar (issue 24: 90-98 % of |error| <= 2 sigma on every
held-out family).

    python bench/bench_method_constants.py                       # seeds 6..47 held out
    python bench/bench_method_constants.py --held-out 102 108 \
        --out bench/results/method_constants_102

For every stack of the twenty synthetic families (:mod:`sffscan.stages.sim.families`, the
study's ten and the ten crossed from them; 64 px, GLVM 9) and every depth method of scan,
replay and stack: the method's errors and the uncertainty's terms, ``b`` as a stack
reconstructed with that method adds it
(:func:`sffscan.stages.depth_study.uncertainty_sample`). Per method:

- ``this tree``: the constants :func:`sffscan.stages.fitted_constants.uncertainty_constants`
  gives it, fixed, scored on the held-out seeds of every family;
- ``own fit``: (a, r, c) fitted on the method's own errors by
  :func:`sffscan.stages.uncertainty_fit.fit_uncertainty` on the twenty families' training
  seeds 0..5 (what a shipped constant is fitted on; the ten study families' seeds 0, 1, 2
  until 2026-12-05, night);
- ``own, per fold``: fitted the same way without the held-out family (the twenty families'
  training seeds; leave one family out) and scored on that family's held-out seeds.

Held-out seeds in sets of six (``--held-out FIRST END``); each (set, family) is a row of
the bar: its coverage in the band, under it (the side that misleads) or over it; and, with
this tree's constants, each family's coverage over all its held-out seeds pooled. Not a
test: nothing here asserts; it writes ``<out>.md`` and ``<out>.json``.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from collections.abc import Sequence
from multiprocessing import Pool
from pathlib import Path
from typing import Any

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from bench_pipeline import machine  # noqa: E402
from sffscan.stages.depth import DEPTH_METHODS  # noqa: E402
from sffscan.stages.depth_study import uncertainty_sample  # noqa: E402
from sffscan.stages.fitted_constants import uncertainty_constants  # noqa: E402
from sffscan.stages.focus_measure import focus_measure  # noqa: E402
from sffscan.stages.sim.families import BLUR_MODELS, family_names, family_stack  # noqa: E402
from sffscan.stages.uncertainty_fit import (  # noqa: E402
    UncertaintyConstants,
    fit_uncertainty,
    uncertainty_coverage,
)

ROOT = Path(__file__).resolve().parents[1]
TRAINING = tuple(range(6))
BAND = (0.90, 0.98)


def sample(job: tuple[str, int, tuple[str, ...], str]
           ) -> tuple[tuple[str, int], dict[str, Any]]:
    """The methods' uncertainty samples on one family stack: ``(family, seed, methods, blur
    model)`` (:data:`sffscan.stages.sim.families.BLUR_MODELS`)."""
    family, seed, methods, blur_model = job
    st = family_stack(family, seed, size_px=64, blur_model=blur_model)  # type: ignore[arg-type]
    vol = focus_measure(st.images, operator="glvm", window=9)
    mask = np.zeros(st.truth_um.shape, bool)
    mask[4:-4, 4:-4] = True
    truth = (st.truth_um - st.focus_um[0]) / (st.focus_um[1] - st.focus_um[0])
    return (family, seed), {m: uncertainty_sample(vol, truth, mask, spread_size=9, method=m)
                            for m in methods}


def side(coverage: float) -> str:
    return "under" if coverage < BAND[0] else "over" if coverage > BAND[1] else "in"


def tally(samples: dict[tuple[str, int], dict[str, Any]], method: str,
          sets: Sequence[Sequence[int]], names: Sequence[str],
          constants: dict[str, UncertaintyConstants]) -> dict[str, int]:
    """In / under / over the band over every (set, family), ``constants`` per held-out
    family."""
    out = {"in": 0, "under": 0, "over": 0}
    for ss in sets:
        for f in names:
            out[side(uncertainty_coverage([samples[f, s][method] for s in ss],
                                          constants[f]))] += 1
    return out


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--held-out", nargs=2, type=int, default=(6, 48), metavar=("FIRST", "END"),
                    help="held-out seeds FIRST .. END - 1, in sets of six (default 6 48)")
    ap.add_argument("--out", type=Path, default=ROOT / "bench" / "results" / "method_constants")
    ap.add_argument("--blur-model", choices=BLUR_MODELS, default="gather",
                    help="how the held-out stacks apply a blur that varies over the image "
                         "(sffscan.stages.sim.families.BLUR_MODELS; the training stacks the "
                         "fits use stay gather, the study's; default gather)")
    ap.add_argument("--methods", default="all",
                    help=f"depth methods, comma separated, or 'all' ({', '.join(DEPTH_METHODS)})")
    args = ap.parse_args(argv)
    methods = tuple(DEPTH_METHODS) if args.methods == "all" else tuple(args.methods.split(","))
    for m in methods:
        if m not in DEPTH_METHODS:
            ap.error(f"--methods: unknown depth method {m!r}")
    first, end = args.held_out
    if first < len(TRAINING) or end - first < 6:
        raise SystemExit(f"--held-out: at least six seeds from {len(TRAINING)} on, "
                         f"got {first} .. {end - 1}")
    sets = [list(range(a, min(a + 6, end))) for a in range(first, end, 6)]
    names = family_names(crossed=True)
    t0 = time.time()
    jobs = [(f, s, methods, "gather" if s in TRAINING else args.blur_model)
            for f in names for s in (*TRAINING, *range(first, end))]
    with Pool(2) as pool:
        samples = dict(pool.imap_unordered(sample, jobs, chunksize=4))
    print(f"{len(jobs)} stacks sampled in {time.time() - t0:.0f} s", flush=True)
    rows: list[dict[str, Any]] = []
    for m in methods:
        groups = {f: [samples[f, s][m] for s in TRAINING] for f in names}
        own = fit_uncertainty([groups[f] for f in names])
        fold = {f: fit_uncertainty([groups[g] for g in names if g != f]) for f in names}
        here = UncertaintyConstants(*uncertainty_constants(m))
        held = list(range(first, end))
        rows.append({"method": m, "this_tree": list(here), "own_fit": list(own),
                     "this_tree_held_out": tally(samples, m, sets, names,
                                                 dict.fromkeys(names, here)),
                     "own_held_out": tally(samples, m, sets, names, fold),
                     # each family's coverage over all its held-out seeds pooled
                     "this_tree_pooled": {f: uncertainty_coverage(
                         [samples[f, s][m] for s in held], here) for f in names}})
        print(m, rows[-1]["this_tree_held_out"], rows[-1]["own_held_out"], flush=True)
    wall = time.time() - t0
    command = "python bench/bench_method_constants.py " + " ".join(
        sys.argv[1:] if argv is None else argv)
    n = len(sets) * len(names)
    lines = [f"# Each depth method's own uncertainty constants ({time.strftime('%Y-%m-%d %H:%M')})",
             "", f"`{command}` ({machine()}; {wall:.0f} s)", "",
             f"Twenty families, held-out seeds {first}..{end - 1} in {len(sets)} sets "
             f"(rendered with the {args.blur_model} blur model; the training seeds with "
             "gather): "
             f"{n} (set, family) rows per method, each in / under / over the "
             f"{BAND[0]:.2f}-{BAND[1]:.2f} band of |error| <= 2 sigma. Own fit: the "
             f"method's errors on the twenty families' seeds 0..{len(TRAINING) - 1}; held "
             "out with it: refitted without the held-out family.", "",
             "| method | this tree (a, r, c) | own fit (a, r, c) | this tree: in / under / "
             "over | own, per fold: in / under / over |",
             "|---|---|---|---:|---:|"]
    for r in rows:
        def fmt(v: list[float]) -> str:
            return ", ".join(f"{x:.4g}" for x in v)

        def cnt(d: dict[str, int]) -> str:
            return f"{d['in']} / {d['under']} / {d['over']}"

        lines.append(f"| {r['method']} | {fmt(r['this_tree'])} | {fmt(r['own_fit'])} | "
                     f"{cnt(r['this_tree_held_out'])} | {cnt(r['own_held_out'])} |")
    lines += ["", f"This tree's constants, each family's coverage over its {end - first} "
              "held-out seeds pooled:", "",
              "| family | " + " | ".join(r["method"] for r in rows) + " |",
              "|---|" + "---:|" * len(rows)]
    for f in names:
        lines.append(f"| {f} | " + " | ".join(
            f"{r['this_tree_pooled'][f]:.3f}" for r in rows) + " |")
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.with_suffix(".md").write_text("\n".join(lines) + "\n")
    args.out.with_suffix(".json").write_text(json.dumps(
        {"command": command, "machine": machine(), "held_out": [first, end - 1],
         "rows": rows}, indent=1) + "\n")
    print(f"wrote {args.out.with_suffix('.md')}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
