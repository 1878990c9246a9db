"""SPC's range guard takes its widths from a floor that noise does not lower
(stages/depth_floor.py)."""

from __future__ import annotations

import math

import numpy as np
import pytest
from sffscan.stages.block_depth import SPC_BLOCKS, block_choice, depth_rows
from sffscan.stages.curve_shape import width_from_sums
from sffscan.stages.depth import depth_from_focus, first_argmax
from sffscan.stages.depth_choice import stack_choice
from sffscan.stages.depth_floor import (
    GuardFloor,
    expected_extreme,
    guard_floor,
    guard_width,
    level_noise,
)
from sffscan.stages.depth_harmonics import curve_moments
from sffscan.stages.depth_levels import median_filter_levels
from sffscan.stages.depth_spc import spc_in_range
from sffscan.stages.depth_statistics import row_median


def gaussians(peaks: np.ndarray, n: int, sigma: float, floor: float = 0.2) -> np.ndarray:
    k = np.arange(n, dtype=np.float64)[:, None, None]
    return (floor + np.exp(-((k - peaks) ** 2) / (2.0 * sigma**2))).astype(np.float32)


def widths(vol: np.ndarray, floor: GuardFloor | None) -> tuple[np.ndarray, np.ndarray]:
    """The widths from the minimum and the guard's, from the curves' sums."""
    h0, _, re, im = curve_moments(vol)
    n = vol.shape[0]
    return (width_from_sums(h0, np.hypot(re, im), vol.min(axis=0), n),
            guard_width(h0, np.hypot(re, im), vol.min(axis=0), n, floor))


def test_expected_extreme_matches_the_tabulated_normal_order_statistics() -> None:
    # E[max of n standard normals]: 1 / sqrt(pi) for n = 2; 1.16296 (n = 5), 1.53875
    # (n = 10), 1.86748 (n = 20), 2.24907 (n = 50) in Harter's tables (1961); Blom's
    # formula within 0.03
    for n, exact in ((2, 1.0 / math.sqrt(math.pi)), (5, 1.16296), (10, 1.53875),
                     (20, 1.86748), (50, 2.24907)):
        assert expected_extreme(n) == pytest.approx(exact, abs=0.03)
    assert expected_extreme(1) == 0.0 and expected_extreme(0) == 0.0


@pytest.mark.parametrize("m", [5, 6, 48, 49])
def test_row_median_is_numpys_median_of_each_row(m: int) -> None:
    # odd and even rows, ties (a third of the values 0) and infinities: np.median's values
    # bit for bit, float32 in, float32 out
    rng = np.random.default_rng(m)
    x = rng.standard_normal((200, m)).astype(np.float32)
    x[rng.random(x.shape) < 0.3] = 0.0
    x[rng.random(x.shape) < 0.05] = np.inf
    got = row_median(x)
    assert got.dtype == np.float32
    np.testing.assert_array_equal(got, np.median(x, axis=1))
    assert row_median(np.array([[3.0, 1.0, 2.0, 10.0]]))[0] == 2.5


def test_level_noise_reads_the_floor_not_the_peak() -> None:
    rng = np.random.default_rng(3)
    clean = gaussians(rng.uniform(12, 38, (40, 40)), 50, 2.5)
    centre = first_argmax(clean)
    # clean curves: the floor's second differences are a Gaussian tail's, about nothing
    assert level_noise(clean, centre) < 1e-3
    for sigma in (0.005, 0.02, 0.08, 0.3):
        noisy = clean + rng.normal(0.0, sigma, clean.shape).astype(np.float32)
        assert level_noise(noisy, median_filter_levels(first_argmax(noisy), 11, 50)) \
            == pytest.approx(sigma, rel=0.1)
    # no curve judged (a mask), N < 5: NaN
    assert math.isnan(level_noise(clean, centre, np.zeros((40, 40), bool)))
    assert math.isnan(level_noise(clean[:4], centre.clip(0, 3)))
    assert all(math.isnan(v) for v in guard_floor(clean, centre, np.zeros((40, 40), bool)))


