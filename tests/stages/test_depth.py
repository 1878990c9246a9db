"""Tests of sffscan.stages.depth: peak localisation, SPC identity, height mapping, pertuz depth."""

from __future__ import annotations

import math
from pathlib import Path

import cv2
import numpy as np
import pytest
import scipy.io
from scipy import ndimage
from sffscan.stages.depth import (
    CANDIDATE_METHODS,
    DEFAULT_METHOD,
    DEPTH_METHODS,
    ESTIMATORS,
    all_in_focus,
    depth_from_focus,
    depth_from_harmonics,
    first_argmax,
    harmonic_table,
    levels_from_heights,
    levels_to_height,
    median_filter_levels,
)
from sffscan.stages.depth_harmonics import magnitude
from sffscan.stages.depth_levels import check_volume, raise_not_finite
from sffscan.stages.focus_measure import focus_measure, to_unit_float

# Largest |depth - true peak| on clean sampled Gaussians (sigma 2 at N = 30, 3 at N = 50,
# zero baseline, peaks at least 4 sigma from both ends), in levels. Measured worst cases:
# argmax 0.49992 (quantisation), gauss3 2e-6 (exact for a Gaussian; float32 logs),
# quadratic3 0.012 (sigma 2) / 0.005 (sigma 3), centroid 2.4e-4, pc and spc 1.6e-4 (the
# Gaussian tails cut off beyond the ends), wcentroid 0.029, adaptive 0.0068.
PEAK_TOL = {
    "argmax": 0.5,
    "gauss3": 1e-4,
    "quadratic3": 0.02,
    "centroid": 1e-3,
    "pc": 1e-3,
    "spc": 1e-3,
    # the 9-level window about the filtered argmax cuts a Gaussian off-centre, and its
    # minimum is subtracted: a bias away from the window's centre (its far end zeroed),
    # measured 0.015 (sigma 2) / 0.029 (sigma 3) levels
    "wcentroid": 0.04,
    # the Gaussian 3-point fit where the filtered peaks span <= 2 levels over 9 x 9 px
    # (exact: 1.2e-6); where this ramp spans 3 (sigma 3), the 11-level centroid: 0.0068
    "adaptive": 0.01,
    # even curves: the 5-level centroid where the filtered peaks span <= 2 levels; the
    # window's minimum subtracted pushes away from its centre (its far end zeroed):
    # measured 0.067 (sigma 2) / 0.077 (sigma 3) levels
    "adaptive_centroid": 0.08,
    # even, clean curves: SPC's depth (test_candidates_recover_gaussian_peak asserts it)
    "shape_select": 1e-3,
}


def spc_by_roll(volume: np.ndarray, *, median_size: int = 11) -> np.ndarray:
    """SPC by its literal definition, the reference of ``depth_from_focus(method="spc")``:
    roll every curve, PC by FFT, undo the shift.

    Each pixel's curve is circularly shifted with ``np.roll`` semantics by
    ``s = round(N/2) - a_med`` (a_med: the argmax median filtered over ``median_size`` px;
    MATLAB's round, halves away from zero), its first DFT harmonic is taken with
    ``np.fft.fft`` in float64, ``d = (-angle(H_1) N / (2 pi)) mod N`` and ``d - s`` is
    returned, (H, W) float64. Slow.
    """
    vol = check_volume(volume)
    if not np.isfinite(vol).all():
        raise_not_finite(vol)
    n = vol.shape[0]
    s = (n + 1) // 2 - median_filter_levels(first_argmax(vol), median_size, n)
    k = np.arange(n).reshape(n, 1, 1)
    rolled = np.take_along_axis(vol, (k - s[None]) % n, axis=0)  # rolled[k] = y[k - s]
    h1 = np.fft.fft(rolled.astype(np.float64), axis=0)[1]
    d = np.mod(-np.angle(h1) * n / (2.0 * np.pi), n)
    return d - s


def gaussian_volume(peaks: np.ndarray, n: int, sigma: float) -> np.ndarray:
    """(n, *peaks.shape) float32 volume of sampled Gaussians exp(-(k - c)^2 / (2 sigma^2))."""
    k = np.arange(n, dtype=np.float64).reshape((n,) + (1,) * peaks.ndim)
    return np.exp(-((k - peaks) ** 2) / (2.0 * sigma**2)).astype(np.float32)


def circular_diff(a: np.ndarray, b: np.ndarray, n: int) -> np.ndarray:
    """a - b reduced to [-n/2, n/2): the difference of two positions on a circle of n levels."""
    return np.mod(a - b + n / 2.0, n) - n / 2.0


# ----------------------------------------------------------------------------- peak recovery


@pytest.mark.parametrize("method", DEPTH_METHODS)
@pytest.mark.parametrize(("n", "sigma"), [(30, 2.0), (50, 3.0)])
def test_recovers_gaussian_peak(method: str, n: int, sigma: float) -> None:
    # a smooth surface: peaks ramp across the columns at fractional positions, so the median
    # filtered argmax of spc is each pixel's own argmax up to a level
    margin = 4.0 * sigma
    cols = np.linspace(margin, n - 1 - margin, 97) + 0.123
    peaks = np.broadcast_to(cols, (13, cols.size)) + np.linspace(0, 0.05, 13)[:, None]
    depth, confidence = depth_from_focus(gaussian_volume(peaks, n, sigma), method=method)
    assert depth.dtype == np.float32 and depth.shape == peaks.shape
    assert confidence.dtype == np.float32 and confidence.shape == peaks.shape
    err = np.abs(depth - peaks).max()
    assert err <= PEAK_TOL[method], f"{method}: max error {err:.3g} levels"
    if method == "argmax":
        np.testing.assert_array_equal(depth, np.rint(peaks))


