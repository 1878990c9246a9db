"""The measurement of issue 24's noisy-scan bar (bench/bench_noisy_scan.py) measures what it
says: the simulator's frames carry the described sensor noise, and the true-offset
reference's headers put every frame where the simulator rendered it."""

from __future__ import annotations

import itertools
import math
from types import ModuleType

import numpy as np
from sffscan.pipeline.plan import plan_frames
from sffscan.pipeline.sim_source import make_optics, make_world, simulate_frames, wobble_px
from sffscan.stages.sim.camera import render_frame

from tests.bench_modules import load_bench


def _bench() -> ModuleType:
    return load_bench("bench_noisy_scan")


def test_true_offset_headers_place_frames_where_rendered() -> None:
    b = _bench()
    cfg = b.scan_config(seed=3, length_mm=1.0, wobble_px=3.0, world="plate",
                        execution="threads")
    cfg = cfg.model_copy(update={"optics": cfg.optics.model_copy(update={"noise_sigma": 0.0})})
    world, optics = make_world(cfg), make_optics(cfg)
    heights = cfg.optics.focus_heights_um()
    px = cfg.optics.pixel_um
    picks = (0, 7, 20)  # frames with the wobble at different phases
    frames = list(itertools.islice(simulate_frames(cfg, world=world), max(picks) + 1))
    plan = list(itertools.islice(plan_frames(cfg), max(picks) + 1))
    true = list(b.true_frames(cfg, frames))
    moved = 0.0
    for k in picks:
        h = true[k].header
        assert h.frame_id == frames[k].header.frame_id
        assert frames[k].header.stage_x_um is not None and h.stage_x_um is not None
        wx, _ = wobble_px(cfg, plan[k].travel_px)
        assert math.isclose(h.stage_x_um - frames[k].header.stage_x_um, wx * px, abs_tol=1e-6)
        moved = max(moved, abs(wx))
        again = render_frame(world, x0=h.stage_x_um / px, y0=(h.stage_y_um or 0.0) / px,
                             focus_um=heights[h.focus_index], optics=optics, rng=None)
        np.testing.assert_array_equal(again, frames[k].image)  # rendered where the header says
        np.testing.assert_array_equal(true[k].image, frames[k].image)
    assert moved > 1.0  # the wobble is there: commanded and true positions differ


def test_sensor_noise_has_the_described_variance() -> None:
    b = _bench()
    cfg = b.scan_config(seed=0, length_mm=1.0, wobble_px=3.0, world="plate",
                        execution="threads")
    assert cfg.optics.bit_depth == 10
    world, optics = make_world(cfg), make_optics(cfg)
    x0, y0 = cfg.motion.x_start_mm * 1000.0 / cfg.optics.pixel_um, 0.0
    pair = [render_frame(world, x0=x0, y0=y0, focus_um=1000.0, optics=optics,
                         rng=np.random.default_rng(s)).astype(np.float64) / 1023.0
            for s in (1, 2)]
    clean = render_frame(world, x0=x0, y0=y0, focus_um=1000.0, optics=optics, rng=None)
    keep = (clean > 150) & (clean < 870)  # away from clipping at 0 and full scale
    var = float(np.var((pair[0] - pair[1])[keep])) / 2.0
    assert keep.sum() > 10_000
    assert abs(var - b.NOISE_VARIANCE_FS) < 0.05 * b.NOISE_VARIANCE_FS, var
