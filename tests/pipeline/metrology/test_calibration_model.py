"""The calibration file (pipeline/metrology/calibration_model.py): saved, loaded, refused
when bad, applied; and the file 'sffscan calibrate sim' writes."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from sffscan.pipeline.cli.main import main
from sffscan.pipeline.formats.schema_gen import SCHEMAS, check_schemas
from sffscan.pipeline.metrology.calibration_fit import fit_z_response
from sffscan.pipeline.metrology.calibration_model import (
    Calibration,
    CalibrationError,
    FieldCurvatureFit,
    ZResponse,
    apply_calibration,
    calibrated_focus_heights,
    load_calibration,
    save_calibration,
)

SCHEMA_DIR = Path(__file__).resolve().parents[3] / "schemas"


def _calibration() -> Calibration:
    z = fit_z_response(np.array([5.0, 20.0, 35.0]), np.array([1050.0, 3900.0, 6750.0]))
    fc = FieldCurvatureFit(frame_width_px=64, frame_height_px=48, centre_px=(31.5, 23.5),
                           coefficients_um=(5.0, 0.0, 0.0, 0.01, 0.0, 0.02),
                           rms_residual_um=1.0)
    return Calibration(z_response=z, field_curvature=fc, noise_um=2.5)


def test_file_roundtrip_and_apply(tmp_path: Path) -> None:
    cal = _calibration()
    path = save_calibration(cal, tmp_path / "cal.json")
    back = load_calibration(path)
    assert back == cal
    assert json.loads(path.read_text())["format_version"] == 1
    np.testing.assert_allclose(calibrated_focus_heights(back, 3), [100.0, 290.0, 480.0])
    levels = np.full((48, 64), 10.0)
    levels[0, 0] = np.nan
    out = apply_calibration(levels, calibration=back, curvature="off")
    assert out.dtype == np.float32 and np.isnan(out[0, 0])
    assert float(out[5, 5]) == pytest.approx(100.0 + 190.0 * 10.0)
    # heights from the nominal table (200 µm per level from 0) give the same result
    out_um = apply_calibration(levels * 200.0, calibration=back, units="um",
                               nominal_heights_um=np.arange(50) * 200.0, curvature="off")
    np.testing.assert_allclose(out_um, out, rtol=1e-6)
    # field curvature: 0 at the centre, 0.01 u² + 0.02 v² subtracted elsewhere
    curved = apply_calibration(levels, calibration=back)
    u, v = 0 - 31.5, 47 - 23.5
    assert float(curved[47, 0]) == pytest.approx(2000.0 - (0.01 * u * u + 0.02 * v * v),
                                                 rel=1e-6)
    with pytest.raises(CalibrationError, match="nominal_heights_um"):
        apply_calibration(levels, calibration=back, units="um")
    with pytest.raises(CalibrationError, match="z_response"):
        apply_calibration(levels, calibration=Calibration())


def test_bad_files_name_the_file_and_field(tmp_path: Path) -> None:
    bad = tmp_path / "bad.json"
    data = json.loads(_calibration().model_dump_json())
    data["z_response"]["pearson_r"] = 3.0
    bad.write_text(json.dumps(data))
    with pytest.raises(CalibrationError, match=r"bad\.json: z_response\.pearson_r"):
        load_calibration(bad)
    data["format_version"] = 2
    bad.write_text(json.dumps(data))
    with pytest.raises(CalibrationError, match="format_version"):
        load_calibration(bad)
    with pytest.raises(CalibrationError, match="missing.json"):
        load_calibration(tmp_path / "missing.json")
    assert main(["calibrate", "show", str(bad)]) == 2
    image = tmp_path / "im_01.png"  # a binary file given for a calibration (or as -o)
    image.write_bytes(b"\x89PNG\r\n\x1a\n")
    with pytest.raises(CalibrationError, match=r"im_01\.png: not a calibration file"):
        load_calibration(image)


def test_schema_is_registered_and_current() -> None:
    assert SCHEMAS["calibration.v1.json"] is Calibration
    assert "calibration.v1.json" not in check_schemas(SCHEMA_DIR)
    assert ZResponse.model_fields["um_per_level"].description


def test_cli_calibrate_sim_writes_a_loadable_file(tmp_path: Path,
                                                  capsys: pytest.CaptureFixture[str]) -> None:
    out = tmp_path / "sim.json"
    assert main(["calibrate", "sim", "-o", str(out)]) == 0
    cal = load_calibration(out)
    assert cal.z_response is not None and cal.lateral is not None
    assert cal.field_curvature is not None and cal.noise_um is not None
    assert cal.z_response.um_per_level == pytest.approx(190.0, rel=0.005)
    assert cal.lateral.um_per_px_x == pytest.approx(8.5, rel=1e-3)
    assert main(["calibrate", "show", str(out)]) == 0
    assert "a_z 190." in capsys.readouterr().out