def test_three_point_fallbacks() -> None:
    n = 10
    vol = np.zeros((n, 1, 4), np.float32)
    vol[:, 0, 0] = np.linspace(1.0, 0.1, n)  # maximum at level 0
    vol[:, 0, 1] = np.linspace(0.1, 1.0, n)  # maximum at level N-1
    vol[:, 0, 2] = 0.5
    vol[4:7, 0, 2] = 1.0  # flat top of three equal values: first index 4
    vol[:, 0, 3] = 0.0
    vol[5, 0, 3] = 1.0  # zero neighbours: log undefined, parabola fine
    for method in ("gauss3", "quadratic3"):
        depth, _ = depth_from_focus(vol, method=method)
        assert depth[0, 0] == 0 and depth[0, 1] == n - 1
    g, _ = depth_from_focus(vol, method="gauss3")
    q, _ = depth_from_focus(vol, method="quadratic3")
    assert g[0, 3] == 5 and q[0, 3] == 5  # symmetric neighbours
    assert g[0, 2] == 4.5 and q[0, 2] == 4.5  # left neighbour equals the max: halfway


def test_centroid_and_pc_values() -> None:
    vol = np.zeros((8, 1, 2), np.float32)
    vol[2, 0, 0], vol[3, 0, 0] = 1.0, 3.0  # centroid 2.75
    vol[0, 0, 1] = 1.0  # a single spike at level 0: pc exactly 0, not 8
    c, _ = depth_from_focus(vol, method="centroid")
    assert c[0, 0] == pytest.approx(2.75, abs=1e-6)
    p, conf = depth_from_focus(vol, method="pc")
    assert p[0, 1] == 0.0 and conf[0, 1] == pytest.approx(1.0)


# ----------------------------------------------------------------------------- the registry


def test_every_method_is_selectable_by_name() -> None:
    """One registry: the scan's methods (the configuration's choices) and the study's
    candidates are its names, and ``depth_from_focus`` runs each candidate as the study
    does, at the settings it tuned on all its families' training seeds."""
    import typing

    from sffscan.pipeline.config import ProcessingConfig
    from sffscan.stages.curve_shape import curve_width
    from sffscan.stages.depth_candidates import gauss_window_fit, window_pc
    from sffscan.stages.depth_choice import shape_select, stack_choice
    from sffscan.stages.depth_floor import guard_width
    from sffscan.stages.depth_harmonics import curve_moments
    from sffscan.stages.depth_spc import (
        SHAPE_SELECT_LIMITS,
        SPC_END_REACH,
        spc_in_range,
        spc_share,
    )
    from sffscan.stages.depth_statistics import shape_statistics

    assert (*DEPTH_METHODS, *CANDIDATE_METHODS) == tuple(ESTIMATORS)
    assert CANDIDATE_METHODS == ("gauss_window_fit", "window_pc", "warped_select")
    assert DEPTH_METHODS[-3:] == ("adaptive", "adaptive_centroid", "shape_select")
    choices = typing.get_args(ProcessingConfig.model_fields["depth_method"].annotation)
    assert choices == DEPTH_METHODS
    rng = np.random.default_rng(11)
    vol = gaussian_volume(rng.uniform(2, 28, (24, 30)), 30, 2.5)
    vol += 0.02 * rng.random(vol.shape, dtype=np.float32)
    centre = median_filter_levels(first_argmax(vol), 11, 30)
    adaptive, _ = depth_from_focus(vol, method="adaptive")
    spc, _ = depth_from_focus(vol, method="spc")
    stats = shape_statistics(vol, first_argmax(vol), curve_width(vol))
    assert SHAPE_SELECT_LIMITS == (0.2, math.inf) and SPC_END_REACH == 1.5
    # the range guard's widths from the floor raised by the curves' noise (depth_floor)
    # SPC's mean-square tests inside the focus window's reach, spread_size // 2 (as the depth)
    choice = stack_choice(vol, first_argmax(vol), margin=4)
    assert choice.spc and choice.floor is not None and choice.floor.noise > 0
    h0, _, re, im = curve_moments(vol)
    guard = guard_width(h0, np.hypot(re, im), vol.min(axis=0), 30, choice.floor)
    in_range = spc_in_range(spc, guard, 30, reach=1.5)
    assert 0 < in_range.mean() < 1  # peaks at levels 2 .. 28 of 30: some near the ends
    # SPC averaged with the fallback by its share (spc_weight) where it is in range
    assert 0.5 <= choice.weight <= 1.0
    fallback = depth_from_focus(vol, method="adaptive_centroid")[0]
    expected = {"gauss_window_fit": gauss_window_fit(vol, centre, adaptive, half_window=3),
                "window_pc": window_pc(vol, centre, factor=3.0),
                "shape_select": np.where(in_range, spc_share(spc, fallback, choice.weight),
                                         shape_select(spc, fallback, stats, max_skew=0.2,
                                                      max_ratio=math.inf, in_range=in_range))}
    expected["warped_select"] = expected["shape_select"]  # even curves: no warp
    for method in (*CANDIDATE_METHODS, "shape_select"):
        depth, confidence = depth_from_focus(vol, method=method)
        np.testing.assert_array_equal(depth, expected[method])
        np.testing.assert_array_equal(confidence, depth_from_focus(vol, method="spc")[1])


@pytest.mark.parametrize("method", (*CANDIDATE_METHODS, "shape_select"))
@pytest.mark.parametrize(("n", "sigma"), [(30, 2.0), (50, 3.0)])
def test_candidates_recover_gaussian_peak(method: str, n: int, sigma: float) -> None:
    # as test_recovers_gaussian_peak; measured worst cases: gauss_window_fit 2.0e-6
    # (a Gaussian fit), window_pc 1.7e-5 levels, shape_select (even, clean curves: SPC)
    margin = 4.0 * sigma
    cols = np.linspace(margin, n - 1 - margin, 97) + 0.123
    peaks = np.broadcast_to(cols, (13, cols.size)) + np.linspace(0, 0.05, 13)[:, None]
    vol = gaussian_volume(peaks, n, sigma)
    depth, _ = depth_from_focus(vol, method=method)
    if method in ("shape_select", "warped_select"):  # even, clean curves (no warp): SPC
        # with (nearly) all the share (spc_weight: its departure from the peaks is about 0),
        # within SPC's tolerance
        from sffscan.stages.depth_choice import stack_choice

        choice = stack_choice(vol, first_argmax(vol), margin=4)
        assert choice.spc and choice.weight > 0.9
        np.testing.assert_array_equal(depth, depth_from_focus(vol, method="shape_select")[0])
    tol = PEAK_TOL["spc"] if method in ("shape_select", "warped_select") else 1e-4
    assert depth.dtype == np.float32 and np.abs(depth - peaks).max() <= tol


