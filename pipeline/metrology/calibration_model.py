"""Calibration file: the versioned :class:`Calibration` model, saved and loaded as JSON,
and what its stored fits mean when applied.

The file (``schemas/calibration.v1.json``, ISO 25178-700 style, SFF_NOTES.md section 6)
holds the z response, the lateral scale and its change with the focus level, the field
curvature, the vignetting and the measurement noise of one instrument. The routines that
measure them from images are in :mod:`sffscan.pipeline.metrology.calibration_fit`.

Applying a calibration, each a pure function of the stored values:

* :func:`calibrated_focus_heights` -- the focus table the depth stage uses in place of the
  nominal ``z_min_um + k * z_step_um``;
* :func:`curvature_correction` -- what is subtracted from a height map for the field
  curvature; :func:`illumination_map` -- the relative illumination (vignetting);
* :func:`pixel_positions_um` -- perspective-corrected lateral positions;
* :func:`apply_calibration` -- depth levels (or nominal µm) to calibrated µm.
"""

from __future__ import annotations

from datetime import UTC, datetime
from pathlib import Path
from typing import Literal

import numpy as np
from pydantic import BaseModel, ConfigDict, Field, ValidationError
from sffscan.pipeline.config import ConfigError

__all__ = [
    "CALIBRATION_FORMAT",
    "Calibration",
    "CalibrationError",
    "FieldCurvatureFit",
    "LateralScale",
    "LevelScale",
    "VignettingFit",
    "ZResponse",
    "apply_calibration",
    "calibrated_focus_heights",
    "curvature_correction",
    "illumination_map",
    "load_calibration",
    "pixel_positions_um",
    "quadratic_terms",
    "save_calibration",
]

CALIBRATION_FORMAT = "sffscan-calibration"


class CalibrationError(ConfigError):
    """A calibration that cannot be computed, read or applied; the message names the cause."""


class _Model(BaseModel):
    model_config = ConfigDict(extra="forbid", allow_inf_nan=False)


class ZResponse(_Model):
    """Linear z response: height = intercept_um + um_per_level * level."""

    um_per_level: float = Field(description="Amplification coefficient a_z, µm per focus level")
    intercept_um: float = Field(description="Height in focus at level 0, µm")
    pearson_r: float = Field(ge=-1, le=1, description="Pearson r of peak levels vs heights")
    heights_um: list[float] = Field(description="Known gauge heights, µm")
    peak_levels: list[float] = Field(description="Measured peak focus level per gauge")
    residuals_um: list[float] = Field(description="Calibrated minus known height, µm")


class LevelScale(_Model):
    level: float = Field(description="Focus level of the measurement")
    um_per_px_x: float = Field(gt=0, description="Object-side scale along x, µm/px")
    um_per_px_y: float = Field(gt=0, description="Object-side scale along y, µm/px")


class LateralScale(_Model):
    """Lateral scale, and its linear change with the focus level (perspective)."""

    um_per_px_x: float = Field(gt=0, description="Scale along x at reference_level, µm/px")
    um_per_px_y: float = Field(gt=0, description="Scale along y at reference_level, µm/px")
    reference_level: float = Field(description="Focus level the scales above refer to")
    slope_x_per_level: float = Field(0.0, description="d(um_per_px_x)/d(level), µm/px per level")
    slope_y_per_level: float = Field(0.0, description="d(um_per_px_y)/d(level), µm/px per level")
    optical_centre_px: tuple[float, float] = Field(
        description="Frame pixel (x, y) the scale change is centred on")
    per_level: list[LevelScale] = Field(default_factory=list,
                                        description="The individual measurements")


class FieldCurvatureFit(_Model):
    """Quadratic fit of a flat reference: c0 + cu u + cv v + cuu u² + cuv u v + cvv v²."""

    frame_width_px: int = Field(ge=1)
    frame_height_px: int = Field(ge=1)
    centre_px: tuple[float, float] = Field(description="Frame pixel (x, y) where u = v = 0")
    coefficients_um: tuple[float, float, float, float, float, float] = Field(
        description="c0, cu, cv, cuu, cuv, cvv; u, v in px from centre_px, result µm")
    rms_residual_um: float = Field(ge=0, description="RMS of the reference minus the fit, µm")


