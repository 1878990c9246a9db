"""Scan planner (pipeline.hardware.planner, `sffscan plan`): the thesis' figures and refusals."""

from __future__ import annotations

import math
from typing import Any

import pytest
from sffscan.pipeline.cli.main import main
from sffscan.pipeline.config import ScanConfig, config_from_dict, max_speed_sliding_mm_s
from sffscan.pipeline.hardware.planner import PlanError, plan_scan
from sffscan.pipeline.plan import pass_bounds_px

THESIS: dict[str, Any] = {"fov_mm": (11.0, 9.0), "fps": 150.0, "n_levels": 50, "overlap": 0.091,
          "pixel_um": 8.5, "area_mm": (100.0, 100.0)}


def test_thesis_plate_25_passes_175_s() -> None:
    """Thesis ch. 6: FOV 11 x 9 mm, 150 fps, N = 50, 9.1 % overlap: 15 mm/s; a 100 x 100 mm
    plate in 25 passes of about 7 s, 175 s; maximum exposure 8.5 µm / 15 mm/s."""
    t = plan_scan(**THESIS).thesis
    assert t.max_speed_mm_s == pytest.approx(15.0, abs=0.01)
    assert t.passes == 25
    assert t.pass_time_s == pytest.approx(7.0, abs=0.05)
    assert t.scan_time_s == pytest.approx(175.0, rel=0.01)
    assert t.max_exposure_us == pytest.approx(8.5 / 15.0 * 1000, rel=1e-3)
    assert t.frames_per_pass == pytest.approx(7.0 * 150, abs=3)


def test_thesis_example_speeds() -> None:
    """300 fps or N = 25 allows 30 mm/s (thesis ch. 6.2.1)."""
    assert plan_scan(**{**THESIS, "fps": 300.0}).thesis.max_speed_mm_s == pytest.approx(
        30.0, abs=0.01)
    assert plan_scan(**{**THESIS, "n_levels": 25}).thesis.max_speed_mm_s == pytest.approx(
        30.0, abs=0.01)


def test_sliding_rule_reuses_the_scan_plan() -> None:
    plan = plan_scan(fov_mm=(10.88, 8.704), fps=150.0, n_levels=50, overlap=0.15,
                     pixel_um=8.5, area_mm=(40.0, 30.0), speed_mm_s=15.0)
    s = plan.sliding
    cfg = config_from_dict({"motion": {"x_end_mm": 40.0}})  # the default thesis optics
    assert s.max_speed_mm_s == pytest.approx(max_speed_sliding_mm_s(cfg), rel=1e-9)
    assert s.frames_per_pass == pass_bounds_px(cfg, 0)[2]
    assert s.pass_time_s == pytest.approx(s.frames_per_pass / 150.0)
    # pitch: usable height (1024 - 2 x 11 px) x (1 - 0.15), 8.5 µm px
    assert s.pass_pitch_mm == pytest.approx(1002 * 0.85 * 0.0085, rel=1e-9)
    assert s.passes == 1 + -(-(30.0 - 1002 * 0.0085) // (1002 * 0.85 * 0.0085))
    assert s.max_speed_mm_s > 2 * plan.thesis.max_speed_mm_s * 0.95  # sliding ~ 2x thesis


def test_direction_y_swaps_the_fov() -> None:
    p = plan_scan(**{**THESIS, "direction": "y"})
    assert p.fov_mm == (9.0, 11.0)
    # the FOV is rounded to whole pixels (1059 px of 8.5 µm = 9.0015 mm): rel 1e-3
    assert p.thesis.max_speed_mm_s == pytest.approx(150 / 50 * 9.0 * 0.909 / 2, rel=1e-3)


@pytest.mark.parametrize("kwargs, reason", [
    ({"overlap": 1.0}, "overlap"),
    ({"area_mm": (0.0, 10.0)}, "area"),
    ({"speed_mm_s": 40.0}, "exceeds the sliding-window limit"),
    ({"fov_mm": (0.5, 9.0)}, "fewer than N = 50"),
    ({"fps": 0.0}, "frame rate = 0: .* finite and > 0"),
    ({"fov_mm": (math.inf, 9.0)}, "FOV width = inf"),  # an OverflowError before
    ({"pixel_um": math.nan}, "pixel scale = nan"),
    ({"area_mm": (math.inf, 10.0)}, "area inf x 10"),
    ({"speed_mm_s": math.inf}, "speed = inf"),
])
def test_impossible_requests_are_refused_with_the_reason(kwargs: dict[str, Any],
                                                          reason: str) -> None:
    with pytest.raises(PlanError, match=reason):
        plan_scan(**{**THESIS, **kwargs})


def test_a_speed_only_the_sliding_rule_allows() -> None:
    p = plan_scan(**{**THESIS, "speed_mm_s": 25.0})
    assert p.thesis.refused is not None and "15.00" in p.thesis.refused
    assert p.sliding.refused is None and p.sliding.speed_mm_s == 25.0


def test_plan_command(capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["plan", "--fov", "11", "9", "--overlap", "0.091"]) == 0
    out = capsys.readouterr().out
    row = {line.split("  ")[1].strip(): line.split()[-2:] for line in out.splitlines()
           if line.startswith("  ")}
    assert row["passes"] == ["25", "13"]
    assert row["scan time, s"][0] == "175.0"
    assert main(["plan", "--speed", "50"]) == 2
    assert "refused" in capsys.readouterr().err
    assert ScanConfig().optics.width_px == 1280  # defaults untouched


def test_max_exposure_never_exceeds_half_a_step() -> None:
    """At 2 mm/s the smear limit is 8.5 µm / 2 mm/s = 4250 µs, but the trigger sits at the
    step's centre: at 150 fps the exposure must end within 1 / 300 s = 3333 µs, or the
    frame mixes two focus levels. The plan's maximum is the smaller of the two."""
    p = plan_scan(**{**THESIS, "speed_mm_s": 2.0})
    assert p.exposure_window_us == pytest.approx(1e6 / 300)
    for rp in (p.thesis, p.sliding):
        assert rp.max_exposure_us == pytest.approx(1e6 / 300)
    fast = plan_scan(**{**THESIS, "speed_mm_s": 10.0})  # 850 µs: the smear limit binds
    assert fast.thesis.max_exposure_us == pytest.approx(850.0)