def test_guard_width_is_near_the_curves_sigma_where_the_minimum_overstates_it() -> None:
    rng = np.random.default_rng(4)
    clean = gaussians(rng.uniform(15, 35, (32, 32)), 50, 2.5)
    old, new = widths(clean, None)  # no floor given: the minimum, as before
    np.testing.assert_array_equal(old, new)
    old, new = widths(clean, guard_floor(clean, first_argmax(clean)))  # no noise: same
    np.testing.assert_allclose(new, old, rtol=1e-3)
    noisy = clean + rng.normal(0.0, 0.05, clean.shape).astype(np.float32)
    floor = guard_floor(noisy, median_filter_levels(first_argmax(noisy), 11, 50))
    old, new = widths(noisy, floor)
    # the minimum lies ~2 noise sigmas under the floor: its width overstates sigma 2.5
    # 3.6x (measured); the guard's lift, the extreme of half the levels, a little less
    # than that: 1.75x (a narrow peak's width is that sensitive to its floor)
    assert np.median(old) > 3.0 * 2.5
    assert 2.5 < np.median(new) < 0.6 * np.median(old) and 2.5 < floor.width < 2.0 * 2.5
    # where the area above the raised floor does not exceed |H_1|: the typical width
    h0, _, re, im = curve_moments(noisy)
    area = h0 - 50 * (noisy.min(axis=0) + expected_extreme(25) * floor.noise)
    undefined = ~(area > np.hypot(re, im))
    assert undefined.any() and (new[undefined] == floor.width).all()


def test_an_even_noisy_stack_keeps_spc_away_from_the_ends_and_off_them() -> None:
    """Peaks at levels 8..42 of 50 (sigma 2.5: at least 3 widths from an end) under heavy
    noise: the minimum's widths (~4x sigma here) sent those within ~16 levels of an end to
    the fallback; the guard's keep SPC there. Curves cut by an end (peaks at level 1) are
    still refused."""
    rng = np.random.default_rng(5)
    peaks = rng.uniform(8, 42, (48, 48))
    peaks[:, :6] = 1.0  # a strip at the range's start: cut curves
    vol = gaussians(peaks, 50, 2.5) + rng.normal(0.0, 0.08, (50, 48, 48)).astype(np.float32)
    choice = stack_choice(vol, first_argmax(vol))
    assert choice.spc and choice.floor is not None
    assert choice.floor.noise == pytest.approx(0.08, rel=0.15)
    spc = depth_from_focus(vol, method="spc")[0]
    old, new = widths(vol, choice.floor)
    middle = (slice(None), slice(12, None))
    assert spc_in_range(spc, old, 50)[middle].mean() < 0.7
    assert spc_in_range(spc, new, 50)[middle].mean() > 0.9
    assert spc_in_range(spc, new, 50)[:, :6].mean() < 0.05
    default = depth_from_focus(vol, method="shape_select")[0]
    fallback = depth_from_focus(vol, method="adaptive_centroid")[0]

    def rmse(d: np.ndarray, where: tuple[slice, slice]) -> float:
        return float(np.sqrt(np.mean((d - peaks)[where] ** 2)))

    strip = (slice(None), slice(0, 6))
    assert rmse(default, middle) < 0.5 * rmse(fallback, middle)
    assert rmse(default, strip) < 1.1 * rmse(fallback, strip) < rmse(spc, strip)


def test_a_scan_block_guards_with_its_choices_floor_whatever_its_bands() -> None:
    rng = np.random.default_rng(6)
    peaks = rng.uniform(8, 42, (128, 40))  # 8 x 5 curves judged (every 16th row, 8th column)
    vol = gaussians(peaks, 50, 2.5) + rng.normal(0.0, 0.08, (50, 128, 40)).astype(np.float32)
    argmax = first_argmax(vol)
    method, _, floor, _, weight = block_choice(vol, argmax)
    assert method in SPC_BLOCKS and floor is not None and 0.5 <= weight <= 1.0
    assert floor.noise == pytest.approx(0.08, rel=0.15)

    def rows(r0: int, r1: int, floor: GuardFloor | None) -> np.ndarray:
        sums = np.empty((3, r1 - r0, 40), np.float32)
        low = np.empty((r1 - r0, 40), np.float32)
        halo0, halo1 = max(r0 - 9, 0), min(r1 + 9, 128)  # the median's and spread's reach
        return depth_rows(vol[:, r0:r1], argmax[halo0:halo1], None, (0, r1 - r0),
                          slice(r0 - halo0, r1 - halo0), slice(0, 40), sums, low,
                          method=method, n_levels=50, median_size=11, spread_size=9,
                          streaming=False, keep_low=False, floor=floor)[0]

    whole = rows(0, 128, floor)
    np.testing.assert_array_equal(np.vstack([rows(0, 50, floor), rows(50, 128, floor)]), whole)
    # SPC (from the block's float32 sums: equal to float32 round-off) where it is kept
    spc = depth_from_focus(vol, method="spc")[0]
    before = rows(0, 128, None)  # the minimum's widths
    kept, kept_before = (np.isclose(d, spc, rtol=0, atol=1e-3) for d in (whole, before))
    assert kept.mean() > 0.9 and kept_before.mean() < 0.7