class VignettingFit(_Model):
    """Relative illumination over the frame: quadratic surface, 1 at the centre."""

    frame_width_px: int = Field(ge=1)
    frame_height_px: int = Field(ge=1)
    centre_px: tuple[float, float] = Field(description="Frame pixel (x, y) where u = v = 0")
    coefficients: tuple[float, float, float, float, float, float] = Field(
        description="1, cu, cv, cuu, cuv, cvv: illumination relative to the centre; u, v in px "
                    "from centre_px")
    corner_loss: float = Field(description="Illumination lost at the frame corners (mean of "
                                           "the four), fraction")


class Calibration(_Model):
    """One instrument's calibration (schemas/calibration.v1.json)."""

    format: Literal["sffscan-calibration"] = "sffscan-calibration"
    format_version: Literal[1] = 1
    created: str = Field(default_factory=lambda: datetime.now(UTC).isoformat(timespec="seconds"))
    description: str = Field("", description="Instrument, objective, targets used")
    z_response: ZResponse | None = None
    lateral: LateralScale | None = None
    field_curvature: FieldCurvatureFit | None = None
    noise_um: float | None = Field(None, ge=0, description="N_M by subtraction, µm")
    vignetting: VignettingFit | None = Field(
        None, description="Illumination over the frame (flat field), from a flat reference")


def save_calibration(cal: Calibration, path: str | Path) -> Path:
    """Write a calibration as JSON (UTF-8); returns the path."""
    p = Path(path)
    p.write_text(cal.model_dump_json(indent=2) + "\n", encoding="utf-8")
    return p


def load_calibration(path: str | Path) -> Calibration:
    """Read and validate a calibration file; errors name the file and the field."""
    p = Path(path)
    try:
        text = p.read_text(encoding="utf-8")
    except OSError as err:
        raise CalibrationError(f"{p}: cannot read calibration: {err.strerror or err}") from err
    except UnicodeDecodeError as err:  # an image, a binary file given for a calibration
        raise CalibrationError(f"{p}: not a calibration file (not UTF-8 text: byte "
                               f"{err.start})") from err
    try:
        return Calibration.model_validate_json(text)
    except ValidationError as err:
        first = err.errors()[0]
        where = ".".join(str(v) for v in first["loc"]) or "(file)"
        raise CalibrationError(f"{p}: {where}: {first['msg']}") from err


# ---------------------------------------------------------------------- applying


def quadratic_terms(u: np.ndarray, v: np.ndarray) -> np.ndarray:
    """The six terms ``1, u, v, u², u v, v²`` of the stored quadratic surfaces, (..., 6).

    The order of :attr:`FieldCurvatureFit.coefficients_um` and
    :attr:`VignettingFit.coefficients`; ``u``, ``v`` in px from the fit's ``centre_px``.
    """
    return np.stack([np.ones_like(u), u, v, u * u, u * v, v * v], axis=-1)


def curvature_correction(fit: FieldCurvatureFit, shape: tuple[int, int], *,
                         frame_origin_px: tuple[int, int] = (0, 0)) -> np.ndarray:
    """What to subtract from a measurement: the fit minus its value at the centre, µm.

    Parameters
    ----------
    fit : FieldCurvatureFit
    shape : (H, W)
        Shape of the height map to correct.
    frame_origin_px : (x, y)
        Frame pixel of its element [0, 0].

    Returns
    -------
    (H, W) float32, µm; 0 at the frame centre.
    """
    h, w = shape
    x0, y0 = frame_origin_px
    if x0 < 0 or y0 < 0 or x0 + w > fit.frame_width_px or y0 + h > fit.frame_height_px:
        raise CalibrationError(
            f"field curvature: region {w} x {h} px at ({x0}, {y0}) lies outside the "
            f"calibrated {fit.frame_width_px} x {fit.frame_height_px} px frame")
    cx, cy = fit.centre_px
    vv, uu = np.mgrid[y0:y0 + h, x0:x0 + w].astype(np.float64)
    c = np.asarray(fit.coefficients_um)
    out = quadratic_terms(uu - cx, vv - cy) @ c - c[0]
    return out.astype(np.float32)


def illumination_map(fit: VignettingFit) -> np.ndarray:
    """Relative illumination of every frame pixel, (H, W) float32 (1 at the centre)."""
    h, w = fit.frame_height_px, fit.frame_width_px
    cx, cy = fit.centre_px
    vv, uu = np.mgrid[0:h, 0:w].astype(np.float64)
    out = quadratic_terms(uu - cx, vv - cy) @ np.asarray(fit.coefficients)
    if not np.all(out > 0.05):
        raise CalibrationError("vignetting: the fitted illumination falls below 5 % in the "
                               "frame")
    return out.astype(np.float32)