def test_shape_statistics_tell_even_and_clean_curves_from_lopsided_and_noisy_ones() -> None:
    """``shape_select``'s two numbers on curves of known shape: an even Gaussian has
    skewness 0 (to the truncation of its window, centred on a whole level while the peaks
    lie up to half a level off: measured 0.038) and a harmonic width equal to the sigma its
    half-height run gives (ratio 1, to the run's whole-level rounding); a curve whose upper
    flank is twice as wide as its lower one skews positive (measured 0.18 at least, beyond
    the 0.08 that ``shape_select`` allows); a narrow peak on a noisy floor widens the
    harmonic width, not the run above half height."""
    from sffscan.stages.curve_shape import curve_width
    from sffscan.stages.depth_choice import shape_select
    from sffscan.stages.depth_statistics import curve_skew, shape_statistics

    n, sigma = 60, 3.0
    k = np.arange(n, dtype=np.float64)[:, None, None]
    peaks = np.full((8, 8), 30.0) + np.linspace(0, 0.5, 64).reshape(8, 8)
    even = np.exp(-0.5 * ((k - peaks) / sigma) ** 2).astype(np.float32)
    lop = np.exp(-0.5 * ((k - peaks) / np.where(k > peaks, 2 * sigma, sigma)) ** 2)
    lop = lop.astype(np.float32)
    centre = np.full((8, 8), 30, np.intp)
    assert np.abs(curve_skew(even, centre, curve_width(even))).max() < 0.05
    assert curve_skew(lop, centre, curve_width(lop)).min() > 0.15
    skew, ratio = shape_statistics(even, centre, curve_width(even))
    assert skew < 0.05 and 0.8 < ratio < 1.25
    rng = np.random.default_rng(3)
    narrow = np.exp(-0.5 * ((k - peaks) / 1.0) ** 2) + 0.3 * rng.random((n, 8, 8))
    narrow = narrow.astype(np.float32)
    assert shape_statistics(narrow, centre, curve_width(narrow))[1] > 6.0
    a, b = np.zeros((8, 8), np.float32), np.ones((8, 8), np.float32)
    assert np.array_equal(shape_select(a, b, (0.05, 2.0), max_skew=0.08, max_ratio=6.0), a)
    assert np.array_equal(shape_select(a, b, (0.10, 2.0), max_skew=0.08, max_ratio=6.0), b)
    assert np.array_equal(shape_select(a, b, (0.05, 7.0), max_skew=0.08, max_ratio=6.0), b)
    # the default's test reads the skewness only while its width limit is infinite: the same
    # skewness, the ratio not measured, and a finite limit refuses to judge without it
    from sffscan.stages.depth_spc import SHAPE_SELECT_LIMITS, spc_shape, takes_spc

    assert math.isinf(SHAPE_SELECT_LIMITS[1])
    for vol in (even, lop, narrow):
        width = curve_width(vol)
        assert spc_shape(vol, centre, width) == (shape_statistics(vol, centre, width)[0], None)
    assert takes_spc((0.05, None)) and not takes_spc((0.5, None))
    with pytest.raises(ValueError, match="width ratio"):
        takes_spc((0.05, None), max_ratio=6.0)


def test_spc_is_kept_only_a_reach_of_widths_from_the_range_s_ends() -> None:
    """spc_in_range: margin = reach x width from 0 and from N - 1 (inclusive), NaN out;
    shape_select takes ``other`` outside it, and only where it takes SPC at all."""
    from sffscan.stages.depth_choice import shape_select
    from sffscan.stages.depth_spc import spc_in_range

    d = np.array([2.9, 3.0, 15.0, 26.0, 26.1, np.nan], np.float32)
    w = np.array([2.0, 2.0, 9.0, 2.0, 2.0, 2.0], np.float32)
    keep = spc_in_range(d, w, 30, reach=1.5)
    assert keep.tolist() == [False, True, True, True, False, False]
    assert spc_in_range(d, w, 30, reach=0.0).tolist() == [True] * 5 + [False]
    other = np.full(6, -1.0, np.float32)
    out = shape_select(d, other, (0.0, 1.0), max_skew=0.08, max_ratio=6.0, in_range=keep)
    np.testing.assert_array_equal(out, np.where(keep, d, other))
    assert np.array_equal(shape_select(d, other, (0.5, 1.0), max_skew=0.08, max_ratio=6.0,
                                       in_range=keep), other)


@pytest.mark.parametrize("peak", ["centroid", "gauss3"])
def test_a_scan_block_that_takes_spc_falls_back_near_the_ends(peak: str) -> None:
    """block_depth.depth_rows of an SPC block (SPC_BLOCKS): SPC's depth where it is in range
    (from the block's float32 sums: within float32 round-off of depth_from_focus's, whose
    sums are float64), what adaptive_centroid's rule gives (its peak estimator named by the
    label) elsewhere, on the same curves; the curves' sums and minimum as the ring methods
    give them, the confidence depth_from_focus's."""
    from sffscan.stages.block_depth import SPC_BLOCKS, depth_rows
    from sffscan.stages.curve_shape import width_from_sums
    from sffscan.stages.depth_harmonics import focus_sums
    from sffscan.stages.depth_spc import spc_in_range

    rng = np.random.default_rng(5)
    n, rows, halo, block = 30, 40, 8, 24
    peaks = np.linspace(0.5, 12.0, rows)[:, None] + np.zeros((1, block + 2 * halo))
    vol = gaussian_volume(peaks + rng.uniform(0, 0.3, peaks.shape), n, 2.0)
    vol += 0.01 * rng.random(vol.shape, dtype=np.float32)
    argmax = first_argmax(vol)
    inner = slice(halo, halo + block)
    label = next(k for k, v in SPC_BLOCKS.items() if v == peak)
    out = np.empty((3, rows, block), np.float32), np.empty((rows, block), np.float32)
    # the block's own columns' levels (SPC from their float32 sums), the halo's argmax
    depth, conf = depth_rows(vol[:, :, inner], argmax, None, (0, rows), slice(0, rows),
                             inner, *out, method=label, n_levels=n, median_size=11,
                             spread_size=9, streaming=False, keep_low=True)
    spc = depth_from_focus(vol, method="spc", argmax=argmax)[0][:, inner]
    other = depth_from_focus(vol, method="adaptive", argmax=argmax)[0][:, inner]
    if peak == "centroid":
        out2 = np.empty((3, rows, block), np.float32), np.empty((rows, block), np.float32)
        other, _ = depth_rows(vol[:, :, inner], argmax, None, (0, rows), slice(0, rows),
                              inner, *out2, method="adaptive_centroid", n_levels=n,
                              median_size=11, spread_size=9, streaming=False, keep_low=True)
    sums, low = out
    np.testing.assert_array_equal(sums, focus_sums(vol[:, :, inner]))
    np.testing.assert_array_equal(low, vol[:, :, inner].min(axis=0))
    keep = spc_in_range(spc, width_from_sums(sums[0], np.hypot(sums[1], sums[2]), low, n), n)
    assert 0.2 < keep.mean() < 0.9  # peaks from 0.5 to 12 levels: both kinds of pixel
    np.testing.assert_allclose(depth[keep], spc[keep], atol=1e-5)
    np.testing.assert_array_equal(depth[~keep], other[~keep])
    np.testing.assert_allclose(conf, depth_from_focus(vol, method="spc")[1][:, inner],
                               rtol=1e-6, atol=1e-7)


