"""The pixel aperture of an aligned stack and the noise floor its equalisation moves
(:mod:`sffscan.stages.fields.aperture`): known answers from the box a sensor pixel is."""

from __future__ import annotations

import math

import numpy as np
import pytest
from sffscan.stages.fields.align import Alignment
from sffscan.stages.fields.aperture import (
    APERTURE_TAPS,
    aperture_kernel,
    equalise_aperture,
    noise_floor_offsets,
    noise_sigma,
)
from sffscan.stages.fields.resample import TAPS, scale_warp, warp_frame
from sffscan.stages.fields.stationary import reconstruct_field
from sffscan.stages.focus_measure import focus_measure


def test_aperture_kernel_is_the_ratio_of_two_pixel_boxes() -> None:
    """Known answer: a pixel of width a has the response sinc(a f); the kernel turns a frame
    pixel of 1 / s reference px into the reference's 1 px: sinc(f) / sinc(f / s)."""
    n = np.arange(-APERTURE_TAPS, APERTURE_TAPS + 1)
    f = np.linspace(0.0, 0.4, 41)
    for s in (0.887, 0.95, 1.05, 1.127):
        k = aperture_kernel(s)
        assert k.size == 2 * APERTURE_TAPS + 1 and math.isclose(float(k.sum()), 1.0)
        got = (k[None, :] * np.cos(2 * np.pi * f[:, None] * n[None, :])).sum(axis=1)
        np.testing.assert_allclose(got, np.sinc(f) / np.sinc(f / s), rtol=2e-3)
    np.testing.assert_array_equal(aperture_kernel(1.0), [1.0])
    img = np.random.default_rng(0).random((20, 30))
    np.testing.assert_array_equal(equalise_aperture(img, 1.0, 1.0), img)
    with pytest.raises(ValueError, match="scale must be > 0"):
        aperture_kernel(0.0)


