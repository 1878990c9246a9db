"""``stack --align`` on strong focus breathing, on stacks made here (not the repository's
simulator or data): RMSE of the aligned stack against the same stack without breathing.

    python bench/bench_align_breathing.py                       # the default grid
    python bench/bench_align_breathing.py --breathing 0.012 --seeds 0 1 2 --noise 0.02

Generator (independent of :mod:`sffscan.stages.sim`): a surface (``bumps``: Gaussian hills
and pits; ``waves``: crossed sinusoids; ``tilt``: a tilted plane; ``terrace``: a tilted plane with
a step), a texture
(``pink``: 1/f noise; ``dots``: random discs; ``grain``: fine blurred noise), both drawn from
the seed. Frame k is in focus at height z_k; each pixel is blurred by a Gaussian of
``sigma = s0 + c |h - z_k|`` px (linear interpolation in a bank of blurred textures), the
world is magnified by ``(1 + breathing)^(k - ref)`` about the frame centre (``ref`` the
middle frame) *before* the sensor: Gaussian read noise of ``--noise`` (fraction of full
scale), then 10-bit quantisation. The same world without breathing, with its own noise, is
the ideal stack. Heights: :func:`sffscan.stages.fields.stationary.reconstruct_field` with
the default settings; all stacks scored over the same pixels (every aligned frame covers
them, less the focus window's reach).

Variants: ``unaligned``; ``aligned`` (:func:`sffscan.stages.fields.align.align_stack`, the
noise floor taken off as ``stack --align`` does: :mod:`sffscan.stages.fields.aperture`);
``true warp`` (the same warp with the true transforms, when ``--true`` is given: isolates
the estimate from the resampling). ``--drift`` adds the largest scale that the alignment
estimates on the breathing-free stack (%, should be 0): what the defocus alone makes the
estimate see. ``--twin`` adds the breathing-free stack again with noise of its own
(``ideal, other noise``): how far a stack's ratio to the ideal moves with the noise alone,
the resolution of a per-stack comparison. Not a test: nothing here asserts.
"""

from __future__ import annotations

import argparse
import math
import statistics
import sys
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import cv2
import numpy as np
from sffscan.pipeline.metrology.compare import compare_height_maps
from sffscan.stages.fields.align import Alignment, align_stack, mask_uncovered
from sffscan.stages.fields.aperture import stack_noise_floor
from sffscan.stages.fields.stationary import reconstruct_field

sys.path.insert(0, str(Path(__file__).resolve().parent))
from against import load_module  # noqa: E402

SURFACES = ("bumps", "waves", "terrace", "tilt")
TEXTURES = ("pink", "dots", "grain")


def stack_seed(surface: str, texture: str, seed: int) -> int:
    """The generator's seed of a stack: ``1000 i + seed``, ``i`` the (surface, texture)
    pair's place in :data:`SURFACES` x :data:`TEXTURES`, so that a run over some of them
    draws the same stacks as the whole grid."""
    return 1000 * (SURFACES.index(surface) * len(TEXTURES) + TEXTURES.index(texture)) + seed


@dataclass(frozen=True)
class Stack:
    real: np.ndarray
    ideal: np.ndarray
    truth: np.ndarray
    zs: np.ndarray
    mags: np.ndarray
    twin: np.ndarray | None = None  # the ideal stack again with noise of its own (--twin)


