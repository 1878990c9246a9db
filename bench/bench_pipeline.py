"""Throughput benchmark: frames/s per stage and end to end, against the thesis baseline.

Frames come from memory (a bank of simulated frames rendered once, then replayed with the
scan plan's headers), so the simulator is not the limit. One run measures, for 1280x1024
frames, N = 50, k = 9:

- the thesis-style torch conv2d GLVM (dense k x k kernel) as the baseline, frames/s;
- each focus measure implementation alone (OpenCV, torch) for GLVM and TENV;
- the whole pipeline end to end (source -> speed shift -> [registration] -> focus measure
  -> SPC depth -> Zarr mosaic), with and without registration, uint8 and uint16 frames;
  per-stage frames/s from each stage's own busy time.

    python bench/bench_pipeline.py --out bench/results.md

Figures depend on the machine: the table names it. Not a test: nothing here asserts.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import resource
import sys
import tempfile
import time
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import torch

from pipeline.config import ScanConfig, demo_config
from pipeline.messages import Frame
from pipeline.plan import plan_frames
from pipeline.wiring import run_scan
from stages.focus_measure import glvm, glvm_conv2d_baseline, glvm_cv, tenv, tenv_cv
from stages.sim_scanner import header_of, simulate_frames


def machine() -> str:
    cpu = platform.processor() or platform.machine()
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                cpu = line.split(":", 1)[1].strip()
                break
    except OSError:
        pass
    return (f"{cpu}, {os.cpu_count()} cores, torch {torch.__version__} "
            f"({torch.get_num_threads()} threads), Python {platform.python_version()}")


def frame_bank(cfg: ScanConfig, count: int) -> list[np.ndarray]:
    out = []
    for i, frame in enumerate(simulate_frames(cfg)):
        if i >= count:
            break
        out.append(frame.image)
    return out


def memory_frames(cfg: ScanConfig, bank: list[np.ndarray], n: int) -> Iterator[Frame]:
    for i, pf in enumerate(plan_frames(cfg)):
        if i >= n:
            return
        yield Frame(header_of(cfg, pf), bank[i % len(bank)])


def rate(fn, images: list[np.ndarray], *, repeat: int = 3) -> float:  # noqa: ANN001
    """Frames/s of ``fn`` over ``images``: the best of ``repeat`` passes (this VM is noisy)."""
    fn(images[0])  # warm up
    best = 0.0
    for _ in range(repeat):
        t0 = time.perf_counter()
        for img in images:
            fn(img)
        best = max(best, len(images) / (time.perf_counter() - t0))
    return best


def focus_rates(bank01: list[np.ndarray], baseline_frames: int) -> dict[str, float]:
    tens = [torch.from_numpy(b) for b in bank01]
    with torch.inference_mode():
        return {
            "thesis torch conv2d GLVM (baseline)":
                rate(lambda t: glvm_conv2d_baseline(t, window=9), tens[:baseline_frames]),
            "GLVM OpenCV": rate(lambda a: glvm_cv(a, window=9), bank01),
            "GLVM torch": rate(lambda t: glvm(t, window=9), tens),
            "TENV OpenCV": rate(lambda a: tenv_cv(a, window=9), bank01),
            "TENV torch": rate(lambda t: tenv(t, window=9), tens),
        }


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--frames", type=int, default=600, help="frames per end-to-end run")
    ap.add_argument("--bank", type=int, default=100, help="distinct frames rendered")
    ap.add_argument("--out", type=Path, default=Path("bench/results.md"))
    args = ap.parse_args(argv)

    print(f"machine: {machine()}", file=sys.stderr)
    rows: list[tuple[str, str, float, str]] = []
    results: dict[str, object] = {"machine": machine()}
    cfg10 = demo_config(motion={"x_end_mm": 200.0}, source={"plate_length_mm": 200.0})
    t0 = time.perf_counter()
    bank16 = frame_bank(cfg10, args.bank)
    print(f"rendered {len(bank16)} frames in {time.perf_counter() - t0:.1f} s", file=sys.stderr)
    bank8 = [(b.astype(np.float32) * (255.0 / 1023.0)).round().astype(np.uint8) for b in bank16]
    bank01 = [b.astype(np.float32) / 1023.0 for b in bank16[:40]]

    fr = focus_rates(bank01, baseline_frames=10)
    base = fr["thesis torch conv2d GLVM (baseline)"]
    for name, value in fr.items():
        rows.append(("focus measure alone", name, value, f"{value / base:.1f}x baseline"))
    results["focus_measure_fps"] = fr

    for bits, bank in ((10, bank16), (8, bank8)):
        for registration in (False, True):
            cfg = demo_config(optics={"bit_depth": bits},
                              processing={"registration": registration},
                              motion={"x_end_mm": 200.0}, source={"plate_length_mm": 200.0})
            with tempfile.TemporaryDirectory() as tmp:
                rep = run_scan(cfg, frames=memory_frames(cfg, bank, args.frames),
                               output=Path(tmp) / "m.zarr", progress=False)
            r = rep.result
            e2e = rep.frames / r.wall_s
            label = f"uint{16 if bits == 10 else 8}, registration {'on' if registration else 'off'}"
            rows.append(("end to end", label, e2e, f"{e2e / base:.1f}x baseline"))
            for s in r.stages:
                if s.name != "source":
                    rows.append((f"stage ({label})", s.name, s.frames_per_s,
                                 f"{s.unit}/s, own busy time"))
            results[f"e2e {label}"] = {"fps": e2e, "stages": {s.name: s.frames_per_s
                                                             for s in r.stages}}
            print(f"{label}: {e2e:.1f} frames/s end to end", file=sys.stderr)
    peak_mb = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
    results["peak_rss_mb"] = peak_mb

    lines = [f"# sffscan benchmark ({time.strftime('%Y-%m-%d')})", "",
             f"Machine: {machine()}", "",
             f"1280x1024 frames, N = 50, k = 9, SPC, {args.frames} frames per end-to-end run "
             "from memory; peak RSS of the whole benchmark process "
             f"{peak_mb:.0f} MB.", "",
             "| what | case | frames/s | note |", "|---|---|---:|---|"]
    lines += [f"| {a} | {b} | {v:.1f} | {n} |" for a, b, v, n in rows]
    text = "\n".join(lines) + "\n"
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(text)
    args.out.with_suffix(".json").write_text(json.dumps(results, indent=2) + "\n")
    print(text)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
