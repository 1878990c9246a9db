"""Recorder and mosaic codecs: write throughput for 1280 x 1024 uint16 frames.

The camera makes 150 frames/s of 1280 x 1024 uint16 = 393 MB/s. For each codec of the
frames array, frames go through the recorder's own writer
(:class:`sffscan.pipeline.formats.recording_writer.RecordingWriter`: one chunk per
frame, metadata every 16 frames)
to a temporary folder, by each of its write paths, interleaved (zarr's setitem, the direct
chunk writes of :mod:`sffscan.pipeline.formats.zarr_chunks` through the page cache, and
the same with the frames past it, :mod:`sffscan.pipeline.formats.unbuffered`, the default
since 2026-12-04; ``--repeat`` times): the
median and best of MB/s of raw frame data, CPU ms per frame of the whole process (blosc and
zarr use their own threads), and the compression ratio. The keys section runs the writer with
the chunk keys of recording formats 2 (``c/i/0/0``) and 3 (``c.i.0.0``) the same way, system
time and fsyncs apart (use >= 300 frames so that the 1 s fsyncs happen while writing). Two
other chunk layouts are timed
with plain zarr. Frames are rendered by the simulator (thesis optics, 10-bit
data, sensor noise), so the ratios are those of real-looking frames. The mosaic part
times blending-and-writing a 1024-row band of 256-px chunks of the four float32 arrays.

    python bench/bench_recorder.py [--frames 60] [--repeat 3] [--dir /tmp]
        [--sections writer,keys,layout,mosaic] [--codecs none,blosc-lz4,...] [--out FILE]

Writes (the whole file, only the sections run) ``bench/recorder_results.md``.
"""

from __future__ import annotations

import argparse
import os
import shutil
import sys
import tempfile
import threading
import time
from pathlib import Path
from typing import Any

import numpy as np
import zarr
from sffscan.pipeline.config import demo_config
from sffscan.pipeline.formats.recording_writer import RecordingWriter, frame_codecs
from sffscan.pipeline.mosaic.layout import mosaic_codecs
from sffscan.pipeline.mosaic.writer import MosaicWriter
from sffscan.pipeline.sim_source import simulate_frames
from sffscan.stages.messages import Frame

CAMERA_MB_S = 1280 * 1024 * 2 * 150 / 1e6


def _du(path: Path) -> int:
    return sum(f.stat().st_size for f in path.rglob("*") if f.is_file())


#: variants of the writer: name -> RecordingWriter keywords
WRITE_PATHS: dict[str, dict[str, Any]] = {
    "zarr setitem": {"via_zarr": True, "page_cache": True},
    "zarr_chunks": {"via_zarr": False, "page_cache": True},
    # the default since 2026-12-04 (sffscan.pipeline.formats.unbuffered)
    "zarr_chunks, frames past the page cache": {"via_zarr": False, "page_cache": False}}
KEY_ENCODINGS: dict[str, dict[str, Any]] = {
    "keys c/i/0/0 (format 2)": {"key_separator": "/"},
    "keys c.i.0.0 (format 3)": {"key_separator": "."}}


def bench_writers(frames: list[Frame], codec: str, folder: Path, repeat: int,
                  variants: dict[str, dict[str, Any]] = WRITE_PATHS, *, keep: bool = False
                  ) -> dict[str, dict[str, float]]:
    """Variants of the recorder's writer, interleaved run by run on the same frames (the
    order reversed every other run): per
    variant the median and best MB/s and CPU ms/frame (user + system; the system part
    apart, fsyncs included), the fsyncs made and the compression ratio."""
    cfg = demo_config()
    runs: dict[str, list[dict[str, float]]] = {name: [] for name in variants}

    def record(path: Path, kwargs: dict[str, Any], out: dict[str, float]) -> None:
        w = RecordingWriter(path, cfg, codec=codec, **kwargs)
        c0, s0, t0 = time.process_time(), os.times().system, time.perf_counter()
        w.write(frames[0])  # creates the recording
        c1, s1, t1 = time.process_time(), os.times().system, time.perf_counter()
        for f in frames[1:]:
            w.write(f)
        c2, s2, t2 = time.process_time(), os.times().system, time.perf_counter()
        syncs = w.sync.syncs
        w.close()
        c3, s3, t3 = time.process_time(), os.times().system, time.perf_counter()
        out.update(wall=t3 - t0, cpu=c3 - c0, sys=s3 - s0, steady_wall=t2 - t1,
                   steady_cpu=c2 - c1, steady_sys=s2 - s1, syncs=syncs)

    for k in range(repeat):
        order = list(enumerate(variants.items()))
        for v, (name, kwargs) in order[::-1] if k % 2 else order:  # who goes first alternates
            path = folder / f"rec-{codec}-{k}-{v}.zarr"
            out: dict[str, float] = {}
            # in a thread, as the recorder sink runs in the pipeline (numcodecs' blosc uses
            # its own threads only when called from the main thread)
            t = threading.Thread(target=record, args=(path, kwargs, out))
            t.start()
            t.join()
            out["size"] = _du(path / "frames")
            runs[name].append(out)
            if not keep:
                shutil.rmtree(path)
    raw = sum(f.image.nbytes for f in frames)
    n = len(frames)
    res = {}
    for name, rs in runs.items():
        def col(key: str, rs: list[dict[str, float]] = rs) -> np.ndarray:
            return np.array([r[key] for r in rs])
        walls, cpus, steady = col("wall"), col("cpu"), col("steady_cpu")
        res[name] = {"MB/s": raw / np.median(walls) / 1e6, "MB/s best": raw / walls.min() / 1e6,
                     "fps": n / np.median(walls), "cpu_ms": 1e3 * np.median(cpus) / n,
                     "cpu_ms best": 1e3 * cpus.min() / n,
                     "steady_cpu_ms": 1e3 * np.median(steady) / (n - 1),
                     "steady_cpu_ms best": 1e3 * steady.min() / (n - 1),
                     "steady MB/s": raw * (n - 1) / n / np.median(col("steady_wall")) / 1e6,
                     "sys_ms": 1e3 * np.median(col("sys")) / n,
                     "steady_sys_ms": 1e3 * np.median(col("steady_sys")) / (n - 1),
                     "syncs": float(np.median(col("syncs"))),
                     "ratio": raw / rs[0]["size"]}
    return res