# ----------------------------------------------------------------------------- SPC identity


def spc_shift_independent(volume: np.ndarray, median_size: int) -> np.ndarray:
    """s = round(N/2) - median(argmax), with scipy's median filter (replicated borders)."""
    n = volume.shape[0]
    a_med = ndimage.median_filter(np.argmax(volume, axis=0), size=median_size, mode="nearest")
    return np.floor(n / 2 + 0.5).astype(int) - a_med


def random_volumes() -> list[np.ndarray]:
    rng = np.random.default_rng(7)
    vols = [rng.random((n, 48, 40), dtype=np.float32) for n in (30, 31, 50)]
    for n, sigma in ((30, 2.0), (50, 3.0)):  # Gaussian peaks anywhere (also near the ends)
        peaks = rng.uniform(0, n - 1, (48, 40))
        noise = 0.05 * rng.random((n, 48, 40), dtype=np.float32)
        vols.append(gaussian_volume(peaks, n, sigma) + noise)
    return vols


@pytest.mark.parametrize("median_size", [1, 5, 11])
def test_spc_equals_literal_roll(median_size: int) -> None:
    """The phase rotation gives what rolling the curves gives.

    Both return ``d_s - s`` with ``d_s`` the PC of the rolled curve in [0, N); they can only
    differ by N where ``d_s`` lies within round-off of the wrap point 0 == N, since one side
    may land on 0 + eps and the other on N - eps. So: equal on the circle everywhere, equal
    outright wherever ``d_s`` is 1e-3 away from the wrap point, and both inside
    [-s, N - s), the interval that unwraps around the filtered argmax.
    """
    for vol in random_volumes():
        n = vol.shape[0]
        fast, _ = depth_from_focus(vol, method="spc", median_size=median_size)
        slow = spc_by_roll(vol, median_size=median_size)
        s = spc_shift_independent(vol, median_size)
        assert np.abs(circular_diff(fast, slow, n)).max() <= 1e-4
        d_s = slow + s
        away = np.minimum(d_s, n - d_s) > 1e-3
        assert away.mean() > 0.99
        assert np.abs(fast - slow)[away].max() <= 1e-4
        assert (fast >= -s - 1e-4).all() and (fast < n - s + 1e-4).all()


def test_spc_unwraps_around_filtered_argmax() -> None:
    n, sigma = 30, 2.0
    peaks = np.full((15, 15), 0.2)  # a plane just above level 0 ...
    peaks[7, 7] = 29.0  # ... with an outlier at the other end, which the median removes
    vol = gaussian_volume(peaks, n, sigma) + np.float32(0.01)
    pc, _ = depth_from_focus(vol, method="pc")
    spc, _ = depth_from_focus(vol, method="spc", median_size=5)
    assert (pc >= 0).all() and (pc < n).all()
    # the same phase: spc only picks which turn of the circle, the one in [a_med - 15, a_med + 15)
    assert np.abs(circular_diff(spc, pc, n)).max() <= 1e-4
    mask = np.ones(peaks.shape, bool)
    mask[7, 7] = False
    np.testing.assert_allclose(spc[mask], pc[mask], atol=1e-5)
    assert pc[7, 7] > 27  # PC: near level 29 (biased inwards: the curve is cut at level 29)
    assert spc[7, 7] == pytest.approx(pc[7, 7] - n, abs=1e-4)  # SPC: next to its neighbours


# ----------------------------------------------------------------------------- confidence


def test_confidence_range_and_order() -> None:
    rng = np.random.default_rng(3)
    n = 40
    peaked = gaussian_volume(rng.uniform(10, 30, (20, 20)), n, 2.0)
    flat = np.float32(1.0) + 0.1 * rng.random((n, 20, 20), dtype=np.float32)
    for method in DEPTH_METHODS:
        _, c_peak = depth_from_focus(peaked, method=method)
        _, c_flat = depth_from_focus(flat, method=method)
        for c in (c_peak, c_flat):
            assert ((c >= 0) & (c <= 1)).all()
        assert c_peak.min() > 0.5 > 0.05 > c_flat.max()
    zero = np.zeros((5, 3, 3), np.float32)
    for method in DEPTH_METHODS:
        depth, conf = depth_from_focus(zero, method=method)
        assert np.isfinite(depth).all() and not conf.any()


# ----------------------------------------------------------------------------- helpers


def test_argmax_matches_numpy_with_ties() -> None:
    vol = np.random.default_rng(5).integers(0, 3, (20, 30, 40)).astype(np.float32)
    np.testing.assert_array_equal(first_argmax(vol), np.argmax(vol, axis=0))


