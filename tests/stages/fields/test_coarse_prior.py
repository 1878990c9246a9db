"""Two-step scanning with a coarse prior: level ranges, subset reconstruction, the plate bar."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import zarr
from sffscan.pipeline.config import max_speed_sliding_mm_s
from sffscan.pipeline.metrology.evaluate import accuracy
from sffscan.pipeline.restrict import restrict_scan, scan_level_range
from sffscan.stages.fields.coarse_prior import (
    CoarsePrior,
    field_levels,
    level_range,
    reconstruct_levels,
    simulated_prior,
    two_step_fields,
)
from sffscan.stages.sim.camera import Optics, focus_heights, render_stack
from sffscan.stages.sim.world import characterisation_plate, sinusoid_world

from tests.scan_helpers import small_config

HEIGHTS = focus_heights(n_levels=50, z_min_um=0.0, z_step_um=200.0)


def test_level_range_known_answers() -> None:
    # 1000..1500 µm, margin 50 -> 950..1550 -> levels 4..8, padded by 2 -> 2..10
    np.testing.assert_array_equal(
        level_range(1000.0, 1500.0, focus_heights_um=HEIGHTS, margin_um=50.0, pad_levels=2),
        np.arange(2, 11))
    # exactly on a level: 1000 -> level 5 only, padded by 1
    np.testing.assert_array_equal(
        level_range(1000.0, 1000.0, focus_heights_um=HEIGHTS, margin_um=0.0, pad_levels=1),
        [4, 5, 6])
    # clipped at the ends, still >= 3 levels
    np.testing.assert_array_equal(
        level_range(-500.0, -400.0, focus_heights_um=HEIGHTS, margin_um=0.0, pad_levels=1),
        [0, 1, 2])
    np.testing.assert_array_equal(
        level_range(0.0, 1e6, focus_heights_um=HEIGHTS, margin_um=0.0), np.arange(50))
    with pytest.raises(ValueError, match="z_lo_um <= z_hi_um"):
        level_range(2.0, 1.0, focus_heights_um=HEIGHTS, margin_um=0.0)


def test_unknown_prior_gives_the_full_range() -> None:
    grid = np.full((10, 10), 2000.0, np.float32)
    grid[7, 7] = np.nan
    prior = CoarsePrior(grid, origin_px=(0.0, 0.0), step_px=10.0, uncertainty_um=50.0)
    assert prior.range_um(0, 0, 40, 40) == (2000.0, 2000.0)
    assert prior.range_um(50, 50, 90, 90) is None  # touches the NaN cell
    assert prior.range_um(-20, 0, 10, 10) is None  # outside the map
    lv = field_levels(prior, x0=0, y0=0, width=40, height=40, focus_heights_um=HEIGHTS,
                      pad_levels=2)
    np.testing.assert_array_equal(lv, np.arange(7, 14))  # 1950..2050 -> 9..11, +-2
    full = field_levels(prior, x0=50, y0=50, width=40, height=40, focus_heights_um=HEIGHTS)
    np.testing.assert_array_equal(full, np.arange(50))


def test_subset_of_levels_measures_like_the_full_stack() -> None:
    world = sinusoid_world(seed=2, pixel_um=17.0, amplitude_um=600.0, period_px=300.0,
                           offset_um=3000.0)
    optics = Optics(width=160, height=160, pixel_um=17.0)
    stack = render_stack(world, x0=0.0, y0=0.0, focus_heights_um=HEIGHTS, optics=optics,
                         rng=np.random.default_rng(1))
    truth = world.height_um(0.0, 0.0, 160, 160)
    lv = level_range(float(truth.min()), float(truth.max()), focus_heights_um=HEIGHTS,
                     margin_um=50.0)
    assert lv.size < 30
    inner = (slice(12, -12), slice(12, -12))
    for method in ("spc", "gauss3"):
        full, _ = reconstruct_levels(stack, np.arange(50), focus_heights_um=HEIGHTS,
                                     max_value=1023, method=method)
        part, conf = reconstruct_levels(stack[lv], lv, focus_heights_um=HEIGHTS,
                                        max_value=1023, method=method)
        assert part.shape == conf.shape == (160, 160)
        e_full = accuracy(full[inner], truth[inner], max_depth=9800.0).rmse_um
        e_part = accuracy(part[inner], truth[inner], max_depth=9800.0).rmse_um
        assert e_part <= (1.05 if method == "spc" else 1.001) * e_full, (method, e_part, e_full)
    with pytest.raises(ValueError, match="consecutive"):
        reconstruct_levels(stack[[1, 3, 5]], np.array([1, 3, 5]), focus_heights_um=HEIGHTS,
                           max_value=1023)


def test_two_step_on_the_characterisation_plate(capsys: pytest.CaptureFixture[str]) -> None:
    """Issue bar: >= 40 % fewer frames than full range, RMSE within 5 % of it."""
    px = 34.0
    world = characterisation_plate(seed=0, pixel_um=px, length_mm=60.0, width_mm=9.0,
                                   z_range_um=(0.0, float(HEIGHTS[-1])))
    region = (0, 0, int(60_000 / px), int(9_000 / px))
    cover = world.height_um(-256.0, -256.0, region[2] + 512, region[3] + 512)
    prior = simulated_prior(cover, step_px=8, uncertainty_um=50.0, origin_px=(-256, -256),
                            rng=np.random.default_rng(3))
    r = two_step_fields(world, optics=Optics(width=128, height=128, pixel_um=px),
                        region_px=region, focus_heights_um=HEIGHTS, prior=prior)
    full = accuracy(r.height_full_um, r.truth_um, max_depth=float(HEIGHTS[-1]))
    part = accuracy(r.height_prior_um, r.truth_um, max_depth=float(HEIGHTS[-1]))
    with capsys.disabled():
        print(f"\ntwo-step, plate 60 x 9 mm, {len(r.levels_per_field)} fields: frames "
              f"{r.frames_full} -> {r.frames_prior} ({100 * r.frames_saved:.1f} % fewer), "
              f"RMSE {full.rmse_um:.1f} -> {part.rmse_um:.1f} µm "
              f"(ratio {part.rmse_um / full.rmse_um:.3f})")
    assert full.coverage == part.coverage == 1.0
    assert r.frames_saved >= 0.40
    assert part.rmse_um <= 1.05 * full.rmse_um
    assert min(r.levels_per_field) < 25 and max(r.levels_per_field) > 40  # flat vs tetrahedron


def test_continuous_scan_levels_from_the_prior() -> None:
    cfg = small_config(source={"world": "sinusoid"})
    # a flat prior at 3 mm over everything the scan sees
    prior = CoarsePrior(np.full((800, 3000), 3000.0, np.float32), origin_px=(-1000.0, -300.0),
                        step_px=1.0, uncertainty_um=50.0)
    lv = scan_level_range(cfg, prior, pad_levels=3)
    np.testing.assert_array_equal(lv, np.arange(11, 20))  # 2950..3050 -> 14..16, +-3
    for p in range(cfg.motion.passes):
        np.testing.assert_array_equal(scan_level_range(cfg, prior, pass_index=p, pad_levels=3), lv)
    fast = restrict_scan(cfg, lv)
    assert fast.optics.n_levels == 9
    assert fast.optics.z_min_um == pytest.approx(11 * 200.0)
    np.testing.assert_allclose(fast.optics.focus_heights_um(), HEIGHTS[lv])
    assert max_speed_sliding_mm_s(fast) == pytest.approx(
        max_speed_sliding_mm_s(cfg) * 50 / 9, rel=1e-9)
    with pytest.raises(ValueError, match="consecutive"):
        restrict_scan(cfg, np.array([3, 5, 7]))
    # a prior that does not cover the scan leaves the full staircase
    small = CoarsePrior(np.full((10, 10), 3000.0, np.float32))
    np.testing.assert_array_equal(scan_level_range(cfg, small), np.arange(50))


def test_previous_layer_mosaic_restricts_a_continuous_scan(tmp_path: Path) -> None:
    """`sffscan restrict`: the previous layer's mosaic bounds the levels of the next scan
    of the same strip; the written configuration runs fewer levels covering the prior's
    range over the strip plus the uncertainty, and loads as a valid scan."""
    from sffscan.pipeline.cli.main import main
    from sffscan.pipeline.config import config_to_toml, load_config, max_speed_sliding_mm_s
    from sffscan.pipeline.restrict import prior_from_mosaic, strip_level_range

    from tests.scan_helpers import scan

    cfg = small_config(source={"world": "sinusoid"})
    layer = scan(cfg, tmp_path / "layer.zarr").output
    toml = tmp_path / "scan.toml"
    toml.write_text(config_to_toml(cfg), encoding="utf-8")
    out = tmp_path / "restricted.toml"
    assert main(["restrict", "--config", str(toml), "--prior", str(layer),
                 "--uncertainty-um", "150", "--pad-levels", "3", "-o", str(out)]) == 0
    restricted = load_config(out)
    prior = prior_from_mosaic(str(layer), uncertainty_um=150.0)
    levels = strip_level_range(cfg, prior, pad_levels=3)
    assert restricted.optics.n_levels == levels.size < cfg.optics.n_levels
    assert restricted.optics.z_min_um == cfg.optics.focus_heights_um()[int(levels[0])]
    assert max_speed_sliding_mm_s(restricted) > max_speed_sliding_mm_s(cfg)
    # the kept heights cover what the previous layer measured over the strip, ± uncertainty
    h = np.asarray(zarr.open_group(str(layer), mode="r")["height"][:])
    kept = restricted.optics.focus_heights_um()
    assert kept[0] <= np.nanmin(h) - 150.0 + 1e-6 or levels[0] == 0
    assert kept[-1] >= np.nanmax(h) + 150.0 - 1e-6 or levels[-1] == cfg.optics.n_levels - 1
    # -o over an existing file (the scan's own configuration): refused unless --overwrite
    before = toml.read_bytes()
    again = ["restrict", "--config", str(toml), "--prior", str(layer), "--uncertainty-um",
             "150", "--pad-levels", "3", "-o", str(toml)]
    assert main(again) == 2 and toml.read_bytes() == before
    assert main([*again, "--overwrite"]) == 0 and load_config(toml) == restricted


def test_a_prior_that_does_not_cover_the_strip_restricts_nothing(tmp_path: Path) -> None:
    from sffscan.pipeline.cli.main import main
    from sffscan.pipeline.config import config_to_toml
    from sffscan.pipeline.wiring import open_writer

    cfg = small_config()
    toml = tmp_path / "scan.toml"
    toml.write_text(config_to_toml(cfg), encoding="utf-8")
    other = small_config(motion={"x_start_mm": 2.0, "x_end_mm": 6.0},
                         output={"path": str(tmp_path / "small.zarr")})
    open_writer(other)  # an empty mosaic of a shorter strip: NaN everywhere, smaller
    out = tmp_path / "r.toml"
    assert main(["restrict", "--config", str(toml), "--prior", str(tmp_path / "small.zarr"),
                 "--uncertainty-um", "100", "-o", str(out)]) == 2
    assert not out.exists()
    assert main(["restrict", "--config", str(toml), "--prior", str(tmp_path / "none.zarr"),
                 "--uncertainty-um", "100", "-o", str(out)]) == 2


def test_twostep_command_runs_and_refuses_bad_options(
        capsys: pytest.CaptureFixture[str]) -> None:
    """``sffscan twostep``: a small run prints its frames and RMSE ratio; a bad option is a
    clear message and exit 2 (each raised a traceback, exit 1; 100000 px fields tried to
    allocate 599 GiB)."""
    from sffscan.pipeline.cli.main import main

    assert main(["twostep", "--field-px", "64", "--pixel-um", "68", "-q"]) == 0
    out = capsys.readouterr().out
    assert "fewer)" in out and "ratio" in out
    for bad, words in ((["--field-px", "100000"], "must fit the 9 mm width"),
                       (["--field-px", "0"], "must fit"),
                       (["--pixel-um", "nan"], "--pixel-um must be a finite number"),
                       (["--prior-step-px", "0"], "step_px must be >= 1"),
                       (["--margin-um", "-5"], "--margin-um must be"),
                       (["--pad-levels", "-3"], "pad_levels >= 1")):
        assert main(["twostep", *bad, "-q"]) == 2, bad
        assert words in capsys.readouterr().err
