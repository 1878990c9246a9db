"""The default depth method against SPC: focus-volume cost per frame, and every method's
accuracy on the scans of the issue's bars.

    python bench/bench_depth_default.py [--frames 300] [--rounds 3] [--methods spc,adaptive]
    python bench/bench_depth_default.py --methods adaptive/no-unc,adaptive --rounds 5
    python bench/bench_depth_default.py --e2e RECORDING [--rounds 3] [--execution threads]
    python bench/bench_depth_default.py --accuracy RECORDING

Default mode: what the depth stage does for every frame of a demo scan (1280 x 1024 px,
N = 50, 15 mm/s, the columns the focus stage measures, ~52 % of each frame), for each
method, *interleaved* in rounds in one process so that all see the same machine load: wall
and CPU ms per frame including the reduction of the completed blocks, and the bytes each
keeps per pass. The focus values are random (gamma distributed): curves with no peak, as
where nothing is in focus, so the filtered peaks scatter and most pixels take ``adaptive``'s
wide centroid (88 % of them, measured 2026-12-06), the costly path of the fallback and its
tests; a scanned surface is the other extreme (98.5 % peak pixels on the demo's recording),
which ``--e2e`` measures. A method written ``NAME/no-unc`` runs without the
per-pixel height uncertainty (the depth stage before it had one): the cost of the
uncertainty is ``NAME`` over ``NAME/no-unc``; ``shape_select/no-window`` is the default
without its 9-level centroid test (stages/depth_window.py). This mode writes its table to
``bench/depth_default_results.md`` (and ``.json``).

``--e2e``: the whole pipeline over a recording (``sffscan demo --record``), frames read
into memory first, the methods interleaved: frames/s and CPU ms per frame (with ``--out``
a table too: bench/results/depth_default_e2e_*.md).

``--accuracy``: every method's RMSE over the recording (replayed, threads) and over the
±3 px wobble scan with noise of the end-to-end tests (tests/scan_helpers.py). Not a test:
nothing here asserts.
"""

from __future__ import annotations

import argparse
import json
import resource
import statistics
import sys
import tempfile
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
from sffscan.pipeline.config import demo_config
from sffscan.pipeline.heap import keep_freed_memory
from sffscan.pipeline.opencv_threads import opencv_thread_limit, opencv_threads
from sffscan.pipeline.plan import plan_frames
from sffscan.stages.depth import DEFAULT_METHOD, DEPTH_METHODS
from sffscan.stages.focus_volume import FocusVolume
from sffscan.stages.sim.camera import focus_heights
from sffscan.stages.volume_columns import new_columns
from threadpoolctl import threadpool_limits


def frames(n: int) -> list[tuple[int, int, int, int, int]]:
    """(x, y, level, c0, c1) of the first n frames of the demo plan."""
    cfg = demo_config()
    w, m = cfg.optics.width_px, cfg.processing.focus_reach_px
    prev: dict[int, int] = {}
    out = []
    for pf, _ in zip(plan_frames(cfg), range(n), strict=False):
        x, y = int(round(pf.x_px)), int(round(pf.y_px))
        c0, c1 = new_columns(x, prev.get(pf.focus_index), width=w, margin=m, direction=1)
        prev[pf.focus_index] = x
        out.append((x, y, pf.focus_index, c0, c1))
    return out