def test_median_filter_paths_agree() -> None:
    levels = np.random.default_rng(6).integers(0, 255, (37, 29))
    expected = ndimage.median_filter(levels, size=11, mode="nearest")
    np.testing.assert_array_equal(median_filter_levels(levels, 11, 255), expected)  # cv2
    np.testing.assert_array_equal(median_filter_levels(levels, 11, 300), expected)  # numpy


@pytest.mark.parametrize("size", [1, 5, 11])
def test_median_filter_at_a_grid_is_the_filtered_map_there(size: int) -> None:
    """median_filter_levels_at (a scan block's choice reads the filtered argmax at its
    sampled curves): scipy's median filter with replicated edges, at the grid's pixels,
    the first and last rows and columns included."""
    from sffscan.stages.depth_levels import median_filter_levels_at

    levels = np.random.default_rng(7).integers(0, 60, (45, 23))
    expected = ndimage.median_filter(levels, size=size, mode="nearest")
    rows, cols = np.arange(0, 45, 16), np.array([0, 3, 11, 22])
    got = median_filter_levels_at(levels, size, rows, cols)
    assert got.dtype == np.intp and got.shape == (3, 4)
    np.testing.assert_array_equal(got, expected[np.ix_(rows, cols)])


def test_a_blocks_judged_centre_is_filtered_with_the_columns_about_it() -> None:
    """judged_centre: the argmax filtered with the halo's columns, at every 16th row and
    8th column of the block's own columns (what a scan's block choice reads)."""
    from sffscan.stages.block_depth import judged_centre

    levels = np.random.default_rng(8).integers(0, 60, (70, 90))
    expected = ndimage.median_filter(levels, size=11, mode="nearest")
    np.testing.assert_array_equal(judged_centre(levels, 11, block=(13, 77)),
                                  expected[::16, 13:77:8])
    np.testing.assert_array_equal(judged_centre(levels, 11), expected[::16, ::8])


def test_levels_to_height() -> None:
    table = np.array([100.0, 110.0, 130.0, 160.0])
    levels = np.array([[0.0, 1.5, 2.25, 3.0], [-1.0, 4.0, np.nan, 1.0]])
    expected = np.array([[100.0, 120.0, 137.5, 160.0], [90.0, 190.0, np.nan, 110.0]])
    out = levels_to_height(levels, focus_heights_um=table)
    assert out.dtype == np.float32 and out.shape == levels.shape
    np.testing.assert_array_equal(out, expected.astype(np.float32))
    out = levels_to_height(levels, focus_heights_um=table[::-1])  # decreasing table
    np.testing.assert_array_equal(out[0], np.array([160.0, 120.0, 107.5, 100.0], np.float32))
    np.testing.assert_array_equal(out[1, :2], np.array([190.0, 90.0], np.float32))


@pytest.mark.parametrize(
    ("table", "match"),
    [
        ([1.0, 2.0, 2.0], "monotonic"),
        ([3.0, 1.0, 2.0], "monotonic"),
        ([1.0], "at least 2"),
        ([1.0, np.nan], "finite"),
        ([[1.0, 2.0]], "1-D"),
    ],
)
def test_levels_to_height_rejects(table: list[float], match: str) -> None:
    with pytest.raises(ValueError, match=match):
        levels_to_height(np.zeros(3), focus_heights_um=np.array(table))
    with pytest.raises(ValueError, match=match):  # the inverse checks the same table
        levels_from_heights(np.zeros(3), focus_heights_um=np.array(table))


def test_all_in_focus() -> None:
    rng = np.random.default_rng(8)
    stack = rng.integers(0, 1024, (6, 5, 7)).astype(np.uint16)
    best = rng.integers(0, 6, (5, 7))
    volume = rng.random((6, 5, 7)).astype(np.float32)
    np.put_along_axis(volume, best[None], 2.0, axis=0)
    out = all_in_focus(stack, volume)
    assert out.dtype == np.uint16
    np.testing.assert_array_equal(out, np.take_along_axis(stack, best[None], axis=0)[0])
    with pytest.raises(ValueError, match="same shape"):
        all_in_focus(stack[:5], volume)


def test_the_function_s_default_is_the_product_s() -> None:
    # a caller of the numerical API gets what scan, replay and stack take (it was "spc",
    # which a bench script took for the default once)
    rng = np.random.default_rng(5)
    k = np.arange(30)[:, None, None]
    peak = rng.uniform(8, 22, (1, 24, 24))
    # lopsided curves (upper flank 2.5x the lower's), which shape_select gives its fallback
    vol = np.exp(-0.5 * ((k - peak) / np.where(k < peak, 2.0, 5.0)) ** 2) \
        + 0.05 * rng.random((30, 24, 24))
    vol = vol.astype(np.float32)
    default = depth_from_focus(vol)
    np.testing.assert_array_equal(default[0], depth_from_focus(vol, method=DEFAULT_METHOD)[0])
    assert not np.array_equal(default[0], depth_from_focus(vol, method="spc")[0])


# ----------------------------------------------------------------------------- validation


def test_validation_errors() -> None:
    vol = np.ones((6, 4, 4), np.float32)
    with pytest.raises(ValueError, match="3-D"):
        depth_from_focus(vol[0])
    with pytest.raises(ValueError, match="at least 3 focus levels"):
        depth_from_focus(vol[:2])
    bad = vol.copy()
    bad[3, 1, 2] = np.nan
    bad[4, 0, 0] = np.inf
    with pytest.raises(ValueError, match="volume contains NaN at level 3"):
        depth_from_focus(bad)
    bad[3, 1, 2] = 1.0
    with pytest.raises(ValueError, match="volume contains inf at level 4"):
        depth_from_focus(bad, method="argmax")
    with pytest.raises(ValueError, match="NaN at level 3"):
        spc_by_roll(np.where(np.arange(6)[:, None, None] == 3, np.nan, vol))
    with pytest.raises(ValueError,
                       match=r"method must be one of \('argmax', .*'adaptive', "
                             r"'adaptive_centroid', 'shape_select'\)"):
        depth_from_focus(vol, method="wavr")
    for size in (0, 10, -1, 3.0):
        with pytest.raises(ValueError, match="median_size"):
            depth_from_focus(vol, median_size=size)  # type: ignore[arg-type]
        with pytest.raises(ValueError, match="spread_size"):
            depth_from_focus(vol, method="adaptive", spread_size=size)  # type: ignore[arg-type]


