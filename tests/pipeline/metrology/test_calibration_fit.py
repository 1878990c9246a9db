"""Calibration routines (pipeline/metrology/calibration_fit.py) on simulated targets with
known answers."""

from __future__ import annotations

import math

import numpy as np
import pytest
from sffscan.pipeline.metrology.calibration_fit import (
    calibrate_lateral,
    calibrate_z,
    fit_field_curvature,
    fit_z_response,
    lateral_scale,
    measure_height,
    noise_by_subtraction,
    symmetric_peak,
)
from sffscan.pipeline.metrology.calibration_model import (
    CalibrationError,
    curvature_correction,
    pixel_positions_um,
)
from sffscan.stages.sim.camera import Optics, focus_heights
from sffscan.stages.sim.targets import (
    checkerboard_image,
    curved_field_stack,
    gauge_block_stacks,
    perspective_checkerboards,
)

TRUE_Z = focus_heights(n_levels=40, z_min_um=100.0, z_step_um=190.0)  # the lens's true table


def test_z_response_recovers_the_true_lens_step() -> None:
    # Nominal 200 µm steps from 0; the simulated lens really steps 190 µm from 100 µm.
    gauges = np.array([1000.0, 2500.0, 4000.0, 5500.0, 7000.0])
    optics = Optics(width=128, height=128, pixel_um=8.5)
    stacks = gauge_block_stacks(gauges, optics=optics, focus_heights_um=TRUE_Z,
                                rng=np.random.default_rng(1))
    z = calibrate_z(stacks, gauges, max_value=optics.max_value)
    assert z.um_per_level == pytest.approx(190.0, rel=0.005)  # measured 190.31
    assert z.intercept_um == pytest.approx(100.0, abs=15.0)  # measured 92.4
    assert z.pearson_r > 0.99999
    assert max(abs(r) for r in z.residuals_um) < 10.0  # < 0.05 level
    expected = (gauges - 100.0) / 190.0
    np.testing.assert_allclose(z.peak_levels, expected, atol=0.06)


def test_fit_z_response_exact_on_linear_data_and_refuses_too_few() -> None:
    lv = np.array([2.0, 9.5, 17.0, 30.25])
    z = fit_z_response(lv, 50.0 + 210.0 * lv)
    assert z.um_per_level == pytest.approx(210.0, rel=1e-12)
    assert z.intercept_um == pytest.approx(50.0, abs=1e-9)
    assert z.pearson_r == pytest.approx(1.0, abs=1e-12)
    assert max(abs(r) for r in z.residuals_um) < 1e-9
    with pytest.raises(CalibrationError, match=">= 3"):
        fit_z_response(lv[:2], lv[:2])
    with pytest.raises(CalibrationError, match="all equal"):
        fit_z_response(lv, np.full(4, 7.0))
    # one gauge's height mistyped: off the line by more than a focus step, named
    wrong = 50.0 + 210.0 * lv
    wrong[2] += 900.0
    with pytest.raises(CalibrationError, match=r"gauge of 4520 µm lies -663.9 µm off"):
        fit_z_response(lv, wrong)
    z = fit_z_response(lv, 50.0 + 210.0 * lv + np.array([30.0, -40.0, 35.0, -20.0]))
    assert max(abs(r) for r in z.residuals_um) < 210.0  # ordinary scatter is kept


@pytest.mark.parametrize("centre", [10.0, 10.23, 10.5, 10.81])
def test_symmetric_peak_of_a_cusped_curve(centre: float) -> None:
    k = np.arange(25, dtype=np.float64)
    lorentz = 1.0 / (1.0 + ((k - centre) / 2.5) ** 2)  # symmetric, broad, not Gaussian
    assert symmetric_peak(lorentz) == pytest.approx(centre, abs=0.005)
    cusp = np.exp(-np.abs(k - centre) / 3.0) + 0.05  # symmetric with a cusp
    assert symmetric_peak(cusp) == pytest.approx(centre, abs=0.03)
    with pytest.raises(CalibrationError, match="too close"):
        symmetric_peak(1.0 / (0.3 + np.abs(k - 0.2)))


def test_lateral_scale_from_outermost_corners() -> None:
    optics = Optics(width=640, height=512, pixel_um=8.5, bit_depth=8)
    img = checkerboard_image(optics=optics, square_um=400.0, squares=(11, 9),
                             rng=np.random.default_rng(3))
    sx, sy = lateral_scale(img, squares=(11, 9), square_um=400.0)
    assert sx == pytest.approx(8.5, rel=1e-3)
    assert sy == pytest.approx(8.5, rel=1e-3)
    with pytest.raises(CalibrationError, match="not found"):
        lateral_scale(np.full((200, 200), 128, np.uint8), squares=(11, 9), square_um=400.0)


