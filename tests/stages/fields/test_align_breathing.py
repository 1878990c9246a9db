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
from sffscan.stages.depth import DEFAULT_METHOD, depth_from_focus
from sffscan.stages.fields.align import align_stack, mask_uncovered
from sffscan.stages.fields.aperture import stack_noise_floor
from sffscan.stages.fields.resample import TAPS, scale_warp
from sffscan.stages.fields.stationary import StackSettings, reconstruct_field
from sffscan.stages.focus_measure import focus_measure
from sffscan.stages.sim.families import family_stack

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
    tex = np.asarray(cv2.GaussianBlur(tex, (0, 0), 0.7), np.float32)
    sigmas = [0.0] + [0.5 * math.sqrt(2.0) ** i for i in range(12)]
    bank = np.stack([tex] + [cv2.GaussianBlur(tex, (0, 0), s) for s in sigmas[1:]])
    ii, jj = np.indices(z.shape)
    real: list[np.ndarray] = []
    ideal: list[np.ndarray] = []
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
            f = f + np.asarray(rng.normal(0.0, NOISE, f.shape), np.float32)
            out.append(np.clip(np.rint(f * 1023), 0, 1023).astype(np.uint16))
    truth = np.asarray(z[pad:pad + H, pad:pad + W], np.float32)
    return np.stack(real), np.stack(ideal), truth, zs, mags


# One stack on which older code failed twice: its Lanczos warp rang past full scale (the
# reconstruction refused the aligned stack) and the scale chain drifted 6 % on the noisy
# frames. A regression test of those two defects. Scored over the pixels every aligned
# frame covers (less the windowed sinc's reach, 8 px): there the unaligned stack is 1.07x
# the no-breathing one, aligned as `stack --align` does 1.09x (the windowed sinc alone
# 1.07x, the 8-tap Lanczos warp before it 1.09x). Its frames are point samples of the world
# (no pixel aperture) with heavy noise: the aperture equalised without the noise floor's
# correction gave 1.53x here. Heights by `adaptive` (the default until 2026-12-02, the method
# these figures were measured with); the default's are checked against them.
@pytest.mark.parametrize("seed", [5])
def test_aligned_breathing_stack_neither_rings_nor_drifts(seed: int) -> None:
    real, ideal, truth, zs, mags = make_stack(seed)
    assert (real == 1023).any()  # saturated pixels: the warp must not ring past full scale
    aligned, valid, al = align_stack(real)
    assert aligned.max() <= 1023
    err = al.scale / mags - 1.0
    mask = np.isfinite(mask_uncovered(np.zeros(valid.shape), valid, reach_px=9))

    floor, sigma = stack_noise_floor(real, al, max_value=1023)
    assert abs(1023 * sigma / (1023 * NOISE) - 1.0) < 0.05  # the sensor noise, estimated

    def rmse(stack: np.ndarray, floor: np.ndarray | None = None,
             method: str = "adaptive") -> float:
        h = reconstruct_field(stack, focus_heights_um=zs, max_value=1023, noise_floor=floor,
                              settings=StackSettings(method=method)).height_um
        got = compare_height_maps(np.where(mask, h, np.nan), truth,
                                  max_depth_um=float(zs[-1])).rmse_um
        assert got is not None
        return float(got)

    base, unaligned, got = rmse(ideal), rmse(real), rmse(aligned, floor)
    default = {s: rmse(*a, method=DEFAULT_METHOD) for s, a in
               (("ideal", (ideal,)), ("aligned", (aligned, floor)))}
    print(f"\nRMSE no breathing {base:.2f} µm, {100 * BREATHING:g} %/frame unaligned "
          f"{unaligned / base:.2f}x, aligned {got / base:.3f}x; scale error per frame, %: "
          f"{np.array2string(100 * err, precision=2)}; {DEFAULT_METHOD}: no breathing "
          f"{default['ideal']:.2f} µm, aligned {default['aligned']:.2f} µm "
          f"({default['aligned'] / default['ideal']:.3f}x)")
    assert unaligned > 1.05 * base  # the breathing matters
    assert got <= 1.10 * base
    assert np.abs(err).max() < 0.02
    # the default: until 2026-12-05 adaptive_centroid's depth here (a 5-level centroid at the
    # peak pixels, where adaptive fits 3 levels), closer to the truth than adaptive on both
    # stacks (18.72 against 19.41 µm; aligned 20.74 against 21.08; its ratio 1.108x). Since
    # then its fallback takes the 9-level centroid where that map's scatter and departure say
    # it errs less (stages/depth_window.py), as it does on both stacks here, and that
    # centroid errs a little more: 19.43 against 19.41 µm, aligned 20.78 against 21.08
    # (1.069x). Checked: within 1 % of adaptive, or better, on both stacks; the alignment
    # within issue 24's 1.10x.
    assert default["ideal"] < 1.01 * base and default["aligned"] < got
    assert default["aligned"] <= 1.10 * default["ideal"]


# ----------------------------------------------------------------------------- the warp