# ----------------------------------------------------------------------------- pertuz data


def test_pertuz_depth_rmse(pertuz_dir: Path) -> None:
    mat = scipy.io.loadmat(pertuz_dir / "imdata.mat", squeeze_me=True, struct_as_record=False)
    imdata = mat["imdata"]
    images = []
    for i in range(1, 31):
        raw = cv2.imread(str(pertuz_dir / f"im_{i:02d}.tif"), cv2.IMREAD_UNCHANGED)
        assert raw is not None, f"cannot read im_{i:02d}.tif"
        images.append(to_unit_float(raw, max_value=255))
    stack = np.stack(images)
    focus_m = np.asarray(imdata.focus, dtype=np.float64)
    x, y, w, h = (int(v) for v in imdata.ROI)
    roi = (slice(y - 1, y - 1 + h), slice(x - 1, x - 1 + w))
    truth = np.asarray(imdata.z, dtype=np.float64)[roi]

    volume = focus_measure(stack, operator="glvm", window=9)
    rmse = {}
    for method in DEPTH_METHODS:
        levels, _ = depth_from_focus(volume, method=method)
        z = levels_to_height(levels, focus_heights_um=focus_m * 1e6).astype(np.float64) / 1e6
        rmse[method] = float(np.sqrt(np.mean((z[roi] - truth) ** 2)))

    step = float(np.mean(np.diff(focus_m)))
    print("\npertuz-simu02, GLVM 9, ROI RMSE")
    for method, value in rmse.items():
        print(f"  {method:<11s} {value:.4f} m  ({value / step:.2f} focus steps)")

    assert 0.030 <= rmse["argmax"] <= 0.045  # toolbox figure: about 0.036 m
    for method in ("gauss3", "quadratic3"):  # barely different from argmax (notes, section 3)
        assert abs(rmse[method] - rmse["argmax"]) <= 0.05 * rmse["argmax"]
    assert rmse["spc"] < rmse["pc"]  # the shift keeps the phase away from its wrap-around
    assert max(rmse.values()) < 0.1


@pytest.mark.parametrize("method", ["argmax", "centroid", "pc", "spc"])
def test_depth_from_harmonics_equals_depth_from_focus(method: str) -> None:
    rng = np.random.default_rng(11)
    vol = rng.random((20, 9, 13))
    sums = np.einsum("mk,khw->mhw", harmonic_table(20), vol)
    got = depth_from_harmonics(sums, np.argmax(vol, axis=0), n_levels=20, method=method,
                               median_size=3)
    want = depth_from_focus(vol, method=method, median_size=3)
    np.testing.assert_allclose(got[0], want[0], atol=1e-4)
    np.testing.assert_allclose(got[1], want[1], atol=1e-6)


def test_depth_from_harmonics_rejects() -> None:
    sums = np.ones((4, 3, 5))
    with pytest.raises(ValueError, match="method"):
        depth_from_harmonics(sums, np.zeros((3, 5), int), n_levels=8, method="gauss3")
    with pytest.raises(ValueError, match="argmax"):
        depth_from_harmonics(sums, None, n_levels=8, method="spc")
    with pytest.raises(ValueError, match="shape"):
        depth_from_harmonics(sums, np.zeros((3, 4), int), n_levels=8)
    with pytest.raises(ValueError, match=r"\(4, H, W\)"):
        depth_from_harmonics(sums[:3], np.zeros((3, 5), int), n_levels=8)
    with pytest.raises(ValueError, match="NaN"):
        depth_from_harmonics(sums * np.nan, np.zeros((3, 5), int), n_levels=8)
    with pytest.raises(ValueError, match="n_levels"):
        depth_from_harmonics(sums, np.zeros((3, 5), int), n_levels=2)
    assert depth_from_harmonics(sums, None, n_levels=8, method="pc")[0].shape == (3, 5)


def test_plane_residual_is_zero_on_a_plane_and_large_at_a_step() -> None:
    """depth_candidates.plane_residual: 0 on any plane (edges reflected keep a plane's
    inner windows exact), a step's RMS about its best plane within reach of the step."""
    from sffscan.stages.depth_candidates import plane_residual

    yy, xx = np.mgrid[0:40, 0:50].astype(np.float64)
    plane = 3.0 + 0.4 * xx - 0.25 * yy
    res = plane_residual(plane, window=9)
    # the variance is E[z^2] - E[z]^2 - ...: round-off of values ~20 levels, square-rooted
    assert np.abs(res[4:-4, 4:-4]).max() < 1e-5
    step = np.where(xx < 25, 0.0, 10.0)
    res = plane_residual(step, window=9)
    assert np.all(res[:, :20] < 1e-5) and np.all(res[:, 31:] < 1e-5)
    # 9 columns of 0 and 10 with the step in the middle: the best plane is the ramp through
    # them; the residual is the RMS of a step about its least-squares line (1.83 levels)
    x = np.arange(-4, 5, dtype=np.float64)
    z = np.where(x < 1, 0.0, 10.0)  # the window about column 24: 5 zeros, 4 tens
    b = (x * (z - z.mean())).sum() / (x * x).sum()
    want = np.sqrt(np.mean((z - z.mean() - b * x) ** 2))
    assert res[20, 24] == pytest.approx(want, rel=1e-9)


