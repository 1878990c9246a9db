"""GLVM on whole frames against GLVM strip by strip (issue 28), interleaved, one process.

    python bench/bench_glvm.py                 # 12 frames, 7 rounds, strips of 64 and 128 rows
    python bench/bench_glvm.py --strips 32,64,128,256 --rounds 11

The scan's focus stage measures each frame's new columns with
:func:`sffscan.stages.focus_measure.focus_measure_raw` (GLVM from the raw 10-bit frame),
then the focus volume adds the map, strip by strip, to its per-pixel sums and running
maximum. Strip-blocked, each band of rows is measured on its own
(``focus_measure_raw(..., rows=...)``, the band widened by the operator's reach, 2 (k // 2)
rows each side) and handed to the accumulation while it is still in cache: the focus
measure never goes to memory as a whole frame, at the cost of measuring the halo rows twice.

Cases, each per frame over the same distinct simulated 1280 x 1024 uint16 frames (the
frame bank of ``bench_pipeline.py``, read into memory first), k = 9:

* ``measure``: the focus measure alone, whole frame or band by band into one output array;
* ``measure + accumulate``: then the accumulation's per-strip arithmetic (a stand-in for
  :meth:`sffscan.stages.focus_volume.FocusVolume._accumulate`: four ``cv2.scaleAdd`` into
  float32 sums and ``cv2.max`` into the running maximum), on the whole map in strips of the
  same rows, or on each band as it is measured.

Rounds alternate the variants (whole first in even rounds, strip-blocked first in odd
ones), so the machine's load hits them alike; the median of the rounds is reported, with
the spread (min-max). CPU time of the process (OpenCV's threads included) and wall time,
per frame. Every round checks that the two variants give bit-identical maps and sums.
OpenCV runs with ``--cv-threads`` threads (default 1: one worker per core, as the scan's
processes share the cores). Not a test: nothing here asserts; it writes
``bench/results/glvm_results.json`` and ``.md``.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import statistics
import sys
import tempfile
import time
from pathlib import Path

import cv2
import numpy as np
from sffscan.pipeline.heap import keep_freed_memory
from sffscan.stages.focus_measure import focus_measure_raw
from threadpoolctl import threadpool_limits

ROOT = Path(__file__).resolve().parents[1]
WINDOW = 9
COEF = (1.0, 17.0, 0.81, -0.59)  # four sums' weights of one level (any fixed values)


def _accumulate(fm: np.ndarray, sums: list[np.ndarray], best: np.ndarray, r0: int) -> None:
    """The accumulation's arithmetic on rows [r0, r0 + len(fm)) of the state."""
    rows = slice(r0, r0 + fm.shape[0])
    for plane, c in zip(sums, COEF, strict=True):
        view = plane[rows]
        cv2.scaleAdd(fm, c, view, dst=view)
    view = best[rows]
    cv2.max(fm, view, dst=view)


def whole(raw: np.ndarray, state: tuple[list[np.ndarray], np.ndarray] | None,
          strip: int) -> np.ndarray:
    """Today: the whole frame's map, then (with ``state``) its strips accumulated."""
    fm = focus_measure_raw(raw, max_value=1023.0, window=WINDOW)[1]
    if state is not None:
        for r0 in range(0, fm.shape[0], strip):
            _accumulate(fm[r0:r0 + strip], *state, r0)
    return fm


def blocked(raw: np.ndarray, state: tuple[list[np.ndarray], np.ndarray] | None,
            strip: int) -> np.ndarray:
    """Strip-blocked: each band measured on its own, accumulated while in cache."""
    h = raw.shape[0]
    out = np.empty(raw.shape, np.float32)
    for r0 in range(0, h, strip):
        r1 = min(r0 + strip, h)
        fm = focus_measure_raw(raw, max_value=1023.0, window=WINDOW, rows=(r0, r1))[1]
        if state is None:
            out[r0:r1] = fm
        else:
            _accumulate(fm, *state, r0)
    return out


def load_frames(cache: Path, n: int) -> list[np.ndarray]:
    """The first ``n`` frames of ``bench_pipeline.py``'s frame bank (rendered there if no
    bank of at least ``n`` frames is in ``cache``)."""
    h, w = 1024, 1280
    banks = sorted(cache.glob(f"bank-u16-{h}x{w}-*.raw"), key=lambda p: p.stat().st_size)
    bank = next((p for p in banks if p.stat().st_size >= n * h * w * 2), None)
    if bank is None:
        sys.path.insert(0, str(Path(__file__).resolve().parent))
        from bench_pipeline import frame_bank

        bank = frame_bank(cache, n)
    data = np.fromfile(bank, np.uint16, count=n * h * w).reshape(n, h, w)
    return [np.ascontiguousarray(f) for f in data]


def _machine() -> str:
    cpu = platform.machine()
    for line in Path("/proc/cpuinfo").read_text().splitlines():
        if line.startswith("model name"):
            cpu = line.split(":", 1)[1].strip()
            break
    return f"{cpu}, {os.cpu_count()} cores, OpenCV {cv2.__version__}"


