"""A lateral calibration whose reference level is not where the objective has the configured
scale (``calibrate lateral --reference-level 0``) is refused, naming both values and their
fields, and the level the configured scale belongs to (issue 24, item 5: the frames were
resampled to the reference level's scale, 9.5 % off here); one at that level gives frames of
``optics.pixel_um`` at every level."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import pytest
from sffscan.pipeline.cli.main import main
from sffscan.pipeline.config import config_from_dict
from sffscan.pipeline.metrology.calibration_model import CalibrationError, load_calibration
from sffscan.pipeline.metrology.correction_stages import optics_correction_stages
from sffscan.pipeline.metrology.optics_correction import StackCorrection
from sffscan.stages.messages import Frame, FrameHeader
from sffscan.stages.sim.camera import Optics
from sffscan.stages.sim.lens import scale_about_centre
from sffscan.stages.sim.targets import perspective_checkerboards

W, H, N = 320, 256, 20
PIXEL_UM = 8.5
STEP_UM = 200.0
SCALE_PER_MM = -0.05  # µm/px 1 % smaller per level: strong breathing
MID = 0.5 * (N - 1) * STEP_UM  # where the objective has the configured scale


def true_scale(level: float) -> float:
    return PIXEL_UM * (1.0 + SCALE_PER_MM * (level * STEP_UM - MID) / 1000.0)


def config(calibration: Path, pixel_um: float = PIXEL_UM):  # noqa: ANN201 - ScanConfig
    return config_from_dict({"optics": {"width_px": W, "height_px": H, "pixel_um": pixel_um,
                                        "n_levels": N, "z_step_um": STEP_UM},
                             "processing": {"calibration": str(calibration)}}, origin="test")


@pytest.fixture(scope="module")
def calibrations(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Path]:
    """``calibrate lateral`` on board images of the breathing objective, the stored scale
    referred to level 0 (9.5 % off the configured scale) and to the middle level (9.5)."""
    d = tmp_path_factory.mktemp("lat")
    levels = np.array([0, 6, 13, 19])
    imgs, scales = perspective_checkerboards(
        optics=Optics(width=W, height=H, pixel_um=PIXEL_UM, bit_depth=8),
        focus_heights_um=levels * STEP_UM, scale_per_mm=SCALE_PER_MM, reference_um=MID,
        square_um=300.0, squares=(7, 5), rng=np.random.default_rng(3))
    np.testing.assert_allclose(scales, [true_scale(lv) for lv in levels])
    files = []
    for lv, img in zip(levels, imgs, strict=True):
        files.append(d / f"board_{lv}.png")
        assert cv2.imwrite(str(files[-1]), img)
    out = {}
    for ref in ("0", "9.5"):
        out[ref] = d / f"cal{ref}.json"
        args = ["calibrate", "lateral", "-o", str(out[ref]), "--squares", "7", "5",
                "--square-um", "300", "--reference-level", ref]
        for lv, f in zip(levels, files, strict=True):
            args += ["--image", str(lv), str(f)]
        assert main(args) == 0
        lat = load_calibration(out[ref]).lateral
        assert lat is not None and lat.reference_level == float(ref)
        assert lat.um_per_px_x == pytest.approx(true_scale(float(ref)), rel=2e-3)
    return out


def breathing_frame(texture: np.ndarray, level: int) -> np.ndarray:
    """What the objective shows at ``level`` of a world whose configured-scale image is
    ``texture`` (padded by 32 px)."""
    return scale_about_centre(texture, PIXEL_UM / true_scale(level), out_shape=(H, W), pad=32)


def test_scan_refuses_a_reference_level_without_the_configured_scale(
        calibrations: dict[str, Path]) -> None:
    with pytest.raises(CalibrationError) as info:
        optics_correction_stages(config(calibrations["0"]), [0.0] * N)
    msg = str(info.value)
    assert "optics.pixel_um = 8.5 µm/px" in msg and "lateral.um_per_px_x" in msg
    assert "lateral.reference_level 0" in msg and "+9.5" in msg
    assert "8.5 µm/px at level 9.5" in msg  # where this objective has the configured scale


def test_scan_frames_have_the_configured_scale_at_every_level(
        calibrations: dict[str, Path]) -> None:
    rng = np.random.default_rng(0)
    texture = cv2.GaussianBlur(rng.random((H + 64, W + 64)).astype(np.float32), (0, 0), 2.0)
    ideal = texture[32:-32, 32:-32]
    (stage,), _ = optics_correction_stages(config(calibrations["9.5"]), [0.0] * N)
    inner = (slice(24, H - 24), slice(24, W - 24))
    for level in (0, N // 2, N - 1):
        hdr = FrameHeader(frame_id=level, timestamp_ns=level, focus_index=level)
        raw = breathing_frame(texture, level)
        (out,) = stage.process(Frame(hdr, raw))
        err = float(np.sqrt(np.mean((out.image[inner] - ideal[inner]) ** 2)))
        raw_err = float(np.sqrt(np.mean((raw[inner] - ideal[inner]) ** 2)))
        assert err < 0.01 and err < 0.2 * raw_err, (level, err, raw_err)


def test_stack_refuses_a_reference_level_without_the_given_scale(
        calibrations: dict[str, Path]) -> None:
    rng = np.random.default_rng(1)
    texture = cv2.GaussianBlur(rng.random((H + 64, W + 64)).astype(np.float32), (0, 0), 2.0)
    stack = np.stack([breathing_frame(texture, k) for k in range(N)])
    with pytest.raises(CalibrationError, match="--pixel-um = 8.5 µm/px"):
        StackCorrection(load_calibration(calibrations["0"]), um_per_px=PIXEL_UM).frames(stack)
    out = StackCorrection(load_calibration(calibrations["9.5"]), um_per_px=PIXEL_UM).frames(stack)
    inner = (slice(24, H - 24), slice(24, W - 24))
    err = np.sqrt(np.mean((out[:, *inner] - texture[32:-32, 32:-32][inner]) ** 2, axis=(1, 2)))
    assert err.max() < 0.01, err


def test_breathing_correction_reproduces_a_band_limited_frame() -> None:
    """Known answer: a frame of a band-limited pattern (periods 7 to 20 px) seen at
    magnification M, corrected by the frame_optics stage, is the pattern at the reference
    scale within 0.5 % of its amplitude away from the border (OpenCV's 4-lobe Lanczos,
    which the stage used before, errs ~1.5 %: bench/bench_frame_optics.py); the stage's
    frames equal unbreathe_frame's, level by level."""
    from sffscan.pipeline.metrology.correction_stages import FrameOpticsStage
    from sffscan.pipeline.metrology.optics_correction import unbreathe_frame
    from sffscan.stages.messages import Frame, FrameHeader

    h, w, centre = 200, 260, (131.3, 97.6)
    yy, xx = np.mgrid[0:h, 0:w].astype(np.float64)

    def pattern(x: np.ndarray, y: np.ndarray) -> np.ndarray:
        return (500 + 200 * np.sin(0.9 * x + 0.3) * np.cos(0.7 * y - 0.2)
                + 150 * np.sin(0.31 * x + 0.45 * y))

    mags = np.array([0.99, 1.0, 1.012])
    stage = FrameOpticsStage(mags, centre_px=centre)
    inner = (slice(30, -30), slice(30, -30))
    for k, m in enumerate(mags):
        # what a lens of relative magnification m shows: the world point at reference
        # pixel u appears at centre + m (u - centre)
        seen = pattern(centre[0] + (xx - centre[0]) / m, centre[1] + (yy - centre[1]) / m)
        frame = np.rint(seen).astype(np.uint16)
        header = FrameHeader(frame_id=k, timestamp_ns=k, focus_index=k, stage_x_um=0.0,
                             stage_y_um=0.0)
        got = next(iter(stage.process(Frame(header, frame)))).image
        assert got.dtype == np.uint16
        np.testing.assert_array_equal(got, unbreathe_frame(frame, float(m), centre_px=centre))
        err = np.abs(got.astype(np.float64) - pattern(xx, yy))[inner]
        assert err.max() < 0.005 * 350, (m, err.max())


