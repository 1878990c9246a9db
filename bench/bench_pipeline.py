"""Throughput benchmark: frames/s per stage and end to end, against the thesis baseline.

One command writes the whole table (``bench/results.md``, and ``bench/results.json``)::

    python bench/bench_pipeline.py

For 1280x1024 frames, N = 50, k = 9, SPC it measures, in one run:

- the thesis-style torch conv2d GLVM (dense k x k kernel): the baseline, frames/s;
- each focus measure alone (OpenCV on the scaled image, the raw-frame fast path the focus
  stage uses, torch CPU), GLVM and TENV;
- the whole pipeline end to end (source -> speed shift -> [registration] -> focus measure
  -> SPC depth -> Zarr mosaic; no viewer, no recorder) for uint16 and uint8 frames, GLVM
  and TENV, registration on and off: frames/s (best of ``--repeat`` runs), CPU per frame
  of each stage's thread and of the whole process (Zarr's codec threads included), and the
  peak resident memory of the run;
- time against frame count (should be linear) and peak memory against scan length
  (should be flat);
- on a CUDA device, if torch sees one: focus measure + depth accumulation in batches.

Frames are distinct simulated frames, rendered once into a file (cached in ``--cache``) and
read into memory before each run, so neither the simulator nor the source is the limit.
Each end-to-end run is a fresh subprocess, so its peak RSS is its own (reported without
the frames held in memory). Figures depend on the
machine (the table names it) and on what else runs on it: every run is repeated and the
best kept; CPU time per frame is the steadier figure. Not a test: nothing here asserts.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import resource
import subprocess
import sys
import tempfile
import time
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import numpy as np
import torch
from sffscan.pipeline.config import ScanConfig, demo_config
from sffscan.pipeline.measuring import measure_stages
from sffscan.pipeline.plan import pass_start_px, plan_frames
from sffscan.pipeline.sim_source import header_of, simulate_frames
from sffscan.pipeline.wiring import run_scan
from sffscan.stages.focus_measure import focus_measure_raw, to_unit_float
from sffscan.stages.focus_torch import glvm, glvm_conv2d_baseline, tenv
from sffscan.stages.messages import Frame, PlacedFrame
from sffscan.stages.operators.opencv import glvm_cv, tenv_cv
from sffscan.stages.protocol import Stage
from sffscan.stages.speed_shift import SpeedShiftStage

ROOT = Path(__file__).resolve().parents[1]


def machine() -> str:
    cpu = platform.processor() or platform.machine()
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                cpu = line.split(":", 1)[1].strip()
                break
    except OSError:
        pass
    mem = ""
    try:
        kb = int(Path("/proc/meminfo").read_text().split()[1])
        mem = f", {kb / 2**20:.0f} GiB"
    except (OSError, ValueError, IndexError):
        pass
    return (f"{cpu}, {os.cpu_count()} cores{mem}, torch {torch.__version__} "
            f"({torch.get_num_threads()} threads), Python {platform.python_version()}")


def bench_config(*, bits: int = 10, registration: bool = True, operator: str = "glvm",
                 method: str = "spc") -> ScanConfig:
    """The demo optics (1280x1024, N = 50, 15 mm/s) on a plate long enough for the runs."""
    return demo_config(optics={"bit_depth": bits}, motion={"x_end_mm": 400.0},
                       source={"plate_length_mm": 400.0},
                       processing={"registration": registration, "focus_operator": operator,
                                   "depth_method": method,
                                   # this benchmark measures the thread runtime (one
                                   # process's CPU); bench_parallel.py compares both
                                   "execution": "threads"})


def bank_path(cache: Path, count: int, bits: int) -> Path:
    return cache / f"bank-u{16 if bits == 10 else 8}-1024x1280-{count}.raw"


def frame_bank(cache: Path, count: int) -> Path:
    """Files of ``count`` distinct simulated frames, 10-bit in uint16 and the same scaled to
    uint8 (rendered once, then cached); returns the uint16 one."""
    cfg = bench_config()
    h, w = cfg.optics.height_px, cfg.optics.width_px
    for n in sorted(int(f.stem.rsplit("-", 1)[1]) for f in cache.glob("bank-u16-*.raw")):
        p16, p8 = bank_path(cache, n, 10), bank_path(cache, n, 8)
        if (n >= count and p8.is_file() and p16.stat().st_size == n * h * w * 2
                and p8.stat().st_size == n * h * w):
            return p16  # a bank with enough frames is there already
    p16, p8 = bank_path(cache, count, 10), bank_path(cache, count, 8)
    cache.mkdir(parents=True, exist_ok=True)
    t0 = time.perf_counter()
    lut = np.round(np.arange(1024) * (255.0 / 1023.0)).astype(np.uint8)
    with p16.with_suffix(".part16").open("wb") as f16, p8.with_suffix(".part8").open("wb") as f8:
        for i, frame in enumerate(rendered_frames(cfg)):
            if i >= count:
                break
            img = np.ascontiguousarray(frame.image, np.uint16)
            f16.write(img.tobytes())
            f8.write(lut[img].tobytes())
            if i % 100 == 99:
                print(f"  rendered {i + 1}/{count} frames", file=sys.stderr)
    p16.with_suffix(".part16").rename(p16)
    p8.with_suffix(".part8").rename(p8)
    print(f"rendered {count} frames in {time.perf_counter() - t0:.0f} s -> {p16}",
          file=sys.stderr)
    return p16


def rendered_frames(cfg: ScanConfig) -> Iterator[Frame]:
    """The scan's simulated frames, rendered by worker processes where there are more than
    2 cores (one per core but one, at most 8: the same frames, ``test_parallel``), else here
    (~0.1 s a full-size frame on the dev VM)."""
    workers = min(8, len(os.sched_getaffinity(0)) - 1)
    if workers < 2:
        return simulate_frames(cfg)
    from sffscan.pipeline.sim_workers import parallel_sim_frames

    return parallel_sim_frames(cfg, workers=workers)


def load_bank(cfg: ScanConfig, bank: Path, n: int) -> list[np.ndarray]:
    """The first ``n`` frames of the bank file, in memory (read before the run starts)."""
    h, w = cfg.optics.height_px, cfg.optics.width_px
    dtype = np.dtype(cfg.optics.dtype)
    data = np.fromfile(bank, dtype, count=n * h * w)
    if data.size != n * h * w:
        raise ValueError(f"{bank}: holds fewer than {n} frames")
    return list(data.reshape(n, h, w))


def replay_frames(cfg: ScanConfig, images: list[np.ndarray]) -> Iterator[Frame]:
    """The plan's first ``len(images)`` frames with these images (from memory)."""
    for image, pf in zip(images, plan_frames(cfg), strict=False):
        yield Frame(header_of(cfg, pf), image)


