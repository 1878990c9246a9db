"""The pipeline applies a calibration file's z response to the mosaic heights."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np
import pytest
import zarr
from sffscan.pipeline.cli.main import main
from sffscan.pipeline.config import ConfigError, config_to_toml
from sffscan.pipeline.metrology.calibration_model import Calibration, ZResponse, save_calibration
from sffscan.pipeline.wiring import run_scan

from tests.scan_helpers import RenderedScan, small_config


def _array(group: zarr.Group, name: str) -> zarr.Array:
    node = group[name]
    assert isinstance(node, zarr.Array), name
    return node


def _calibration(path: Path) -> Path:
    z = ZResponse(um_per_level=190.0, intercept_um=100.0, pearson_r=1.0,
                  heights_um=[100.0, 9410.0], peak_levels=[0.0, 49.0], residuals_um=[0.0, 0.0])
    return save_calibration(Calibration(description="test", z_response=z), path)


def test_scan_heights_follow_the_calibrated_z_response(tmp_path: Path) -> None:
    cal = _calibration(tmp_path / "cal.json")
    # the calibration is processing only: both scans read the same frames, rendered once
    frames = RenderedScan(small_config())
    nominal = run_scan(frames.cfg, frames=iter(frames), output=tmp_path / "nominal.zarr",
                       progress=False)
    cfg = small_config(processing={"calibration": str(cal)})
    assert cfg.model_copy(update={"processing": frames.cfg.processing}) == frames.cfg
    calibrated = run_scan(cfg, frames=iter(frames), output=tmp_path / "calibrated.zarr",
                          progress=False)
    h_nom = np.asarray(_array(zarr.open_group(str(nominal.output), mode="r"), "height")[:])
    g = zarr.open_group(str(calibrated.output), mode="r")
    h_cal = np.asarray(_array(g, "height")[:])
    assert np.array_equal(np.isnan(h_nom), np.isnan(h_cal))
    valid = np.isfinite(h_nom)
    assert valid.sum() > 10_000
    # nominal: 200 µm per level from 0; calibrated: 190 µm per level from 100 µm
    np.testing.assert_allclose(h_cal[valid], 100.0 + 0.95 * h_nom[valid], atol=0.05)
    attrs: dict[str, Any] = dict(g.attrs)
    assert attrs["processing"]["calibration"] == str(cal)
    assert attrs["focus_heights_um"][:2] == [100.0, 290.0]


def test_missing_or_bad_calibration_file_is_refused_naming_it(tmp_path: Path) -> None:
    from sffscan.pipeline.measuring import focus_heights_um

    with pytest.raises(ConfigError, match="nope.json"):
        focus_heights_um(small_config(processing={"calibration": str(tmp_path / "nope.json")}))
    bad = tmp_path / "bad.json"
    bad.write_text('{"format": "sffscan-calibration", "format_version": 1, "noise_um": -1}')
    toml = tmp_path / "scan.toml"
    toml.write_text(config_to_toml(small_config()), encoding="utf-8")
    code = main(["scan", "--config", str(toml), "-o", str(tmp_path / "m.zarr"), "-q",
                 "--calibration", str(bad)])
    assert code == 2
    assert not (tmp_path / "m.zarr").exists()
