"""``stack --align`` on strong focus breathing, on stacks of the repository's camera
simulator (:func:`sffscan.stages.sim.camera.render_stack`): a lens whose magnification grows
``--breathing`` a frame about the middle frame's focus, against the same scene through ideal
optics (noise of its own). A third generator beside the synthetic families
(``bench_align_families.py``) and the point-sampled stacks (``bench_align_breathing.py``).

    python bench/bench_align_camera.py --seeds 101 102 103 --out bench/results/align_camera.md

Worlds: ``plate`` (:func:`~sffscan.stages.sim.world.characterisation_plate`: steps, domes,
slopes on a base) and ``sinusoid`` (:func:`~sffscan.stages.sim.world.sinusoid_world`,
amplitude 0.2-0.4 of the range and period 150-400 px drawn from the seed), the camera at a
position drawn from the seed; 17 µm pixels. Heights: :func:`sffscan.stages.fields.
stationary.reconstruct_field` with the default settings, the aligned stack as ``stack
--align`` reconstructs it (the noise floor taken off, the covered pixels' box); RMSE (µm)
over the pixels every aligned frame covers, less the focus window's reach, the same pixels
for every column. Not a test: nothing here asserts.
"""

from __future__ import annotations

import argparse
import logging
import sys
import time
from pathlib import Path

import numpy as np
from sffscan.stages.fields.align import align_stack, mask_uncovered
from sffscan.stages.fields.aperture import stack_noise_floor
from sffscan.stages.fields.stationary import reconstruct_field
from sffscan.stages.sim.camera import Optics, focus_heights, render_stack
from sffscan.stages.sim.world import PlateWorld, characterisation_plate, sinusoid_world

OUT = Path(__file__).resolve().parent / "results" / "align_camera.md"
PIXEL_UM = 17.0


def _world(kind: str, seed: int, top_um: float) -> PlateWorld:
    if kind == "plate":
        return characterisation_plate(seed=seed, pixel_um=PIXEL_UM, length_mm=24.0,
                                      width_mm=8.0, z_range_um=(0.0, top_um))
    rng = np.random.default_rng(seed)
    return sinusoid_world(seed=seed, pixel_um=PIXEL_UM,
                          amplitude_um=float(rng.uniform(0.2, 0.4) * top_um),
                          period_px=float(rng.uniform(150.0, 400.0)), offset_um=top_um / 2,
                          length_mm=24.0, width_mm=8.0)


def score(kind: str, seed: int, *, breathing: float, frames: int, width: int, height: int,
          step_um: float) -> dict[str, float]:
    """Ideal optics' RMSE (µm); the breathing stack's unaligned and aligned RMSE over it; the
    largest error of the estimated scale, %."""
    zs = focus_heights(n_levels=frames, z_step_um=step_um)
    world = _world(kind, seed, float(zs[-1]))
    x0 = float(np.random.default_rng([seed, 7]).uniform(100.0, 900.0))
    ideal = Optics(width=width, height=height, pixel_um=PIXEL_UM)
    real = Optics(width=width, height=height, pixel_um=PIXEL_UM,
                  magnification_per_mm=breathing / (step_um / 1000.0),
                  magnification_ref_um=float(zs[frames // 2]))
    st_i = render_stack(world, x0=x0, y0=0.0, focus_heights_um=zs, optics=ideal,
                        rng=np.random.default_rng([seed, 1]))
    st_r = render_stack(world, x0=x0, y0=0.0, focus_heights_um=zs, optics=real,
                        rng=np.random.default_rng([seed, 2]))
    truth = world.height_um(x0, 0.0, width, height)
    full = float(np.iinfo(st_r.dtype).max)
    aligned, valid, al = align_stack(st_r)
    floor = stack_noise_floor(st_r, al, max_value=full)[0]
    mask = np.isfinite(mask_uncovered(np.zeros(valid.shape), valid, reach_px=9))

    def rmse(height_um: np.ndarray) -> float:
        e = (height_um - truth)[mask]
        return float(np.sqrt(np.mean(e[np.isfinite(e)] ** 2)))

    base = rmse(reconstruct_field(st_i, focus_heights_um=zs).height_um)
    unaligned = rmse(reconstruct_field(st_r, focus_heights_um=zs).height_um)
    done = rmse(reconstruct_field(aligned, focus_heights_um=zs, max_value=full,
                                  noise_floor=floor, valid=valid).height_um)
    mags = np.array([real.magnification(float(z)) for z in zs])
    true_scale = mags / mags[frames // 2]
    return {"ideal": base, "unaligned": unaligned / base, "aligned": done / base,
            "scale error %": float(100 * np.abs(al.scale / true_scale - 1.0).max())}


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--worlds", nargs="+", choices=["plate", "sinusoid"],
                    default=["plate", "sinusoid"])
    ap.add_argument("--seeds", type=int, nargs="+", default=[0, 1, 2])
    ap.add_argument("--breathing", type=float, default=0.012, help="per frame (0.012: 1.2 %%)")
    ap.add_argument("--frames", type=int, default=21)
    ap.add_argument("--width", type=int, default=320, help="px")
    ap.add_argument("--height", type=int, default=240, help="px")
    ap.add_argument("--step-um", type=float, default=300.0, help="focus step, µm")
    ap.add_argument("--out", type=Path, default=OUT, help="results file (default: %(default)s)")
    args = ap.parse_args(argv)
    logging.disable(logging.WARNING)  # ECC's per-pair notes; the table says what matters
    t0 = time.perf_counter()
    cols = ["ideal", "unaligned", "aligned", "scale error %"]
    lines = [f"{args.frames} frames of {args.width} x {args.height} px, {args.step_um:g} µm "
             f"steps, {100 * args.breathing:g} %/frame breathing; RMSE (µm) through ideal "
             "optics, the breathing stack's over it", "",
             "| world | seed | " + " | ".join(cols) + " |", "|---|---:|" + "---:|" * len(cols)]
    print("\n".join(lines), flush=True)
    ratios: list[float] = []
    for kind in args.worlds:
        for seed in args.seeds:
            r = score(kind, seed, breathing=args.breathing, frames=args.frames,
                      width=args.width, height=args.height, step_um=args.step_um)
            ratios.append(r["aligned"])
            line = f"| {kind} | {seed} | " + " | ".join(f"{r[c]:.3f}" for c in cols) + " |"
            lines.append(line)
            print(line, flush=True)
    v = np.array(ratios)
    tail = (f"\naligned / ideal: median {np.median(v):.3f}, worst {v.max():.3f}, over 1.10x "
            f"{int(np.sum(v > 1.10))} of {v.size}; {time.perf_counter() - t0:.0f} s")
    lines.append(tail)
    print(tail)
    sys.path.insert(0, str(Path(__file__).resolve().parent))
    from bench_pipeline import write_table  # torch with it: loaded after the measurements
    write_table(args.out, "Alignment on breathing stacks of the camera simulator",
                "bench_align_camera.py", argv, lines)
    print(f"wrote {args.out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