def placed_frames(cfg: ScanConfig, images: list[np.ndarray], *, register: bool = True
                  ) -> tuple[list[PlacedFrame], dict[str, Stage]]:
    """The frames placed by the speed shift and, with ``register`` where the
    configuration registers, by its registration stage (all of it, its end included);
    and the configuration's measuring stages (:func:`sffscan.pipeline.measuring.measure_stages`)
    by name, for the benchmark to run or copy."""
    built = {s.name: s for s in measure_stages(cfg)}
    shift = SpeedShiftStage(pixel_um=cfg.optics.pixel_um, speed_mm_s=cfg.motion.speed_mm_s,
                            pass_start=lambda i: pass_start_px(cfg, i))
    placed = [y for f in replay_frames(cfg, images) for y in shift.process(f)]
    reg = built.get("registration") if register else None
    if reg is not None:
        placed = [y for q in placed for y in reg.process(q)] + list(reg.finish())
    return placed, built


def run_case(case: dict[str, Any]) -> dict[str, Any]:
    """One end-to-end run (call in a fresh process): frames/s, CPU per frame, peak RSS.

    The frames are read into memory first, so the source costs nothing; the peak RSS
    reported for the pipeline is the process's peak minus those frames' bytes.
    """
    cfg = bench_config(bits=case["bits"], registration=case["registration"],
                       operator=case["operator"])
    bank = Path(case["bank"].replace("-u16-", "-u16-" if case["bits"] == 10 else "-u8-"))
    images = load_bank(cfg, bank, case["frames"])
    bank_mb = sum(i.nbytes for i in images) / 2**20
    best: dict[str, Any] | None = None
    for _ in range(case["repeat"]):
        ru0 = resource.getrusage(resource.RUSAGE_SELF)
        with tempfile.TemporaryDirectory() as tmp:
            rep = run_scan(cfg, frames=replay_frames(cfg, images),
                           output=Path(tmp) / "m.zarr", progress=False)
        ru1 = resource.getrusage(resource.RUSAGE_SELF)
        r = rep.result
        out = {
            "frames": rep.frames, "wall_s": r.wall_s, "fps": rep.frames / r.wall_s,
            "dropped": r.dropped,
            "process_cpu_ms": 1e3 * (ru1.ru_utime + ru1.ru_stime - ru0.ru_utime
                                     - ru0.ru_stime) / rep.frames,
            "stages": {s.name: {"cpu_ms_per_frame": 1e3 * s.cpu_s / rep.frames,
                                "items": s.frames, "busy_s": s.busy_s,
                                "items_per_busy_s": s.frames_per_s, "unit": s.unit}
                       for s in r.stages},
        }
        if best is None or out["fps"] > best["fps"]:
            best = out
    assert best is not None
    peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
    best["peak_rss_mb"] = peak - bank_mb
    best["frame_bank_mb"] = bank_mb
    return best


