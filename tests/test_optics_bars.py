"""Issue 14's bars: the realistic optics (2 % breathing over the range, 150 µm field
curvature at the corner, 20 % vignetting) measured with and without a calibration made by
the ``sffscan calibrate`` commands from simulated target images, against ideal optics, for
the continuous scan, ``stack`` and ``stopgo``. Each test prints its ratios (``-s``)."""

from __future__ import annotations

import contextlib
import io
import re
from pathlib import Path

import cv2
import numpy as np
import pytest
import zarr
from sffscan.pipeline.cli.main import main
from sffscan.pipeline.config import REALISTIC_OPTICS, ScanConfig
from sffscan.pipeline.metrology.compare import compare_height_maps
from sffscan.pipeline.wiring import run_scan
from sffscan.stages.recorder import recorder_sink
from sffscan.stages.sim.camera import Optics, focus_heights, render_stack
from sffscan.stages.sim.optics_targets import calibration_commands, write_optics_targets
from sffscan.stages.sim.scanner import make_optics, simulate_frames
from sffscan.stages.sim.world import characterisation_plate

from sffscan.api import replay
from tests.scan_helpers import mosaic_height, scan, score, small_config, strip_region

ZS = focus_heights(n_levels=50, z_step_um=200.0)
MID = 0.5 * float(ZS[0] + ZS[-1])


def calibrate(folder: Path, optics: Optics) -> Path:
    """Targets through ``optics`` written as images, then the commands, in order."""
    targets = write_optics_targets(folder / "targets", optics=optics, focus_heights_um=ZS)
    out = folder / "calibration.json"
    for cmd in calibration_commands(targets, out):
        assert main(cmd) == 0, cmd
    return out


def scan_rmse(cfg: ScanConfig, out: Path) -> float:
    report = scan(cfg, out)
    assert report.result.dropped == 0
    region = strip_region(cfg)
    est = mosaic_height(out, region)
    return score(cfg, est, region, np.ones(est.shape, bool)).rmse_um


def test_continuous_scan(tmp_path: Path) -> None:
    real = small_config(optics=dict(REALISTIC_OPTICS))
    cal = calibrate(tmp_path, make_optics(real))
    ideal = scan_rmse(small_config(), tmp_path / "ideal.zarr")
    raw = scan_rmse(real, tmp_path / "real.zarr")
    cal_cfg = small_config(optics=dict(REALISTIC_OPTICS), processing={"calibration": str(cal)})
    corrected = scan_rmse(cal_cfg, tmp_path / "cal.zarr")
    print(f"\ncontinuous scan RMSE: ideal optics {ideal:.1f} µm; realistic optics without "
          f"calibration {raw:.1f} µm ({raw / ideal:.3f}x), with {corrected:.1f} µm "
          f"({corrected / ideal:.3f}x)")
    assert corrected <= 1.10 * ideal
    assert raw >= 1.3 * ideal  # the simulated effects are strong enough to matter
    attrs = zarr.open_group(str(tmp_path / "cal.zarr"), mode="r").attrs["processing"]
    assert set(attrs["calibration_applied"]) == {"z_response", "magnification_per_level",
                                                  "field_curvature", "vignetting"}
    # the raw stream recorded without calibration, replayed with it: the same heights
    rec = tmp_path / "rec.zarr"
    run_scan(real, frames=simulate_frames(real), output=tmp_path / "r2.zarr", progress=False,
             sinks=[recorder_sink(real, rec)])
    replay(rec, output=tmp_path / "replay.zarr", processing={"calibration": str(cal)})
    region = strip_region(real)
    a = mosaic_height(tmp_path / "replay.zarr", region)
    b = mosaic_height(tmp_path / "cal.zarr", region)
    np.testing.assert_array_equal(a, b)


