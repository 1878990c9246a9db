"""``sffscan calibrate z | lateral | curvature | noise`` on image files, as a user would run
them: the simulated targets of tests/pipeline/metrology/test_calibration_fit.py written to PNG
files, the commands
run in order into one calibration file, the known answers within the same tolerances."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import pytest
from sffscan.pipeline.cli.main import main
from sffscan.pipeline.metrology.calibration_model import load_calibration
from sffscan.stages.sim.camera import Optics, focus_heights
from sffscan.stages.sim.targets import (
    curved_field_stack,
    gauge_block_stacks,
    perspective_checkerboards,
)

# the lens's true table: 190 µm steps from 100 µm; nominally 200 µm from 0
TRUE_Z = focus_heights(n_levels=40, z_min_um=100.0, z_step_um=190.0)
GAUGES = (1000.0, 2500.0, 4000.0, 5500.0, 7000.0)
CURV = (2e-2, 5e-3, 1e-2)


def write_stack(folder: Path, stack: np.ndarray) -> Path:
    folder.mkdir(parents=True)
    for k, img in enumerate(stack):  # unpadded numbers: the natural order must hold
        assert cv2.imwrite(str(folder / f"img_{k}.png"), img)
    return folder


@pytest.fixture(scope="module")
def calibrated(tmp_path_factory: pytest.TempPathFactory) -> dict:
    d = tmp_path_factory.mktemp("cal")
    out = d / "cal.json"
    rng = np.random.default_rng(11)
    o = Optics(width=128, height=128, pixel_um=8.5)
    gauges = gauge_block_stacks(np.array(GAUGES), optics=o, focus_heights_um=TRUE_Z, rng=rng)
    args = ["calibrate", "z", "-o", str(out), "--bit-depth", "10"]
    for h, st in zip(GAUGES, gauges, strict=True):
        args += ["--gauge", f"{h:g}", str(write_stack(d / f"gauge{h:g}", st))]
    assert main(args) == 0

    oc = Optics(width=192, height=160, pixel_um=8.5)
    flat = [curved_field_stack(optics=oc, focus_heights_um=TRUE_Z, curvature_um_px2=CURV,
                               surface_um=4000.0, x_offset_px=x, rng=rng) for x in (0.0, 0.0)]
    f1 = write_stack(d / "flat1", flat[0])
    f2 = write_stack(d / "flat2", flat[1])
    assert main(["calibrate", "curvature", str(f1), "-o", str(out), "--bit-depth", "10"]) == 0
    assert main(["calibrate", "noise", str(f1), str(f2), "-o", str(out),
                 "--bit-depth", "10"]) == 0
    # the boards come from another simulated lens (strong breathing) than the flat stacks:
    # calibrated last, so the curvature above is not resampled by its scale
    ob = Optics(width=640, height=512, pixel_um=8.5, bit_depth=8)
    levels = np.array([0, 13, 26, 39])
    imgs, true_scale = perspective_checkerboards(
        optics=ob, focus_heights_um=TRUE_Z[levels], scale_per_mm=-0.02,
        reference_um=float(TRUE_Z[0]), square_um=400.0, squares=(11, 9), rng=rng)
    args = ["calibrate", "lateral", "-o", str(out), "--squares", "11", "9", "--square-um",
            "400", "--reference-level", "0"]
    for lv, img in zip(levels, imgs, strict=True):
        f = d / f"board_{lv}.png"
        cv2.imwrite(str(f), img)
        args += ["--image", str(lv), str(f)]
    assert main(args) == 0
    return {"cal": load_calibration(out), "true_scale": true_scale, "dir": d, "out": out}


def test_z_response_from_gauge_images(calibrated: dict) -> None:
    z = calibrated["cal"].z_response
    assert z.um_per_level == pytest.approx(190.0, rel=0.005)
    assert z.intercept_um == pytest.approx(100.0, abs=15.0)
    assert z.pearson_r > 0.99999
    assert max(abs(r) for r in z.residuals_um) < 10.0


def test_lateral_scale_from_board_images(calibrated: dict) -> None:
    lat = calibrated["cal"].lateral
    for m, s in zip(lat.per_level, calibrated["true_scale"], strict=True):
        assert m.um_per_px_x == pytest.approx(s, rel=1e-3)
        assert m.um_per_px_y == pytest.approx(s, rel=1e-3)
    true_slope = 8.5 * -0.02 * 0.190
    assert lat.slope_x_per_level == pytest.approx(true_slope, rel=0.02)
    assert lat.slope_y_per_level == pytest.approx(true_slope, rel=0.02)


def test_curvature_from_flat_images_through_the_z_response(calibrated: dict) -> None:
    # heights through the calibrated z response (written first): the true µm
    c0, _, _, cuu, cuv, cvv = calibrated["cal"].field_curvature.coefficients_um
    a, b, c = CURV
    assert cuu == pytest.approx(-a, rel=0.03)
    assert cuv == pytest.approx(-b, rel=0.05)
    assert cvv == pytest.approx(-c, rel=0.03)
    assert c0 == pytest.approx(4000.0, abs=15.0)


def test_noise_from_two_stacks_and_sections_kept(calibrated: dict) -> None:
    cal = calibrated["cal"]
    assert 0.1 < cal.noise_um < 20.0  # two noisy measurements of one surface
    # each step kept the others' sections: the last one (lateral) kept them all
    assert None not in (cal.z_response, cal.field_curvature, cal.vignetting, cal.lateral)


def test_bad_input_names_the_file(calibrated: dict, capsys: pytest.CaptureFixture[str]) -> None:
    d = calibrated["dir"]
    (d / "empty").mkdir()
    assert main(["calibrate", "curvature", str(d / "empty"), "-o",
                 str(d / "other.json")]) == 2
    assert "empty: no image files" in capsys.readouterr().err
    assert main(["calibrate", "z", "-o", str(d / "other.json"), "--gauge", "100",
                 str(d / "nothere")]) == 2
    assert "nothere" in capsys.readouterr().err


def test_a_stack_or_image_given_twice_or_a_gauge_off_the_line_is_refused(
        calibrated: dict, capsys: pytest.CaptureFixture[str]) -> None:
    """One gauge's stack given for two heights fitted r = 0.87 with residuals of 833 µm and
    was written (exit 0); one flat for both noise stacks gives a noise of 0; one board for
    two levels a wrong scale change. Each is refused naming the path; nothing is written."""
    d, out = calibrated["dir"], calibrated["dir"] / "twice.json"
    g = [str(d / f"gauge{h:g}") for h in GAUGES]
    args = ["calibrate", "z", "-o", str(out), "--bit-depth", "10"]
    assert main([*args, "--gauge", "1000", g[0], "--gauge", "2500", g[0] + "/",
                 "--gauge", "4000", g[2]]) == 2
    assert f"{g[0]}/: given twice (--gauge 1 and 2)" in capsys.readouterr().err
    # distinct stacks, one with the wrong height: more than a focus step off the line
    assert main([*args, "--gauge", "1000", g[0], "--gauge", "4000", g[1],
                 "--gauge", "4000", g[2], "--gauge", "5500", g[3]]) == 2
    assert "off the fitted line, more than one focus step" in capsys.readouterr().err
    assert main(["calibrate", "noise", str(d / "flat1"), str(d / "flat1"), "-o", str(out),
                 "--focus-start", "0", "--focus-step", "200"]) == 2
    assert "given twice (stack 1 and 2)" in capsys.readouterr().err
    board = str(d / "board_0.png")
    assert main(["calibrate", "lateral", "-o", str(out), "--squares", "11", "9",
                 "--square-um", "400", "--image", "0", board, "--image", "13", board]) == 2
    assert "given twice (--image 1 and 2)" in capsys.readouterr().err
    assert not out.exists()


@pytest.mark.parametrize("argv, words", [
    (["lateral", "--squares", "1", "1", "--square-um", "400"], "at least 4 squares"),
    (["lateral", "--squares", "11", "9", "--square-um", "0"], "--square-um: must be a finite"),
    (["lateral", "--squares", "11", "9", "--square-um", "400", "--reference-level", "nan"],
     "--reference-level: must be a finite number"),
    (["z", "--gauge", "1000", "g", "--bit-depth", "40"], "a bit depth is 1..16, got 40"),
    (["curvature", "FLAT", "--margin-px", "-1"], "--margin-px must be 0 .. 79"),
    (["noise", "FLAT", "FLAT2", "--margin-px", "100000", "--focus-start", "0",
      "--focus-step", "200"], "--margin-px must be 0 .. 79"),
])
def test_bad_options_are_named_not_a_traceback(
        calibrated: dict, argv: list[str], words: str,
        capsys: pytest.CaptureFixture[str]) -> None:
    """Each gave an OpenCV error (traceback), pydantic's raw text, "SVD did not converge",
    "negative dimensions" or was accepted (a negative margin, 40 bits)."""
    d = calibrated["dir"]
    argv = [str(d / "flat1") if a == "FLAT" else str(d / "flat2") if a == "FLAT2" else a
            for a in argv]
    if argv[0] == "lateral":
        argv += ["--image", "0", str(d / "board_0.png"), "--image", "13",
                 str(d / "board_13.png")]
    code = None
    try:
        code = main(["calibrate", *argv, "-o", str(d / "bad.json")])
    except SystemExit as err:  # argparse's usage errors
        code = int(err.code or 0)
    assert code == 2
    assert words in capsys.readouterr().err
    assert not (d / "bad.json").exists()


def test_targets_command_writes_the_images_and_prints_the_commands(
        tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    from sffscan.pipeline.config import REALISTIC_OPTICS, config_to_toml, demo_config

    cfg = demo_config(optics={**REALISTIC_OPTICS, "width_px": 256, "height_px": 128,
                              "n_levels": 12, "z_step_um": 400.0},
                      motion={"speed_mm_s": 1.0})
    toml = tmp_path / "small.toml"
    toml.write_text(config_to_toml(cfg), encoding="utf-8")
    assert main(["calibrate", "targets", str(tmp_path / "t"), "--config", str(toml),
                 "-o", str(tmp_path / "c.json")]) == 0
    out = capsys.readouterr().out
    assert out.count("  sffscan calibrate ") == 4
    assert len(list((tmp_path / "t" / "flat1").glob("img_*.png"))) == 12
    assert len(list((tmp_path / "t").glob("board_*.png"))) == 5
    img = cv2.imread(str(tmp_path / "t" / "board_0.png"), cv2.IMREAD_UNCHANGED)
    assert img.shape == (128, 256) and img.dtype == np.uint16