class SurfaceCurves:
    """Focus curves of a scanned surface for the default mode's ``--curves surface``: the
    demo's characterisation plate (its true heights, world px), each pixel's curve a
    Gaussian of sigma 2.5 levels about its height, scaled by a fixed texture contrast, over
    a floor of small gamma noise (7 frames, as the random curves'); made per frame, outside
    the timed calls."""

    SIGMA_LEVELS = 2.5

    def __init__(self, plan: list[tuple[int, int, int, int, int]]) -> None:
        from sffscan.pipeline.sim_source import make_world

        cfg = demo_config()
        o = cfg.optics
        h, w = o.height_px, o.width_px
        x0 = min(x for x, *_ in plan)
        y0 = min(y for _, y, *_ in plan)
        span = max(x for x, *_ in plan) + w - x0
        rows = max(y for _, y, *_ in plan) + h - y0
        z = make_world(cfg).height_um(float(x0), float(y0), span, rows)
        self.levels = ((z - o.z_min_um) / o.z_step_um).astype(np.float32)
        rng = np.random.default_rng(1)
        self.contrast = rng.gamma(2.0, 0.05, (rows, span)).astype(np.float32)
        self.floor = [rng.gamma(2.0, 0.002, (h, w)).astype(np.float32) for _ in range(7)]
        self.origin = (x0, y0)

    def __call__(self, i: int, x: int, y: int, level: int, c0: int, c1: int) -> np.ndarray:
        h = self.floor[0].shape[0]
        r0, u0 = y - self.origin[1], x - self.origin[0]
        d = self.levels[r0:r0 + h, u0 + c0:u0 + c1] - np.float32(level)
        fm = np.exp(d * d * np.float32(-0.5 / self.SIGMA_LEVELS**2))
        fm *= self.contrast[r0:r0 + h, u0 + c0:u0 + c1]
        fm += self.floor[i % len(self.floor)][:, c0:c1]
        return fm


def run(spec: str, plan: list[tuple[int, int, int, int, int]],
        focus: Callable[[int, int, int, int, int, int], np.ndarray],
        tex: np.ndarray) -> tuple[float, float, int]:
    method, _, flag = spec.partition("/")
    cfg = demo_config()
    o, p = cfg.optics, cfg.processing
    vol = FocusVolume(n_levels=o.n_levels, frame_shape=(o.height_px, o.width_px),
                      focus_heights_um=focus_heights(n_levels=o.n_levels, z_min_um=o.z_min_um,
                                                     z_step_um=o.z_step_um).tolist(),
                      margin=p.focus_reach_px, method=method, median_size=p.median_size,
                      spread_size=p.window, block_columns=p.block_columns,
                      uncertainty=flag != "no-unc")
    if flag == "no-window":  # shape_select as before its 9-level centroid test
        vol.window_test = False
    wall = cpu = 0.0  # the volume's calls only, after its start-up (its pages touched there)
    for i, (x, y, level, c0, c1) in enumerate(plan):
        fm = focus(i, x, y, level, c0, c1)
        t0, c0_cpu = time.perf_counter(), time.process_time()
        vol.add(fm, tex[:, c0:c1], x=x, y=y, level=level, col0=c0)
        wall += time.perf_counter() - t0
        cpu += time.process_time() - c0_cpu
    t0, c0_cpu = time.perf_counter(), time.process_time()
    vol.finish()
    wall += time.perf_counter() - t0
    cpu += time.process_time() - c0_cpu
    n = len(plan)
    return 1e3 * wall / n, 1e3 * cpu / n, vol.nbytes


def random_curves(h: int, w: int) -> Callable[[int, int, int, int, int, int], np.ndarray]:
    """The default mode's random curves: 7 frames of gamma-distributed focus values, in
    turn (curves with no peak)."""
    rng = np.random.default_rng(0)
    bank = [rng.gamma(2.0, 0.01, (h, w)).astype(np.float32) for _ in range(7)]
    return lambda i, x, y, level, c0, c1: bank[i % len(bank)][:, c0:c1]