def test_width_from_the_shared_sums_equals_curve_width() -> None:
    """``shape_select`` on a stack takes the curves' widths from the float64 sums every
    estimator shares (no float64 copy of the volume): curve_width's values to float64
    round-off, on curves narrow, wide, lopsided and flat."""
    from sffscan.stages.curve_shape import curve_width, width_from_sums
    from sffscan.stages.depth_harmonics import curve_moments

    rng = np.random.default_rng(11)
    n = 50
    k = np.arange(n, dtype=np.float32)[:, None, None]
    centre = rng.uniform(-3.0, n + 3.0, (1, 24, 32)).astype(np.float32)
    sigma = rng.uniform(0.8, 12.0, (1, 24, 32)).astype(np.float32)
    upper = sigma * rng.uniform(1.0, 2.5, sigma.shape).astype(np.float32)
    s = np.where(k > centre, upper, sigma)
    vol = np.exp(-0.5 * ((k - centre) / s) ** 2) + 0.05 * rng.random((n, 24, 32))
    vol = vol.astype(np.float32)
    vol[:, 0, :4] = 0.3  # flat curves
    m = curve_moments(vol)
    want = curve_width(vol)
    got = width_from_sums(m[0], np.hypot(m[2], m[3]), vol.min(axis=0), n)
    np.testing.assert_allclose(got, want, rtol=1e-12, atol=1e-12)
    assert want[0, :4].min() > n / 10  # the flat curves: wide, finite


@pytest.mark.parametrize("n", [5, 12, 50])
def test_the_levels_beyond_the_range_are_those_of_c_plus_j(n: int) -> None:
    """The range masks of the peak estimators (one comparison an offset since 2026-12-06):
    level c + j lies outside 0..N-1, for windows up to wider than the range."""
    from sffscan.stages.depth_peak import _beyond

    c = np.random.default_rng(n).integers(0, n, 4000)
    for h in (1, 2, 4, 5):
        for j, mask in zip(range(-h, h + 1), _beyond(c, h, n), strict=True):
            k = c + j
            expected = (k < 0) | (k > n - 1)
            if mask is None:
                assert not expected.any()
            else:
                np.testing.assert_array_equal(mask, expected)


def test_spc_s_mean_square_tests_leave_out_the_focus_window_s_reach() -> None:
    """stack_choice(margin=m): SPC's noise, floor and departure (mean squares, which a few
    wild curves carry) are judged on the curves m px or more from the edges, where the
    focus measure reads no padding; the depth passes its spread_size // 2. Border curves
    made wild change the departure judged on every curve, not the one judged inside."""
    from sffscan.stages.depth_choice import stack_choice

    rng = np.random.default_rng(3)
    truth = 10.0 + 6.0 * np.sin(np.mgrid[0:40, 0:40][1] / 5.0)
    vol = gaussian_volume(truth, 30, 2.5) + 0.01 * rng.random((30, 40, 40), dtype=np.float32)
    wild = vol.copy()
    edge = np.ones((40, 40), bool)
    edge[4:-4, 4:-4] = False
    # a second, lower peak 12 levels off on the border's curves: their argmax (and the
    # filtered argmax the tests measure about) stays, their first harmonic's phase moves
    wild[:, edge] += 0.5 * gaussian_volume(truth + 12.0, 30, 2.5)[:, edge]
    np.testing.assert_array_equal(first_argmax(wild), first_argmax(vol))
    inside, inside_wild = (stack_choice(v, first_argmax(v), margin=4) for v in (vol, wild))
    every, every_wild = (stack_choice(v, first_argmax(v)) for v in (vol, wild))
    assert inside.spc and inside_wild.spc and every.spc
    assert inside_wild.bias == pytest.approx(inside.bias, abs=1e-6)
    assert inside_wild.floor is not None and inside.floor is not None
    assert inside_wild.floor.noise == pytest.approx(inside.floor.noise, rel=1e-6)
    # judged on every curve, the border moves what SPC's tests read
    assert every_wild.bias != pytest.approx(every.bias, abs=1e-3) or not every_wild.spc
    # and the depth judges as stack_choice(margin=spread_size // 2) does
    from sffscan.stages.depth import shape_select_with_bias

    for v in (vol, wild):
        bias = shape_select_with_bias(v, spread_size=9)[2]
        assert bias == pytest.approx(stack_choice(v, first_argmax(v), margin=4).bias)


def test_spc_s_share_is_the_inverse_of_the_two_estimated_errors() -> None:
    """spc_weight: w = E_f / (E_f + E_spc), E_spc = d^2 + sigma^2, E_f = max(0, max(0.03,
    s)^2 - sigma^2) (sigma 0 under 0.03, as in the departure test; s the departures' robust
    spread): 0 .. 1, 1/2 where the two are equal; spc_departures gives the robust spread
    (1.4826 MAD) beside the test's root mean square, which a few far curves carry."""
    from sffscan.stages.depth_spc import spc_departure, spc_departures, spc_share, spc_weight

    assert spc_weight((0.3, 0.5), 0.1) == pytest.approx(0.24 / 0.34)  # E_spc 0.10, E_f 0.24
    assert spc_weight((0.0, 0.2), 0.02) == 1.0  # no departure, a negligible noise
    assert spc_weight((0.0, 0.01), 0.0) == 1.0  # the spread floored at 0.03
    assert spc_weight((0.4, 0.5), 0.0) == pytest.approx(0.25 / 0.41)
    assert spc_weight((0.3, math.sqrt(0.09 + 2 * 0.04)), 0.2) == pytest.approx(0.5)
    assert spc_weight((0.6, 0.5), 0.0) == pytest.approx(0.25 / 0.61)  # SPC errs more: < 1/2
    assert spc_weight((0.2, 0.1), 0.3) == 0.0  # SPC's noise alone over the spread: E_f 0
    assert math.isnan(spc_weight((math.nan, 0.5), 0.1))
    assert math.isnan(spc_weight((0.1, 0.5), math.nan))
    rng = np.random.default_rng(2)
    for d, s, sigma in rng.uniform(0.0, 1.0, (500, 3)) * [1.0, 1.2, 0.6]:
        w = spc_weight((float(d), float(s)), float(sigma))
        sig = 0.0 if sigma < 0.03 else sigma
        assert 0.0 <= w <= 1.0
        assert (w >= 0.5) == (d * d + 2 * sig * sig <= max(0.03, s) ** 2)
    spc, other = np.full(3, 4.0, np.float32), np.array([2.0, 3.0, 4.0], np.float32)
    np.testing.assert_allclose(spc_share(spc, other, 0.75), [3.5, 3.75, 4.0])
    np.testing.assert_array_equal(spc_share(spc, np.full(3, np.nan, np.float32), 1.0), spc)
    # the spreads: 40 curves, 36 even ones and 4 whose peak sits 3 levels off SPC's reading
    # (far curves): the RMS carries them, the robust spread does not
    rng = np.random.default_rng(5)
    peaks = rng.uniform(12.0, 18.0, (4, 10))
    vol = gaussian_volume(peaks, 30, 2.5) + 0.002 * rng.random((30, 4, 10), dtype=np.float32)
    far = vol.copy()
    far[:, 0, :4] += 0.6 * gaussian_volume(peaks[0, :4] + 6.0, 30, 2.5)
    centre = first_argmax(vol)
    calm, wild = spc_departures(vol, centre), spc_departures(far, first_argmax(far))
    assert (calm.departure, calm.spread) == spc_departure(vol, centre)
    assert wild.spread > 3 * calm.spread and wild.robust < 2 * calm.robust + 0.01