def scan_figures(rep: Any, cpu_s: float) -> dict[str, Any]:
    """A :func:`run_scan` report's frames, frames/s, CPU per frame (ms: every process's CPU
    while streaming where the placement counts it, else ``cpu_s``), drops, each stage's
    own CPU per frame (ms), its wall time inside its own code per frame (``busy``, ms: the
    stage whose busy time is nearest the frame period is the one that sets it) and each
    queue's mean fill at a put (a full queue's consumer is behind)."""
    r = rep.result
    cpu = r.extras.get("processes", {}).get("cpu_s") or cpu_s
    n = max(1, rep.frames)
    return {"frames": rep.frames, "fps": rep.frames / r.wall_s,
            "cpu_ms_per_frame": 1e3 * cpu / rep.frames, "dropped": r.dropped,
            "stages": {s.name: round(1e3 * s.cpu_s / n, 2) for s in r.stages},
            "busy": {s.name: round(1e3 * s.busy_s / n, 2) for s in r.stages},
            "queues": {q.name: [round(q.mean_fill, 2), q.capacity] for q in r.queues}}


def spawn_case(case: dict[str, Any]) -> dict[str, Any]:
    cmd = [sys.executable, str(Path(__file__).resolve()), "--case", json.dumps(case)]
    env = {**os.environ, "PYTHONPATH": os.pathsep.join(
        [str(ROOT), os.environ.get("PYTHONPATH", "")]).rstrip(os.pathsep)}
    done = subprocess.run(cmd, capture_output=True, text=True, env=env, check=False)
    if done.returncode != 0:
        raise RuntimeError(f"case {case} failed:\n{done.stderr[-3000:]}")
    return json.loads(done.stdout.strip().splitlines()[-1])


def rate(fn: Callable[[Any], Any], images: list[Any], *, repeat: int = 3) -> float:
    """Frames/s of ``fn`` over ``images``: the best of ``repeat`` passes."""
    fn(images[0])  # warm up
    best = 0.0
    for _ in range(repeat):
        t0 = time.perf_counter()
        for img in images:
            fn(img)
        best = max(best, len(images) / (time.perf_counter() - t0))
    return best


def focus_rates(raw16: list[np.ndarray], baseline_frames: int) -> dict[str, float]:
    """Focus measure alone, frames/s (best of 3): whole 1280x1024 frames, and the column
    range the focus stage measures at 15 mm/s (the columns that can still be new, 48 %)."""
    f01 = [r.astype(np.float32) / 1023.0 for r in raw16]
    tens = [torch.from_numpy(b) for b in f01]
    part = slice(300, 300 + 620)
    with torch.inference_mode():
        return {
            "thesis torch conv2d GLVM (baseline)":
                rate(lambda t: glvm_conv2d_baseline(t, window=9), tens[:baseline_frames]),
            "GLVM OpenCV, whole frame (scaled image given)":
                rate(lambda a: glvm_cv(a, window=9), f01),
            "GLVM torch CPU, whole frame": rate(lambda t: glvm(t, window=9), tens),
            "TENV OpenCV, whole frame": rate(lambda a: tenv_cv(a, window=9), f01),
            "TENV torch CPU, whole frame": rate(lambda t: tenv(t, window=9), tens),
            "focus stage's work, 620 columns of raw uint16: scale, then GLVM OpenCV":
                rate(lambda a: glvm_cv(to_unit_float(a[:, part], max_value=1023), window=9),
                     raw16),
            "focus stage's work, 620 columns of raw uint16: fused raw path (now used)":
                rate(lambda a: focus_measure_raw(a[:, part], max_value=1023, window=9), raw16),
        }


