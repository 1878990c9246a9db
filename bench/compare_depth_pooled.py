"""Two runs of ``bench/bench_depth_pooled.py`` on the same seeds (two trees, or a candidate
against the shipped default), compared family by family and stack by stack: what a
declared decision rule reads (docs/depth-method-log.md).

    python bench/compare_depth_pooled.py SHIPPED.json CANDIDATE.json [--over 1.10]

Per family: the default's RMSE over the best single method, pooled, in each run, and the
stacks over ``--over`` times their own best single method in each; then every stack whose
side of ``--over`` differs between the runs, with both ratios (the knife-edge choices a
change flips, and which way). The best single method is each run's own (the default is one
of the methods, as in the pooled table). Prints to stdout; nothing asserts.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path
from typing import Any


def _run(path: Path) -> tuple[str, dict[str, dict[str, Any]]]:
    """A run's default method and its rows by family."""
    try:
        data = json.loads(path.read_text())
        return data["default"], {r["family"]: r for r in data["rows"]}
    except (OSError, ValueError, KeyError, TypeError) as exc:
        raise SystemExit(f"{path}: not a bench_depth_pooled.py JSON ({exc})") from exc


def stack_ratios(row: dict[str, Any], default: str) -> dict[str, float]:
    """Each stack's default RMSE over its best single method's, by seed (a row of
    ``bench_depth_pooled.py``'s JSON with ``stack_rmse_levels``; empty without)."""
    out = {}
    for seed, rmse in row.get("stack_rmse_levels", {}).items():
        best = min(rmse.values())
        out[seed] = rmse[default] / best if best > 0 else 1.0
    return out


def compare(a: Path, b: Path, *, over: float = 1.10) -> list[str]:
    """The comparison's lines (see the module's docstring)."""
    (da, ra), (db, rb) = _run(a), _run(b)
    if set(ra) != set(rb):
        raise SystemExit(f"the runs hold different families: {sorted(set(ra) ^ set(rb))}")
    lines = [f"| family | {a.name} pooled | {b.name} pooled | stacks over {over:.2f}x "
             "(first -> second) |", "|---|---:|---:|---:|"]
    flips = []
    total = [0, 0]
    for fam in ra:
        sa, sb = stack_ratios(ra[fam], da), stack_ratios(rb[fam], db)
        if set(sa) != set(sb):
            raise SystemExit(f"{fam}: the runs hold different seeds")
        na = sum(x > over for x in sa.values())
        nb = sum(x > over for x in sb.values())
        total[0] += na
        total[1] += nb
        lines.append(f"| {fam} | {ra[fam]['default_over_best']:.3f}x | "
                     f"{rb[fam]['default_over_best']:.3f}x | {na} -> {nb} |")
        flips += [f"{fam} seed {s}: {sa[s]:.3f}x -> {sb[s]:.3f}x" for s in sorted(sa, key=int)
                  if (sa[s] > over) != (sb[s] > over)]
    lines += ["", f"stacks over {over:.2f}x: {total[0]} -> {total[1]}; across the line:"]
    lines += [f"- {f}" for f in flips] or ["- none"]
    return lines


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("first", type=Path, help="a bench_depth_pooled.py JSON (e.g. shipped)")
    ap.add_argument("second", type=Path, help="another on the same seeds (e.g. a candidate)")
    ap.add_argument("--over", type=float, default=1.10,
                    help="a stack's ratio to its best single method counted over (default 1.10)")
    args = ap.parse_args(argv)
    print("\n".join(compare(args.first, args.second, over=args.over)))
    return 0


if __name__ == "__main__":
    sys.exit(main())
