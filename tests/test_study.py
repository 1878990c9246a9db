"""``sffscan study``: a table and a plot of operators x windows x methods on a known truth."""

from __future__ import annotations

import csv
import json
from pathlib import Path

import pytest
from sffscan.pipeline.cli.main import main


def test_study_on_pertuz(pertuz_dir: Path, tmp_path: Path, capsys: pytest.CaptureFixture
                         ) -> None:
    out = tmp_path / "study"
    rc = main(["study", "--imdata", str(pertuz_dir / "imdata.mat"), "--operators", "GLVM,lapm",
               "--windows", "5,9", "--methods", "gauss3,wcentroid", "-o", str(out)])
    assert rc == 0
    with (out / "study.csv").open() as f:
        rows = list(csv.DictReader(f))
    assert len(rows) == 2 * 2 * 2
    assert {r["operator"] for r in rows} == {"glvm", "lapm"}
    table = {(r["operator"], int(r["window"]), r["method"]): float(r["rmse_um"]) for r in rows}
    # the figures of test_default_depth: GLVM 9, all ROI pixels, raw heights
    assert table["glvm", 9, "wcentroid"] == pytest.approx(15.22e3, rel=0.01)
    assert table["glvm", 9, "gauss3"] == pytest.approx(36.74e3, rel=0.01)
    assert json.loads((out / "study.json").read_text())["rows"][0]["operator"] == "glvm"
    assert (out / "study.png").read_bytes()[:4] == b"\x89PNG"
    assert "best: " in capsys.readouterr().out


def test_study_rejects_bad_input(tmp_path: Path, capsys: pytest.CaptureFixture) -> None:
    assert main(["study", "--chapter3", "--operators", "wavs", "-o", str(tmp_path)]) == 2
    assert "wavs" in capsys.readouterr().err
    assert main(["study", "--chapter3", "--windows", "4", "-o", str(tmp_path)]) == 2
    assert main(["study", "--imdata", str(tmp_path / "missing.mat"), "-o", str(tmp_path)]) == 2
    assert "missing.mat" in capsys.readouterr().err
