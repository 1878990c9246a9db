"""``stack --align`` on strong focus breathing (issue 24, item 3), on a stack made here rather
than by the repository's simulator: another surface (Gaussian hills and pits over the whole
focus range), another texture (random discs, some bright enough to saturate), heavy sensor
noise, 10 bits. Bar: the aligned stack within 1.10x the RMSE of the same stack without
breathing; every frame's scale within 2 %."""

from __future__ import annotations

import math

import cv2
import numpy as np
import pytest
from sffscan.pipeline.metrology.compare import compare_height_maps
from sffscan.stages.fields.align import align_stack, mask_uncovered
from sffscan.stages.fields.stationary import reconstruct_field

N, W, H = 25, 192, 144
BREATHING = 0.012  # per frame
NOISE = 0.045  # of full scale (variance 0.002)
STEP_UM = 40.0
BLUR_PX_PER_UM = 0.05


def make_stack(seed: int) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """(breathing stack, ideal stack, truth µm, focus table µm, true scale per frame)."""
    rng = np.random.default_rng(seed)
    mags = (1.0 + BREATHING) ** (np.arange(N) - N // 2)
    pad = int(math.ceil(0.5 * W * (1.0 / mags.min() - 1.0))) + 8
    hh, ww = H + 2 * pad, W + 2 * pad
    zs = np.arange(N) * STEP_UM
    yy, xx = np.mgrid[0:hh, 0:ww].astype(np.float64)
    z = np.zeros((hh, ww))
    for _ in range(10):
        cx, cy, r = rng.uniform(0, ww), rng.uniform(0, hh), rng.uniform(0.08, 0.25) * W
        z += rng.choice([-1.0, 1.0]) * np.exp(-((xx - cx) ** 2 + (yy - cy) ** 2) / (2 * r * r))
    z = (0.02 + 0.96 * (z - z.min()) / np.ptp(z)) * zs[-1]
    tex = np.full((hh, ww), 0.35, np.float32)
    for _ in range(hh * ww // 40):
        cv2.circle(tex, (int(rng.integers(0, ww)), int(rng.integers(0, hh))),
                   int(rng.integers(1, 4)), float(rng.uniform(0.1, 1.05)), -1)
    tex = cv2.GaussianBlur(tex, (0, 0), 0.7)
    sigmas = [0.0] + [0.5 * math.sqrt(2.0) ** i for i in range(12)]
    bank = np.stack([tex] + [cv2.GaussianBlur(tex, (0, 0), s) for s in sigmas[1:]])
    ii, jj = np.indices(z.shape)
    real, ideal = [], []
    for k in range(N):
        u = np.interp(0.6 + BLUR_PX_PER_UM * np.abs(z - zs[k]), sigmas, np.arange(len(sigmas)))
        lo = np.floor(u).astype(int)
        hi = np.minimum(lo + 1, len(sigmas) - 1)
        t = (u - lo).astype(np.float32)
        img = (1 - t) * bank[lo, ii, jj] + t * bank[hi, ii, jj]
        for m, out in ((mags[k], real), (1.0, ideal)):
            a = 1.0 / m  # frame pixel (u, v) sees the world at centre + (u, v - centre) / m
            mat = np.array([[a, 0.0, pad + (W - 1) / 2.0 * (1 - a)],
                            [0.0, a, pad + (H - 1) / 2.0 * (1 - a)]])
            f = cv2.warpAffine(img, mat, (W, H), flags=cv2.INTER_LANCZOS4 | cv2.WARP_INVERSE_MAP)
            f = f + rng.normal(0.0, NOISE, f.shape).astype(np.float32)
            out.append(np.clip(np.rint(f * 1023), 0, 1023).astype(np.uint16))
    truth = z[pad:pad + H, pad:pad + W].astype(np.float32)
    return np.stack(real), np.stack(ideal), truth, zs, mags


# One stack on which the code before this fix failed twice: its Lanczos warp rang past full
# scale (the reconstruction refused the aligned stack) and the scale chain drifted 6 % on
# the noisy frames. This is a regression test of those two defects, not evidence for the
# issue's general bar: on other seeds of this heavy-noise generator the aligned stack is
# 1.02-1.29x the no-breathing one (bench/bench_align_breathing.py), and the 1.10x bar is
# not met there (see the note).
@pytest.mark.parametrize("seed", [5])
def test_aligned_breathing_stack_neither_rings_nor_drifts(seed: int) -> None:
    real, ideal, truth, zs, mags = make_stack(seed)
    assert (real == 1023).any()  # saturated pixels: the warp must not ring past full scale
    aligned, valid, al = align_stack(real)
    assert aligned.max() <= 1023
    err = al.scale / mags - 1.0
    mask = np.isfinite(mask_uncovered(np.zeros(valid.shape), valid, reach_px=9))

    def rmse(stack: np.ndarray) -> float:
        h = reconstruct_field(stack, focus_heights_um=zs, max_value=1023).height_um
        return compare_height_maps(np.where(mask, h, np.nan), truth,
                                   max_depth_um=float(zs[-1])).rmse_um

    base, unaligned, got = rmse(ideal), rmse(real), rmse(aligned)
    print(f"\nRMSE no breathing {base:.2f} µm, {100 * BREATHING:g} %/frame unaligned "
          f"{unaligned / base:.2f}x, aligned {got / base:.3f}x; scale error per frame, %: "
          f"{np.array2string(100 * err, precision=2)}")
    assert unaligned > 1.1 * base  # the breathing matters
    assert got <= 1.10 * base
    assert np.abs(err).max() < 0.02
