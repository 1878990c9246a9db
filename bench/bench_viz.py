"""Overhead of the live view: end-to-end frames/s with and without the viewer sink.

Frames come from memory (a bank of simulated 1280 x 1024 frames rendered once, replayed
with the scan plan's headers; demo optics, N = 50, GLVM k = 9, SPC, registration on), so
the simulator is not the limit. Cases, interleaved and repeated (this VM is noisy):

- ``off``: no viewer;
- ``save``: the viewer sink writing an .rrd recording (what the viewer gets, to disk);
- ``serve``: the viewer sink serving the web viewer (gRPC server in this process, no
  browser connected: the server buffers everything).

For each case: end-to-end frames/s (median and best of the repeats), the CPU time of the
whole process per frame (all threads, Rerun's included: the figure that does not depend on
what else runs on the machine), the viewer sink thread's own CPU time per frame, items the
viewer dropped, and the .rrd size.

    python bench/bench_viz.py --out bench/viz_results.md

Not a test: nothing here asserts.
"""

from __future__ import annotations

import argparse
import contextlib
import json
import os
import platform
import statistics
import sys
import tempfile
import time
from collections.abc import Iterator
from pathlib import Path

import numpy as np
from sffscan.pipeline.config import ScanConfig, demo_config
from sffscan.pipeline.plan import plan_frames
from sffscan.pipeline.sim_source import header_of, simulate_frames
from sffscan.pipeline.viz.sink import VizSink, open_recording
from sffscan.pipeline.wiring import run_scan
from sffscan.stages.messages import Frame
from sffscan.stages.protocol import Sink


def machine() -> str:
    cpu = platform.processor() or platform.machine()
    with contextlib.suppress(OSError):
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                cpu = line.split(":", 1)[1].strip()
                break
    return f"{cpu}, {os.cpu_count()} cores, Python {platform.python_version()}"


def frame_bank(cfg: ScanConfig, count: int) -> list[np.ndarray]:
    """``count`` simulated frames, rendered once."""
    out = []
    for i, frame in enumerate(simulate_frames(cfg)):
        if i >= count:
            break
        out.append(frame.image)
    return out


def memory_frames(cfg: ScanConfig, bank: list[np.ndarray], n: int) -> Iterator[Frame]:
    """``n`` frames with the scan plan's headers, images cycled from ``bank``."""
    for i, pf in enumerate(plan_frames(cfg)):
        if i >= n:
            return
        yield Frame(header_of(cfg, pf), bank[i % len(bank)])


def one_run(case: str, bank: list[np.ndarray], frames: int, tmp: Path) -> dict[str, float]:
    cfg = demo_config(motion={"x_end_mm": 200.0}, source={"plate_length_mm": 200.0})
    sinks: list[Sink] = []
    rrd = tmp / f"{case}.rrd"
    if case != "off":
        mode = ["save", str(rrd)] if case == "save" else ["serve"]
        rec, _ = open_recording(mode)
        sinks.append(VizSink(cfg, rec))
    c0 = time.process_time()
    rep = run_scan(cfg, frames=memory_frames(cfg, bank, frames), output=tmp / "m.zarr",
                   overwrite=True, progress=False, sinks=sinks)
    if sinks:
        time.sleep(0.5)  # let Rerun's own threads finish encoding and writing
    cpu = time.process_time() - c0
    r = rep.result
    out = {"fps": rep.frames / r.wall_s, "frames": float(rep.frames),
           "process_cpu_ms_per_frame": 1000 * cpu / rep.frames, "load1": os.getloadavg()[0]}
    for s in r.stages:
        if s.name == "viewer":
            out["viewer_cpu_ms_per_frame"] = 1000 * s.cpu_s / rep.frames
            out["viewer_busy_ms_per_frame"] = 1000 * s.busy_s / rep.frames
    for q in r.queues:
        if q.name.endswith("->viewer"):
            out["viewer_dropped"] = float(q.dropped)
            out["viewer_items"] = float(q.puts)
    if rrd.exists():
        out["rrd_mb"] = rrd.stat().st_size / 1e6
        rrd.unlink()
    return out


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--frames", type=int, default=600, help="frames per run")
    ap.add_argument("--bank", type=int, default=100, help="distinct frames rendered")
    ap.add_argument("--repeat", type=int, default=3, help="runs per case, interleaved")
    ap.add_argument("--cases", default="off,save,serve")
    ap.add_argument("--out", type=Path, default=Path("bench/viz_results.md"))
    args = ap.parse_args(argv)

    print(f"machine: {machine()}", file=sys.stderr)
    cfg = demo_config(motion={"x_end_mm": 200.0}, source={"plate_length_mm": 200.0})
    bank = frame_bank(cfg, args.bank)
    cases = args.cases.split(",")
    runs: dict[str, list[dict[str, float]]] = {c: [] for c in cases}
    with tempfile.TemporaryDirectory() as tmpdir:
        for i in range(args.repeat):
            for case in cases:
                res = one_run(case, bank, args.frames, Path(tmpdir))
                runs[case].append(res)
                print(f"run {i + 1} {case}: {res['fps']:.1f} frames/s "
                      f"{ {k: round(v, 2) for k, v in res.items() if k != 'fps'} }",
                      file=sys.stderr)

    base = statistics.median(r["fps"] for r in runs["off"]) if "off" in runs else None
    lines = [f"# Live view overhead ({time.strftime('%Y-%m-%d')})", "",
             f"Machine: {machine()}", "",
             f"{args.frames} frames of 1280 x 1024 px (uint16, 10 bit) from memory, demo optics, "
             "N = 50, GLVM k = 9, SPC, registration on; "
             f"{args.repeat} runs per case, interleaved. `python bench/bench_viz.py`.", "",
             "| viewer | frames/s median | best | vs off (median) | process CPU ms/frame "
             "| viewer thread CPU ms/frame | viewer dropped / items | .rrd MB |",
             "|---|---:|---:|---:|---:|---:|---:|---:|"]
    for case, rs in runs.items():
        fps = [r["fps"] for r in rs]
        med = statistics.median(fps)
        rel = f"{100 * (med / base - 1):+.1f} %" if base else "-"
        cpu = statistics.median(r.get("viewer_cpu_ms_per_frame", 0.0) for r in rs)
        pcpu = statistics.median(r["process_cpu_ms_per_frame"] for r in rs)
        drop = "/".join(str(int(r.get("viewer_dropped", 0))) for r in rs)
        items = int(rs[0].get("viewer_items", 0))
        mb = statistics.median(r.get("rrd_mb", 0.0) for r in rs)
        lines.append(f"| {case} | {med:.1f} | {max(fps):.1f} | {rel} | {pcpu:.1f} | "
                     f"{cpu:.2f} | {drop} / {items} | {mb:.1f} |")
    loads = [r["load1"] for rs in runs.values() for r in rs]
    lines += ["", f"1-minute load average after each run: {min(loads):.1f} to {max(loads):.1f} "
              f"on {os.cpu_count()} cores (other work on the machine slows every case)."]
    text = "\n".join(lines) + "\n"
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(text)
    args.out.with_suffix(".json").write_text(json.dumps({"machine": machine(), "runs": runs},
                                                        indent=2) + "\n")
    print(text)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
