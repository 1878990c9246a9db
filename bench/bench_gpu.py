"""The GPU placement of the focus measure and the accumulation, in one prepared run (issue
28, item 4): checked against the CPU path, then timed, on a lent GPU machine.

    python bench/bench_gpu.py --out "$OUT"                      # on the GPU machine (CUDA)
    python bench/bench_gpu.py --device cpu --frames 40 --quick  # a smoke run anywhere

What it measures, in this order (each section's results are written as soon as it ends, so
a run cut short keeps what it measured):

1. **agreement**: a synthetic stack with a true surface (:func:`family_stack`, 10-bit,
   N = 50) measured by the scan's CPU path (:func:`focus_measure_raw`, OpenCV) and on the
   device (:class:`DeviceFocus`, the torch definitions): the focus maps' largest difference
   relative to their largest value, for GLVM and TENV; then the device accumulation
   (:func:`accumulate_levels_torch`, float32 sums and running argmax) against the CPU's
   (:func:`depth_from_focus` with SPC on the CPU focus volume): the argmax's share of equal
   pixels and the depth's largest and RMS difference, levels; and both depths' RMS error
   against the truth, µm.
2. **device throughput**: focus measure (GLVM and TENV) + accumulation of full-size frames
   (the scan's 1280 x 1024, uint16 and uint8) on the device in batches of 1, 8 and 32
   frames, uploads included, frames/s (:func:`bench_pipeline.device_rates`: the frames are
   re-sent, throughput only).
3. **end to end**: the scan of ``--frames`` simulated frames from memory (the default
   configuration, processes placement) with ``processing.backend = "opencv"`` and with
   ``"torch"`` on the device, alternating for ``--rounds`` rounds: frames/s, CPU per frame,
   and the two mosaics' height difference (RMS and largest, µm, over the pixels valid in
   both; pixels valid in one only are counted); and the torch one again with
   ``OMP_NUM_THREADS=1`` in the scan's worker processes (its CPU cost's cause, 2026-12-04).
   The torch backend measures each frame on
   the device and copies the focus measure back: the accumulation stays on the CPU in the
   scan, so section 2 is the device's bound and section 3 what the scan gets today.

Writes ``gpu_<device>.json`` and ``.md`` into ``--out`` (default ``bench/results``). Not a
test: nothing here asserts. On the lent machine the packages the image lacks are carried as
wheels: ``bash bench/gpu_wheels.sh`` here first (docs/performance.md, "A lent GPU machine").
"""

from __future__ import annotations

import argparse
import contextlib
import json
import os
import resource
import sys
import tempfile
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from bench_pipeline import (  # noqa: E402
    bench_config,
    device_rates,
    machine,
    replay_frames,
    scan_figures,
)
from sffscan.pipeline.config import ScanConfig  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
#: the synthetic stack of section 1: a family with steps and slopes of the surface
AGREEMENT_FAMILY = "steps"


def machine_and_device(device: str) -> str:
    """The machine (:func:`bench_pipeline.machine`) and the torch device, in words."""
    import torch

    dev = (torch.cuda.get_device_name(torch.device(device))
           if device.startswith("cuda") else device)
    return f"{machine()}, device {dev}"


# ----------------------------------------------------------------------------- 1. agreement


