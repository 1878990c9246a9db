"""Tests of pipeline.stopgo: grid planning, placement and blending, a simulated grid."""

from __future__ import annotations

import re
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import zarr
from sffscan.pipeline.cli.main import main
from sffscan.pipeline.mosaic.layout import mosaic_array
from sffscan.pipeline.mosaic.writer import MosaicWriter
from sffscan.pipeline.stopgo import (
    SimFieldCamera,
    feather_weights,
    plan_grid,
    run_stop_and_go,
    stitch_field,
)
from sffscan.stages.fields.stationary import FieldResult
from sffscan.stages.sim.camera import Optics, focus_heights
from sffscan.stages.sim.world import sinusoid_world

PX = 17.0


def test_plan_grid_covers_with_overlap() -> None:
    grid = plan_grid(x_um=(0.0, 100 * PX), y_um=(0.0, 50 * PX), field_px=(40, 30),
                     pixel_um=PX, overlap_px=10)
    xs = sorted({round(p.stage_x_um / PX) for p in grid})
    ys = sorted({round(p.stage_y_um / PX) for p in grid})
    assert xs[0] == 0 and xs[-1] + 40 == 100 and ys[0] == 0 and ys[-1] + 30 == 50
    assert all(b - a <= 40 - 10 for a, b in zip(xs, xs[1:], strict=False))  # overlap >= 10
    assert all(b - a <= 30 - 10 for a, b in zip(ys, ys[1:], strict=False))
    assert len(grid) == len(xs) * len(ys)
    row1 = [p.ix for p in grid if p.iy == 1]
    assert row1 == sorted(row1, reverse=True)  # serpentine
    with pytest.raises(ValueError, match="overlap_px"):
        plan_grid(x_um=(0, 1), y_um=(0, 1), field_px=(40, 30), pixel_um=PX, overlap_px=30)


def test_feather_weights() -> None:
    f = feather_weights((6, 10), overlap_px=4)
    np.testing.assert_allclose(f[3, :5], [0.125 * 0.625, 0.375 * 0.625, 0.625 * 0.625,
                                          0.875 * 0.625, 0.625], rtol=1e-6)
    assert (feather_weights((6, 10), overlap_px=0) == 1).all()


def _field(h: np.ndarray) -> FieldResult:
    conf = np.full(h.shape, 0.5, np.float32)
    return FieldResult(height_um=h.astype(np.float32), raw_height_um=h.astype(np.float32),
                       levels=h.astype(np.float32), texture=np.full(h.shape, 0.5, np.float32),
                       confidence=conf)


def test_stitch_places_fields_by_position(tmp_path: Path) -> None:
    """Fields cut from one ramp (height = world x + 1000 y) must rebuild it exactly."""
    w = MosaicWriter(tmp_path / "m.zarr", origin_px=(100, 50), shape=(50, 70), pixel_um=PX)
    feather = feather_weights((30, 40), overlap_px=10)
    yy, xx = np.mgrid[0:30, 0:40]
    for x0, y0 in ((100, 50), (130, 50), (100, 70), (130, 70)):
        stitch_field(w, _field((x0 + xx) + 1000.0 * (y0 + yy)), x0_px=x0, y0_px=y0,
                     feather=feather)
    h = np.asarray(mosaic_array(w.group, "height")[...])
    gy, gx = np.mgrid[50:100, 100:170]
    np.testing.assert_allclose(h, gx + 1000.0 * gy, rtol=1e-6)


def test_stitch_cross_fades_in_the_overlap(tmp_path: Path) -> None:
    w = MosaicWriter(tmp_path / "m.zarr", origin_px=(0, 0), shape=(20, 70), pixel_um=PX)
    feather = feather_weights((20, 40), overlap_px=10)
    stitch_field(w, _field(np.full((20, 40), 100.0)), x0_px=0, y0_px=0, feather=feather)
    stitch_field(w, _field(np.full((20, 40), 200.0)), x0_px=30, y0_px=0, feather=feather)
    row = np.asarray(mosaic_array(w.group, "height")[10])
    np.testing.assert_allclose(row[:30], 100.0, rtol=1e-6)
    np.testing.assert_allclose(row[40:], 200.0, rtol=1e-6)
    band = row[30:40]
    assert (np.diff(band) > 0).all() and 100 < band[0] and band[-1] < 200  # no step: a ramp
    np.testing.assert_allclose(band[::-1] - 150.0, 150.0 - band, rtol=1e-5)  # symmetric


def _sim_camera(seed: int = 1) -> SimFieldCamera:
    world = sinusoid_world(pixel_um=PX, amplitude_um=3000.0, period_px=300.0, offset_um=4800.0)
    return SimFieldCamera(world, Optics(width=160, height=128, pixel_um=PX),
                          focus_heights(n_levels=25, z_step_um=400.0), seed=seed)


