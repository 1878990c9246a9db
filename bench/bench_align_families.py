"""``stack --align`` on strong focus breathing, on stacks of the synthetic families
(:func:`sffscan.stages.sim.families.family_stack` with ``breathing``; not the repository's
data): depth RMSE of the aligned stack over that of its breathing-free twin (same world,
texture and noise; rendered 4x finer and integrated per pixel).

    python bench/bench_align_families.py                       # writes the table below
    python bench/bench_align_families.py --families slopes --seeds 0 1 --size 96

Columns: ``unaligned``; ``Lanczos`` (the estimated transforms, each frame warped by OpenCV's
8-tap Lanczos, the warp before 103b380); ``no aperture`` (the windowed sinc alone, the warp
before the pixel aperture was equalised); ``aperture, no floor`` (:func:`sffscan.stages.
fields.align.align_stack` without the noise floor's correction); ``aligned`` (what ``stack
--align`` does: the windowed sinc, the aperture equalised, the noise floor taken off the
focus volume, :mod:`sffscan.stages.fields.aperture`); ``as taken`` (the same, the transforms
estimated on the frames as taken, ``estimate_alignment(normalise=False)``, as before
2026-12-06: :func:`sffscan.stages.fields.align_pairs.registration_frame`); ``true warp``
(the true transforms, the same warp: the estimate's share); ``same box`` (``aligned`` over
the twin reconstructed on the same box as the aligned stack: what the alignment costs with
the field the depth method judges held equal; the twin on its whole field is the bar's
reading, as a user without breathing would reconstruct it); the largest error of the
estimated scale, %.
Depth: GLVM 9, the default method (``--method``), levels, over the pixels every aligned
frame covers less the focus window's reach; the breathing stacks measured on the box those
pixels span (as ``stack --align`` does since 2026-12-06), the twin on the whole field.
Writes bench/align_families_results.md (``--out``). Not a test: nothing here asserts.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import cv2
import numpy as np
from sffscan.stages.depth import DEFAULT_METHOD, DEPTH_METHODS, depth_from_focus
from sffscan.stages.fields.align import (
    Alignment,
    align_stack,
    estimate_alignment,
    mask_uncovered,
)
from sffscan.stages.fields.aperture import stack_noise_floor
from sffscan.stages.fields.stationary import valid_box
from sffscan.stages.focus_measure import focus_measure
from sffscan.stages.sim.families import BLUR_MODELS, family_stack

OUT = Path(__file__).resolve().parent / "align_families_results.md"
DEFAULT_FAMILIES = ["even-gauss", "even-noisy", "lens-gauss", "pillbox", "lens-pillbox-noisy",
                    "slopes", "clean-coarse", "steps"]


def _lanczos(stack: np.ndarray, al: Alignment) -> np.ndarray:
    h, w = stack.shape[1:]
    out = [cv2.warpAffine(f, m, (w, h), flags=cv2.INTER_LANCZOS4 | cv2.WARP_INVERSE_MAP,
                          borderMode=cv2.BORDER_REPLICATE) for f, m in zip(stack, al.matrices,
                                                                           strict=True)]
    return np.clip(np.stack(out), 0.0, 1.0)


def score(family: str, seed: int, *, n: int, size: int, breathing: float,
          method: str = DEFAULT_METHOD, blur_model: str = "gather") -> dict[str, float]:
    real = family_stack(family, seed, size_px=size, n_levels=n, breathing=breathing,
                        blur_model=blur_model)  # type: ignore[arg-type]
    twin = family_stack(family, seed, size_px=size, n_levels=n, breathing=0.0,
                        pad_for_breathing=breathing,
                        blur_model=blur_model)  # type: ignore[arg-type]
    truth = real.truth_um / 10.0
    aligned, valid, al = align_stack(real.images)
    floor = stack_noise_floor(real.images, al, max_value=1.0)[0]
    mags = (1.0 + breathing) ** (np.arange(n) - n // 2)
    true_al = Alignment.breathing(mags, real.images.shape[1:])
    true = align_stack(real.images, alignment=true_al)[0]
    raw_al = estimate_alignment(real.images, normalise=False)
    raw = align_stack(real.images, alignment=raw_al)[0]
    raw_floor = stack_noise_floor(real.images, raw_al, max_value=1.0)[0]
    true_floor = stack_noise_floor(real.images, true_al, max_value=1.0)[0]
    mask = np.isfinite(mask_uncovered(np.zeros(valid.shape), valid, reach_px=9))
    # the breathing stacks are measured on the box every aligned frame covers, as ``stack
    # --align`` measures them (reconstruct_field's ``valid``): beyond it a frame holds its
    # replicated border, whose curves would take part in the depth method's choice; the
    # twin, which covers the whole field, on the whole field
    box = valid_box(valid, valid.shape)
    whole = (slice(None), slice(None))

    def rmse(stack: np.ndarray, floor: np.ndarray | None = None, *,
             region: tuple[slice, slice] = box) -> float:
        fm = focus_measure(stack[:, region[0], region[1]], window=9)
        if floor is not None:
            fm = np.maximum(fm - floor[:, None, None].astype(np.float32), np.float32(0.0))
        d = depth_from_focus(fm, method=method)[0]
        return float(np.sqrt(np.mean((d - truth[region])[mask[region]] ** 2)))

    base = rmse(twin.images, region=whole)
    done = rmse(aligned, floor)
    return {"ideal": base, "unaligned": rmse(real.images) / base,
            "Lanczos": rmse(_lanczos(real.images, al)) / base,
            "no aperture": rmse(align_stack(real.images, alignment=al, aperture=False)[0])
            / base,
            "aperture, no floor": rmse(aligned) / base,
            "aligned": done / base,
            "as taken": rmse(raw, raw_floor) / base,
            "true warp": rmse(true, true_floor) / base,
            "same box": done / rmse(twin.images),
            "scale error %": float(100 * np.abs(al.scale / mags - 1.0).max())}


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--families", nargs="+", default=DEFAULT_FAMILIES)
    ap.add_argument("--seeds", type=int, nargs="+", default=[0, 1, 2])
    ap.add_argument("--frames", type=int, default=21)
    ap.add_argument("--size", type=int, default=128)
    ap.add_argument("--breathing", type=float, default=0.012)
    ap.add_argument("--method", choices=DEPTH_METHODS, default=DEFAULT_METHOD,
                    help=f"depth method (default {DEFAULT_METHOD})")
    ap.add_argument("--blur-model", choices=BLUR_MODELS, default="gather",
                    help="how the stacks apply a blur that varies over the image "
                         "(sffscan.stages.sim.families.BLUR_MODELS; default gather)")
    ap.add_argument("--out", type=Path, default=OUT,
                    help="results file (default: bench/align_families_results.md)")
    args = ap.parse_args(argv)
    t0 = time.perf_counter()
    head = (f"{args.frames} levels of {args.size} x {args.size} px, "
            f"{100 * args.breathing:g} %/frame breathing, depth method {args.method}, "
            f"{args.blur_model} blur model; RMSE "
            "(levels) of the no-breathing twin, the others over it")
    cols = ["ideal", "unaligned", "Lanczos", "no aperture", "aperture, no floor", "aligned",
            "as taken", "true warp", "same box", "scale error %"]
    lines = [head, "", "| family | seed | " + " | ".join(cols) + " |",
             "|---|---:|" + "---:|" * len(cols)]
    print("\n".join(lines), flush=True)
    worst = {"Lanczos": 0.0, "no aperture": 0.0, "aperture, no floor": 0.0, "aligned": 0.0,
             "as taken": 0.0}
    over = {"aligned": 0, "as taken": 0, "true warp": 0, "same box": 0}
    total = {"aligned": 0.0, "as taken": 0.0}
    scored = 0
    for fam in args.families:
        for seed in args.seeds:
            try:
                r = score(fam, seed, n=args.frames, size=args.size, breathing=args.breathing,
                          method=args.method, blur_model=args.blur_model)
            except ValueError as err:  # ECC gave up on a featureless pair: say so, go on
                line = f"| {fam} | {seed} | alignment failed: {err} |"
            else:
                worst = {k: max(v, r[k]) for k, v in worst.items()}
                over = {k: v + int(r[k] > 1.10) for k, v in over.items()}
                total = {k: v + r[k] for k, v in total.items()}
                scored += 1
                line = (f"| {fam} | {seed} | {r['ideal']:.3f} | " + " | ".join(
                    f"{r[c]:.3f}" for c in cols[1:]) + " |")
            lines.append(line)
            print(line, flush=True)
    tail = (f"\nworst aligned/twin: {worst['aligned']:.3f} (without the aperture: "
            f"{worst['no aperture']:.3f}; the aperture without the noise floor: "
            f"{worst['aperture, no floor']:.3f}; Lanczos warp: {worst['Lanczos']:.3f}); "
            f"transforms estimated on the frames as taken: {worst['as taken']:.3f}\n"
            f"over the 1.10x bar: aligned {over['aligned']}, as taken {over['as taken']}, "
            f"true warp {over['true warp']}, against the twin on the same box "
            f"{over['same box']} of {scored}; mean aligned/twin "
            f"{total['aligned'] / max(scored, 1):.4f}, as taken "
            f"{total['as taken'] / max(scored, 1):.4f}; {time.perf_counter() - t0:.0f} s")
    lines.append(tail)
    print(tail)
    sys.path.insert(0, str(Path(__file__).resolve().parent))
    from bench_pipeline import write_table  # torch with it: loaded after the measurements
    write_table(args.out, "Alignment on breathing family stacks", "bench_align_families.py",
                argv, lines)
    print(f"wrote {args.out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
