"""Throughput of the default depth method against SPC: focus-volume accumulation per frame.

    python bench/bench_depth_default.py [--frames 300] [--rounds 3] [--e2e RECORDING]

What the depth stage does for every frame of a demo scan (1280 x 1024 px, N = 50, 15 mm/s,
the columns the focus stage measures, ~52 % of each frame), for ``spc`` (running sums and
argmax, no N-level ring) and ``wcentroid`` (the N-level ring of the 3-point fits, reduced
by the windowed centroid), *interleaved* in rounds in one process so that both see the
same machine load: ms per frame including the reduction of the completed blocks, and the
bytes each keeps per pass. Not a test: nothing here asserts.
"""

from __future__ import annotations

import argparse
import json
import resource
import time

import numpy as np
from sffscan.pipeline.config import demo_config
from sffscan.pipeline.plan import plan_frames
from sffscan.stages.focus_volume import FocusVolume, new_columns
from sffscan.stages.sim.camera import focus_heights


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


def run(method: str, plan: list[tuple[int, int, int, int, int]], bank: list[np.ndarray],
        tex: np.ndarray) -> tuple[float, float, int]:
    cfg = demo_config()
    o, p = cfg.optics, cfg.processing
    vol = FocusVolume(n_levels=o.n_levels, frame_shape=(o.height_px, o.width_px),
                      focus_heights_um=focus_heights(n_levels=o.n_levels, z_min_um=o.z_min_um,
                                                     z_step_um=o.z_step_um),
                      margin=p.focus_reach_px, method=method, median_size=p.median_size,
                      block_columns=p.block_columns)
    t0 = time.perf_counter()  # after the volume's start-up (its pages are touched there)
    c0_cpu = time.process_time()
    for i, (x, y, level, c0, c1) in enumerate(plan):
        fm = bank[i % len(bank)][:, c0:c1]
        vol.add(fm, tex[:, c0:c1], x=x, y=y, level=level, col0=c0)
    vol.finish()
    n = len(plan)
    return (1e3 * (time.perf_counter() - t0) / n, 1e3 * (time.process_time() - c0_cpu) / n,
            vol.nbytes)


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--frames", type=int, default=300)
    ap.add_argument("--rounds", type=int, default=3)
    ap.add_argument("--e2e", metavar="RECORDING",
                    help="also replay this recording end to end (e.g. one of 'sffscan demo "
                         "--record'), SPC and wcentroid interleaved")
    ap.add_argument("--execution", default="threads", choices=["threads", "processes"])
    args = ap.parse_args()
    if args.e2e:
        print(json.dumps(end_to_end(args.e2e, args.rounds, args.execution)))
        return 0
    cfg = demo_config()
    h, w = cfg.optics.height_px, cfg.optics.width_px
    rng = np.random.default_rng(0)
    bank = [rng.gamma(2.0, 0.01, (h, w)).astype(np.float32) for _ in range(7)]
    tex = rng.random((h, w), dtype=np.float32)
    plan = frames(args.frames)
    res: dict[str, list[float]] = {"spc": [], "wcentroid": []}
    cpu: dict[str, list[float]] = {"spc": [], "wcentroid": []}
    mem = {}
    for _ in range(args.rounds):
        for method in res:
            ms, cpu_ms, nbytes = run(method, plan, bank, tex)
            res[method].append(ms)
            cpu[method].append(cpu_ms)
            mem[method] = nbytes
    best = {m: min(v) for m, v in res.items()}
    best_cpu = {m: min(v) for m, v in cpu.items()}
    print(json.dumps({"ms_per_frame": res, "cpu_ms_per_frame": cpu, "best_ms_per_frame": best,
                      "best_cpu_ms_per_frame": best_cpu,
                      "state_MiB": {m: round(b / 2**20, 1) for m, b in mem.items()},
                      "wcentroid_over_spc": round(best["wcentroid"] / best["spc"], 3),
                      "wcentroid_over_spc_cpu": round(best_cpu["wcentroid"] / best_cpu["spc"],
                                                      3)}))
    return 0


def end_to_end(recording: str, rounds: int, execution: str) -> dict[str, object]:
    """Replay a recording (frames read into memory first) through the whole pipeline with
    SPC and wcentroid, interleaved: frames/s, the depth stage's and the whole process's CPU
    ms per frame (the steadier figure on a shared machine)."""
    import tempfile
    from pathlib import Path

    from sffscan.pipeline.formats.recording import open_recording
    from sffscan.pipeline.wiring import run_scan

    rec = open_recording(recording)
    frames_in = list(rec.frames())
    out: dict[str, dict[str, list[float]]] = {}
    for _ in range(rounds):
        for method in ("spc", "wcentroid"):
            proc = rec.config.processing.model_copy(
                update={"depth_method": method, "execution": execution})
            cfg = rec.config.model_copy(update={"processing": proc})
            ru0 = resource.getrusage(resource.RUSAGE_SELF)
            with tempfile.TemporaryDirectory() as tmp:
                rep = run_scan(cfg, frames=iter(frames_in), output=Path(tmp) / "m.zarr",
                               progress=False)
            ru1 = resource.getrusage(resource.RUSAGE_SELF)
            r = rep.result
            depth = next(s for s in r.stages if s.name == "depth")
            row = out.setdefault(method, {"fps": [], "depth_cpu_ms": [], "process_cpu_ms": []})
            row["fps"].append(rep.frames / r.wall_s)
            row["depth_cpu_ms"].append(1e3 * depth.cpu_s / rep.frames)
            row["process_cpu_ms"].append(1e3 * (ru1.ru_utime + ru1.ru_stime - ru0.ru_utime
                                                - ru0.ru_stime) / rep.frames)
    best = {m: max(v["fps"]) for m, v in out.items()}
    cpu = {m: min(v["process_cpu_ms"]) for m, v in out.items()}
    return {"runs": out, "best_fps": best, "least_process_cpu_ms": cpu,
            "wcentroid_over_spc_fps": round(best["wcentroid"] / best["spc"], 3),
            "wcentroid_over_spc_cpu": round(cpu["wcentroid"] / cpu["spc"], 3)}


if __name__ == "__main__":
    raise SystemExit(main())
