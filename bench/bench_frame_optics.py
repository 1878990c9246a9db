"""What the breathing correction costs a calibrated scan (issue 28): CPU per frame of the
``frame_optics`` stage (:class:`sffscan.pipeline.metrology.correction_stages.FrameOpticsStage`,
every frame resampled to the reference level's scale about the optical centre), this tree's
separable resampling against OpenCV's ``warpAffine`` with ``INTER_LANCZOS4`` (what the
stage did before 2026-12-03), interleaved; and how closely each reproduces a band-limited
image sampled at the exact positions.

    python bench/bench_frame_optics.py [--frames 50] [--rounds 5]
    python bench/bench_frame_optics.py --write-calibration /tmp/lateral.json

The second form only writes a calibration for the benchmarks' optics
(``bench_pipeline.bench_config``): a ``lateral`` section (its scale at the middle level, 2 %
less over the range, centred) and the nominal focus table as ``z_response``, for whole
scans with the correction on (``bench_placement.py --calibration``).

Frames: 1280 x 1024 uint16 (10-bit) textures, one per focus level of N = 50, magnification
per level as ``REALISTIC_OPTICS`` (+2 % over the range, the reference level in the middle).
OpenCV and BLAS on one thread (as a scan's stages on 2 cores). Writes
bench/results/frame_optics.md and .json. Not a test: nothing here asserts.
"""

from __future__ import annotations

import argparse
import json
import statistics
import sys
import time
from collections.abc import Callable
from pathlib import Path

import cv2
import numpy as np
from sffscan.pipeline.metrology.calibration_model import (
    Calibration,
    LateralScale,
    ZResponse,
    save_calibration,
)
from sffscan.pipeline.metrology.correction_stages import FrameOpticsStage
from sffscan.pipeline.metrology.optics_correction import unbreathe_frame, unbreathe_matrix
from sffscan.stages.messages import Frame, FrameHeader
from threadpoolctl import threadpool_limits

sys.path.insert(0, str(Path(__file__).resolve().parent))
from bench_pipeline import bench_config, machine  # noqa: E402

OUT = Path(__file__).resolve().parent / "results" / "frame_optics"
H, W, N = 1024, 1280, 50
CENTRE = (639.3, 512.6)


def opencv_lanczos4(image: np.ndarray, magnification: float) -> np.ndarray:
    """The correction as it was: ``cv2.warpAffine``, ``INTER_LANCZOS4``, replicated border."""
    mat = unbreathe_matrix(magnification, centre_px=CENTRE)
    return cv2.warpAffine(image, mat, (image.shape[1], image.shape[0]),
                          flags=cv2.INTER_LANCZOS4 | cv2.WARP_INVERSE_MAP,
                          borderMode=cv2.BORDER_REPLICATE)


def frames(count: int) -> list[Frame]:
    rng = np.random.default_rng(0)
    out = []
    for i in range(count):
        tex = cv2.GaussianBlur(rng.random((H, W), dtype=np.float32), (0, 0), 1.0)
        img = np.clip((tex - 0.5) * 4000 + 512, 0, 1023).astype(np.uint16)
        out.append(Frame(FrameHeader(frame_id=i, timestamp_ns=i, focus_index=i % N,
                                     stage_x_um=0.0, stage_y_um=0.0), img))
    return out


def cpu_ms(run: Callable[[], object], n: int) -> float:
    t = time.process_time()
    run()
    return 1e3 * (time.process_time() - t) / n


def accuracy(m: float) -> dict[str, float]:
    """RMS and largest error (grey levels, amplitude ~350) against the exact resampling of
    a band-limited image (periods 7 to 20 px), away from the border."""
    yy, xx = np.mgrid[0:H, 0:W].astype(np.float64)

    def f(x: np.ndarray, y: np.ndarray) -> np.ndarray:
        return (500 + 200 * np.sin(0.9 * x + 0.3) * np.cos(0.7 * y - 0.2)
                + 150 * np.sin(0.31 * x + 0.45 * y))

    img = f(xx, yy).astype(np.float32)
    mat = unbreathe_matrix(m, centre_px=CENTRE)  # output px -> frame px
    truth = f(mat[0, 0] * xx + mat[0, 2], mat[1, 1] * yy + mat[1, 2])
    inner = (slice(40, -40), slice(40, -40))
    out = {}
    for name, got in (("this tree", unbreathe_frame(img, m, centre_px=CENTRE)),
                      ("OpenCV Lanczos4", opencv_lanczos4(img, m))):
        e = (got.astype(np.float64) - truth)[inner]
        out[f"{name} rms"] = float(np.sqrt(np.mean(e * e)))
        out[f"{name} max"] = float(np.abs(e).max())
    return out


