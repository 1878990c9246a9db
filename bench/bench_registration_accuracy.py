"""Registration accuracy against the simulator's known frame positions, old against new.

    python bench/bench_registration_accuracy.py --against /tmp/old     # old tree too
    python bench/bench_registration_accuracy.py --geometry full --seeds 0 1 2 \
        --against /tmp/old --out bench/results/registration_accuracy.md

The simulated scan (:func:`sffscan.pipeline.sim_source.simulate_frames`) places every frame
at its commanded position plus a periodic wobble of ±``--wobble`` px along and across the
motion (:func:`sffscan.pipeline.sim_source.wobble_px`): the truth. Each frame is placed by
the speed-shift stage and refined by a registration stage; its position error is
``predicted + correction - truth``, less the pass's mean (the absolute offset is a free
constant of the solve). Reported: RMS error x / y, px, per configuration (tree x pair lags),
all configurations on the same rendered frames in one run, with the speed prediction alone
as a reference, the pairs measured and refused, and each configuration's CPU time per
frame (registration only, interleaved: each seed runs every configuration in turn).

Geometries: ``test`` is the scan of ``tests/pipeline/test_scan_bars.py`` (640 x 256 px of 17 µm,
registration at half resolution); ``full`` the demo optics (1280 x 1024 px of 8.5 µm,
registration at a quarter), a 12 mm strip. Seeds change the plate's texture and heights.
Not a test: nothing here asserts.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path
from types import ModuleType
from typing import Any

import numpy as np
from sffscan.pipeline.config import ScanConfig, config_from_dict, demo_config
from sffscan.pipeline.plan import plan_frames
from sffscan.pipeline.sim_source import simulate_frames, wobble_px
from sffscan.pipeline.wiring import build_stages
from sffscan.stages import registration

sys.path.insert(0, str(Path(__file__).resolve().parent))
from against import load_module  # noqa: E402


def geometry_config(geometry: str, *, seed: int, wobble: float) -> ScanConfig:
    motion = {"wobble_along_px": wobble, "wobble_across_px": wobble}
    if geometry == "test":
        return config_from_dict({
            "source": {"world": "plate", "plate_length_mm": 24.0, "plate_width_mm": 4.0,
                       "seed": seed},
            "optics": {"width_px": 640, "height_px": 256, "pixel_um": 17.0},
            "motion": {"x_start_mm": 2.0, "x_end_mm": 22.0, **motion},
            "processing": {"block_columns": 64, "registration_scale": 2},
            "output": {"chunk_px": 128}}, origin="bench")
    return demo_config(source={"seed": seed, "plate_length_mm": 16.0},
                       motion={"x_start_mm": 2.0, "x_end_mm": 14.0, **motion})


def position_errors(cfg: ScanConfig, placed: list[Any], truth: np.ndarray,
                    stage: Any) -> tuple[np.ndarray, float]:
    """Position errors (n, 2), px, less their mean; and the CPU seconds the stage took."""
    t0 = time.process_time()
    out = [y for q in placed for y in stage.process(q)] + list(stage.finish())
    cpu = time.process_time() - t0
    got = np.array([(o.predicted_px[0] + o.correction_px[0],
                     o.predicted_px[1] + o.correction_px[1]) for o in out])
    err = got - truth
    return err - err.mean(axis=0), cpu


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--geometry", choices=("test", "full"), default="test")
    ap.add_argument("--seeds", type=int, nargs="+", default=[0])
    ap.add_argument("--wobble", type=float, default=3.0, help="±px along and across")
    ap.add_argument("--against", type=Path, help="another source tree (its stages/ folder)")
    ap.add_argument("--lags", nargs="+", default=["1,2,3,4", "1,2,3", "1,2", "1"],
                    help="short-lag sets to try (the period pair N is always added)")
    ap.add_argument("--out", type=Path, help="also write the table (Markdown) here")
    args = ap.parse_args(argv)
    trees: dict[str, ModuleType] = {"new": registration}
    if args.against is not None:
        trees["old"] = load_module("_old_registration",
                                   args.against / "stages" / "registration.py")
    lag_sets = [tuple(int(v) for v in s.split(",")) for s in args.lags]
    errors: dict[tuple[str, tuple[int, ...]], list[np.ndarray]] = {}
    cpu: dict[tuple[str, tuple[int, ...]], float] = {}
    pairs: dict[tuple[str, tuple[int, ...]], list[int]] = {}
    frames_total = 0
    for seed in args.seeds:
        cfg = geometry_config(args.geometry, seed=seed, wobble=args.wobble)
        o, p = cfg.optics, cfg.processing
        built = {s.name: s for s in build_stages(cfg, iter(()), None)}  # type: ignore[arg-type]
        frames = list(simulate_frames(cfg))
        placed = [y for f in frames for y in built["speed_shift"].process(f)]
        truth = np.array([(pf.x_px + wobble_px(cfg, pf.travel_px)[0],
                           pf.y_px + wobble_px(cfg, pf.travel_px)[1])
                          for pf in plan_frames(cfg)])
        pred = np.array([q.predicted_px for q in placed]) - truth
        errors.setdefault(("speed prediction", ()), []).append(pred - pred.mean(axis=0))
        frames_total += len(placed)
        for lags in lag_sets:
            for tree, mod in trees.items():
                stage = mod.RegistrationStage(n_levels=o.n_levels, scale=p.registration_scale,
                                              lags=lags)
                err, sec = position_errors(cfg, placed, truth, stage)
                errors.setdefault((tree, lags), []).append(err)
                cpu[tree, lags] = cpu.get((tree, lags), 0.0) + sec
                st = stage.extra_stats()
                got = pairs.setdefault((tree, lags), [0, 0])
                got[0] += int(st["pairs_measured"])
                got[1] += int(st["pairs_rejected"])
        print(f"seed {seed}: {len(placed)} frames", file=sys.stderr)
    lines = [f"geometry {args.geometry}, wobble ±{args.wobble:g} px, seeds {args.seeds}, "
             f"{frames_total} frames: position error against the simulator's truth, RMS px "
             "(pass mean removed)", "",
             "| tree | pairs per frame (lags) | RMS x | RMS y | pairs measured / refused "
             "| CPU ms per frame |", "|---|---|---:|---:|---:|---:|"]
    for (tree, lags), errs in errors.items():
        e = np.concatenate(errs)
        rms = np.sqrt(np.mean(e * e, axis=0))
        if not lags:
            lines.append(f"| {tree} | - | {rms[0]:.3f} | {rms[1]:.3f} | - | - |")
            continue
        n_ok, n_no = pairs[tree, lags]
        lines.append(f"| {tree} | {len(lags) + 1} ({', '.join(map(str, lags))}, N) | "
                     f"{rms[0]:.3f} | {rms[1]:.3f} | {n_ok} / {n_no} | "
                     f"{1e3 * cpu[tree, lags] / frames_total:.2f} |")
    text = "\n".join(lines) + "\n"
    print(text, end="")
    if args.out is not None:
        args.out.parent.mkdir(parents=True, exist_ok=True)
        args.out.write_text(text, encoding="utf-8")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
