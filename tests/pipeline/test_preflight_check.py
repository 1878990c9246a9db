"""``scan --check`` refuses what the scan itself could not start with, exit 2 before anything
is created (issue 26 item 3): a calibration file that does not exist, a camera source without
a GenTL producer, a DAQ set for the simulator, torch asked for where it is not installed."""

from __future__ import annotations

import sys
from pathlib import Path
from typing import Any

import pytest
from sffscan.pipeline.cli.main import main
from sffscan.pipeline.config import config_to_toml

from tests.scan_helpers import small_config


def _toml(tmp_path: Path, **sections: dict[str, Any]) -> str:
    path = tmp_path / "scan.toml"
    path.write_text(config_to_toml(small_config(**sections)), encoding="utf-8")
    return str(path)


def _check(capsys: pytest.CaptureFixture[str], toml: str, out: Path, *extra: str
           ) -> tuple[int, str]:
    code = main(["scan", "--config", toml, "-o", str(out), "-q", "--no-evaluate", *extra])
    return code, capsys.readouterr().err


def test_a_plain_configuration_is_ready(tmp_path: Path,
                                        capsys: pytest.CaptureFixture[str]) -> None:
    code, err = _check(capsys, _toml(tmp_path), tmp_path / "m.zarr", "--check")
    assert code == 0 and "ready to scan" in err


def test_a_missing_calibration_file_is_refused(tmp_path: Path,
                                               capsys: pytest.CaptureFixture[str]) -> None:
    missing = tmp_path / "nowhere" / "cal.json"
    toml = _toml(tmp_path, processing={"calibration": str(missing)})
    code, err = _check(capsys, toml, tmp_path / "m.zarr", "--check")
    assert code == 2 and "ready to scan" not in err
    assert "processing.calibration" in err and "no such file" in err and str(missing) in err
    bad = tmp_path / "bad.json"
    bad.write_text("{}", encoding="utf-8")
    code, err = _check(capsys, _toml(tmp_path, processing={"calibration": str(bad)}),
                       tmp_path / "m.zarr", "--check")
    assert code == 2 and "processing.calibration" in err and str(bad) in err


def test_a_camera_without_a_gentl_producer_exits_2_before_any_mosaic(
        tmp_path: Path, capsys: pytest.CaptureFixture[str],
        monkeypatch: pytest.MonkeyPatch) -> None:
    for name in ("SFFSCAN_CTI", "GENICAM_GENTL64_PATH"):
        monkeypatch.delenv(name, raising=False)
    toml = _toml(tmp_path, source={"kind": "camera"})
    out = tmp_path / "m.zarr"
    code, err = _check(capsys, toml, out, "--check")
    assert code == 2 and "no GenTL producer" in err and "ready to scan" not in err
    code, err = _check(capsys, toml, out)  # the scan itself: exit 1 and a failed mosaic before
    assert code == 2 and "no GenTL producer" in err
    assert not out.exists()
    toml = _toml(tmp_path, source={"kind": "camera"}, camera={"cti": str(tmp_path / "x.cti")})
    code, err = _check(capsys, toml, out, "--check")
    assert code == 2 and "x.cti not found" in err


def test_a_daq_for_the_simulator_is_refused(tmp_path: Path,
                                            capsys: pytest.CaptureFixture[str]) -> None:
    toml = _toml(tmp_path, daq={"kind": "nidaqmx"})
    out = tmp_path / "m.zarr"
    for extra in (["--check"], []):  # the scan ran, the DAQ ignored without a word
        code, err = _check(capsys, toml, out, *extra)
        assert code == 2 and "daq.kind = 'nidaqmx'" in err and "simulated" in err
        assert not out.exists()


@pytest.mark.parametrize("processing", [{"backend": "torch"}, {"focus_operator": "lapm"}])
def test_torch_asked_for_without_torch_names_the_extra(
        processing: dict[str, str], tmp_path: Path, capsys: pytest.CaptureFixture[str],
        monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setitem(sys.modules, "torch", None)  # as if not installed: import fails
    toml = _toml(tmp_path, processing=processing)
    out = tmp_path / "m.zarr"
    for extra in (["--check"], []):
        code, err = _check(capsys, toml, out, *extra)
        assert code == 2, err
        assert "pip install 'sffscan[torch]'" in err and "Traceback" not in err
        assert f"processing.{next(iter(processing))}" in err
        assert not out.exists()


def test_the_operators_without_torch_are_the_focus_measures_opencv_ones() -> None:
    from sffscan.pipeline.preflight import OPENCV_OPERATORS
    from sffscan.stages.operators import FOCUS_OPERATORS

    assert set(OPENCV_OPERATORS) == {name for name, op in FOCUS_OPERATORS.items() if op.opencv}