def device_rates(raw16: list[np.ndarray], *, device: str = "cuda", batch: int = 32,
                 reps: int = 20) -> dict[str, Any]:
    """Focus measure + depth accumulation on a torch device, in batches of ``batch`` frames.

    Raw frames go up from pinned memory (:class:`sffscan.stages.focus_torch.DeviceFocus`) and are
    added to per-pixel sums and argmax (:func:`sffscan.stages.focus_torch.accumulate_levels_torch`)
    at levels 0..batch-1; the same frames are sent again and again (throughput only).
    """
    from sffscan.stages.focus_torch import (
        DeviceFocus,
        accumulate_levels_torch,
        new_accumulator_torch,
    )

    dev = torch.device(device)
    sync = torch.cuda.synchronize if dev.type == "cuda" else (lambda: None)
    frames = np.stack([raw16[i % len(raw16)] for i in range(batch)])
    levels = torch.arange(batch, device=dev) % 50
    name = torch.cuda.get_device_name(dev) if dev.type == "cuda" else str(dev)
    out: dict[str, Any] = {"device": name, "batch": batch}
    for op in ("glvm", "tenv"):
        for bits, arr in ((16, frames), (8, (frames >> 2).astype(np.uint8))):
            df = DeviceFocus(device=dev, operator=op, window=9,
                             max_value=255 if bits == 8 else 1023)
            acc = new_accumulator_torch(n_levels=50, shape=arr.shape[1:], device=dev)
            for _ in range(2):  # warm up
                accumulate_levels_torch(acc, df.measure(arr)[1], levels)
            sync()
            t0 = time.perf_counter()
            for _ in range(reps):
                accumulate_levels_torch(acc, df.measure(arr)[1], levels)
            sync()
            out[f"{op.upper()} uint{bits}"] = reps * batch / (time.perf_counter() - t0)
    return out