def test_scale_warp_keeps_fine_texture_that_lanczos_blurs() -> None:
    """A sinusoid of 0.35 cycles/px magnified by 1.2 %: the windowed sinc reproduces it
    (within 1 % of its amplitude), OpenCV's 8-tap Lanczos attenuates it by a few % depending
    on the sub-pixel phase; an identity map is exact; a rotation is refused."""
    h, w = 40, 200
    xx = np.arange(w, dtype=np.float64)
    f = 0.35

    def wave(x: np.ndarray) -> np.ndarray:
        return 0.5 + 0.4 * np.sin(2 * np.pi * f * x)

    img = np.tile(wave(xx), (h, 1))
    s, c = 1.012, (w - 1) / 2.0
    m = np.array([[s, 0.0, c - s * c], [0.0, 1.0, 0.0]])
    want = wave(s * xx + c - s * c)
    inner = slice(3 * TAPS, w - 3 * TAPS)
    got = scale_warp(img, m)[h // 2, inner]
    lz = cv2.warpAffine(img, m, (w, h), flags=cv2.INTER_LANCZOS4 | cv2.WARP_INVERSE_MAP,
                        borderMode=cv2.BORDER_REPLICATE)[h // 2, inner]
    err_sinc = float(np.abs(got - want[inner]).max())
    err_lz = float(np.abs(lz - want[inner]).max())
    print(f"max error, amplitude 0.4: sinc {err_sinc:.4f}, Lanczos4 {err_lz:.4f}")
    assert err_sinc < 0.004 and err_lz > 3 * err_sinc
    grey = (img * 1000).astype(np.uint16)
    np.testing.assert_array_equal(scale_warp(grey, np.eye(2, 3)), grey)
    with pytest.raises(ValueError, match="rotation or shear"):
        scale_warp(img, np.array([[1.0, 0.01, 0.0], [-0.01, 1.0, 0.0]]))


def test_breathing_family_stack_aligns_like_the_stack_without_breathing() -> None:
    """Issue 24 item 3 on a stack of the synthetic families (not the repository's sets):
    ``slopes`` (a thin lens' lopsided blur, a slope at the focus window's limit), 1.2 %/frame
    breathing, rendered 4x finer and integrated per pixel; its breathing-free twin has the same
    world, texture and noise. The aligned stack's RMSE within 1.10x the twin's (the 8-tap
    Lanczos warp: 1.16x on this stack, the untouched reference frame being the sharpest;
    the same scale estimate, within 0.5 % per frame)."""
    n, b = 21, 0.012
    real = family_stack("slopes", 3, size_px=80, n_levels=n, breathing=b)
    twin = family_stack("slopes", 3, size_px=80, n_levels=n, breathing=0.0,
                        pad_for_breathing=b)
    np.testing.assert_array_equal(real.images[n // 2], twin.images[n // 2])  # the reference
    aligned, valid, al = align_stack(real.images)
    mags = (1.0 + b) ** (np.arange(n) - n // 2)
    assert np.abs(al.scale / mags - 1.0).max() < 0.006
    mask = np.isfinite(mask_uncovered(np.zeros(valid.shape), valid, reach_px=9))
    truth = real.truth_um / 10.0

    def rmse(stack: np.ndarray) -> float:
        d = depth_from_focus(focus_measure(stack, window=9), method="adaptive")[0]
        return float(np.sqrt(np.mean((d - truth)[mask] ** 2)))

    base, unaligned, got = rmse(twin.images), rmse(real.images), rmse(aligned)
    print(f"slopes seed 3: no breathing {base:.3f} levels; unaligned {unaligned / base:.2f}x, "
          f"aligned {got / base:.3f}x")
    assert unaligned > 1.2 * base
    assert got <= 1.10 * base


def test_a_featureless_frame_takes_the_mean_breathing_step(
        caplog: pytest.LogCaptureFixture) -> None:
    """ECC cannot align a frame without texture (a far-defocused end of a stack: seen on a
    ``steps`` family stack, bench/align_families_results.md). For the ``"scale"`` model
    that step takes the other steps' mean (a lens breathes smoothly) with a warning,
    instead of failing the whole stack; other models still refuse, naming the frame."""
    rng = np.random.default_rng(3)
    n, size, b = 8, 96, 0.01
    tex = np.asarray(cv2.GaussianBlur(rng.random((size, size)).astype(np.float32), (0, 0),
                                      1.5), np.float32)
    c = (size - 1) / 2.0
    frames = []
    for k in range(n):
        s = (1.0 + b) ** (n // 2 - k)  # frame k shows the world magnified (1 + b)^(k - ref)
        frames.append(scale_warp(tex, np.array([[s, 0.0, c - s * c], [0.0, s, c - s * c]])))
    stack = np.stack(frames)
    stack[-1] = 0.5  # featureless
    with caplog.at_level("WARNING"):
        _, _, al = align_stack(stack)
    assert "frame 7: ECC did not converge against frame 6" in caplog.text
    assert np.isnan(al.correlation[-1]) and np.isfinite(al.correlation[:-1]).all()
    want = (1.0 + b) ** (np.arange(n) - n // 2)
    np.testing.assert_allclose(al.scale, want, rtol=2e-3)  # the last one extrapolated
    with pytest.raises(ValueError, match="frame 7: cannot align to frame 6"):
        align_stack(stack, model="similarity")