def _surface(kind: str, shape: tuple[int, int], z_max: float, rng: np.random.Generator
             ) -> np.ndarray:
    h, w = shape
    yy, xx = np.mgrid[0:h, 0:w].astype(np.float64)
    if kind == "bumps":
        z = np.zeros(shape)
        for _ in range(12):
            cx, cy = rng.uniform(0, w), rng.uniform(0, h)
            r = rng.uniform(0.05, 0.2) * w
            z += rng.choice([-1.0, 1.0]) * np.exp(-((xx - cx) ** 2 + (yy - cy) ** 2) / (2 * r * r))
    elif kind == "waves":
        fx, fy = rng.uniform(1.5, 3.0, 2) / np.array([w, h])
        z = np.sin(2 * np.pi * fx * xx + rng.uniform(0, 6)) * np.cos(2 * np.pi * fy * yy
                                                                       + rng.uniform(0, 6))
    elif kind == "tilt":
        a = rng.uniform(0.3, 1.0, 2) * rng.choice([-1.0, 1.0], 2)
        z = a[0] * xx / w + a[1] * yy / h
    elif kind == "terrace":
        a = rng.uniform(-1, 1, 2)
        z = a[0] * xx / w + a[1] * yy / h + 0.8 * (xx > rng.uniform(0.3, 0.7) * w)
    else:
        raise ValueError(kind)
    z = (z - z.min()) / max(np.ptp(z), 1e-9)
    return (0.02 + 0.96 * z) * z_max  # heights over the whole focus range


def _texture(kind: str, shape: tuple[int, int], rng: np.random.Generator) -> np.ndarray:
    h, w = shape
    t: np.ndarray
    if kind == "pink":
        f = np.hypot(np.fft.fftfreq(h)[:, None], np.fft.rfftfreq(w)[None, :])
        spec = (rng.normal(size=f.shape) + 1j * rng.normal(size=f.shape)) / np.maximum(f, 1 / w)
        t = np.fft.irfft2(spec, s=shape)
    elif kind == "dots":
        t = np.zeros(shape, np.float32)
        for _ in range(int(h * w / 60)):
            cv2.circle(t, (int(rng.integers(0, w)), int(rng.integers(0, h))),
                       int(rng.integers(1, 4)), float(rng.uniform(0.3, 1.0)), -1)
        t = cv2.GaussianBlur(t, (0, 0), 0.7)
    elif kind == "grain":
        t = cv2.GaussianBlur(rng.random(shape).astype(np.float32), (0, 0), 1.2)
    else:
        raise ValueError(kind)
    t = np.asarray(t, np.float64)
    t = (t - t.mean()) / max(t.std(), 1e-9)
    return np.clip(0.5 + 0.15 * t, 0.02, 0.98).astype(np.float32)


def _blurred(tex: np.ndarray, heights: np.ndarray, focus: float, *, s0: float, c: float,
             bank: list[tuple[float, np.ndarray]]) -> np.ndarray:
    sig = s0 + c * np.abs(heights - focus)
    sigmas = np.array([s for s, _ in bank])
    u = np.interp(sig, sigmas, np.arange(sigmas.size))
    lo = np.floor(u).astype(int)
    hi = np.minimum(lo + 1, sigmas.size - 1)
    t = (u - lo).astype(np.float32)
    imgs = np.stack([b for _, b in bank])
    ii, jj = np.indices(heights.shape)
    return (1 - t) * imgs[lo, ii, jj] + t * imgs[hi, ii, jj]


def make_stack(*, surface: str, texture: str, seed: int, n: int = 21, width: int = 384,
               height: int = 288, breathing: float = 0.012, noise: float = 0.01,
               step_um: float = 50.0, c_px_per_um: float = 0.04, twin: bool = False) -> Stack:
    rng = np.random.default_rng(seed)
    ref = n // 2
    mags = (1.0 + breathing) ** (np.arange(n) - ref)
    pad = int(math.ceil(0.5 * max(width, height) * (1.0 / mags.min() - 1.0))) + 8
    shape = (height + 2 * pad, width + 2 * pad)
    zs = np.arange(n) * step_um
    world_z = _surface(surface, shape, float(zs[-1]), rng)
    tex = _texture(texture, shape, rng)
    s_max = 0.6 + c_px_per_um * float(zs[-1])
    bank = [(0.0, tex)]
    s = 0.5
    while bank[-1][0] < s_max:
        bank.append((s, cv2.GaussianBlur(tex, (0, 0), s)))
        s *= math.sqrt(2.0)
    cx, cy = (width - 1) / 2.0 + pad, (height - 1) / 2.0 + pad
    real: list[np.ndarray] = []
    ideal: list[np.ndarray] = []
    clean: list[np.ndarray] = []
    for k in range(n):
        img = _blurred(tex, world_z, float(zs[k]), s0=0.6, c=c_px_per_um, bank=bank)
        for m, out in ((mags[k], real), (1.0, ideal)):
            # frame pixel (u, v) sees the world at centre + (u - cx, v - cy) / m
            a = 1.0 / m
            mat = np.array([[a, 0.0, cx - a * (width - 1) / 2.0],
                            [0.0, a, cy - a * (height - 1) / 2.0]])
            f = cv2.warpAffine(img, mat, (width, height),
                               flags=cv2.INTER_LANCZOS4 | cv2.WARP_INVERSE_MAP)
            if twin and out is ideal:
                clean.append(f)
            out.append(_sensor(f, rng, noise))
    truth = world_z[pad:pad + height, pad:pad + width].astype(np.float32)
    other = None
    if twin:  # a draw of its own: the stacks above are the same with or without --twin
        rng2 = np.random.default_rng([seed, 1])
        other = np.stack([_sensor(f, rng2, noise) for f in clean])
    return Stack(np.stack(real), np.stack(ideal), truth, zs, mags, other)