def focus_volume_cost(methods: list[str], n_frames: int, rounds: int,
                      curves: str = "random") -> dict[str, object]:
    cfg = demo_config()
    h, w = cfg.optics.height_px, cfg.optics.width_px
    plan = frames(n_frames)
    focus = random_curves(h, w) if curves == "random" else SurfaceCurves(plan)
    tex = np.random.default_rng(0).random((h, w), dtype=np.float32)
    wall: dict[str, list[float]] = {m: [] for m in methods}
    cpu: dict[str, list[float]] = {m: [] for m in methods}
    mem = {}
    # BLAS and OpenCV threads as in the scan's focus worker (OpenCV one thread where the
    # cores are no more than the placement's three processes; before 2026-12-04 this
    # benchmark left OpenCV a thread per core, which the worker does not run with)
    with threadpool_limits(limits=1, user_api="blas"), \
            opencv_thread_limit(opencv_threads(3)):
        for _ in range(rounds):
            for method in methods:
                ms, cpu_ms, nbytes = run(method, plan, focus, tex)
                wall[method].append(round(ms, 3))
                cpu[method].append(round(cpu_ms, 3))
                mem[method] = nbytes
    best = {m: min(v) for m, v in wall.items()}
    best_cpu = {m: min(v) for m, v in cpu.items()}
    ref = methods[0]
    return {"ms_per_frame": wall, "cpu_ms_per_frame": cpu, "best_ms_per_frame": best,
            "best_cpu_ms_per_frame": best_cpu,
            "state_MiB": {m: round(b / 2**20, 1) for m, b in mem.items()},
            f"over_{ref}_wall": {m: round(best[m] / best[ref], 3) for m in methods},
            f"over_{ref}_cpu": {m: round(best_cpu[m] / best_cpu[ref], 3) for m in methods}}


def end_to_end(recording: str, rounds: int, execution: str,
               methods: list[str]) -> dict[str, object]:
    """Replay a recording (frames read into memory first) through the whole pipeline with
    each method, interleaved: frames/s, the depth stage's and the whole process's CPU ms per
    frame (the steadier figure on a shared machine)."""
    from sffscan.pipeline.formats.recording_reader import open_recording
    from sffscan.pipeline.wiring import run_scan

    rec = open_recording(recording)
    frames_in = list(rec.frames())
    out: dict[str, dict[str, list[float]]] = {}
    for _ in range(rounds):
        for method in methods:
            proc = rec.config.processing.model_copy(
                update={"depth_method": method, "execution": execution})
            cfg = rec.config.model_copy(update={"processing": proc})
            ru0 = resource.getrusage(resource.RUSAGE_SELF)
            ch0 = resource.getrusage(resource.RUSAGE_CHILDREN)
            with tempfile.TemporaryDirectory() as tmp:
                rep = run_scan(cfg, frames=iter(frames_in), output=Path(tmp) / "m.zarr",
                               progress=False)
            ru1 = resource.getrusage(resource.RUSAGE_SELF)
            ch1 = resource.getrusage(resource.RUSAGE_CHILDREN)
            r = rep.result
            depth = next(s for s in r.stages if s.name == "depth")
            cpu_s = sum(b.ru_utime + b.ru_stime - a.ru_utime - a.ru_stime
                        for a, b in ((ru0, ru1), (ch0, ch1)))
            row = out.setdefault(method, {"fps": [], "depth_cpu_ms": [], "process_cpu_ms": []})
            row["fps"].append(round(rep.frames / r.wall_s, 2))
            row["depth_cpu_ms"].append(round(1e3 * depth.cpu_s / rep.frames, 3))
            row["process_cpu_ms"].append(round(1e3 * cpu_s / rep.frames, 3))
    best = {m: max(v["fps"]) for m, v in out.items()}
    cpu = {m: min(v["process_cpu_ms"]) for m, v in out.items()}
    ref = methods[0]
    c = rec.config
    scene = (f"{len(frames_in)} frames of a simulated {c.source.world} (seed {c.source.seed}), "
             f"{c.motion.passes} passes at {c.motion.speed_mm_s:g} mm/s, wobble "
             f"±{c.motion.wobble_along_px:g} px, field curvature "
             f"{c.optics.field_curvature_um:g} µm, vignetting {c.optics.vignetting:g}")
    return {"recording": scene, "runs": out, "best_fps": best, "least_process_cpu_ms": cpu,
            f"fps_over_{ref}": {m: round(best[m] / best[ref], 3) for m in methods},
            f"cpu_over_{ref}": {m: round(cpu[m] / cpu[ref], 3) for m in methods}}


