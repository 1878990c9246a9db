"""The warped level axis (stages/depth_warp.py): known answers on analytic curves (Gaussians
even in the level, and even in a thin lens' ``g(k) = k / (1 + s k)``), the warp's round trip,
and the candidate ``warped_select`` on a thin-lens family's training seed."""

from __future__ import annotations

import numpy as np
import pytest
from sffscan.stages.depth import CANDIDATE_METHODS, DEPTH_METHODS, depth_from_focus
from sffscan.stages.depth_warp import (
    MAX_CURVES,
    half_height_crossings,
    lens_asymmetry,
    unwarp_levels,
    warp_volume,
)
from sffscan.stages.focus_measure import focus_measure
from sffscan.stages.sim.families import family_stack


def _volume(n: int, c: float, sigma: float, *, noise: float = 0.0, seed: int = 0
            ) -> tuple[np.ndarray, np.ndarray]:
    """(N, 48, 48) Gaussian curves of width ``sigma`` even in g (c = 0: in k) over a tilted
    plane (peaks from 0.3 to 0.7 of the range across the columns), a floor of 0.05 and
    Gaussian noise; returns the volume and the true peaks (levels)."""
    rng = np.random.default_rng(seed)
    s = c / (n - 1)
    peaks = np.broadcast_to((0.3 + 0.4 * np.linspace(0, 1, 48)) * (n - 1), (48, 48))
    k = np.arange(n, dtype=np.float64)[:, None, None]
    g, gp = k / (1 + s * k), peaks / (1 + s * peaks)
    vol = 0.05 + np.exp(-0.5 * ((g - gp) / sigma) ** 2)
    vol += noise * rng.standard_normal(vol.shape)
    return np.maximum(vol, 0).astype(np.float32), peaks


def test_crossings_of_a_gaussian() -> None:
    k = np.arange(30, dtype=np.float64)
    curve = np.exp(-0.5 * ((k - 10.3) / 2.0) ** 2)
    f, zl, zr = half_height_crossings(curve[None])
    hwhm = 2.0 * np.sqrt(2 * np.log(2))  # minimum ~0: half height at +-1.1774 sigma
    # a 3-point Gaussian is exact on one (to the float32 of depth_peak.three_point_offset)
    assert f[0] == pytest.approx(10.3, abs=1e-6)
    assert zl[0] == pytest.approx(10.3 - hwhm, abs=0.05)  # linear between levels
    assert zr[0] == pytest.approx(10.3 + hwhm, abs=0.05)


def test_a_curve_cut_by_the_range_gives_no_crossing() -> None:
    k = np.arange(20, dtype=np.float64)
    cut = np.exp(-0.5 * ((k - 1.0) / 3.0) ** 2)  # never under half height on the left
    f, zl, zr = half_height_crossings(cut[None])
    assert f.size == zl.size == zr.size == 0


@pytest.mark.parametrize("c", [0.8, 1.667, -0.5])
def test_thin_lens_curves_give_their_warp(c: float) -> None:
    # curves of a sigma of at least 3 levels everywhere (g's slope is 1 at k = 0 and
    # (1 + c)^-2 at the far end): narrower ones, sampled coarsely, shrink the estimate
    n = 60
    vol, _ = _volume(n, c, sigma=3.0 * max(1.0, (1 + c) ** -2), noise=0.01)
    warp = lens_asymmetry(vol)
    assert warp.c == pytest.approx(c, abs=0.1)
    assert warp.applied


def test_narrow_curves_shrink_the_estimate_never_inflate_it() -> None:
    vol, _ = _volume(60, 0.8, sigma=1.5)
    assert 0.6 < lens_asymmetry(vol).c < 0.8


def test_even_curves_are_not_warped_and_warped_select_is_the_default() -> None:
    vol, _ = _volume(50, 0.0, sigma=3.0, noise=0.01)
    warp = lens_asymmetry(vol)
    assert abs(warp.c) < 0.1
    assert not warp.applied
    a = depth_from_focus(vol, method="warped_select")[0]
    b = depth_from_focus(vol, method="shape_select")[0]
    np.testing.assert_array_equal(a, b)