def _sensor(f: np.ndarray, rng: np.random.Generator, noise: float) -> np.ndarray:
    """A frame as the sensor gives it: Gaussian read noise of ``noise`` (full scale), then
    10-bit quantisation."""
    f = f + np.asarray(rng.normal(0.0, noise, f.shape), np.float32)
    return np.clip(np.rint(f * 1023), 0, 1023).astype(np.uint16)


def true_alignment(st: Stack) -> Alignment:
    return Alignment.breathing(st.mags, st.real.shape[1:])


def score(st: Stack, *, use_true: bool, old: Any = None, drift: bool = False
          ) -> dict[str, float]:
    aligned, valid, al = align_stack(st.real)
    mask = np.isfinite(mask_uncovered(np.zeros(valid.shape), valid, reach_px=9))
    stacks = {"ideal": st.ideal, "unaligned": st.real, "aligned": aligned}
    if st.twin is not None:
        stacks["ideal twin"] = st.twin
    floors = {"aligned": stack_noise_floor(st.real, al, max_value=1023)[0]}
    out = {}
    if old is not None:
        aligned_old, _, al_old = old.align_stack(st.real)
        # the old warp rang past full scale (refused by the reader): clipped here
        stacks["old"] = np.minimum(aligned_old, 1023)
        out["old scale error %"] = float(100 * np.max(np.abs(al_old.scale / st.mags - 1.0)))
    if use_true:
        stacks["true warp"] = align_stack(st.real, alignment=true_alignment(st))[0]
        floors["true warp"] = stack_noise_floor(st.real, true_alignment(st), max_value=1023)[0]
    for name, s in stacks.items():
        r = reconstruct_field(s, focus_heights_um=st.zs, max_value=1023,
                              noise_floor=floors.get(name))
        h = np.where(mask, r.height_um, np.nan)
        rmse = compare_height_maps(h, st.truth, max_depth_um=float(st.zs[-1])).rmse_um
        out[name] = math.nan if rmse is None else rmse  # None: no pixel to compare
    out["scale error %"] = float(100 * np.max(np.abs(al.scale / st.mags - 1.0)))
    if drift:
        out["drift %"] = float(100 * np.max(np.abs(align_stack(st.ideal)[2].scale - 1.0)))
    return out


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--breathing", type=float, default=0.012, help="per frame")
    ap.add_argument("--noise", type=float, nargs="+", default=[0.01, 0.03])
    ap.add_argument("--seeds", type=int, nargs="+", default=[0, 1])
    ap.add_argument("--surfaces", nargs="+", choices=SURFACES,
                    default=["bumps", "waves", "terrace"])
    ap.add_argument("--textures", nargs="+", choices=TEXTURES, default=list(TEXTURES))
    ap.add_argument("--frames", type=int, default=21)
    ap.add_argument("--true", action="store_true", help="also warp with the true transforms")
    ap.add_argument("--twin", action="store_true",
                    help="also the breathing-free stack with noise of its own: how much the "
                         "ratio to the ideal stack moves with the noise alone")
    ap.add_argument("--drift", action="store_true",
                    help="also the scale estimated on the breathing-free stack")
    ap.add_argument("--against", type=Path, help="another tree: its stages/fields/align.py too")
    ap.add_argument("--size", type=int, nargs=2, default=[384, 288], metavar=("W", "H"))
    ap.add_argument("--span-um", type=float, default=1000.0, help="focus range, µm")
    ap.add_argument("--out", type=Path, help="also write the table there (Markdown)")
    args = ap.parse_args(argv)
    lines: list[str] = []

    def say(line: str) -> None:
        print(line, flush=True)
        lines.append(line)
    old = None if args.against is None else load_module(
        "_old_align", args.against / "stages" / "fields" / "align.py")
    t0 = time.perf_counter()
    rows = []
    say(f"{args.frames} frames of {args.size[0]} x {args.size[1]} px, {100 * args.breathing:g} "
          f"%/frame breathing; RMSE / the ideal stack's")
    say("| surface | texture | noise | seed | ideal µm | unaligned | aligned | "
          + ("old aligned | " if old else "") + ("true warp | " if args.true else "")
          + ("ideal, other noise | " if args.twin else "")
          + "max scale error % |" + (" old |" if old else "")
          + (" drift without breathing % |" if args.drift else ""))
    say("|---|---|---:|---:|---:|---:|---:|" + ("---:|" if old else "")
          + ("---:|" if args.true else "") + ("---:|" if args.twin else "") + "---:|"
          + ("---:|" if old else "")
          + ("---:|" if args.drift else ""))
    for noise in args.noise:
        for surf, tex in ((s, t) for s in args.surfaces for t in args.textures):
            for seed in args.seeds:
                st = make_stack(surface=surf, texture=tex, seed=stack_seed(surf, tex, seed),
                                breathing=args.breathing, noise=noise, n=args.frames,
                                width=args.size[0], height=args.size[1],
                                step_um=args.span_um / (args.frames - 1), twin=args.twin)
                r = score(st, use_true=args.true, old=old, drift=args.drift)
                rows.append(r)
                extra = f"{r['old'] / r['ideal']:.3f}x | " if old else ""
                extra += f"{r['true warp'] / r['ideal']:.3f}x | " if args.true else ""
                extra += f"{r['ideal twin'] / r['ideal']:.3f}x | " if args.twin else ""
                tail = f" {r['old scale error %']:.3f} |" if old else ""
                tail += f" {r['drift %']:.3f} |" if args.drift else ""
                say(f"| {surf} | {tex} | {noise:g} | {seed} | {r['ideal']:.2f} | "
                    f"{r['unaligned'] / r['ideal']:.3f}x | {r['aligned'] / r['ideal']:.3f}x | "
                    f"{extra}{r['scale error %']:.3f} |{tail}")
    keys = ("unaligned", "aligned", *(("old",) if old else ()),
            *(("true warp",) if args.true else ()), *(("ideal twin",) if args.twin else ()))
    for key in keys:
        ratios = [r[key] / r["ideal"] for r in rows]
        total = sum(r[key] for r in rows) / sum(r["ideal"] for r in rows)
        say(f"{key}: median {statistics.median(ratios):.3f}x, worst {max(ratios):.3f}x; "
              f"RMSE ratio of the sums {total:.3f}x")
    print(f"{len(rows)} stacks, {time.perf_counter() - t0:.0f} s", file=sys.stderr)
    if args.out is not None:
        from bench_pipeline import machine

        cmd = "python bench/bench_align_breathing.py " + " ".join(
            sys.argv[1:] if argv is None else argv)
        args.out.write_text(f"# Alignment under focus breathing: point-sampled stacks\n\n"
                            f"`{cmd.strip()}` ({machine()}; {len(rows)} stacks, "
                            f"{time.perf_counter() - t0:.0f} s)\n\n" + "\n".join(lines) + "\n")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