def test_perspective_scale_per_focus_level() -> None:
    optics = Optics(width=640, height=512, pixel_um=8.5, bit_depth=8)
    levels = np.array([0, 13, 26, 39])
    imgs, true_scale = perspective_checkerboards(
        optics=optics, focus_heights_um=TRUE_Z[levels], scale_per_mm=-0.02,
        reference_um=float(TRUE_Z[0]), square_um=400.0, squares=(11, 9),
        rng=np.random.default_rng(4))
    lat = calibrate_lateral(imgs, levels=levels, squares=(11, 9), square_um=400.0,
                            reference_level=0.0)
    for m, s in zip(lat.per_level, true_scale, strict=True):
        assert m.um_per_px_x == pytest.approx(s, rel=1e-3)
        assert m.um_per_px_y == pytest.approx(s, rel=1e-3)
    true_slope = 8.5 * -0.02 * 0.190  # µm/px per level: 190 µm per level
    assert lat.slope_x_per_level == pytest.approx(true_slope, rel=0.02)
    assert lat.slope_y_per_level == pytest.approx(true_slope, rel=0.02)
    # a pixel 100 px right of the centre at level 39 lies at 100 * scale(39) µm
    d = np.full((1, 1), 39.0)
    x, _ = pixel_positions_um(d, lateral=lat,
                              frame_origin_px=(int(lat.optical_centre_px[0] + 100.5), 0))
    assert float(x[0, 0]) == pytest.approx((100.5 - 0.0) * true_scale[-1], rel=2e-3)


def test_field_curvature_known_answer_and_correction() -> None:
    optics = Optics(width=192, height=160, pixel_um=8.5)
    a, b, c = 2e-2, 5e-3, 1e-2  # µm/px²: 184 µm at the corners
    stack = curved_field_stack(optics=optics, focus_heights_um=TRUE_Z,
                               curvature_um_px2=(a, b, c), surface_um=4000.0,
                               rng=np.random.default_rng(5))
    height, _ = measure_height(stack, focus_heights_um=TRUE_Z, max_value=optics.max_value)
    fit = fit_field_curvature(height, margin_px=10)
    c0, cu, cv, cuu, cuv, cvv = fit.coefficients_um
    assert cuu == pytest.approx(-a, rel=0.03)
    assert cuv == pytest.approx(-b, rel=0.05)
    assert cvv == pytest.approx(-c, rel=0.03)
    assert c0 == pytest.approx(4000.0, abs=10.0)
    # a second measurement elsewhere on the reference is flat after the correction
    other = curved_field_stack(optics=optics, focus_heights_um=TRUE_Z,
                               curvature_um_px2=(a, b, c), surface_um=4000.0,
                               x_offset_px=500.0, rng=np.random.default_rng(6))
    h2, _ = measure_height(other, focus_heights_um=TRUE_Z, max_value=optics.max_value)
    inner = (slice(10, -10), slice(10, -10))
    corrected = h2 - curvature_correction(fit, h2.shape)
    assert np.std(corrected[inner]) < 0.2 * np.std(h2[inner])
    with pytest.raises(CalibrationError, match="outside"):
        curvature_correction(fit, (10, 10), frame_origin_px=(190, 0))


def test_noise_by_subtraction() -> None:
    rng = np.random.default_rng(7)
    surface = rng.uniform(0, 5000, (300, 300))
    z1 = surface + rng.normal(0, 4.0, surface.shape)
    z2 = surface + rng.normal(0, 4.0, surface.shape) + 30.0  # an offset is not noise
    assert noise_by_subtraction(z1, z2) == pytest.approx(4.0, rel=0.02)
    z1[0, 0] = np.nan  # NaN pixels are left out, not filled
    assert math.isfinite(noise_by_subtraction(z1, z2))
    with pytest.raises(CalibrationError, match="shape"):
        noise_by_subtraction(z1, z2[:-1])
    # simulated: identical repeat measurements give 0; sensor noise gives > 0
    optics = Optics(width=96, height=96, pixel_um=8.5)
    kw = dict(optics=optics, focus_heights_um=TRUE_Z, curvature_um_px2=(0.0, 0.0, 0.0),
              surface_um=3000.0)
    quiet = [measure_height(curved_field_stack(**kw, rng=None),  # type: ignore[arg-type]
                            focus_heights_um=TRUE_Z, max_value=1023)[0] for _ in range(2)]
    assert noise_by_subtraction(*quiet) == 0.0
    noisy = [measure_height(curved_field_stack(**kw, rng=np.random.default_rng(s)),  # type: ignore[arg-type]
                            focus_heights_um=TRUE_Z, max_value=1023)[0] for s in (1, 2)]
    assert 0.5 < noise_by_subtraction(*noisy) < 50.0