def test_sim_grid_is_seamless(tmp_path: Path) -> None:
    cam = _sim_camera()
    grid = plan_grid(x_um=(0.0, 4500.0), y_um=(0.0, 3500.0), field_px=(160, 128), pixel_um=PX,
                     overlap_px=32)
    rep = run_stop_and_go(cam, grid, tmp_path / "m.zarr", overlap_px=32)
    g: Any = zarr.open_group(str(tmp_path / "m.zarr"), mode="r")
    assert g.attrs["status"] == "complete" and g.attrs["processing"]["mode"] == "stop-and-go"
    assert rep.fields == 4
    h = np.asarray(g["height"][...])
    ox, oy = g.attrs["origin_px"]
    truth = cam.world.height_um(float(ox), float(oy), h.shape[1], h.shape[0])
    count = np.zeros(h.shape, int)
    for p in grid:
        x, y = round(p.stage_x_um / PX) - ox, round(p.stage_y_um / PX) - oy
        count[y:y + 128, x:x + 160] += 1
    err = h - truth
    assert np.isfinite(h).all()  # every pixel of the grid covered
    overlap = float(np.sqrt(np.mean(err[count > 1] ** 2)))
    single = float(np.sqrt(np.mean(err[count == 1] ** 2)))
    total = float(np.sqrt(np.mean(err**2)))
    print(f"\nstop-and-go 2x2 grid (N=25, 400 µm): RMSE {total:.1f} µm; overlap bands "
          f"{overlap:.1f} µm, single-field pixels {single:.1f} µm")
    assert total < 100.0  # a quarter of a focus step
    assert overlap <= 1.10 * single  # blending leaves no seam


def test_failed_field_keeps_earlier_fields(tmp_path: Path) -> None:
    cam = _sim_camera()
    grid = plan_grid(x_um=(0.0, 4500.0), y_um=(0.0, 2000.0), field_px=(160, 128), pixel_um=PX,
                     overlap_px=32)
    calls = []

    class Broken(SimFieldCamera):
        def acquire(self, *, stage_x_um: float, stage_y_um: float) -> np.ndarray:
            calls.append(stage_x_um)
            if len(calls) == 2:
                raise RuntimeError("stage fault")
            return super().acquire(stage_x_um=stage_x_um, stage_y_um=stage_y_um)

    broken = Broken(cam.world, cam.optics, cam.focus_heights)
    with pytest.raises(RuntimeError, match="stage fault"):
        run_stop_and_go(broken, grid, tmp_path / "m.zarr", overlap_px=32)
    g: Any = zarr.open_group(str(tmp_path / "m.zarr"), mode="r")
    assert g.attrs["status"] == "failed" and g.attrs["blocks"] == 1
    assert np.isfinite(np.asarray(g["height"][:, :100])).all()  # the first field is kept


def test_stopgo_command(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    out = tmp_path / "sg.zarr"
    assert main(["stopgo", "-o", str(out), "--area-mm", "3", "7", "0", "3", "--field", "160",
                 "128", "--levels", "25", "--z-step-um", "400", "-q"]) == 0
    text = capsys.readouterr().out
    assert "RMSE" in text and "coverage 100.0 %" in text
    # and the height uncertainty's share within 2 sigma of the truth, as the mosaic holds it
    got = re.search(r"uncertainty (\d+\.\d) % of (\d+) px within 2 sigma", text)
    assert got is not None, text
    g: Any = zarr.open_group(str(out), mode="r")
    u, h = np.asarray(g["uncertainty"]), np.asarray(g["height"])
    assert int(got.group(2)) == int((np.isfinite(u) & np.isfinite(h)).sum()) > 0
    assert 50.0 < float(got.group(1)) <= 100.0
    assert "not calibrated" not in text  # GLVM 9, the measure the constants were fitted with
    assert main(["stopgo", "-o", str(out), "--field", "10", "10", "-q"]) == 2  # overlap > field
    # refused before anything is written: an area typed in metres (it planned ~1e8 fields
    # and did not end), a stack of two levels (refused at the first field, after the mosaic)
    for bad in (["--area-mm", "3", "1e9", "0", "3"], ["--levels", "2"],
                ["--plate-width-mm", "1e30"], ["--pixel-um", "nan"]):  # 1e30: no end either
        other = tmp_path / "other.zarr"
        assert main(["stopgo", "-o", str(other), "--field", "160", "128", "-q", *bad]) == 2
        assert not other.exists()
    # one field seeing a flat (no correlation defined): said, not a TypeError (exit 1)
    capsys.readouterr()
    assert main(["stopgo", "-o", str(tmp_path / "flat.zarr"), "--pixel-um", "9000", "-q"]) == 0
    assert "CORR n/a (a map without variation)" in capsys.readouterr().out


def test_stopgo_warns_that_another_focus_measure_s_uncertainty_is_not_calibrated(
        tmp_path: Path, caplog: pytest.LogCaptureFixture) -> None:
    with caplog.at_level("WARNING"):
        assert main(["stopgo", "-o", str(tmp_path / "w.zarr"), "--area-mm", "3", "5", "0", "2",
                     "--field", "96", "80", "--levels", "12", "--z-step-um", "800",
                     "--window", "5", "-q"]) == 0
    assert "with GLVM k=5 it is not calibrated" in caplog.text
