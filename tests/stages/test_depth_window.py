"""The default's fallback on a wider window (stages/depth_window.py): the 9-level centroid
where its scatter and departure say it errs less."""

from __future__ import annotations

import numpy as np
import pytest
from sffscan.stages.depth import depth_from_focus, first_argmax
from sffscan.stages.depth_adaptive import adaptive_block
from sffscan.stages.depth_peak import windowed_centroid
from sffscan.stages.depth_window import (
    WINDOW_STRIPS,
    map_scatter,
    takes_window_centroid,
    window_choice,
)


@pytest.mark.parametrize("n", [6, 12, 50])
@pytest.mark.parametrize("peak", ["gauss3", "centroid"])
def test_adaptive_block_gives_the_nine_level_centroid_bit_for_bit(n: int, peak: str) -> None:
    rng = np.random.default_rng(n)
    vol = rng.gamma(2.0, size=(n, 70, 33)).astype(np.float32)
    centre = rng.integers(0, n, size=(70, 33))  # the ends included: windows cut there
    spread = rng.integers(0, 5, size=(70, 33))  # peak and wide pixels both
    window = np.full((70, 33), np.nan, np.float32)
    depth, conf = adaptive_block(vol, centre, spread, peak=peak, window_out=window)
    np.testing.assert_array_equal(window, windowed_centroid(vol, centre))
    d0, c0 = adaptive_block(vol, centre, spread, peak=peak)  # its own outputs unchanged
    np.testing.assert_array_equal(depth, d0)
    np.testing.assert_array_equal(conf, c0)
    with pytest.raises(ValueError, match="half_window"):
        adaptive_block(vol, centre, spread, half_window=3, window_out=window)


def test_map_scatter_is_the_noise_of_a_plane() -> None:
    # white noise about a plane: x minus the median of 25 such values has a variance of
    # sigma^2 (1 + pi / 50 - 2 / 25) = 0.983 sigma^2 for Gaussian noise
    rng = np.random.default_rng(3)
    yy, xx = np.mgrid[0:300, 0:200]
    plane = (10.0 + 0.01 * xx + 0.02 * yy).astype(np.float32)
    judged = np.zeros(plane.shape, bool)
    judged[2:-2, 2:-2] = True  # the median's replicated borders bend a plane
    assert map_scatter(plane, judged) < 1e-5
    noisy = plane + rng.normal(0.0, 0.2, plane.shape).astype(np.float32)
    assert map_scatter(noisy, judged) == pytest.approx(0.2 * np.sqrt(0.983), rel=0.03)
    # strips: a quarter of the rows, the same noise
    assert map_scatter(noisy, judged, strips=WINDOW_STRIPS) == pytest.approx(
        0.2 * np.sqrt(0.983), rel=0.05)
    # invalid pixels (wild values) take the median: they are not their neighbours' scatter
    wild = noisy.copy()
    bad = rng.random(plane.shape) < 0.05
    wild[bad] = 1e3
    got = map_scatter(wild, ~bad, valid=~bad)
    assert got == pytest.approx(0.2 * np.sqrt(0.983), rel=0.1)
    assert np.isnan(map_scatter(noisy, np.zeros(plane.shape, bool)))


def test_takes_window_centroid_weighs_scatter_against_departure() -> None:
    assert takes_window_centroid((0.3, 0.2), 0.0)
    assert takes_window_centroid((0.3, 0.2), 0.2)  # 0.04 + 0.04 < 0.09
    assert not takes_window_centroid((0.3, 0.2), 0.25)  # 0.04 + 0.0625 > 0.09
    assert not takes_window_centroid((0.2, 0.3), 0.0)
    assert not takes_window_centroid((float("nan"), 0.1), 0.0)


