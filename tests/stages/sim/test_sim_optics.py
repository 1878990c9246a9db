"""Real-lens effects of the simulator (stages/sim/lens.py): breathing, field curvature,
vignetting, each measured back from rendered frames with an independent method."""

from __future__ import annotations

import numpy as np
import pytest
from sffscan.pipeline.config import REALISTIC_OPTICS, demo_config
from sffscan.pipeline.metrology.calibration_fit import fit_field_curvature, measure_height
from sffscan.pipeline.sim_source import make_optics
from sffscan.stages.sim.camera import Optics, focus_heights, render_frame, render_stack
from sffscan.stages.sim.lens import radius2_map, scale_about_centre
from sffscan.stages.sim.world import PlateWorld


def test_defaults_are_ideal_and_realistic_values_as_documented() -> None:
    assert Optics().ideal
    cfg = demo_config()
    assert make_optics(cfg).ideal
    real = make_optics(demo_config(optics=dict(REALISTIC_OPTICS)))
    heights = cfg.optics.focus_heights_um()
    change = real.magnification(heights[-1]) / real.magnification(heights[0]) - 1.0
    assert change == pytest.approx(0.0198, abs=1e-4)  # about 2 % over the focus range
    assert real.magnification(0.5 * (heights[0] + heights[-1])) == pytest.approx(1.0)
    assert real.field_curvature_um == 150.0 and real.vignetting == 0.2


def test_radius_map_is_one_at_the_corner() -> None:
    r2 = radius2_map((5, 7))
    assert r2[2, 3] == 0.0
    assert r2[0, 0] == pytest.approx(1.0) and r2[-1, -1] == pytest.approx(1.0)


def test_breathing_is_a_magnification_about_the_frame_centre() -> None:
    """A frame at magnification M equals the M = 1 frame magnified about the centre (both
    rendered; the blur is the same flat-focus blur, no noise)."""
    world = PlateWorld(seed=3, pixel_um=10.0, texture_tile_px=256)
    m = 1.012
    ideal = Optics(width=96, height=64, pixel_um=10.0, bit_depth=10, noise_sigma=0.0)
    real = Optics(width=96, height=64, pixel_um=10.0, bit_depth=10, noise_sigma=0.0,
                  magnification_per_mm=0.012, magnification_ref_um=0.0)
    assert real.magnification(1000.0) == pytest.approx(m)
    big = Optics(width=96 + 40, height=64 + 40, pixel_um=10.0, noise_sigma=0.0)
    # the ideal frame with 20 px of context, magnified about its centre by M
    wide = render_frame(world, x0=-20.0, y0=-20.0, focus_um=1000.0, optics=big, rng=None)
    expect = scale_about_centre(wide.astype(np.float32), m, out_shape=(64, 96), pad=20)
    got = render_frame(world, x0=0.0, y0=0.0, focus_um=1000.0, optics=real, rng=None)
    plain = render_frame(world, x0=0.0, y0=0.0, focus_um=1000.0, optics=ideal, rng=None)
    diff = np.abs(got.astype(np.float64) - expect)[4:-4, 4:-4]
    assert diff.mean() < 1.5  # 10-bit LSB: same image up to the warp's rounding
    assert np.abs(plain.astype(np.float64) - got)[4:-4, 4:-4].mean() > 10 * diff.mean()


def test_field_curvature_is_measured_back_as_a_quadratic_surface() -> None:
    """A flat plane at 4 mm through a 150 µm (corner) curved field reads 150 µm low at the
    corners: the fitted quadratic's corner value, measured by SFF, within 20 µm."""
    zs = focus_heights(n_levels=50, z_step_um=200.0)
    o = Optics(width=160, height=128, pixel_um=8.5, field_curvature_um=150.0)
    world = PlateWorld(seed=1, pixel_um=8.5, base_um=4000.0, texture_tile_px=256)
    stack = render_stack(world, x0=0.0, y0=0.0, focus_heights_um=zs, optics=o,
                         rng=np.random.default_rng(0))
    height, _ = measure_height(stack, focus_heights_um=zs, max_value=o.max_value)
    fit = fit_field_curvature(height, margin_px=10)
    c = np.asarray(fit.coefficients_um)
    cx, cy = fit.centre_px
    corner = c[3] * cx * cx + c[4] * cx * cy + c[5] * cy * cy
    print(f"\nfield curvature measured at the corner: {corner:+.1f} µm (true -150)")
    assert corner == pytest.approx(-150.0, abs=20.0)
    assert abs(c[4]) * cx * cy < 10.0  # rotationally symmetric: no cross term


def test_vignetting_darkens_the_corners() -> None:
    o = Optics(width=200, height=160, pixel_um=10.0, noise_sigma=0.0, vignetting=0.2)
    world = PlateWorld(seed=2, pixel_um=10.0, texture_tile_px=256, texture_contrast=0.0)
    img = render_frame(world, x0=0.0, y0=0.0, focus_um=0.0, optics=o, rng=None)
    centre = float(img[76:84, 96:104].mean())
    corner = float(img[:3, :3].mean())
    assert centre == pytest.approx(0.5 * 1023, abs=1.0)
    assert corner / centre == pytest.approx(0.8, abs=0.01)


def test_demo_realistic_switch_parses() -> None:
    from sffscan.pipeline.cli.main import build_parser

    assert build_parser().parse_args(["demo", "--realistic"]).realistic is True
    assert build_parser().parse_args(["demo"]).realistic is False