def write_calibration(path: Path) -> Path:
    """A calibration of the benchmarks' optics with a ``lateral`` section only."""
    cfg = bench_config()
    o = cfg.optics
    p, n = o.pixel_um, o.n_levels
    slope = -0.02 * p / (n - 1)
    zs = [o.z_min_um + k * o.z_step_um for k in (0, n // 2, n - 1)]
    return save_calibration(Calibration(
        description="bench_frame_optics.py: synthetic lateral scale (2 % over the range), "
                    "the nominal focus table as z response",
        z_response=ZResponse(um_per_level=o.z_step_um, intercept_um=o.z_min_um, pearson_r=1.0,
                             heights_um=zs, peak_levels=[0.0, float(n // 2), n - 1.0],
                             residuals_um=[0.0, 0.0, 0.0]),
        lateral=LateralScale(um_per_px_x=p, um_per_px_y=p, reference_level=(n - 1) / 2,
                             slope_x_per_level=slope, slope_y_per_level=slope,
                             optical_centre_px=((o.width_px - 1) / 2, (o.height_px - 1) / 2))),
        path)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--frames", type=int, default=50, help="frames per run (one per level)")
    ap.add_argument("--rounds", type=int, default=5, help="interleaved rounds (median)")
    ap.add_argument("--out", type=Path, default=OUT, help="results, without suffix")
    ap.add_argument("--write-calibration", type=Path, metavar="PATH",
                    help="only write a lateral calibration for bench_placement.py")
    args = ap.parse_args(argv)
    if args.write_calibration:
        print(write_calibration(args.write_calibration))
        return 0
    t_run = time.perf_counter()
    mags = 1.0 + 0.02 * (np.arange(N) - (N - 1) / 2) / (N - 1)
    items = frames(args.frames)
    cases: dict[str, Callable[[], object]] = {}
    stage = FrameOpticsStage(mags, centre_px=CENTRE)
    with threadpool_limits(limits=1, user_api="blas"):
        cv2.setNumThreads(1)
        t0 = time.process_time()
        for it in items:  # the first pass prepares every level's resampling
            list(stage.process(it))
        prepare_ms = 1e3 * (time.process_time() - t0) / len(items)
        cases["this tree (levels prepared)"] = lambda: [
            None for it in items for _ in stage.process(it)]
        cases["OpenCV warpAffine Lanczos4"] = lambda: [
            opencv_lanczos4(it.image, float(mags[it.header.focus_index])) for it in items]
        cpu: dict[str, list[float]] = {k: [] for k in cases}
        for r in range(args.rounds):
            order = list(cases) if r % 2 == 0 else list(cases)[::-1]
            for name in order:
                cpu[name].append(cpu_ms(cases[name], len(items)))
            print(f"round {r + 1}: " + ", ".join(f"{k} {v[-1]:.2f}" for k, v in cpu.items()),
                  file=sys.stderr, flush=True)
        acc = {m: accuracy(m) for m in (0.99, 1.004, 1.01)}
    result = {"machine": machine(), "frames": args.frames, "rounds": args.rounds,
              "cpu_ms_per_frame": cpu, "first_pass_ms_per_frame": prepare_ms,
              "accuracy": {str(k): v for k, v in acc.items()},
              "command": "python bench/bench_frame_optics.py " + " ".join(
                  sys.argv[1:] if argv is None else argv),
              "date": time.strftime("%Y-%m-%d %H:%M"), "run_s": time.perf_counter() - t_run}
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.with_suffix(".json").write_text(json.dumps(result, indent=1), encoding="utf-8")
    lines = [
        "# The breathing correction's cost: frame_optics, CPU per frame", "",
        f"`{result['command']}` ({result['date']}, {result['run_s']:.0f} s)", "",
        f"Machine: {result['machine']}. {W} x {H} uint16 frames, N = {N} levels "
        f"(magnification 0.99 .. 1.01), {args.frames} frames a run, {args.rounds} rounds "
        "interleaved; OpenCV and BLAS on one thread; CPU ms per frame, median (min-max).", "",
        "| case | CPU ms/frame | runs |", "|---|---:|---|"]
    for name, v in cpu.items():
        lines.append(f"| {name} | {statistics.median(v):.2f} ({min(v):.2f}-{max(v):.2f}) | "
                     + ", ".join(f"{x:.2f}" for x in v) + " |")
    lines += ["", f"This tree's first pass over the levels (each level's resampling prepared "
              f"at its first frame, then applied): {prepare_ms:.2f} ms a frame.", "",
              "Accuracy against the exact resampling of a band-limited image (grey levels; "
              "amplitude ~350, periods 7-20 px; 40 px from the border left out):", "",
              "| magnification | this tree RMS | max | OpenCV Lanczos4 RMS | max |",
              "|---:|---:|---:|---:|---:|"]
    for m, a in acc.items():
        lines.append(f"| {m} | {a['this tree rms']:.3f} | {a['this tree max']:.3f} | "
                     f"{a['OpenCV Lanczos4 rms']:.3f} | {a['OpenCV Lanczos4 max']:.3f} |")
    args.out.with_suffix(".md").write_text("\n".join(lines) + "\n", encoding="utf-8")
    print("\n".join(lines))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