def _stopgo_rmse(args: list[str]) -> float:
    buf = io.StringIO()
    with contextlib.redirect_stdout(buf):
        assert main(["stopgo", "-q", *args]) == 0
    m = re.search(r"RMSE ([0-9.]+) µm", buf.getvalue())
    assert m is not None, buf.getvalue()
    return float(m.group(1))


def test_stopgo(tmp_path: Path) -> None:
    # fields of the thesis' field of view at half resolution (640 x 512 px of 17 µm): on
    # the default 320 x 256 fields the breathing barely shows (1.11x without calibration)
    field = ["--field", "640", "512"]
    optics = Optics(width=640, height=512, pixel_um=17.0, magnification_ref_um=MID,
                    **REALISTIC_OPTICS)
    cal = calibrate(tmp_path, optics)
    ideal = _stopgo_rmse(["-o", str(tmp_path / "i.zarr"), *field])
    raw = _stopgo_rmse(["-o", str(tmp_path / "r.zarr"), "--realistic", *field])
    corrected = _stopgo_rmse(["-o", str(tmp_path / "c.zarr"), "--realistic",
                              "--calibration", str(cal), *field])
    print(f"\nstop-and-go RMSE: ideal optics {ideal:.1f} µm; realistic optics without "
          f"calibration {raw:.1f} µm ({raw / ideal:.3f}x), with {corrected:.1f} µm "
          f"({corrected / ideal:.3f}x)")
    assert corrected <= 1.10 * ideal
    assert raw >= 1.3 * ideal  # the simulated optics show their effect


def test_stack(tmp_path: Path) -> None:
    w, h = 640, 480
    real = Optics(width=w, height=h, pixel_um=17.0, magnification_ref_um=MID,
                  **REALISTIC_OPTICS)
    ideal = Optics(width=w, height=h, pixel_um=17.0)
    cal = calibrate(tmp_path, real)
    world = characterisation_plate(seed=0, pixel_um=17.0, length_mm=24.0, width_mm=8.0,
                                   z_range_um=(0.0, float(ZS[-1])))
    truth = world.height_um(300.0, 0.0, w, h)
    rmse = {}
    for name, optics, extra in (("ideal", ideal, []), ("real", real, []),
                                ("cal", real, ["--calibration", str(cal)])):
        folder = tmp_path / f"stack_{name}"
        if not folder.exists():
            folder.mkdir()
            st = render_stack(world, x0=300.0, y0=0.0, focus_heights_um=ZS, optics=optics,
                              rng=np.random.default_rng(5))
            for k, img in enumerate(st):
                cv2.imwrite(str(folder / f"z{k}.png"), img)
        npy = tmp_path / f"{name}.npy"
        files = [str(folder / f"z{k}.png") for k in range(ZS.size)]
        assert main(["stack", *files, "--focus-start", "0", "--focus-step", "200",
                     "--pixel-um", "17", "--bit-depth", "10", "-o", str(tmp_path / f"{name}.zarr"),
                     "--save-npy", str(npy), *extra]) == 0
        est = np.load(npy)
        rmse[name] = compare_height_maps(est[12:-12, 12:-12], truth[12:-12, 12:-12],
                                         max_depth_um=float(ZS[-1])).rmse_um
    ratio_raw, ratio_cal = rmse["real"] / rmse["ideal"], rmse["cal"] / rmse["ideal"]
    print(f"\nstack RMSE: ideal optics {rmse['ideal']:.1f} µm; realistic optics without "
          f"calibration {rmse['real']:.1f} µm ({ratio_raw:.3f}x), with {rmse['cal']:.1f} µm "
          f"({ratio_cal:.3f}x)")
    assert ratio_cal <= 1.10
    assert ratio_raw > 1.0


def test_scan_refuses_a_missing_calibration(tmp_path: Path) -> None:
    cfg = small_config(processing={"calibration": str(tmp_path / "nothere.json")})
    with pytest.raises(ValueError, match="nothere.json"):
        scan(cfg, tmp_path / "x.zarr")