def accuracy_table(recording: str, methods: list[str]) -> dict[str, dict[str, float]]:
    """RMSE (µm) of every method over the recording and over the ±3 px wobble scan."""
    from sffscan.pipeline.formats.recording_reader import open_recording
    from sffscan.pipeline.metrology.evaluate import mosaic_accuracy
    from sffscan.pipeline.sim_source import make_world
    from sffscan.pipeline.wiring import run_scan

    sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # tests.scan_helpers
    from tests.scan_helpers import mosaic_height, scan, score, small_config, strip_region

    rec = open_recording(recording)
    out: dict[str, dict[str, float]] = {}
    with tempfile.TemporaryDirectory() as tmp:
        for m in methods:
            proc = rec.config.processing.model_copy(update={"depth_method": m,
                                                            "execution": "threads"})
            cfg = rec.config.model_copy(update={"processing": proc})
            path = Path(tmp) / f"demo-{m}.zarr"
            run_scan(cfg, frames=rec.frames(), output=path, progress=False)
            o = cfg.optics
            acc = mosaic_accuracy(path, make_world(cfg),
                                  max_depth=(o.n_levels - 1) * o.z_step_um)
            wcfg = small_config(motion={"wobble_along_px": 3.0, "wobble_across_px": 3.0},
                                processing={"depth_method": m})
            wpath = Path(tmp) / f"wobble-{m}.zarr"
            scan(wcfg, wpath)
            region = strip_region(wcfg)
            wob = score(wcfg, mosaic_height(wpath, region), region)
            out[m] = {"recording_rmse_um": round(acc.rmse_um, 2),
                      "wobble_rmse_um": round(wob.rmse_um, 2)}
            print(m, json.dumps(out[m]), flush=True)
    return out


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--frames", type=int, default=300)
    ap.add_argument("--rounds", type=int, default=3)
    ap.add_argument("--methods", default=f"spc,wcentroid,{DEFAULT_METHOD}",
                    help="comma-separated; the first is the reference of the ratios")
    ap.add_argument("--curves", choices=["random", "surface"], default="random",
                    help="the default mode's focus curves: random values with no peak "
                         "(bench/depth_default_results.md) or a scanned plate's "
                         "(SurfaceCurves; bench/depth_default_surface_results.md)")
    ap.add_argument("--e2e", metavar="RECORDING",
                    help="replay this recording end to end (e.g. one of 'sffscan demo "
                         "--record'), the methods interleaved")
    ap.add_argument("--accuracy", metavar="RECORDING",
                    help="every method's RMSE over this recording and the wobble scan")
    ap.add_argument("--execution", default="threads", choices=["threads", "processes"])
    ap.add_argument("--out", type=Path, metavar="MD",
                    help="--e2e: also write the runs as a table here (e.g. "
                         "bench/results/depth_default_e2e.md)")
    args = ap.parse_args()
    keep_freed_memory()  # the heap setting of the scan's focus worker (pipeline/heap.py)
    methods = [m for m in args.methods.split(",") if m]
    bad = [m for m in methods if m.partition("/")[0] not in DEPTH_METHODS
           or m.partition("/")[2] not in ("", "no-unc", "no-window")]
    if bad:
        ap.error(f"unknown methods {bad}; choose from {DEPTH_METHODS}")
    if args.accuracy:
        print(json.dumps(accuracy_table(args.accuracy, list(DEPTH_METHODS))))
    elif args.e2e:
        res = end_to_end(args.e2e, args.rounds, args.execution, methods)
        print(json.dumps(res))
        if args.out:
            write_e2e(res, methods, args)
    else:
        res = focus_volume_cost(methods, args.frames, args.rounds, args.curves)
        print(json.dumps(res))
        write_results(res, methods, args)
    return 0