def agreement(device: str, *, size_px: int) -> dict[str, Any]:
    """The device's focus measure and accumulation against the CPU path on one stack."""
    import torch
    from sffscan.stages.depth import depth_from_focus, depth_from_harmonics
    from sffscan.stages.focus_measure import focus_measure_raw
    from sffscan.stages.focus_torch import (
        DeviceFocus,
        accumulate_levels_torch,
        new_accumulator_torch,
    )
    from sffscan.stages.sim.families import family_stack

    stack = family_stack(AGREEMENT_FAMILY, 0, size_px=size_px, n_levels=50)
    raw = np.round(np.clip(stack.images, 0.0, 1.0) * 1023.0).astype(np.uint16)
    n = raw.shape[0]
    out: dict[str, Any] = {"stack": f"{AGREEMENT_FAMILY} seed 0, {size_px} x {size_px} px, "
                                    f"N = {n}, 10-bit"}
    for op in ("glvm", "tenv"):
        cpu = np.stack([focus_measure_raw(f, max_value=1023.0, operator=op)[1] for f in raw])
        dev = DeviceFocus(device=device, operator=op, window=9, max_value=1023.0)
        gpu = dev.measure(raw)[1].cpu().numpy()
        out[f"{op} focus: largest difference / largest value"] = float(
            np.abs(gpu - cpu).max() / cpu.max())
        if op != "glvm":
            continue
        acc = new_accumulator_torch(n_levels=n, shape=raw.shape[1:], device=device)
        levels = torch.arange(n, device=torch.device(device))
        for a in range(0, n, 8):  # batches, as a scan would send them
            accumulate_levels_torch(acc, torch.as_tensor(gpu[a:a + 8], device=device),
                                    levels[a:a + 8])
        sums = acc["sums"].cpu().numpy()
        amax = acc["argmax"].cpu().numpy()
        d_gpu, _ = depth_from_harmonics(sums, amax, n_levels=n, method="spc")
        d_cpu, _ = depth_from_focus(cpu, method="spc")
        ref_amax = np.argmax(cpu, axis=0)
        diff = np.abs(d_gpu - d_cpu)
        out.update({
            "argmax equal share": float(np.mean(amax == ref_amax)),
            "SPC depth: largest difference, levels": float(diff.max()),
            "SPC depth: RMS difference, levels": float(np.sqrt(np.mean(diff ** 2))),
            "SPC RMS error CPU, um": rms_error(d_cpu, stack),
            "SPC RMS error device, um": rms_error(d_gpu, stack),
        })
    return out


def rms_error(depth: np.ndarray, stack: Any) -> float:
    """RMS of a depth map's height error against the stack's truth, µm."""
    from sffscan.stages.depth_levels import levels_to_height

    height = levels_to_height(depth, focus_heights_um=stack.focus_um)
    return float(np.sqrt(np.mean((height - stack.truth_um) ** 2)))


# ----------------------------------------------------------------------------- 2. throughput


def throughput(images: list[np.ndarray], device: str, *, batches: tuple[int, ...],
               frames: int) -> list[dict[str, Any]]:
    """Focus measure + accumulation of full frames on the device, frames/s per batch size
    (:func:`bench_pipeline.device_rates`, about ``frames`` frames timed per case)."""
    return [device_rates(images, device=device, batch=b, reps=max(2, round(frames / b)))
            for b in batches]


# ----------------------------------------------------------------------------- 3. end to end


def scan_config(backend: str, device: str) -> ScanConfig:
    """The benchmarks' scan (:func:`bench_pipeline.bench_config`) with the default depth
    method, in the processes placement, the focus measure on ``backend`` and ``device``."""
    base = bench_config()
    default = type(base.processing).model_fields["depth_method"].default
    data = base.model_dump()
    data["processing"].update(depth_method=default, execution="processes", backend=backend,
                              device=device)
    return ScanConfig.model_validate(data)


def render(count: int) -> list[np.ndarray]:
    """``count`` frames of the default simulated scan, in memory (rendered in parallel)."""
    from sffscan.pipeline.sim_workers import ParallelSimFrames, render_workers

    cfg = scan_config("opencv", "cpu")
    frames = ParallelSimFrames(cfg, workers=render_workers(cfg))
    out: list[np.ndarray] = []
    try:
        for f in frames:
            out.append(np.array(f.image, copy=True))
            if len(out) == count:
                break
    finally:
        frames.close()
    return out


def scan(backend: str, device: str, images: list[np.ndarray], out: Path) -> dict[str, Any]:
    from sffscan.pipeline.wiring import run_scan

    cfg = scan_config(backend, device)
    c0 = resource.getrusage(resource.RUSAGE_SELF)
    rep = run_scan(cfg, frames=replay_frames(cfg, images), output=out, progress=False)
    c1 = resource.getrusage(resource.RUSAGE_SELF)
    return scan_figures(rep, c1.ru_utime + c1.ru_stime - c0.ru_utime - c0.ru_stime)


