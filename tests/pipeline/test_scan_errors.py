"""End to end: bad input, the command line and its errors, Ctrl-C, --overwrite (split from
tests/pipeline/test_scan_pipeline.py so that pytest-xdist's --dist loadfile can run the two on
different workers)."""

from __future__ import annotations

import signal
import subprocess
import sys
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import pytest
import zarr
from sffscan.pipeline.cli.main import main
from sffscan.pipeline.config import config_to_toml
from sffscan.pipeline.runtime import StageFailed
from sffscan.pipeline.wiring import run_scan
from sffscan.stages.messages import Frame

from tests import scan_helpers
from tests.scan_helpers import RenderedScan, small_config


def _with_bad_frame(frames: Iterator[Frame], at: int, kind: str) -> Iterator[Frame]:
    for f in frames:
        h = f.header
        if h.frame_id == at:
            if kind == "shape":
                f = Frame(h, f.image[:-1])
            elif kind == "dtype":
                f = Frame(h, f.image.astype(np.float32))
            elif kind == "nan":
                img = f.image.astype(np.float32)
                img[3, 4] = np.nan
                f = Frame(h, img)
            elif kind == "overflow":
                img = f.image.copy()
                img[5, 5] = 4000  # above the 10-bit full scale
                f = Frame(h, img)
            elif kind == "level":
                f = Frame(h.model_copy(update={"focus_index": (h.focus_index + 1) % 50}),
                          f.image)
            elif kind == "pass":
                f = Frame(h.model_copy(update={"pass_index": 5}), f.image)
            elif kind == "position":
                f = Frame(h.model_copy(update={"stage_y_um": 1e12}), f.image)
            elif kind == "duplicate":
                yield f
        yield f


@pytest.fixture(scope="module")
def small_scan() -> RenderedScan:
    """The small scan, its frames rendered once for the eight bad-frame variants (each reads
    the same frames up to the bad one; rendering is most of a small scan's time)."""
    return RenderedScan(small_config())


@pytest.mark.parametrize(("kind", "message"), [
    ("shape", "shape"), ("dtype", "dtype"), ("nan", "NaN"), ("overflow", "full scale"),
    ("level", "out of step"), ("pass", "pass_index 5"), ("position", "stage_y_um"),
    ("duplicate", "duplicated or out of order")])
def test_bad_frame_stops_with_its_id_and_keeps_what_was_written(
        tmp_path: Path, kind: str, message: str, small_scan: RenderedScan) -> None:
    cfg = small_scan.cfg
    out = tmp_path / "bad.zarr"
    frames = _with_bad_frame(iter(small_scan), 200, kind)
    with pytest.raises(StageFailed, match=f"frame_id 200.*{message}") as info:
        run_scan(cfg, frames=frames, output=out, progress=False)
    assert info.value.stage == "source"
    g = zarr.open_group(str(out), mode="r")
    assert g.attrs["status"] == "failed"
    assert np.isfinite(np.asarray(g["height"])).sum() > 1000  # the completed part is kept


@pytest.fixture
def session_scanner(monkeypatch: pytest.MonkeyPatch) -> None:
    """The command line's simulated scans read from the session's rendered scans."""
    from sffscan.pipeline import sim_source

    monkeypatch.setattr(sim_source, "simulate_frames", scan_helpers.session_scanner)


def test_cli_scan_from_toml_and_errors(tmp_path: Path, capsys: pytest.CaptureFixture,
                                       session_scanner: None) -> None:
    cfg = small_config(motion={"x_end_mm": 8.0})
    toml = tmp_path / "scan.toml"
    toml.write_text(config_to_toml(cfg))
    out = tmp_path / "cli.zarr"
    assert main(["scan", "--config", str(toml), "-o", str(out), "-q"]) == 0
    text = capsys.readouterr().out
    assert "dropped     0 frames" in text and "RMSE" in text and "PSNR" in text
    assert zarr.open_group(str(out), mode="r").attrs["status"] == "complete"
    # an existing mosaic is not overwritten
    assert main(["scan", "--config", str(toml), "-o", str(out), "-q"]) == 2
    assert "exists" in capsys.readouterr().err
    # impossible speed: exit 2, the field named
    assert main(["scan", "--config", str(toml), "-o", str(tmp_path / "x.zarr"), "--speed",
                 "99"]) == 2
    assert "motion.speed_mm_s" in capsys.readouterr().err
    # an output path under a regular file: exit 2, the path named
    blocker = tmp_path / "file.txt"
    blocker.write_text("x")
    assert main(["scan", "--config", str(toml), "-o", str(blocker / "m.zarr"), "-q"]) == 2
    assert "file.txt" in capsys.readouterr().err


def test_console_script_help() -> None:
    res = subprocess.run([sys.executable, "-m", "sffscan", "demo", "--help"],
                         capture_output=True, text=True, check=False)
    assert res.returncode == 0 and "15 mm/s" in res.stdout


def test_interrupt_leaves_a_readable_mosaic(tmp_path: Path, sigint_handled: None) -> None:
    """Ctrl-C during a scan: exit 130, the mosaic readable with status 'failed'."""
    cfg = small_config()
    toml = tmp_path / "scan.toml"
    toml.write_text(config_to_toml(cfg))
    out = tmp_path / "int.zarr"
    proc = subprocess.Popen([sys.executable, "-m", "sffscan", "scan", "--config", str(toml),
                             "-o", str(out)], stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                            text=True)
    # wait for the first progress line, then interrupt
    assert proc.stderr is not None
    for line in proc.stderr:
        if line.startswith("frames "):
            break
    proc.send_signal(signal.SIGINT)
    _, err = proc.communicate(timeout=60)
    assert proc.returncode == 130, err
    assert "interrupted" in err
    g = zarr.open_group(str(out), mode="r")
    assert g.attrs["status"] == "failed"
    np.asarray(g["height"])  # readable


def test_overwrite_refuses_what_is_not_a_mosaic(tmp_path: Path, capsys: pytest.CaptureFixture,
                                                session_scanner: None) -> None:
    cfg = small_config(motion={"x_end_mm": 6.0})
    toml = tmp_path / "scan.toml"
    toml.write_text(config_to_toml(cfg))
    precious = tmp_path / "thesis"
    precious.mkdir()
    (precious / "chapter1.txt").write_text("years of work")
    assert main(["scan", "--config", str(toml), "-o", str(precious), "--overwrite", "-q"]) == 2
    assert "not an sffscan mosaic" in capsys.readouterr().err
    assert (precious / "chapter1.txt").read_text() == "years of work"
    out = tmp_path / "m.zarr"
    assert main(["scan", "--config", str(toml), "-o", str(out), "-q"]) == 0
    assert main(["scan", "--config", str(toml), "-o", str(out), "--overwrite", "-q"]) == 0