def test_a_thin_lens_noisy_slope_that_passes_spc_s_test_takes_the_fallback_s_share() -> None:
    """The held-out stack the switch gave SPC at 1.5x the fallback's error
    (``slopes-lens-noisy`` seed 360, 30 levels: its test passed just, d^2 + 2 sigma^2 <=
    s^2, with the fallback's error overestimated from the peaks' scatter;
    docs/depth-method-log.md): SPC averaged with the fallback by the test's estimates
    (about half each here) errs less than SPC alone and within 1.2x the fallback."""
    from sffscan.stages.depth_choice import stack_choice
    from sffscan.stages.sim.families import family_stack

    st = family_stack("slopes-lens-noisy", 360)
    vol = focus_measure(st.images, operator="glvm", window=9)
    truth = (st.truth_um - st.focus_um[0]) / (st.focus_um[1] - st.focus_um[0])
    choice = stack_choice(vol, first_argmax(vol), margin=4)
    assert choice.spc and 0.5 <= choice.weight < 0.6
    inner = (slice(4, -4), slice(4, -4))

    def rmse(method: str) -> float:
        d = depth_from_focus(vol, method=method, spread_size=9)[0]
        return float(np.sqrt(np.mean((d - truth)[inner] ** 2)))

    default, spc, fallback = rmse("shape_select"), rmse("spc"), rmse("adaptive_centroid")
    assert spc > 1.4 * fallback  # SPC alone: 1.52 against 1.04 levels
    assert default < 0.8 * spc and default < 1.2 * fallback  # measured 1.18


def test_a_noisy_stepped_stack_gives_spc_the_share_its_bulk_of_curves_allows() -> None:
    """``steps-lens-noisy`` seed 881 (80 levels): the departure test takes SPC, whose
    differences from the peaks are small on most curves and large at the steps' edges,
    where SPC reads the blend of two heights; the mean square counts the edges as the
    fallback's noise, the robust spread does not, and SPC's share falls under 1/2 (it had
    nearly all of it, 1.69 levels RMSE, against SPC's 1.79 and the fallback's 0.99)."""
    from sffscan.stages.depth_choice import stack_choice
    from sffscan.stages.sim.families import family_stack

    st = family_stack("steps-lens-noisy", 881)
    vol = focus_measure(st.images, operator="glvm", window=9)
    truth = (st.truth_um - st.focus_um[0]) / (st.focus_um[1] - st.focus_um[0])
    choice = stack_choice(vol, first_argmax(vol), margin=4)
    assert choice.spc and 0.3 < choice.weight < 0.5
    inner = (slice(4, -4), slice(4, -4))

    def rmse(method: str) -> float:
        d = depth_from_focus(vol, method=method, spread_size=9)[0]
        return float(np.sqrt(np.mean((d - truth)[inner] ** 2)))

    default, spc, fallback = rmse("shape_select"), rmse("spc"), rmse("adaptive_centroid")
    assert default < 0.7 * spc and default < 1.15 * fallback  # measured 1.09, 1.79, 0.99


@pytest.mark.parametrize("shape", [(7,), (33, 17), (3, 40, 600), (2, 3, 4, 5)])
@pytest.mark.parametrize("dtype", [np.float32, np.float64])
def test_magnitude_is_hypot_within_two_ulp(shape: tuple[int, ...], dtype: type) -> None:
    rng = np.random.default_rng(len(shape))
    x = (rng.standard_normal(shape) * 10.0).astype(dtype)
    y = (rng.standard_normal(shape) * 10.0).astype(dtype)
    m = magnitude(x, y)
    ref = np.hypot(x, y)
    assert m.shape == ref.shape and m.dtype == ref.dtype
    assert np.all(np.abs(m - ref) <= 2 * np.spacing(ref))


def test_magnitude_of_a_band_is_the_band_of_the_magnitude() -> None:
    # a scan block's values are bit for bit the same whatever its bands (rows), strides or
    # offsets: no path that rounds a pixel differently by where it lies in the array
    rng = np.random.default_rng(5)
    x = rng.standard_normal((1040, 128)).astype(np.float32)
    y = rng.standard_normal((1040, 128)).astype(np.float32)
    whole = magnitude(x, y)
    for rows, cols in ((slice(3, 700), slice(None)), (slice(None), slice(5, 127)),
                       (slice(1, None, 3), slice(2, None, 7)), (slice(1039, None), slice(0, 1))):
        np.testing.assert_array_equal(magnitude(x[rows, cols], y[rows, cols]), whole[rows, cols])


def test_magnitude_known_values_and_non_finite() -> None:
    x = np.array([[3.0, 0.0, np.nan, np.inf], [-5.0, 8.0, 1.0, -np.inf]], np.float32)
    y = np.array([[4.0, 0.0, 1.0, 1.0], [12.0, -6.0, np.inf, np.nan]], np.float32)
    m = magnitude(x, y)
    np.testing.assert_array_equal(m[0, :2], [5.0, 0.0])
    np.testing.assert_array_equal(m[1, :2], [13.0, 10.0])
    assert np.isnan(m[0, 2]) and np.isinf(m[0, 3]) and np.isinf(m[1, 2])
    # mixed dtypes fall back to numpy's hypot, in its result type
    assert magnitude(np.float32([3.0]), np.float64([4.0])).dtype == np.float64
    assert float(magnitude(3, 4)) == 5.0  # integers: numpy's hypot