def height_difference(a: Path, b: Path) -> dict[str, float]:
    import zarr

    ha = np.asarray(zarr.open_array(store=str(a), path="height", mode="r")[...], np.float64)
    hb = np.asarray(zarr.open_array(store=str(b), path="height", mode="r")[...], np.float64)
    both = np.isfinite(ha) & np.isfinite(hb)
    d = np.abs(ha[both] - hb[both])
    return {"pixels valid in both": int(both.sum()),
            "valid in one only": int((np.isfinite(ha) ^ np.isfinite(hb)).sum()),
            "RMS difference, um": float(np.sqrt(np.mean(d ** 2))) if d.size else float("nan"),
            "largest difference, um": float(d.max()) if d.size else float("nan")}


#: the third case of section 3: the torch backend with one OpenMP thread in the workers
OMP_ONE = "torch, OMP_NUM_THREADS=1 in the workers"


@contextlib.contextmanager
def worker_env(name: str, value: str | None) -> Iterator[None]:
    """``name`` set to ``value`` (None: left as it is) while the scan's worker processes
    start (they are spawned, so they read it; this process's libraries have started)."""
    before = os.environ.get(name)
    if value is not None:
        os.environ[name] = value
    try:
        yield
    finally:
        if before is None:
            os.environ.pop(name, None)
        else:
            os.environ[name] = before


def end_to_end(images: list[np.ndarray], device: str, *, rounds: int, tmp: Path
               ) -> dict[str, Any]:
    """The scan with each backend, alternating; on 2026-12-04's lent H200 the torch one
    used 74.8 ms of CPU a frame against 23.5, and 25.0 with ``OMP_NUM_THREADS=1`` for the
    whole run: the third case sets it for the workers only (where the focus stage runs)."""
    runs: dict[str, list[dict[str, Any]]] = {"opencv": [], "torch": [], OMP_ONE: []}
    diffs = []
    for r in range(rounds):
        order = list(runs) if r % 2 == 0 else list(runs)[::-1]
        paths: dict[str, Path] = {}
        for case in order:
            paths[case] = tmp / f"{len(paths)}-{r}.zarr"
            backend = "opencv" if case == "opencv" else "torch"
            with worker_env("OMP_NUM_THREADS", "1" if case == OMP_ONE else None):
                runs[case].append(scan(backend, device if backend == "torch" else "cpu",
                                       images, paths[case]))
        diffs.append(height_difference(paths["opencv"], paths["torch"]))
    return {"runs": runs, "height difference": diffs}


# ----------------------------------------------------------------------------- report


def write(out: Path, device: str, results: dict[str, Any]) -> Path:
    name = "gpu_" + "".join(c if c.isalnum() else "_" for c in device)
    (out / f"{name}.json").write_text(json.dumps(results, indent=2) + "\n")
    lines = [f"# The focus measure and the accumulation on a torch device ({results['date']})",
             "", f"Machine: {results['machine']}", "", f"Command: `{results['command']}`", ""]
    if "agreement" in results:
        lines += ["## 1. Agreement with the CPU path", "", results["agreement"]["stack"], "",
                  "| quantity | value |", "|---|---:|"]
        lines += [f"| {k} | {v:.3g} |" for k, v in results["agreement"].items()
                  if k != "stack"]
        lines.append("")
    if "throughput" in results:
        cases = [k for k in results["throughput"][0] if k not in ("device", "batch")]
        lines += ["## 2. Focus measure + accumulation on the device (1280 x 1024, k = 9, "
                  "N = 50, uploads included), frames/s", "",
                  "| batch | " + " | ".join(cases) + " |",
                  "|---:|" + "---:|" * len(cases)]
        lines += [f"| {t['batch']} | " + " | ".join(f"{t[c]:,.0f}" for c in cases) + " |"
                  for t in results["throughput"]]
        lines.append("")
    if "end to end" in results:
        e = results["end to end"]
        lines += ["## 3. The scan, frames from memory, processes placement "
                  f"({results['frames']} frames, rounds alternating)", "",
                  "| backend | frames/s (median) | runs | CPU ms/frame (median) |",
                  "|---|---:|---|---:|"]
        for backend, runs in e["runs"].items():
            fps = [x["fps"] for x in runs]
            cpu = [x["cpu_ms_per_frame"] for x in runs]
            lines.append(f"| {backend} | {np.median(fps):.1f} | "
                         f"{', '.join(f'{v:.1f}' for v in fps)} | {np.median(cpu):.2f} |")
        lines += ["", "Height difference between the two mosaics (each round): " + "; ".join(
            f"RMS {d['RMS difference, um']:.3g} µm, max {d['largest difference, um']:.3g} µm, "
            f"{d['valid in one only']} px valid in one only" for d in e["height difference"]),
            ""]
    (out / f"{name}.md").write_text("\n".join(lines))
    return out / f"{name}.md"


