"""Placement benchmark (issue 27): the default scan with every stage in a thread and with
the process placement, on 1 and 2 cores, this tree against another, interleaved in one run.

    python bench/bench_placement.py --against /tmp/sffscan-before   # about 6 min, 2 cores

The other tree (``--against``: a checkout of the commit before, e.g. ``git worktree add
--detach /tmp/sffscan-before COMMIT``) is imported instead of this one in its own runs
(``PYTHONPATH``; the worker processes inherit it). Every run is one end-to-end scan in a
fresh process (``bench/bench_parallel.py --case``: demo optics 1280 x 1024 uint16, N = 50,
GLVM k = 9, SPC unless ``--method``, registration on, Zarr mosaic (in ``--outputs``),
distinct simulated frames read into memory first), pinned to 1 or 2 CPUs (``--cores``);
frames/s = frames / wall time of streaming (processes: from the moment every worker is
ready); CPU ms/frame: the whole process tree's while streaming
(less sensitive than frames/s to other work on a shared machine). Round-robin over the
cases, ``--rounds`` times, median. Writes ``--out`` (markdown) and the same figures as
JSON beside it.
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "bench"))


def run(tree: Path, case: dict[str, Any]) -> dict[str, Any]:
    """One case in a fresh process importing sffscan (and the bench scripts) from
    ``tree``."""
    env = {**os.environ, "PYTHONPATH": str(tree)}
    done = subprocess.run([sys.executable, str(tree / "bench" / "bench_parallel.py"),
                           "--case", json.dumps(case)], capture_output=True, text=True,
                          env=env, check=False, timeout=900)
    if done.returncode != 0:
        raise RuntimeError(f"{tree}: case {case} failed:\n{done.stderr[-3000:]}")
    return dict(json.loads(done.stdout.strip().splitlines()[-1]))


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--against", type=Path, required=True, help="the other tree (before)")
    ap.add_argument("--tree", type=Path, default=ROOT, help="this tree (after)")
    ap.add_argument("--frames", type=int, default=300, help="frames per run")
    ap.add_argument("--rounds", type=int, default=2, help="interleaved rounds (median)")
    ap.add_argument("--cache", type=Path, default=Path(tempfile.gettempdir()) / "sffscan-bench",
                    help="where the rendered frames are kept")
    ap.add_argument("--out", type=Path, default=ROOT / "bench" / "results" / "placement.md")
    ap.add_argument("--cores", default="1,2", help="core counts, e.g. 2 (default 1,2)")
    ap.add_argument("--method", default="spc",
                    help="depth method of the runs (default spc, as before; 'default': the "
                         "configuration's default)")
    ap.add_argument("--outputs", type=Path,
                    help="folder the runs write their mosaics in (default: --cache; see "
                         "bench_parallel.py --outputs)")
    ap.add_argument("--calibration", type=Path,
                    help="calibration file every run applies (processing.calibration), e.g. "
                         "bench_frame_optics.py --write-calibration's; the other tree's "
                         "bench_parallel.py must pass it on too")
    args = ap.parse_args(argv)
    from bench_parallel import resolve_method
    from bench_pipeline import frame_bank, machine

    t0 = time.perf_counter()
    load_before = " ".join(f"{v:.2f}" for v in os.getloadavg())
    bank = frame_bank(args.cache, args.frames)
    trees = {"before": args.against.resolve(), "after": args.tree.resolve()}
    cores = [c for c in (int(v) for v in args.cores.split(","))
             if c <= len(os.sched_getaffinity(0))]
    method = resolve_method(args.method)
    outputs = args.outputs or args.cache
    outputs.mkdir(parents=True, exist_ok=True)
    cases = [(t, {"frames": args.frames, "bank": str(bank), "tmp": str(outputs),
                  "method": method, "source": "memory", "record": False, "mode": m,
                  "cores": c, "calibration": str(args.calibration or "")})
             for c in cores for m in ("threads", "processes") for t in trees]
    fps: dict[tuple[str, str, int], list[float]] = {
        (t, c["mode"], c["cores"]): [] for t, c in cases}
    cpu: dict[tuple[str, str, int], list[float]] = {k: [] for k in fps}
    for r in range(args.rounds):
        order = cases if r % 2 == 0 else cases[::-1]  # neither tree always goes first
        for t, c in order:
            got = run(trees[t], c)
            fps[(t, c["mode"], c["cores"])].append(got["fps"])
            cpu[(t, c["mode"], c["cores"])].append(got["cpu_ms_per_frame"])
            print(f"round {r + 1}: {t}, {c['mode']}, {c['cores']} core(s): "
                  f"{got['fps']:.1f} frames/s, {got['cpu_ms_per_frame']:.1f} CPU ms/frame "
                  f"(load {os.getloadavg()[0]:.1f})", file=sys.stderr, flush=True)
    med = {k: statistics.median(v) for k, v in fps.items()}
    mcpu = {k: statistics.median(v) for k, v in cpu.items()}
    lines = [f"# Placement: threads and processes, before and after "
             f"({time.strftime('%Y-%m-%d %H:%M')})", "",
             f"Machine: {machine()}; load average before / after: {load_before} / "
             + " ".join(f"{v:.2f}" for v in os.getloadavg()), "",
             f"Command: `python bench/bench_placement.py {' '.join(argv or sys.argv[1:])}` "
             f"({args.frames} frames per run, {args.rounds} rounds interleaved, median; "
             f"whole run {time.perf_counter() - t0:.0f} s). Before: `{trees['before']}`, "
             f"after: `{trees['after']}`. Depth method {method}; mosaics written in "
             f"{outputs}"
             + (f"; calibration `{args.calibration}` applied" if args.calibration else "")
             + ".", "",
             "| placement | cores | before frames/s | after frames/s | after / before |"
             " CPU ms/frame before | after | runs before | runs after |",
             "|---|---:|---:|---:|---:|---:|---:|---|---|"]
    for n in cores:
        for m in ("threads", "processes"):
            b, a = med[("before", m, n)], med[("after", m, n)]
            lines.append(f"| {m} | {n} | {b:.1f} | {a:.1f} | {a / b:.2f} | "
                         f"{mcpu[('before', m, n)]:.1f} | {mcpu[('after', m, n)]:.1f} | "
                         + ", ".join(f"{v:.1f}" for v in fps[("before", m, n)]) + " | "
                         + ", ".join(f"{v:.1f}" for v in fps[("after", m, n)]) + " |")
    if len(cores) == 2:
        lines.append("")
        for m in ("threads", "processes"):
            lines.append(f"- {m}, 2 cores / 1 core: before "
                         f"{med[('before', m, 2)] / med[('before', m, 1)]:.2f}x, after "
                         f"{med[('after', m, 2)] / med[('after', m, 1)]:.2f}x")
    lines.append("")
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text("\n".join(lines), encoding="utf-8")
    args.out.with_suffix(".json").write_text(json.dumps(
        {"runs": [{"tree": k[0], "mode": k[1], "cores": k[2], "fps": v,
                   "cpu_ms_per_frame": cpu[k]} for k, v in fps.items()]}, indent=1),
        encoding="utf-8")
    print(args.out.read_text(encoding="utf-8"))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