def _state(shape: tuple[int, int]) -> tuple[list[np.ndarray], np.ndarray]:
    return [np.zeros(shape, np.float32) for _ in COEF], np.full(shape, -1.0, np.float32)


def run(frames: list[np.ndarray], strips: list[int], rounds: int) -> dict[str, object]:
    shape = frames[0].shape
    cases: dict[str, dict[str, list[float]]] = {}
    identical = True

    def record(name: str, cpu_wall: tuple[float, float]) -> None:
        entry = cases.setdefault(name, {"cpu_ms": [], "wall_ms": []})
        entry["cpu_ms"].append(cpu_wall[0])
        entry["wall_ms"].append(cpu_wall[1])

    for rnd in range(rounds):
        for strip in strips:
            for consumer in (False, True):
                kind = "measure + accumulate" if consumer else "measure"
                results = {}
                order = [("whole", whole), (f"strips of {strip}", blocked)]
                if rnd % 2:
                    order.reverse()
                for label, fn in order:
                    state = _state(shape) if consumer else None
                    c0, w0 = time.process_time(), time.perf_counter()
                    maps = [fn(raw, state, strip) for raw in frames]
                    cpu_wall = ((time.process_time() - c0) / len(frames) * 1e3,
                                (time.perf_counter() - w0) / len(frames) * 1e3)
                    name = f"{kind}, {'whole frame' if label == 'whole' else label}"
                    if label == "whole" and consumer:
                        name += f" (accumulated in strips of {strip})"
                    record(name, cpu_wall)
                    results[label] = (maps, state)
                (m_a, s_a), (m_b, s_b) = results["whole"], results[f"strips of {strip}"]
                if consumer:
                    assert s_a is not None and s_b is not None
                    same = all(np.array_equal(a, b) for a, b in zip(s_a[0], s_b[0], strict=True))
                    identical &= same and np.array_equal(s_a[1], s_b[1])
                else:
                    identical &= all(np.array_equal(a, b) for a, b in zip(m_a, m_b, strict=True))
    summary = {name: {key: {"median": statistics.median(v), "min": min(v), "max": max(v)}
                      for key, v in entry.items()} for name, entry in cases.items()}
    return {"cases": summary, "bit_identical": identical}


def write(result: dict[str, object], out: Path) -> None:
    out.parent.mkdir(parents=True, exist_ok=True)
    out.with_suffix(".json").write_text(json.dumps(result, indent=2) + "\n")
    lines = [
        "# GLVM: whole frames against strip-blocked (bench/bench_glvm.py)",
        "",
        f"Machine: {result['machine']}. Command: `{result['command']}`.",
        f"{result['frames']} distinct 1280 x 1024 uint16 frames, k = {WINDOW}, "
        f"{result['rounds']} interleaved rounds, OpenCV threads: {result['cv_threads']}. "
        f"Bit-identical maps and sums in every round: **{result['bit_identical']}**.",
        "",
        "| case | CPU ms/frame (median, min-max) | wall ms/frame (median, min-max) |",
        "|---|---|---|",
    ]
    cases = result["cases"]
    assert isinstance(cases, dict)
    for name, e in cases.items():
        c, w = e["cpu_ms"], e["wall_ms"]
        lines.append(f"| {name} | {c['median']:.2f} ({c['min']:.2f}-{c['max']:.2f}) | "
                     f"{w['median']:.2f} ({w['min']:.2f}-{w['max']:.2f}) |")
    out.with_suffix(".md").write_text("\n".join(lines) + "\n")


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--frames", type=int, default=12, help="distinct frames per pass")
    ap.add_argument("--rounds", type=int, default=7, help="interleaved rounds")
    ap.add_argument("--strips", default="64,128", help="rows per strip, comma-separated")
    ap.add_argument("--cv-threads", type=int, default=1, help="cv2.setNumThreads")
    ap.add_argument("--cache", type=Path, default=Path(tempfile.gettempdir()) / "sffscan-bench",
                    help="where the rendered frame bank is kept (bench_pipeline.py's)")
    ap.add_argument("--out", type=Path, default=ROOT / "bench" / "results" / "glvm_results.md")
    args = ap.parse_args(argv)
    keep_freed_memory()  # the heap setting of the scan's focus worker (pipeline/heap.py)
    cv2.setNumThreads(args.cv_threads)
    frames = load_frames(args.cache, args.frames)
    with threadpool_limits(1):
        result = run(frames, [int(s) for s in args.strips.split(",")], args.rounds)
    result.update(machine=_machine(), frames=args.frames, rounds=args.rounds,
                  cv_threads=args.cv_threads,
                  command="python bench/bench_glvm.py " + " ".join(argv or sys.argv[1:]))
    write(result, args.out)
    print(args.out.with_suffix(".md").read_text())
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