def write_e2e(res: dict[str, Any], methods: list[str], args: argparse.Namespace) -> None:
    """``--out``: the end-to-end runs as a table (frames/s and the depth stage's CPU per
    frame, every round; best, least and median, and their ratios to the first method)."""
    sys.path.insert(0, str(Path(__file__).resolve().parent))
    from bench_pipeline import write_table  # torch with it: loaded after the measurements

    runs, ref = res["runs"], methods[0]
    med = {m: {k: statistics.median(v) for k, v in runs[m].items()} for m in methods}
    lines = [f"Recording `{args.e2e}`: {res['recording']}; execution {args.execution}, "
             f"{args.rounds} rounds, the "
             f"methods interleaved in every round ({time.strftime('%Y-%m-%d %H:%M')}). "
             "Frames/s: the whole pipeline's; depth CPU: the depth stage's (its process's "
             "CPU a frame).", "",
             f"| method | frames/s (rounds) | best | median | / {ref} (best, median) | "
             f"depth CPU ms/frame (rounds) | least | median | / {ref} (least, median) |",
             "|---|---|---:|---:|---:|---|---:|---:|---:|"]
    for m in methods:
        r, d = runs[m], med[m]
        fps_best, cpu_least = max(r["fps"]), min(r["depth_cpu_ms"])
        lines.append(
            f"| {m} | {', '.join(f'{v:.1f}' for v in r['fps'])} | {fps_best:.1f} | "
            f"{d['fps']:.1f} | {fps_best / max(runs[ref]['fps']):.3f}, "
            f"{d['fps'] / med[ref]['fps']:.3f} | "
            f"{', '.join(f'{v:.2f}' for v in r['depth_cpu_ms'])} | {cpu_least:.2f} | "
            f"{d['depth_cpu_ms']:.2f} | {cpu_least / min(runs[ref]['depth_cpu_ms']):.3f}, "
            f"{d['depth_cpu_ms'] / med[ref]['depth_cpu_ms']:.3f} |")
    write_table(args.out, "Depth methods end to end over a recording (bench_depth_default.py "
                "--e2e)", "bench_depth_default.py", None, lines)


def write_results(res: dict[str, Any], methods: list[str], args: argparse.Namespace) -> None:
    """bench/depth_default_results.md and .json: the table of this run."""
    sys.path.insert(0, str(Path(__file__).resolve().parent))
    from bench_pipeline import machine  # torch with it: loaded after the measurements
    here = Path(__file__).resolve().parent
    ref = methods[0]
    surface = args.curves == "surface"
    lines = ["# Depth stage: CPU per frame of the demo scan (bench_depth_default.py)", "",
             f"Command: `python bench/bench_depth_default.py --frames {args.frames} --rounds "
             f"{args.rounds} --methods {','.join(methods)}"
             f"{' --curves surface' if surface else ''}` "
             f"({time.strftime('%Y-%m-%d %H:%M')}"
             f", {machine()}, methods interleaved in every round; best of the "
             "rounds; the volume's calls timed). Curves: "
             + ("the demo plate's (Gaussians about its true heights)." if surface
                else "random values, no peak."), "",
             f"| method | wall ms/frame (rounds) | best | CPU ms/frame best | state MiB | "
             f"wall / {ref} | CPU / {ref} |", "|---|---|---:|---:|---:|---:|---:|"]
    for m in methods:
        lines.append(f"| {m} | {', '.join(f'{v:.2f}' for v in res['ms_per_frame'][m])} | "
                     f"{res['best_ms_per_frame'][m]:.2f} | "
                     f"{res['best_cpu_ms_per_frame'][m]:.2f} | {res['state_MiB'][m]} | "
                     f"{res[f'over_{ref}_wall'][m]:.3f} | {res[f'over_{ref}_cpu'][m]:.3f} |")
    stem = "depth_default_surface_results" if surface else "depth_default_results"
    (here / f"{stem}.md").write_text("\n".join(lines) + "\n")
    (here / f"{stem}.json").write_text(json.dumps(res, indent=1) + "\n")


if __name__ == "__main__":
    raise SystemExit(main())