def fmt(v: float) -> str:
    return f"{v:,.1f}" if v < 1000 else f"{v:,.0f}"


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--frames", type=int, default=600, help="frames per end-to-end run")
    ap.add_argument("--repeat", type=int, default=2, help="runs per case (best kept)")
    ap.add_argument("--scaling", default="300,600,1200",
                    help="frame counts of the time / memory scaling runs")
    ap.add_argument("--cache", type=Path,
                    default=Path(tempfile.gettempdir()) / "sffscan-bench",
                    help="where the rendered frame bank is kept")
    ap.add_argument("--out", type=Path, default=ROOT / "bench" / "results.md")
    ap.add_argument("--quick", action="store_true", help="main GLVM cases only")
    ap.add_argument("--case", help=argparse.SUPPRESS)
    args = ap.parse_args(argv)
    if args.case:
        print(json.dumps(run_case(json.loads(args.case))))
        return 0

    scaling = [int(v) for v in args.scaling.split(",") if v]
    print(f"machine: {machine()}", file=sys.stderr)
    bank = frame_bank(args.cache, max([args.frames, *scaling]))
    h, w = 1024, 1280
    raw16 = [np.fromfile(bank, np.uint16, h * w, offset=i * h * w * 2).reshape(h, w)
             for i in range(40)]
    results: dict[str, Any] = {"machine": machine(), "date": time.strftime("%Y-%m-%d"),
                               "frames": args.frames}
    fr = focus_rates(raw16, baseline_frames=10)
    base = fr["thesis torch conv2d GLVM (baseline)"]
    results["focus_measure_fps"] = fr
    print(f"baseline {base:.1f} frames/s", file=sys.stderr)

    cases = []
    for op in ("glvm",) if args.quick else ("glvm", "tenv"):
        for bits in (10, 8):
            for reg in (True, False):
                cases.append({"operator": op, "bits": bits, "registration": reg})
    e2e = []
    for c in cases:
        res = spawn_case({**c, "frames": args.frames, "repeat": args.repeat,
                          "bank": str(bank)})
        e2e.append((c, res))
        print(f"{c}: {res['fps']:.1f} frames/s, {res['process_cpu_ms']:.2f} ms CPU/frame",
              file=sys.stderr)
    results["end_to_end"] = [{**c, **r} for c, r in e2e]

    scale_rows = []
    for n in scaling:
        res = spawn_case({"operator": "glvm", "bits": 10, "registration": True, "frames": n,
                          "repeat": args.repeat, "bank": str(bank)})
        scale_rows.append((n, res))
        print(f"scaling {n} frames: {res['wall_s']:.2f} s, {res['peak_rss_mb']:.0f} MB",
              file=sys.stderr)
    results["scaling"] = [{"frames": n, **r} for n, r in scale_rows]

    gpu: dict[str, Any] | None = None
    if torch.cuda.is_available():
        gpu = device_rates(raw16)
        results["cuda"] = gpu

    lines = [f"# sffscan benchmark ({results['date']})", "",
             f"Machine: {machine()}", "",
             f"Command: `python bench/bench_pipeline.py` (frames per end-to-end run "
             f"{args.frames}, best of {args.repeat}; frames replayed from a file of distinct "
             "simulated frames). 1280 x 1024 px, N = 50, k = 9, SPC, Zarr mosaic; no viewer, "
             "no recorder.", "",
             "## Focus measure alone (best of 3)", "",
             "| implementation | frames/s | vs baseline |", "|---|---:|---:|"]
    lines += [f"| {k} | {fmt(v)} | {v / base:.1f}x |" for k, v in fr.items()]
    stage_names = ["source", "speed_shift", "registration", "focus_measure", "depth", "mosaic"]
    lines += ["", "## End to end", "",
              "frames/s: frames / wall time of the run. CPU ms/frame: each stage's thread "
              "(thread CPU time) and the whole process (all threads, Zarr's codec threads "
              "included). Peak RSS: the run's process (imports included), less the frames "
              "held in memory for the replay.", "",
              "| frames | operator | registration | frames/s | vs baseline | process CPU "
              "ms/frame | " + " | ".join(stage_names) + " | peak RSS MB | dropped |",
              "|---|---|---|---:|---:|---:|" + "---:|" * len(stage_names) + "---:|---:|"]
    for c, r in e2e:
        cpu = [r["stages"].get(s, {}).get("cpu_ms_per_frame") for s in stage_names]
        lines.append(
            f"| uint{16 if c['bits'] == 10 else 8} | {str(c['operator']).upper()} | "
            f"{'on' if c['registration'] else 'off'} | {r['fps']:.1f} | "
            f"{r['fps'] / base:.1f}x | {r['process_cpu_ms']:.2f} | "
            + " | ".join("-" if v is None else f"{v:.2f}" for v in cpu)
            + f" | {r['peak_rss_mb']:.0f} | {r['dropped']} |")
    lines += ["", f"## Scaling (uint16, GLVM, registration on, best of {args.repeat})", "",
              "| frames | wall s | s per 100 frames | peak RSS MB |", "|---:|---:|---:|---:|"]
    for n, r in scale_rows:
        lines.append(f"| {n} | {r['wall_s']:.2f} | {100 * r['wall_s'] / n:.3f} | "
                     f"{r['peak_rss_mb']:.0f} |")
    if len(scale_rows) >= 2:
        (n0, r0), (n1, r1) = scale_rows[0], scale_rows[-1]
        lines += ["", f"Time ratio {r1['wall_s'] / r0['wall_s']:.2f} for {n1 / n0:.1f}x the "
                  f"frames; peak RSS {r0['peak_rss_mb']:.0f} -> {r1['peak_rss_mb']:.0f} MB "
                  f"({100 * (r1['peak_rss_mb'] / r0['peak_rss_mb'] - 1):+.1f} %)."]
    lines += ["", "## CUDA (focus measure + depth accumulation, batches on the device)", ""]
    if gpu is None:
        lines.append("Not measured: torch sees no CUDA device on this machine.")
    else:
        lines += [f"Device: {gpu['device']}, batches of {gpu['batch']} frames, raw frames "
                  "uploaded from pinned memory, converted on the device.", "",
                  "| case | frames/s |", "|---|---:|"]
        lines += [f"| {k} | {fmt(v)} |" for k, v in gpu.items()
                  if k not in ("device", "batch")]
    text = "\n".join(lines) + "\n"
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(text)
    args.out.with_suffix(".json").write_text(json.dumps(results, indent=2) + "\n")
    print(text)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
