"""``sffscan calibrate targets`` says what it does while it renders (issue 26 item 4: over
5 minutes without a word at the real optics' size)."""

from __future__ import annotations

import re
from pathlib import Path

import pytest
from sffscan.pipeline.cli.main import main


def test_targets_show_their_progress(tmp_path: Path,
                                     capsys: pytest.CaptureFixture[str]) -> None:
    from sffscan.pipeline.config import REALISTIC_OPTICS, config_to_toml, demo_config

    cfg = demo_config(optics={**REALISTIC_OPTICS, "width_px": 128, "height_px": 64,
                              "n_levels": 6, "z_step_um": 800.0},
                      motion={"speed_mm_s": 1.0})
    toml = tmp_path / "small.toml"
    toml.write_text(config_to_toml(cfg), encoding="utf-8")
    assert main(["calibrate", "targets", str(tmp_path / "t"), "--config", str(toml),
                 "-o", str(tmp_path / "c.json")]) == 0
    err = capsys.readouterr().err
    assert "rendering the calibration targets" in err and "6 focus levels" in err
    # 5 gauge stacks and 2 flat stacks of 6 images, 5 board images: 47; the first count
    # comes after the first gauge stack
    assert re.search(r"images 6/47 \(12\.8 %\)", err), err
    assert re.search(r"rendered in \d+\.\d s", err), err
    # -q: no progress display, no status lines; the commands are still printed
    out = tmp_path / "q"
    assert main(["calibrate", "targets", str(out), "--config", str(toml), "-q"]) == 0
    captured = capsys.readouterr()
    assert "images" not in captured.err and "rendered in" not in captured.err
    assert "sffscan calibrate z" in captured.out
    # a folder that is not empty (the user's own images) is refused, untouched
    mine = tmp_path / "mine"
    (mine / "gauge_1470").mkdir(parents=True)
    (mine / "gauge_1470" / "img_0.png").write_bytes(b"the user's image")
    assert main(["calibrate", "targets", str(mine), "--config", str(toml), "-q"]) == 2
    assert "exists and is not an empty folder" in capsys.readouterr().err
    assert (mine / "gauge_1470" / "img_0.png").read_bytes() == b"the user's image"
    assert sorted(p.name for p in mine.rglob("*")) == ["gauge_1470", "img_0.png"]