def pixel_positions_um(depth_levels: np.ndarray, *, lateral: LateralScale,
                       frame_origin_px: tuple[int, int] = (0, 0)) -> tuple[np.ndarray, np.ndarray]:
    """Perspective-corrected lateral positions of a field's pixels, µm from the optical axis.

    Pixel (u, v) of the frame, at depth level d, lies at ``(u - cx) * s_x(d)``,
    ``(v - cy) * s_y(d)`` with ``s(d) = s_ref + slope * (d - reference_level)``.

    Parameters
    ----------
    depth_levels : (H, W) array of float
        Depth of each pixel in focus levels (NaN stays NaN).
    lateral : LateralScale
    frame_origin_px : (x, y)
        Frame pixel of the array's element [0, 0] (for a crop of the frame).

    Returns
    -------
    x_um, y_um : (H, W) float64 each.
    """
    d = np.asarray(depth_levels, dtype=np.float64)
    if d.ndim != 2:
        raise ValueError(f"depth_levels must be (H, W), got shape {d.shape}")
    cx, cy = lateral.optical_centre_px
    u = np.arange(d.shape[1]) + frame_origin_px[0] - cx
    v = np.arange(d.shape[0]) + frame_origin_px[1] - cy
    sx = lateral.um_per_px_x + lateral.slope_x_per_level * (d - lateral.reference_level)
    sy = lateral.um_per_px_y + lateral.slope_y_per_level * (d - lateral.reference_level)
    return u[None, :] * sx, v[:, None] * sy


def calibrated_focus_heights(cal: Calibration, n_levels: int) -> np.ndarray:
    """Height in focus at each level 0..n_levels-1 by the z response, (N,) float64 µm.

    The table ``sffscan.stages.depth.levels_to_height`` takes; the pipeline's depth stage uses it
    in place of the nominal ``z_min_um + k * z_step_um``.
    """
    if cal.z_response is None:
        raise CalibrationError("calibration has no z_response")
    z = cal.z_response
    return z.intercept_um + z.um_per_level * np.arange(int(n_levels), dtype=np.float64)


def apply_calibration(depth: np.ndarray, *, calibration: Calibration,
                      units: Literal["levels", "um"] = "levels",
                      nominal_heights_um: np.ndarray | None = None,
                      curvature: Literal["field", "off"] = "field",
                      frame_origin_px: tuple[int, int] = (0, 0)) -> np.ndarray:
    """Calibrated heights of a stationary field, µm.

    Parameters
    ----------
    depth : (H, W) array of float
        Depth in focus levels (``units="levels"``), or heights in µm from the nominal focus
        table (``units="um"``, then ``nominal_heights_um`` is required to recover the
        levels). NaN stays NaN.
    calibration : Calibration
        Must have ``z_response``; ``field_curvature`` is applied when present and
        ``curvature="field"``.
    nominal_heights_um : (N,) array_like of float, optional
        The nominal table the µm were computed with (linear).
    frame_origin_px : (x, y)
        Frame pixel of ``depth[0, 0]`` (for a crop of the frame).

    Returns
    -------
    (H, W) float32 heights, µm: ``intercept + a_z * level - curvature_correction``.
    """
    if calibration.z_response is None:
        raise CalibrationError("calibration has no z_response: cannot map levels to µm")
    d = np.asarray(depth, dtype=np.float64)
    if units == "um":
        if nominal_heights_um is None:
            raise CalibrationError("units='um' needs nominal_heights_um to recover the levels")
        t = np.asarray(nominal_heights_um, dtype=np.float64)
        if t.ndim != 1 or t.size < 2 or not np.allclose(np.diff(t), t[1] - t[0]):
            raise CalibrationError("nominal_heights_um must be a linear table of >= 2 levels")
        d = (d - t[0]) / (t[1] - t[0])
    elif units != "levels":
        raise ValueError(f"units must be 'levels' or 'um', got {units!r}")
    z = calibration.z_response
    out = z.intercept_um + z.um_per_level * d
    if curvature == "field" and calibration.field_curvature is not None:
        out = out - curvature_correction(calibration.field_curvature, d.shape,
                                         frame_origin_px=frame_origin_px)
    elif curvature not in ("field", "off"):
        raise ValueError(f"curvature must be 'field' or 'off', got {curvature!r}")
    return out.astype(np.float32)
