"""Streaming cost of the mosaic's resolution pyramid: end-to-end frames/s with and without it.

The frames of a recording are read into memory once (so neither the disk nor the
decoding is the limit, which would hide the pyramid's cost) and run through the whole
pipeline (``run_scan``: speed shift, registration, focus measure, focus volume, depth,
mosaic) alternately with the pyramid (the default levels, kept current through the writer's
write-back cache of upper-level chunks, :class:`sffscan.pipeline.mosaic.pyramid.PyramidCache`)
and without it (``levels=1``: level 0 only, the mosaic of format version 1 plus NGFF
metadata). Runs are interleaved
(ABBA...), so a change of the machine's load hits both variants alike; the 1-minute load
average is recorded beside each run. Reported: median end-to-end frames/s of each variant,
their ratio, the CPU time per frame of the main process (source, speed shift and the mosaic
stage, where the pyramid's work happens; the registration and focus/depth worker
processes of the process runtime are not counted) and the mosaic stage's busy time.

    python bench/bench_pyramid.py RECORDING [--pairs 3] [--dir /tmp] [--depth-method adaptive]

The depth method is today's default unless ``--depth-method`` names another (a recording
keeps the method it was made with).

A demo-sized recording: ``sffscan demo --passes 2 --viewer off -o d.zarr --record rec.zarr``.
Writes ``bench/pyramid_results.md`` and ``bench/pyramid_results.json``.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import resource
import shutil
import statistics
import tempfile
import time
from pathlib import Path
from typing import Any

import zarr
from sffscan.pipeline import wiring
from sffscan.pipeline.config import ScanConfig
from sffscan.pipeline.formats.recording_reader import open_recording
from sffscan.pipeline.mosaic.writer import MosaicWriter
from sffscan.stages.depth import DEFAULT_METHOD, DEPTH_METHODS
from sffscan.stages.messages import Frame


def one_run(cfg: ScanConfig, frames: list[Frame], out: Path, *, pyramid: bool
            ) -> dict[str, Any]:
    # the pipeline's own writer factory, with the pyramid switched off for the baseline
    made: list[MosaicWriter] = []

    def factory(*args: Any, **kwargs: Any) -> MosaicWriter:
        made.append(MosaicWriter(*args, **kwargs) if pyramid
                    else MosaicWriter(*args, levels=1, **kwargs))
        return made[-1]

    load = os.getloadavg()[0]
    cpu0 = time.process_time()
    children0 = resource.getrusage(resource.RUSAGE_CHILDREN)
    orig = wiring.MosaicWriter
    wiring.MosaicWriter = factory  # type: ignore[misc, assignment]
    try:
        report = wiring.run_scan(cfg, frames=iter(frames), output=out, overwrite=True,
                                 progress=False)
    finally:
        wiring.MosaicWriter = orig  # type: ignore[misc]
    # every thread of this process (zarr's too): the source, speed shift and mosaic; with
    # the process runtime (execution auto), the registration and focus/depth workers are
    # other processes, not counted
    cpu = time.process_time() - cpu0
    # the worker processes, once joined (the process runtime joins them at the end)
    children1 = resource.getrusage(resource.RUSAGE_CHILDREN)
    workers = (children1.ru_utime + children1.ru_stime
               - children0.ru_utime - children0.ru_stime)
    cache = made[0].cache
    r = report.result
    mosaic = next(s for s in r.stages if s.name == "mosaic")
    g = zarr.open_group(str(out), mode="r")
    ome: Any = g.attrs["ome"]
    levels = len(ome["multiscales"][0]["datasets"])
    shutil.rmtree(out)
    return {"pyramid": pyramid, "levels": levels, "frames": report.frames,
            "wall_s": r.wall_s, "fps": report.frames / r.wall_s,
            "process_cpu_ms_per_frame": 1e3 * cpu / report.frames,  # main process only
            "all_cpu_ms_per_frame": 1e3 * (cpu + workers) / report.frames,
            "pyramid_chunks_written": cache.chunks_written if cache is not None else 0,
            "pyramid_chunks_read": cache.chunks_read if cache is not None else 0,
            "mosaic_busy_s": mosaic.busy_s, "mosaic_cpu_s": mosaic.cpu_s,
            "load_1min_before": load, "load_1min_after": os.getloadavg()[0]}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("recording", type=Path)
    ap.add_argument("--pairs", type=int, default=3, help="pairs of runs (with, without)")
    ap.add_argument("--dir", type=Path, default=None, help="folder of the temporary mosaics")
    ap.add_argument("--out", type=Path, default=Path(__file__).parent / "pyramid_results")
    ap.add_argument("--depth-method", default=DEFAULT_METHOD, choices=DEPTH_METHODS)
    args = ap.parse_args()
    rec = open_recording(args.recording)
    cfg = rec.config.model_copy(update={"processing": rec.config.processing.model_copy(
        update={"depth_method": args.depth_method})})
    frames = list(rec.frames())
    runs = []
    with tempfile.TemporaryDirectory(dir=args.dir) as tmp:
        for i in range(args.pairs):
            order = (True, False) if i % 2 == 0 else (False, True)  # ABBA...
            for pyramid in order:
                run = one_run(cfg, frames, Path(tmp) / f"m{i}{int(pyramid)}.zarr",
                              pyramid=pyramid)
                runs.append(run)
                print(f"pair {i} pyramid={pyramid!s:<5} levels {run['levels']}  "
                      f"{run['fps']:.2f} frames/s  mosaic busy {run['mosaic_busy_s']:.2f} s  "
                      f"load {run['load_1min_before']:.2f}", flush=True)
    on = [r for r in runs if r["pyramid"]]
    off = [r for r in runs if not r["pyramid"]]
    med = {k: statistics.median(r["fps"] for r in v) for k, v in (("on", on), ("off", off))}
    pair_ratios = [a["fps"] / b["fps"] for a, b in zip(on, off, strict=True)]
    summary = {
        "recording": str(args.recording), "frames": runs[0]["frames"],
        "depth_method": args.depth_method,
        "machine": f"{platform.processor() or platform.machine()}, {os.cpu_count()} cores",
        "fps_with_pyramid_median": med["on"], "fps_without_median": med["off"],
        "ratio_of_medians": med["on"] / med["off"], "pair_ratios": pair_ratios,
        "cpu_ms_per_frame_with_median": statistics.median(
            r["process_cpu_ms_per_frame"] for r in on),
        "cpu_ms_per_frame_without_median": statistics.median(
            r["process_cpu_ms_per_frame"] for r in off),
        "all_cpu_ms_per_frame_with_median": statistics.median(
            r["all_cpu_ms_per_frame"] for r in on),
        "all_cpu_ms_per_frame_without_median": statistics.median(
            r["all_cpu_ms_per_frame"] for r in off),
        "mosaic_busy_s_with": statistics.median(r["mosaic_busy_s"] for r in on),
        "mosaic_busy_s_without": statistics.median(r["mosaic_busy_s"] for r in off),
        "runs": runs,
    }
    args.out.with_suffix(".json").write_text(json.dumps(summary, indent=2))
    lines = ["# Streaming cost of the mosaic pyramid", "",
             f"`python bench/bench_pyramid.py {args.recording} --pairs {args.pairs}`, "
             f"depth method {args.depth_method}, {summary['machine']}; "
             f"{summary['frames']} frames per run (held in memory), runs "
             "interleaved (ABBA); load = the 1-minute load average before the run.", "",
             "| pair | pyramid | levels | frames/s | main-process CPU ms/frame | all processes "
             "CPU ms/frame | mosaic busy s | pyramid chunks written / read | load (1 min) |",
             "|---|---|---|---|---|---|---|---|---|"]
    for i, r in enumerate(runs):
        lines.append(f"| {i // 2} | {'yes' if r['pyramid'] else 'no'} | {r['levels']} | "
                     f"{r['fps']:.2f} | {r['process_cpu_ms_per_frame']:.2f} | "
                     f"{r['all_cpu_ms_per_frame']:.1f} | {r['mosaic_busy_s']:.2f} | "
                     f"{r['pyramid_chunks_written']} / {r['pyramid_chunks_read']} | "
                     f"{r['load_1min_before']:.2f} |")
    lines += ["", f"Median frames/s: {med['on']:.2f} with the pyramid, {med['off']:.2f} "
              f"without: ratio {summary['ratio_of_medians']:.3f} (pairs: "
              + ", ".join(f"{x:.3f}" for x in pair_ratios) + "). Main-process CPU per frame "
              f"(median): {summary['cpu_ms_per_frame_with_median']:.2f} ms with, "
              f"{summary['cpu_ms_per_frame_without_median']:.2f} ms without; all processes "
              f"(main and workers): {summary['all_cpu_ms_per_frame_with_median']:.1f} ms "
              f"with, {summary['all_cpu_ms_per_frame_without_median']:.1f} ms without. A "
              "pyramid chunk written or read counts its four arrays once."]
    args.out.with_suffix(".md").write_text("\n".join(lines) + "\n")
    print("\n".join(lines))


if __name__ == "__main__":
    main()