def test_warped_levels_are_the_curves_means_over_their_original_levels() -> None:
    n, c = 41, 1.3
    k = np.arange(n, dtype=np.float32)[:, None, None] * np.ones((n, 2, 3), np.float32)
    warped = warp_volume(k, c)  # a curve equal to its level: a level's mean is the middle
    j = np.arange(n, dtype=np.float64)  # of the original levels it stands for
    lo = np.clip(unwarp_levels(j - 0.5, c, n), 0, n - 1)
    hi = np.clip(unwarp_levels(j + 0.5, c, n), 0, n - 1)
    np.testing.assert_allclose(warped[:, 0, 0], (lo + hi) / 2, atol=1e-4)
    assert np.all(np.diff((hi - lo)[1:-1]) > 0)  # the far end's stand for more levels
    np.testing.assert_array_equal(warp_volume(np.full((n, 2, 2), 0.25, np.float32), c), 0.25)
    # unwarp: the warped grid's ends are the range's, beyond the lens' focal point NaN
    assert unwarp_levels(np.array([0.0, n - 1.0]), c, n) == pytest.approx([0.0, n - 1.0])
    assert np.isnan(unwarp_levels(np.array([(n - 1) * (1 + c) / c + 1]), c, n)[0])


def test_the_warp_removes_a_centroids_pull_on_lopsided_curves() -> None:
    n, c = 60, 1.667
    vol, peaks = _volume(n, c, sigma=1.5)
    assert lens_asymmetry(vol).applied
    error = {m: depth_from_focus(vol, method=m)[0] - peaks
             for m in ("wcentroid", "shape_select", "warped_select")}
    assert np.mean(error["wcentroid"]) > 0.1  # a centroid is pulled into the longer flank
    assert abs(np.mean(error["warped_select"])) < 0.02
    rms = {m: float(np.sqrt(np.mean(e ** 2))) for m, e in error.items()}
    assert rms["warped_select"] < 0.7 * rms["shape_select"]


def test_warped_select_on_a_thin_lens_flat_training_seed() -> None:
    st = family_stack("flat-lens-12bit", 0)  # a training seed of the rule's thresholds
    vol = focus_measure(st.images, operator="glvm", window=9)
    truth = (st.truth_um - st.focus_um[0]) / (st.focus_um[1] - st.focus_um[0])
    inner = (slice(4, -4), slice(4, -4))

    def rmse(method: str) -> float:
        d = depth_from_focus(vol, method=method, median_size=11, spread_size=9)[0]
        return float(np.sqrt(np.mean((d - truth)[inner] ** 2)))

    assert "warped_select" in CANDIDATE_METHODS and "warped_select" not in DEPTH_METHODS
    assert lens_asymmetry(vol).applied
    assert rmse("warped_select") <= 0.7 * rmse("shape_select")


def test_a_large_volume_is_judged_on_a_bounded_sample_of_its_curves() -> None:
    vol, _ = _volume(30, 1.0, sigma=3.0)
    big = np.tile(vol, (1, 13, 13))  # 624 x 624 px: 97,344 curves at every second pixel
    warp = lens_asymmetry(big)
    assert 0 < warp.curves <= MAX_CURVES
    assert warp.c == pytest.approx(lens_asymmetry(vol).c, abs=0.1)


def test_the_warp_in_bands_of_rows_equals_one_band(monkeypatch: pytest.MonkeyPatch) -> None:
    import sffscan.stages.depth_warp as depth_warp

    vol, _ = _volume(37, 1.2, sigma=2.0, noise=0.02)
    whole = warp_volume(vol, 1.2)
    monkeypatch.setattr(depth_warp, "WARP_BAND_VALUES", 37 * 48 * 5)  # bands of 5 rows
    np.testing.assert_array_equal(warp_volume(vol, 1.2), whole)
