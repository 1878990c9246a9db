"""Issue 14's bars for the stationary tools: ``stopgo`` and ``stack`` with the realistic
optics, with and without a calibration made by the ``sffscan calibrate`` commands, against
ideal optics (split from test_optics_bars.py so that pytest-xdist's workers can run these
scans beside the continuous one; the test bodies are unchanged). Each test prints its
ratios (``-s``)."""

from __future__ import annotations

import contextlib
import io
import re
from pathlib import Path

import cv2
import numpy as np
import pytest
from sffscan.pipeline.cli.main import main
from sffscan.pipeline.config import REALISTIC_OPTICS
from sffscan.pipeline.metrology.compare import compare_height_maps
from sffscan.stages.sim.camera import Optics, render_stack
from sffscan.stages.sim.world import characterisation_plate

from tests.pipeline.test_optics_bars import MID, ZS, calibrate

#: the fields of both tools: the thesis' field of view at half resolution (640 x 512 px of
#: 17 µm); one calibration of these optics serves both tests
FIELD_W, FIELD_H = 640, 512
REAL = Optics(width=FIELD_W, height=FIELD_H, pixel_um=17.0, magnification_ref_um=MID,
              **REALISTIC_OPTICS)  # type: ignore[arg-type]  # the floats of Optics' fields


@pytest.fixture(scope="module")
def calibration(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """The calibration of the realistic optics ``REAL`` by the ``sffscan calibrate`` commands
    (made once for the module: rendering and reading the targets is most of its time)."""
    return calibrate(tmp_path_factory.mktemp("calibration"), REAL)


def _stopgo_rmse(args: list[str]) -> float:
    buf = io.StringIO()
    with contextlib.redirect_stdout(buf):
        assert main(["stopgo", "-q", *args]) == 0
    m = re.search(r"RMSE ([0-9.]+) µm", buf.getvalue())
    assert m is not None, buf.getvalue()
    return float(m.group(1))


def test_stopgo(tmp_path: Path, calibration: Path) -> None:
    # fields of the thesis' field of view at half resolution (640 x 512 px of 17 µm): on
    # the default 320 x 256 fields the breathing barely shows (1.11x without calibration)
    field = ["--field", str(FIELD_W), str(FIELD_H)]
    cal = calibration
    ideal = _stopgo_rmse(["-o", str(tmp_path / "i.zarr"), *field])
    raw = _stopgo_rmse(["-o", str(tmp_path / "r.zarr"), "--realistic", *field])
    corrected = _stopgo_rmse(["-o", str(tmp_path / "c.zarr"), "--realistic",
                              "--calibration", str(cal), *field])
    print(f"\nstop-and-go RMSE: ideal optics {ideal:.1f} µm; realistic optics without "
          f"calibration {raw:.1f} µm ({raw / ideal:.3f}x), with {corrected:.1f} µm "
          f"({corrected / ideal:.3f}x)")
    assert corrected <= 1.10 * ideal
    assert raw >= 1.3 * ideal  # the simulated optics show their effect


def test_stack(tmp_path: Path, calibration: Path) -> None:
    w, h = FIELD_W, FIELD_H
    real = REAL
    ideal = Optics(width=w, height=h, pixel_um=17.0)
    cal = calibration
    world = characterisation_plate(seed=0, pixel_um=17.0, length_mm=24.0, width_mm=8.0,
                                   z_range_um=(0.0, float(ZS[-1])))
    truth = world.height_um(300.0, 0.0, w, h)
    rmse: dict[str, float] = {}
    # the realistic optics' stack, rendered once, reconstructed without and with calibration
    for name, optics, extra in (("ideal", ideal, []), ("real", real, []),
                                ("cal", real, ["--calibration", str(cal)])):
        folder = tmp_path / f"stack_{'real' if optics is real else name}"
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
        rmse_um = compare_height_maps(est[12:-12, 12:-12], truth[12:-12, 12:-12],
                                      max_depth_um=float(ZS[-1])).rmse_um
        assert rmse_um is not None, name
        rmse[name] = rmse_um
    ratio_raw, ratio_cal = rmse["real"] / rmse["ideal"], rmse["cal"] / rmse["ideal"]
    print(f"\nstack RMSE: ideal optics {rmse['ideal']:.1f} µm; realistic optics without "
          f"calibration {rmse['real']:.1f} µm ({ratio_raw:.3f}x), with {rmse['cal']:.1f} µm "
          f"({ratio_cal:.3f}x)")
    assert ratio_cal <= 1.10
    assert ratio_raw > 1.0