def test_flat_field_then_resampling_in_the_work_arrays_is_the_two_steps() -> None:
    """With vignetting and a magnification, an integer frame is flat-fielded into the
    resampling's work array: the frames equal flat_field then unbreathe_frame, bit for
    bit, level after level (the arrays reused); a frame of another shape is refused with
    its frame_id."""
    from sffscan.pipeline.metrology.correction_stages import FrameOpticsStage
    from sffscan.pipeline.metrology.optics_correction import flat_field, unbreathe_frame
    from sffscan.stages.messages import Frame, FrameError, FrameHeader

    rng = np.random.default_rng(2)
    h, w, centre = 70, 90, (44.2, 35.9)
    yy, xx = np.mgrid[0:h, 0:w]
    illum = (1.0 - 0.2 * ((xx - centre[0]) ** 2 + (yy - centre[1]) ** 2)
             / (centre[0] ** 2 + centre[1] ** 2)).astype(np.float32)
    mags = np.array([0.99, 1.0, 1.011])
    stage = FrameOpticsStage(mags, centre_px=centre, illumination=illum, max_value=1023.0)
    for i in range(6):
        k = i % 3
        frame = rng.integers(0, 1024, (h, w), dtype=np.uint16)
        header = FrameHeader(frame_id=i, timestamp_ns=i, focus_index=k, stage_x_um=0.0,
                             stage_y_um=0.0)
        got = next(iter(stage.process(Frame(header, frame)))).image
        want = unbreathe_frame(flat_field(frame, illum, max_value=1023.0), float(mags[k]),
                               centre_px=centre)
        assert got.dtype == np.uint16
        np.testing.assert_array_equal(got, want)
    header = FrameHeader(frame_id=9, timestamp_ns=9, focus_index=2, stage_x_um=0.0,
                         stage_y_um=0.0)
    with pytest.raises(FrameError, match=r"frame_id 9: vignetting calibrated on \(90, 70\)"):
        list(stage.process(Frame(header, np.zeros((h, w + 2), np.uint16))))
