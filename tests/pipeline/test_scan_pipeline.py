"""End to end: passes and seams, bounded memory, frames without stage positions (bad
input and the command line: tests/pipeline/test_scan_errors.py)."""

from __future__ import annotations

import tracemalloc
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import pytest
from sffscan.pipeline.config import ScanConfig, pass_pitch_px
from sffscan.pipeline.sim_source import make_world, simulate_frames
from sffscan.pipeline.wiring import run_scan
from sffscan.stages.messages import Frame

from tests.scan_helpers import (
    RenderedScan,
    mosaic_height,
    scan,
    score,
    small_config,
    strip_region,
)


def test_three_passes_blend_without_seams(tmp_path: Path) -> None:
    # the sinusoidal world has the same relief statistics everywhere, so that the bands
    # between passes and the rest can be compared (the plate puts its features mid-plate)
    cfg = small_config(source={"world": "sinusoid", "plate_width_mm": 12.0},
                       motion={"passes": 3})
    out = tmp_path / "passes.zarr"
    report = scan(cfg, out)
    assert report.result.dropped == 0
    o, m = cfg.optics, cfg.processing.edge_margin_px
    pitch = pass_pitch_px(cfg)
    x0, y0, x1, y1 = strip_region(cfg)
    y1 = int(2 * pitch) + o.height_px - m
    region = (x0, y0, x1, y1)
    est = mosaic_height(out, region)
    assert np.isfinite(est).mean() == 1.0  # the passes tile the plate without gaps
    rows = np.arange(y0, y1)
    # overlap bands: rows seen by two passes
    overlap = np.zeros(rows.shape, bool)
    for p in (1, 2):
        top = p * pitch + m
        bottom = (p - 1) * pitch + o.height_px - m
        overlap |= (rows >= top) & (rows < bottom)
    band = np.repeat(overlap[:, None], est.shape[1], axis=1)
    in_band = score(cfg, est, region, band)
    away = score(cfg, est, region, ~band)
    print(f"\n3 passes: RMSE in overlap bands {in_band.rmse_um:.1f} µm, away from them "
          f"{away.rmse_um:.1f} µm, ratio {in_band.rmse_um / away.rmse_um:.3f}")
    assert in_band.pixels > 1000 and away.pixels > 1000
    assert in_band.rmse_um <= 1.10 * away.rmse_um


def _traced_peak(cfg: ScanConfig, out: Path) -> int:
    """Peak of numpy/Python allocations during a scan, after the world's one-off set-up."""
    world = make_world(cfg)
    assert world.texture_tile.size  # built before tracing: a fixed cost, not the scan's
    tracemalloc.start()
    try:
        run_scan(cfg, frames=simulate_frames(cfg, world=world), output=out, progress=False)
        return tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()


def test_memory_is_flat_in_scan_length(tmp_path: Path) -> None:
    # small queues: what is in flight depends on thread timing; the test is about growth
    short = small_config(source={"plate_length_mm": 40.0}, motion={"x_end_mm": 15.0},
                         processing={"queue_capacity": 2})
    long = small_config(source={"plate_length_mm": 40.0}, motion={"x_end_mm": 28.0},
                        processing={"queue_capacity": 2})
    p_short = _traced_peak(short, tmp_path / "short.zarr")
    p_long = _traced_peak(long, tmp_path / "long.zarr")
    print(f"\npeak traced memory: 13 mm strip {p_short / 1e6:.1f} MB, 26 mm strip "
          f"{p_long / 1e6:.1f} MB")
    assert p_long <= 1.10 * p_short


def test_frames_without_stage_positions_follow_the_speed_model(tmp_path: Path) -> None:
    cfg = small_config(motion={"passes": 2}, source={"plate_width_mm": 8.0})
    region = strip_region(cfg)

    def no_positions(frames: Iterator[Frame]) -> Iterator[Frame]:
        for f in frames:
            yield Frame(f.header.model_copy(update={"stage_x_um": None, "stage_y_um": None}),
                        f.image)

    frames = RenderedScan(cfg)  # rendered once, fed to both scans
    run_scan(cfg, frames=iter(frames), output=tmp_path / "with.zarr", progress=False)
    run_scan(cfg, frames=no_positions(iter(frames)), output=tmp_path / "without.zarr",
             progress=False)
    with_pos = score(cfg, mosaic_height(tmp_path / "with.zarr", region), region)
    without = score(cfg, mosaic_height(tmp_path / "without.zarr", region), region)
    assert without.coverage == with_pos.coverage == 1.0
    assert without.rmse_um == pytest.approx(with_pos.rmse_um, rel=0.02)