def bench_layout(frames: list[Frame], chunks: tuple[int, int, int], folder: Path,
                 repeat: int) -> dict[str, float]:
    """Plain zarr writes of the frames array alone with another chunk layout (blosc-lz4),
    frames written in groups of chunks[0]."""
    best = None
    n = len(frames) // chunks[0] * chunks[0]
    stack = np.stack([f.image for f in frames[:n]])
    for k in range(repeat):
        path = folder / f"lay-{k}.zarr"
        arr = zarr.create_array(str(path), shape=stack.shape, chunks=chunks, dtype="uint16",
                                compressors=frame_codecs("blosc-lz4"))
        t0 = time.perf_counter()
        for a in range(0, n, chunks[0]):
            arr[a:a + chunks[0]] = stack[a:a + chunks[0]]
        wall = time.perf_counter() - t0
        shutil.rmtree(path)
        best = wall if best is None else min(best, wall)
    assert best is not None
    return {"MB/s": stack.nbytes / best / 1e6, "fps": n / best}


def bench_mosaic(codec: str, folder: Path, repeat: int) -> dict[str, float]:
    rng = np.random.default_rng(0)
    rows, cols = 1024, 256
    w = rng.uniform(0.1, 1.0, (rows, cols))
    new: dict[str, np.ndarray] = {"height": rng.uniform(0, 9800, (rows, cols)) * w,
                                  "texture": rng.uniform(0, 1, (rows, cols)) * w,
                                  "weight": w, "confidence": w.astype(np.float32)}
    best = None
    for k in range(repeat):
        path = folder / f"mos-{codec}-{k}.zarr"
        mw = MosaicWriter(path, origin_px=(0, 0), shape=(rows, cols * 8), pixel_um=8.5,
                          codec=codec)
        c0, t0 = time.process_time(), time.perf_counter()
        for b in range(8):
            mw.write_region(b * cols, 0, new)
        wall, cpu = time.perf_counter() - t0, time.process_time() - c0
        size = sum(_du(path / n) for n in ("height", "texture", "confidence", "weight"))
        shutil.rmtree(path)
        if best is None or wall < best[0]:
            best = (wall, cpu, size)
    assert best is not None
    wall, cpu, size = best
    return {"ms_band": 1e3 * wall / 8, "cpu_ms_band": 1e3 * cpu / 8,
            "ratio": 8 * 4 * rows * cols * 4 / size}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--frames", type=int, default=60)
    ap.add_argument("--repeat", type=int, default=3)
    ap.add_argument("--dir", default=None, help="folder to write in (default: system temp)")
    ap.add_argument("--out", default=str(Path(__file__).with_name("recorder_results.md")))
    ap.add_argument("--sections", default="writer,layout,mosaic",
                    help="comma-separated: writer (its write paths, all codecs), keys (the "
                         "two chunk key encodings of frames and headers, formats 2 and 3), "
                         "layout, mosaic")
    ap.add_argument("--codecs", default="none,blosc-lz4,blosc-zstd,zstd",
                    help="frames codecs of the writer section")
    ap.add_argument("--keep-runs", action="store_true",
                    help="writer section: keep every run's recording until the end (the page "
                         "cache then grows as it does under a long recording) instead of "
                         "deleting each after its run (its pages are then reused)")
    args = ap.parse_args()
    sections = set(args.sections.split(","))
    cfg = demo_config()
    frames = []
    for f in simulate_frames(cfg):
        frames.append(f)
        if len(frames) == args.frames:
            break
    folder = Path(tempfile.mkdtemp(dir=args.dir))
    try:
        lines = [f"# Recorder and mosaic codecs ({args.frames} simulated 1280x1024 uint16 frames, "
                 f"{args.repeat} runs; {os.cpu_count()} CPU(s), load average "
                 f"{os.getloadavg()[0]:.1f} at the start; folder {folder.parent})", "",
                 f"Command: `python bench/bench_recorder.py {' '.join(sys.argv[1:])}`. "
                 f"Camera: 150 frames/s = {CAMERA_MB_S:.0f} MB/s."]
        if "writer" in sections:
            lines += ["", "Recorder's writer, its write paths interleaved run by run, in a "
                      "thread as in the pipeline (median, best in brackets). Whole: from the "
                      "first frame (which creates the recording) to the end of close (fsync "
                      "included); steady: the frames after the first, close excluded. "
                      + ("Every run's recording kept until the end (--keep-runs)."
                         if args.keep_runs else "Each run's recording deleted after it."), "",
                      "| frames codec (1 frame/chunk) | write path | MB/s whole | frames/s "
                      "whole | CPU ms/frame whole | MB/s steady | CPU ms/frame steady | ratio |",
                      "|---|---|---|---|---|---|---|---|"]
            for codec in args.codecs.split(","):
                for name, r in bench_writers(frames, codec, folder, args.repeat,
                                             keep=args.keep_runs).items():
                    lines.append(f"| {codec} | {name} | {r['MB/s']:.0f} ({r['MB/s best']:.0f}) | "
                                 f"{r['fps']:.0f} | {r['cpu_ms']:.1f} ({r['cpu_ms best']:.1f}) | "
                                 f"{r['steady MB/s']:.0f} | {r['steady_cpu_ms']:.2f} "
                                 f"({r['steady_cpu_ms best']:.2f}) | {r['ratio']:.2f} |")
                    print(lines[-1], flush=True)
        if "keys" in sections:
            lines += ["", "Recorder's writer (zarr_chunks), the chunk keys of frames and headers "
                      "of format 2 (`c/i/0/0`, a folder per frame) and format 3 (`c.i.0.0`, "
                      "one folder), interleaved run by run, in a thread (median, best in "
                      "brackets). CPU = user + system of the process; system apart; fsyncs "
                      "every 1 s (`fsync_s`) while writing (count in the table) and at close.",
                      "", "| frames codec | chunk keys | MB/s whole | CPU ms/frame whole | "
                      "system ms/frame whole | CPU ms/frame steady | system ms/frame steady | "
                      "syncs while writing |", "|---|---|---|---|---|---|---|---|"]
            for codec in args.codecs.split(","):
                for name, r in bench_writers(frames, codec, folder, args.repeat,
                                             KEY_ENCODINGS).items():
                    lines.append(f"| {codec} | {name} | {r['MB/s']:.0f} ({r['MB/s best']:.0f}) | "
                                 f"{r['cpu_ms']:.2f} ({r['cpu_ms best']:.2f}) | "
                                 f"{r['sys_ms']:.2f} | {r['steady_cpu_ms']:.2f} "
                                 f"({r['steady_cpu_ms best']:.2f}) | {r['steady_sys_ms']:.2f} | "
                                 f"{r['syncs']:.0f} |")
                    print(lines[-1], flush=True)
        if "layout" in sections:
            lines += ["", "| frames chunk layout (blosc-lz4, plain zarr, best) | MB/s | "
                      "frames/s |", "|---|---|---|"]
        layouts = ((1, 1024, 1280), (4, 1024, 1280), (1, 256, 1280))
        for chunks in layouts if "layout" in sections else ():
            r = bench_layout(frames, chunks, folder, args.repeat)
            lines.append(f"| {chunks} | {r['MB/s']:.0f} | {r['fps']:.0f} |")
            print(lines[-1], flush=True)
        if "mosaic" in sections:
            lines += ["", "| mosaic codec (4 float32 arrays, 1024 x 256 band, journaled, best) | "
                      "ms/band | CPU ms/band | ratio |", "|---|---|---|---|"]
        for codec in ("zstd", "blosc-lz4", "none") if "mosaic" in sections else ():
            mosaic_codecs(codec)
            r = bench_mosaic(codec, folder, args.repeat)
            lines.append(f"| {codec} | {r['ms_band']:.1f} | {r['cpu_ms_band']:.1f} | "
                         f"{r['ratio']:.2f} |")
            print(lines[-1], flush=True)
    finally:
        shutil.rmtree(folder, ignore_errors=True)
    Path(args.out).write_text("\n".join(lines) + "\n", encoding="utf-8")
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