def test_window_choice_takes_the_smoother_unbiased_map_only() -> None:
    rng = np.random.default_rng(5)
    truth = np.full((120, 90), 20.3, np.float32)
    rough = truth + rng.normal(0.0, 0.3, truth.shape).astype(np.float32)
    smooth = truth + rng.normal(0.0, 0.1, truth.shape).astype(np.float32)
    depth = rough.copy()
    # the bias the uncertainty adds: the scatter the rough map showed that the smooth one
    # does not, sqrt(0.983 (0.3^2 - 0.1^2)) (test_map_scatter_is_the_noise_of_a_plane)
    assert window_choice(depth, smooth) == pytest.approx(np.sqrt(0.983 * 0.08), rel=0.1)
    np.testing.assert_array_equal(depth, smooth)
    # the same map 0.4 levels off: its departure outweighs the scatter it saves
    depth = rough.copy()
    assert window_choice(depth, smooth + np.float32(0.4)) is None
    np.testing.assert_array_equal(depth, rough)
    # judged on the valid pixels only: wild values elsewhere do not decide
    wild = smooth.copy()
    wild[:, :10] = rng.normal(20.0, 50.0, (120, 10))
    valid = np.ones(truth.shape, bool)
    valid[:, :12] = False
    depth = rough.copy()
    assert window_choice(depth, wild, valid=valid, strips=WINDOW_STRIPS) is not None
    assert window_choice(rough.copy(), wild) is None


def test_the_default_takes_the_wider_centroid_on_a_thin_lens_flat() -> None:
    """A thin lens' 12-bit flat (a training seed of the study's crossed family): wide curves
    whose 5-level peaks scatter; the 9-level centroid errs less, and the default takes it
    (docs/depth-method-log.md: 0.702 -> 0.454 levels RMSE on this stack)."""
    from sffscan.stages.focus_measure import focus_measure
    from sffscan.stages.sim.families import family_stack

    st = family_stack("flat-lens-12bit", 12)
    vol = focus_measure(st.images, operator="glvm", window=9)
    truth = (st.truth_um - st.focus_um[0]) / (st.focus_um[1] - st.focus_um[0])
    a = first_argmax(vol)
    inner = (slice(4, -4), slice(4, -4))

    def rmse(method: str) -> float:
        d = depth_from_focus(vol, method=method, argmax=a, spread_size=9)[0]
        return float(np.sqrt(np.mean((d - truth)[inner] ** 2)))

    default, fallback, wide = rmse("shape_select"), rmse("adaptive_centroid"), rmse("wcentroid")
    assert default == wide
    assert wide < 0.8 * fallback


def test_a_tall_block_is_judged_on_its_strips_a_short_one_on_every_row() -> None:
    rng = np.random.default_rng(8)
    rows = 4 * WINDOW_STRIPS[1]  # the shortest map judged on strips
    rough = (20.0 + rng.normal(0.0, 0.3, (rows, 64))).astype(np.float32)
    smooth = (20.0 + rng.normal(0.0, 0.1, (rows, 64))).astype(np.float32)
    between = (np.arange(rows) % WINDOW_STRIPS[1] >= WINDOW_STRIPS[0] + 8)[:, None]
    wide = np.where(between, rng.normal(20.0, 5.0, (rows, 64)), smooth).astype(np.float32)
    # only the strips (and 2 rows about them) are read: the rows between do not count
    assert window_choice(rough.copy(), wide, strips=WINDOW_STRIPS) is not None
    assert window_choice(rough.copy(), wide) is None
    # fewer rows than 4 strips' periods: every row judged, strips or not
    short = slice(0, rows - 1)
    assert window_choice(rough[short].copy(), wide[short], strips=WINDOW_STRIPS) is None


def test_shape_select_with_bias_is_the_default_and_its_bias_in_one_pass() -> None:
    from sffscan.stages.depth import shape_select_with_bias
    from sffscan.stages.depth_choice import stack_choice
    from sffscan.stages.focus_measure import focus_measure
    from sffscan.stages.sim.families import family_stack

    vol = focus_measure(family_stack("flat-lens-12bit", 12).images, operator="glvm", window=9)
    depth, conf, bias, _ = shape_select_with_bias(vol)
    d0, c0 = depth_from_focus(vol, method="shape_select")
    np.testing.assert_array_equal(depth, d0)
    np.testing.assert_array_equal(conf, c0)
    # this stack takes the 9-level centroid: its bias adds to the fallback's
    assert bias > stack_choice(vol, first_argmax(vol)).bias > 0.0
