"""End to end: passes and seams, bounded memory, bad input, the command line."""

from __future__ import annotations

import signal
import subprocess
import sys
import tracemalloc
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import pytest
import zarr
from sffscan.pipeline.cli.main import main
from sffscan.pipeline.config import ScanConfig, config_to_toml, pass_pitch_px
from sffscan.pipeline.messages import Frame
from sffscan.pipeline.runtime import StageFailed
from sffscan.pipeline.wiring import run_scan
from sffscan.stages.sim.scanner import make_world, simulate_frames

from tests.scan_helpers import (
    RenderedScan,
    mosaic_height,
    scan,
    score,
    small_config,
    strip_region,
)


def test_three_passes_blend_without_seams(tmp_path: Path) -> None:
    # the sinusoidal world has the same relief statistics everywhere, so that the bands
    # between passes and the rest can be compared (the plate puts its features mid-plate)
    cfg = small_config(source={"world": "sinusoid", "plate_width_mm": 12.0},
                       motion={"passes": 3})
    out = tmp_path / "passes.zarr"
    report = scan(cfg, out)
    assert report.result.dropped == 0
    o, m = cfg.optics, cfg.processing.edge_margin_px
    pitch = pass_pitch_px(cfg)
    x0, y0, x1, y1 = strip_region(cfg)
    y1 = int(2 * pitch) + o.height_px - m
    region = (x0, y0, x1, y1)
    est = mosaic_height(out, region)
    assert np.isfinite(est).mean() == 1.0  # the passes tile the plate without gaps
    rows = np.arange(y0, y1)
    # overlap bands: rows seen by two passes
    overlap = np.zeros(rows.shape, bool)
    for p in (1, 2):
        top = p * pitch + m
        bottom = (p - 1) * pitch + o.height_px - m
        overlap |= (rows >= top) & (rows < bottom)
    band = np.repeat(overlap[:, None], est.shape[1], axis=1)
    in_band = score(cfg, est, region, band)
    away = score(cfg, est, region, ~band)
    print(f"\n3 passes: RMSE in overlap bands {in_band.rmse_um:.1f} µm, away from them "
          f"{away.rmse_um:.1f} µm, ratio {in_band.rmse_um / away.rmse_um:.3f}")
    assert in_band.pixels > 1000 and away.pixels > 1000
    assert in_band.rmse_um <= 1.10 * away.rmse_um


def _traced_peak(cfg: ScanConfig, out: Path) -> int:
    """Peak of numpy/Python allocations during a scan, after the world's one-off set-up."""
    world = make_world(cfg)
    assert world.texture_tile.size  # built before tracing: a fixed cost, not the scan's
    tracemalloc.start()
    try:
        run_scan(cfg, frames=simulate_frames(cfg, world=world), output=out, progress=False)
        return tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()


def test_memory_is_flat_in_scan_length(tmp_path: Path) -> None:
    # small queues: what is in flight depends on thread timing; the test is about growth
    short = small_config(source={"plate_length_mm": 40.0}, motion={"x_end_mm": 15.0},
                         processing={"queue_capacity": 2})
    long = small_config(source={"plate_length_mm": 40.0}, motion={"x_end_mm": 28.0},
                        processing={"queue_capacity": 2})
    p_short = _traced_peak(short, tmp_path / "short.zarr")
    p_long = _traced_peak(long, tmp_path / "long.zarr")
    print(f"\npeak traced memory: 13 mm strip {p_short / 1e6:.1f} MB, 26 mm strip "
          f"{p_long / 1e6:.1f} MB")
    assert p_long <= 1.10 * p_short


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


def test_cli_scan_from_toml_and_errors(tmp_path: Path, capsys: pytest.CaptureFixture) -> None:
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


def test_interrupt_leaves_a_readable_mosaic(tmp_path: Path) -> None:
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


def test_frames_without_stage_positions_follow_the_speed_model(tmp_path: Path) -> None:
    cfg = small_config(motion={"passes": 2}, source={"plate_width_mm": 8.0})
    region = strip_region(cfg)

    def no_positions(frames: Iterator[Frame]) -> Iterator[Frame]:
        for f in frames:
            yield Frame(f.header.model_copy(update={"stage_x_um": None, "stage_y_um": None}),
                        f.image)

    frames = RenderedScan(cfg)  # rendered once, fed to both scans
    run_scan(cfg, frames=iter(frames), output=tmp_path / "with.zarr", progress=False)
    run_scan(cfg, frames=no_positions(iter(frames)), output=tmp_path / "without.zarr",
             progress=False)
    with_pos = score(cfg, mosaic_height(tmp_path / "with.zarr", region), region)
    without = score(cfg, mosaic_height(tmp_path / "without.zarr", region), region)
    assert without.coverage == with_pos.coverage == 1.0
    assert without.rmse_um == pytest.approx(with_pos.rmse_um, rel=0.02)


def test_overwrite_refuses_what_is_not_a_mosaic(tmp_path: Path,
                                                capsys: pytest.CaptureFixture) -> None:
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
