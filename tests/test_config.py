"""Configuration: defaults follow the thesis, errors name the field, schemas do not drift."""

from __future__ import annotations

from pathlib import Path

import pytest
from sffscan.pipeline.config import (
    ConfigError,
    config_from_dict,
    config_to_toml,
    demo_config,
    load_config,
    max_speed_sliding_mm_s,
    max_speed_thesis_mm_s,
    shift_per_frame_px,
)
from sffscan.pipeline.formats.schema_gen import check_schemas
from sffscan.pipeline.plan import frame_count, pass_bounds_px, plan_frames, scan_extent_px

SCHEMA_DIR = Path(__file__).resolve().parents[1] / "schemas"


def test_defaults_follow_the_thesis() -> None:
    cfg = config_from_dict({})
    o = cfg.optics
    assert (o.width_px, o.height_px, o.pixel_um, o.fps, o.n_levels) == (1280, 1024, 8.5, 150, 50)
    assert cfg.motion.speed_mm_s == 15.0
    assert shift_per_frame_px(cfg) == pytest.approx(11.7647, abs=1e-4)  # thesis: ~11.6 px
    # thesis eq. 6.1-6.3 with w = 10.88 mm, r = 150 fps, N = 50, P = 0
    assert max_speed_thesis_mm_s(cfg) == pytest.approx(150 / 50 * 10.88 / 2)
    # sliding window: (1280 - 2*11 - 2) px / 50 levels per frame at 150 fps, 8.5 µm/px;
    # margin 11 = GLVM's reach 2*(9//2) + 1 + 2 px kept for registration
    assert cfg.processing.edge_margin_px == 11
    assert max_speed_sliding_mm_s(cfg) == pytest.approx(1256 / 50 * 150 * 8.5 / 1000)


@pytest.mark.parametrize(
    ("data", "field"),
    [
        ({"motion": {"speed_mm_s": 40.0}}, "motion.speed_mm_s"),
        ({"optics": {"n_levels": 2}}, "optics.n_levels"),
        ({"optics": {"pixel_um": -8.5}}, "optics.pixel_um"),
        ({"processing": {"window": 8}}, "processing.window"),
        ({"processing": {"depth_method": "magic"}}, "processing.depth_method"),
        ({"optics": {"fps": 0}}, "optics.fps"),
        ({"motion": {"x_start_mm": 5.0, "x_end_mm": 1.0}}, "motion.x_end_mm"),
        ({"optic": {}}, "optic"),
        ({"motion": {"x_start_mm": float("nan")}}, "motion.x_start_mm"),
        ({"optics": {"fps": float("inf")}}, "optics.fps"),
    ],
)
def test_impossible_configurations_name_the_field(data: dict, field: str) -> None:
    with pytest.raises(ConfigError, match=field.replace(".", r"\.")):
        config_from_dict(data)


def test_toml_round_trip_and_file_errors(tmp_path: Path) -> None:
    cfg = demo_config(passes=2, output={"path": 'C:\\scans\\new "plate".zarr'})
    path = tmp_path / "scan.toml"
    path.write_text(config_to_toml(cfg))
    assert load_config(path) == cfg
    with pytest.raises(ConfigError, match="not found"):
        load_config(tmp_path / "missing.toml")
    bad = tmp_path / "bad.toml"
    bad.write_text("[optics]\npixel_um = -1\n")
    with pytest.raises(ConfigError, match=r"bad\.toml: optics\.pixel_um"):
        load_config(bad)


def test_plan_covers_the_strip_and_stays_in_extent() -> None:
    cfg = demo_config(passes=2)
    frames = list(plan_frames(cfg))
    assert len(frames) == frame_count(cfg)
    assert [f.focus_index for f in frames[:3]] == [0, 1, 2]
    assert all(f.focus_index == f.frame_id % cfg.optics.n_levels for f in frames)
    d = shift_per_frame_px(cfg)
    p0 = [f for f in frames if f.pass_index == 0]
    p1 = [f for f in frames if f.pass_index == 1]
    assert p0[1].x_px - p0[0].x_px == pytest.approx(d)
    assert p1[1].x_px - p1[0].x_px == pytest.approx(-d)  # serpentine
    x0, y0, x1, y1 = scan_extent_px(cfg)
    for f in frames:
        assert x0 <= f.x_px and f.x_px + cfg.optics.width_px <= x1
        assert y0 <= f.y_px and f.y_px + cfg.optics.height_px <= y1
    first, last, n = pass_bounds_px(cfg, 0)
    assert n == len(p0) and last == pytest.approx(p0[-1].x_px)
    assert all(b.timestamp_ns > a.timestamp_ns for a, b in zip(frames, frames[1:], strict=False))


def test_schemas_match_the_models() -> None:
    stale = check_schemas(SCHEMA_DIR)
    assert stale == [], f"schemas out of date: {stale}; run 'sffscan schemas'"