def test_a_magnified_frame_gets_the_reference_pixels_aperture() -> None:
    """A sinusoid of 0.3 cycles/px integrated over each pixel (the box a sensor pixel is),
    seen at magnification 1 (the reference) and 1.12 (pixels 1 / 1.12 px wide in the
    reference's units). Warped back with the aperture, the magnified frame's amplitude is the
    reference's within 1 %; without it, it is larger by the ratio of the two boxes' responses
    (sinc(0.3 / 1.12) / sinc(0.3): 1.032), which a focus measure reads as a sharper frame."""
    h, w, f, s = 8, 400, 0.3, 1.12
    c = (w - 1) / 2.0

    def seen(mag: float) -> np.ndarray:  # frame px u sees the world at c + (u - c) / mag
        u = np.arange(w, dtype=np.float64)
        lo, hi = c + (u - 0.5 - c) / mag, c + (u + 0.5 - c) / mag  # the pixel's box
        row = (np.cos(2 * np.pi * f * lo) - np.cos(2 * np.pi * f * hi)) / (
            2 * np.pi * f * (hi - lo))  # the mean of sin(2 pi f x) over the box
        return np.tile(0.5 + 0.4 * row, (h, 1))

    m = np.array([[s, 0.0, c - s * c], [0.0, 1.0, 0.0]])  # reference px -> frame px
    inner = slice(4 * TAPS, w - 4 * TAPS)

    def amplitude(row: np.ndarray) -> float:
        x = np.arange(w, dtype=np.float64)[inner]
        basis = np.stack([np.sin(2 * np.pi * f * x), np.cos(2 * np.pi * f * x), np.ones_like(x)])
        coef = np.linalg.lstsq(basis.T, row[inner], rcond=None)[0]
        return float(np.hypot(coef[0], coef[1]))

    ref = amplitude(seen(1.0)[h // 2])
    with_ap = amplitude(scale_warp(seen(s), m, aperture=True)[h // 2])
    without = amplitude(scale_warp(seen(s), m)[h // 2])
    box = float(np.sinc(f / s) / np.sinc(f))
    print(f"amplitude / reference's: aperture {with_ap / ref:.4f}, without {without / ref:.4f} "
          f"(box ratio {box:.4f})")
    assert abs(with_ap / ref - 1.0) < 0.01
    assert abs(without / ref - box) < 0.005 and box > 1.03


def test_noise_sigma_reads_white_noise_under_texture() -> None:
    """Immerkaer's estimator, made robust by the median: white noise of sigma 0.02 over a
    ramp and a coarse texture reads within 3 %; no noise reads ~0."""
    rng = np.random.default_rng(2)
    yy, xx = np.mgrid[0:300, 0:400] / 400.0
    scene = 0.3 + 0.4 * xx + 0.1 * np.sin(2 * np.pi * 6 * yy) * np.cos(2 * np.pi * 4 * xx)
    got = noise_sigma(scene + rng.normal(0.0, 0.02, scene.shape))
    assert abs(got / 0.02 - 1.0) < 0.03
    assert noise_sigma(scene) < 1e-3
    with pytest.raises(ValueError, match="H, W >= 3"):
        noise_sigma(np.zeros((2, 9)))


def test_the_noise_floor_is_the_warps_again_once_the_offsets_are_taken_off() -> None:
    """A stack of pure sensor noise (white, sigma 0.03, a new draw per frame), warped as 25
    frames breathing 1.2 %/frame: with the aperture equalised, the mean GLVM of its levels
    tilts by more than 20 % from the first frame to the last (the demagnified frames' noise
    amplified, the magnified ones' attenuated); with :func:`noise_floor_offsets` (measured
    on another noise patch) taken off, every level is within 3 % of the same draws warped
    without the aperture, whose floor is level but for the reference frame, which is not
    resampled (the sinc's interpolation leaves the others ~10 % less noise). An identity
    alignment has zero offsets."""
    n, size, sigma = 25, 200, 0.03
    mags = 1.012 ** (np.arange(n) - n // 2)
    al = Alignment.breathing(mags, (size, size))
    c = (size - 1) / 2.0  # a breathing about the centre: the centre stays, the corners scale
    np.testing.assert_allclose(al.matrices @ [c, c, 1.0], np.full((n, 2), c))
    np.testing.assert_allclose(al.matrices @ [0.0, 0.0, 1.0], np.outer(c - mags * c, [1, 1]))
    rng = np.random.default_rng(7)
    draws = [rng.normal(0.5, sigma, (size, size)) for _ in range(n)]

    def floor(aperture: bool) -> np.ndarray:
        warped = np.stack([warp_frame(d, m, aperture=aperture)
                           for d, m in zip(draws, al.matrices, strict=True)])
        vol = focus_measure(warped.astype(np.float32), window=9)
        return np.asarray(vol[:, 20:-20, 20:-20].mean(axis=(1, 2)), np.float64)

    with_ap, without = floor(True), floor(False)
    off = noise_floor_offsets(al, sigma=sigma, window=9)
    assert off[0] > 0 > off[-1] and off[n // 2] == 0.0
    raw_tilt = (with_ap[0] - with_ap[-1]) / with_ap[n // 2]
    fixed = with_ap - off
    print(f"tilt of the noise floor, first to last frame: {raw_tilt:.3f} with the aperture, "
          f"{(fixed[0] - fixed[-1]) / fixed[n // 2]:.3f} corrected, "
          f"{(without[0] - without[-1]) / without[n // 2]:.3f} without the aperture")
    assert raw_tilt > 0.2
    np.testing.assert_allclose(fixed, without, rtol=0.03)
    others = np.delete(without, n // 2)
    np.testing.assert_allclose(others, np.median(others), rtol=0.03)
    same = Alignment.breathing(np.ones(4), (size, size))
    np.testing.assert_array_equal(noise_floor_offsets(same, sigma=sigma), np.zeros(4))
    np.testing.assert_array_equal(noise_floor_offsets(al, sigma=0.0), np.zeros(n))


def test_reconstruct_field_takes_the_noise_floor_off_and_checks_its_length() -> None:
    rng = np.random.default_rng(1)
    stack = rng.random((5, 40, 40)).astype(np.float32)
    base = reconstruct_field(stack, focus_heights_um=np.arange(5.0))
    none = reconstruct_field(stack, focus_heights_um=np.arange(5.0), noise_floor=np.zeros(5))
    np.testing.assert_array_equal(base.levels, none.levels)
    # a large floor on level 0 only: no pixel peaks there any more
    tilted = reconstruct_field(stack, focus_heights_um=np.arange(5.0),
                               noise_floor=np.array([10.0, 0, 0, 0, 0]))
    assert (np.rint(tilted.levels) != 0).all() and (np.rint(base.levels) == 0).any()
    with pytest.raises(ValueError, match="noise_floor must hold 5 finite values"):
        reconstruct_field(stack, focus_heights_um=np.arange(5.0), noise_floor=np.zeros(4))
