"""Configuration: defaults follow the thesis, errors name the field, schemas do not drift."""

from __future__ import annotations

import tomllib
import typing
from pathlib import Path

import pytest
from sffscan.pipeline.config import (
    ConfigError,
    ProcessingConfig,
    ScanConfig,
    config_from_dict,
    config_to_toml,
    demo_config,
    load_config,
    max_speed_sliding_mm_s,
    max_speed_thesis_mm_s,
    shift_per_frame_px,
)
from sffscan.pipeline.config_groups import ConfigModel, parts_of
from sffscan.pipeline.formats.schema_gen import check_schemas
from sffscan.pipeline.plan import frame_count, pass_bounds_px, plan_frames, scan_extent_px

SCHEMA_DIR = Path(__file__).resolve().parents[2] / "schemas"


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


# Format version 1 as users' files hold it: the groups of settings (what is measured, how
# it runs, the simulator's own) are a split of the code and the docs, not of the file.
#: keys added since, with defaults that keep a version-1 file's meaning
ADDED_SINCE_V1 = {"processing": {"workers", "bands"}, "optics": {"blur_model"}}
V1_KEYS = {
    "source": {"kind", "address", "idle_timeout_s", "max_bad_messages", "keys_dir", "seed",
               "world", "plate_length_mm", "plate_width_mm"},
    "optics": {"width_px", "height_px", "pixel_um", "n_levels", "z_min_um", "z_step_um", "fps",
               "bit_depth", "psf_s0_px", "psf_c_px_per_um", "sigma_max_px", "noise_sigma",
               "magnification_per_mm", "magnification_ref_um", "field_curvature_um",
               "vignetting"},
    "motion": {"speed_mm_s", "x_start_mm", "x_end_mm", "y_start_mm", "passes", "pass_overlap",
               "serpentine", "wobble_along_px", "wobble_across_px", "wobble_period_mm"},
    "processing": {"focus_operator", "window", "depth_method", "median_size", "registration",
                   "registration_scale", "backend", "device", "calibration", "queue_capacity",
                   "block_columns", "execution"},
    "output": {"path", "chunk_px", "overwrite"},
}

V1_FILE = """\
version = 1
[source]
kind = "sim"
seed = 7
world = "sinusoid"
[optics]
width_px = 640
height_px = 256
n_levels = 20
psf_s0_px = 0.7
noise_sigma = 0.01
magnification_per_mm = 0.002
field_curvature_um = 150.0
vignetting = 0.2
[motion]
x_end_mm = 20.0
speed_mm_s = 5.0
wobble_along_px = 1.5
wobble_period_mm = 3.0
[processing]
focus_operator = "TENV"
depth_method = "spc"
backend = "opencv"
calibration = "cal.json"
queue_capacity = 4
execution = "threads"
[output]
path = "m.zarr"
"""


def test_a_version_1_file_loads_with_every_key_where_it_was(tmp_path: Path) -> None:
    cfg = ScanConfig()
    for table, keys in V1_KEYS.items():
        fields = set(type(getattr(cfg, table)).model_fields)
        assert fields - keys == ADDED_SINCE_V1.get(table, set()), table
        assert keys <= fields, table
    path = tmp_path / "v1.toml"
    path.write_text(V1_FILE, encoding="utf-8")
    cfg = load_config(path)
    assert (cfg.source.seed, cfg.source.world) == (7, "sinusoid")
    assert (cfg.optics.psf_s0_px, cfg.optics.noise_sigma, cfg.optics.vignetting) == (
        0.7, 0.01, 0.2)
    assert (cfg.optics.magnification_per_mm, cfg.optics.field_curvature_um) == (0.002, 150.0)
    assert (cfg.motion.wobble_along_px, cfg.motion.wobble_period_mm) == (1.5, 3.0)
    p = cfg.processing
    assert (p.focus_operator, p.depth_method, p.calibration, p.queue_capacity, p.execution) == (
        "tenv", "spc", "cal.json", 4, "threads")
    assert load_config(_written(tmp_path, config_to_toml(cfg))) == cfg


def _written(folder: Path, text: str) -> Path:
    path = folder / "again.toml"
    path.write_text(text, encoding="utf-8")
    return path


def test_choices_of_operator_and_depth_method_are_the_registries() -> None:
    from sffscan.stages.depth import DEPTH_METHODS
    from sffscan.stages.operators import FOCUS_OPERATORS

    fields = ProcessingConfig.model_fields
    assert typing.get_args(fields["focus_operator"].annotation) == tuple(FOCUS_OPERATORS)
    assert typing.get_args(fields["depth_method"].annotation) == tuple(DEPTH_METHODS)
    for name in FOCUS_OPERATORS:
        assert config_from_dict({"processing": {"focus_operator": name.upper()}}
                                ).processing.focus_operator == name


def _parts(table: object) -> list[type[ConfigModel]]:
    assert isinstance(table, type) and issubclass(table, ConfigModel)
    return parts_of(table)


def test_every_field_of_a_table_is_in_exactly_one_group() -> None:
    composed = 0
    for info in ScanConfig.model_fields.values():
        table = info.annotation
        if not (isinstance(table, type) and issubclass(table, ConfigModel)):
            continue  # version; [camera] and [daq] (pipeline.hardware.config)
        names = [k for part in _parts(table) for k in part.model_fields]
        assert names == list(table.model_fields), table.__name__  # each once, in order
        composed += 1
    assert composed == 5


def test_what_a_resume_may_change_is_how_it_runs() -> None:
    from sffscan.pipeline.run import RUN_ONLY

    tables = {k: v.annotation for k, v in ScanConfig.model_fields.items()}
    for table, name in RUN_ONLY:
        owner = next(p for p in _parts(tables[table]) if name in p.model_fields)
        assert owner.group == "execution", f"{table}.{name}"


def test_a_written_file_marks_the_groups_and_loads_back() -> None:
    text = config_to_toml(demo_config())
    optics = text.split("[optics]\n", 1)[1].split("\n\n", 1)[0].splitlines()
    assert optics[0] == "# -- what is measured --"
    assert optics[optics.index("# -- the simulator's own parameters --") + 1] == "psf_s0_px = 0.6"
    assert "[output]\npath = " in text  # a table of one group: no comment
    assert config_from_dict(tomllib.loads(text)) == demo_config()


def test_auto_band_workers_are_the_cores_less_two_from_one_to_eight(
        monkeypatch: pytest.MonkeyPatch) -> None:
    from sffscan.pipeline import cores
    from sffscan.pipeline.cores import auto_band_workers

    assert [auto_band_workers(c) for c in (1, 2, 3, 4, 8, 10, 16, 64)] == [
        1, 1, 1, 2, 6, 8, 8, 8]
    monkeypatch.setattr(cores, "cores_available", lambda: 16)
    cfg = ScanConfig.model_validate({"processing": {"workers": "auto"}})
    assert cfg.processing.band_workers() == 8
    assert ScanConfig.model_validate({"processing": {"workers": 3}}).processing.band_workers() == 3