def main(argv: list[str] | None = None) -> int:
    import torch

    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--device", default="cuda" if torch.cuda.is_available() else "cpu",
                    help="torch device (default: cuda where there is one, else cpu)")
    ap.add_argument("--frames", type=int, default=300, help="frames of the end-to-end scans")
    ap.add_argument("--rounds", type=int, default=2, help="end-to-end rounds (alternating)")
    ap.add_argument("--timed", type=int, default=320,
                    help="frames timed per throughput case (batch size and operator)")
    ap.add_argument("--stack-px", type=int, default=512, help="agreement stack size, px")
    ap.add_argument("--sections", default="agreement,throughput,end-to-end",
                    help="comma-separated sections to run (default: all three)")
    ap.add_argument("--quick", action="store_true",
                    help="a smoke run: a small stack, short timings, one round")
    ap.add_argument("--out", type=Path, default=ROOT / "bench" / "results")
    args = ap.parse_args(argv)
    sections = set(args.sections.split(","))
    unknown = sections - {"agreement", "throughput", "end-to-end"}
    if unknown:
        ap.error(f"--sections: unknown {', '.join(sorted(unknown))} (agreement, throughput, "
                 "end-to-end)")
    if args.device.startswith("cuda") and not torch.cuda.is_available():
        print(f"--device {args.device}: torch {torch.__version__} sees no CUDA device",
              file=sys.stderr)
        return 2
    if args.quick:
        args.rounds, args.timed, args.stack_px = 1, min(args.timed, 8), min(args.stack_px, 128)
    args.out.mkdir(parents=True, exist_ok=True)
    results: dict[str, Any] = {
        "date": time.strftime("%Y-%m-%d %H:%M"), "machine": machine_and_device(args.device),
        "command": "python bench/bench_gpu.py " + " ".join(
            sys.argv[1:] if argv is None else argv), "frames": args.frames}
    t0 = time.perf_counter()
    md = write(args.out, args.device, results)
    if "agreement" in sections:
        results["agreement"] = agreement(args.device, size_px=args.stack_px)
        print(f"agreement done ({time.perf_counter() - t0:.0f} s)", file=sys.stderr)
        md = write(args.out, args.device, results)
    if sections & {"throughput", "end-to-end"}:
        images = render(args.frames)
        print(f"{len(images)} frames rendered ({time.perf_counter() - t0:.0f} s)",
              file=sys.stderr)
    if "throughput" in sections:
        results["throughput"] = throughput(images, args.device, batches=(1, 8, 32),
                                           frames=args.timed)
        print(f"throughput done ({time.perf_counter() - t0:.0f} s)", file=sys.stderr)
        md = write(args.out, args.device, results)
    if "end-to-end" in sections:
        with tempfile.TemporaryDirectory() as tmp:
            results["end to end"] = end_to_end(images, args.device, rounds=args.rounds,
                                               tmp=Path(tmp))
        md = write(args.out, args.device, results)
    print(f"done in {time.perf_counter() - t0:.0f} s: {md}", file=sys.stderr)
    print(md.read_text())
    return 0


if __name__ == "__main__":
    sys.exit(main())
