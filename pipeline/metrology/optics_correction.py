"""Applying a calibration's optics: magnification per focus level, field curvature, z response.

A calibration (:mod:`sffscan.pipeline.metrology.calibration_fit`) measures three properties of a
real objective; this module undoes them where a measurement is made:

* **Magnification per level** (``lateral``: µm/px at each focus level, a non-telecentric
  objective): every frame is resampled about the optical centre to the scale of the
  calibration's reference level *before* its focus measure is placed in world coordinates
  (:func:`unbreathe_frame`), so a world point keeps its pixel at every level; a reference
  level whose scale is not the configured ``optics.pixel_um`` (the scale frames are placed
  by) is refused (:func:`check_configured_scale`).
* **Field curvature** (``field_curvature``: the height a flat reference reads over the
  frame): subtracted from the heights. For a stationary field (``stack``, ``stopgo``) each
  pixel has one frame position (:func:`correct_field`). In a continuous scan a world point
  is seen at a different frame column at each level; its height comes from the frame that
  saw its peak level. :class:`ScanCurvature` works out, from the scan plan, which frame
  column each world column's first view at each level came from (the focus volume keeps
  the first observation per level), and subtracts the curvature at that column.
* **Vignetting** (``vignetting``: the illumination over the frame): every frame is divided
  by it first (:func:`flat_field`); in a continuous scan a world point crosses the frame, so
  uneven light would tilt its focus curve toward the bright centre.
* **z response**: the focus table (already applied by the depth stage,
  :func:`sffscan.pipeline.measuring.focus_heights_um`).

All functions are pure; the pipeline stages are in
:mod:`sffscan.pipeline.metrology.correction_stages`.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace
from typing import TYPE_CHECKING

import numpy as np
from sffscan.pipeline.metrology.calibration_model import (
    Calibration,
    CalibrationError,
    FieldCurvatureFit,
    LateralScale,
    calibrated_focus_heights,
    curvature_correction,
    illumination_map,
)
from sffscan.stages.fields.resample import ScaleResampler, scale_warp

if TYPE_CHECKING:
    from sffscan.pipeline.config import ScanConfig
    from sffscan.stages.fields.stationary import FieldResult

__all__ = [
    "ScanCurvature",
    "StackCorrection",
    "applied",
    "correct_field",
    "curvature_at",
    "first_view_columns",
    "flat_field",
    "flat_field_into",
    "check_configured_scale",
    "level_magnification",
    "level_scale",
    "unbreathe_frame",
    "unbreathe_matrix",
    "unbreathe_resampler",
]


MAX_SCALE_MISMATCH_PX = 1.0
"""Largest misplacement at the frame corner (px) that :func:`check_configured_scale` lets a
calibration's reference scale cause against the configured scale."""


def level_scale(lateral: LateralScale, levels: np.ndarray | float) -> np.ndarray:
    """Calibrated object-side scale at each focus level, µm/px (mean of x and y), float64."""
    d = np.asarray(levels, dtype=np.float64) - lateral.reference_level
    s_ref = 0.5 * (lateral.um_per_px_x + lateral.um_per_px_y)
    s: np.ndarray = s_ref + 0.5 * (lateral.slope_x_per_level + lateral.slope_y_per_level) * d
    if np.any(s <= 0):
        raise CalibrationError("lateral: the calibrated scale is not positive at every level")
    return s


def level_magnification(lateral: LateralScale, levels: np.ndarray | float) -> np.ndarray:
    """Magnification at each focus level relative to the reference level, ``s_ref / s(d)``.

    ``s(d)`` is the calibrated object-side scale (µm/px, mean of x and y) at level d: a level
    whose pixels cover fewer µm shows the world larger. A ratio of two calibrated scales: a
    bias common to all of them (the board's corners found a little off) cancels, which
    resampling to an absolute scale would not do (measured: a 0.13 % bias made the
    test-geometry scan 1.147x the ideal optics' RMSE instead of 1.033x). The frames so have
    the reference level's scale: :func:`check_configured_scale` makes sure it is the one
    the frames are placed by.

    Returns
    -------
    ndarray of float64, the shape of ``levels``.
    """
    return 0.5 * (lateral.um_per_px_x + lateral.um_per_px_y) / level_scale(lateral, levels)


def check_configured_scale(lateral: LateralScale, um_per_px: float, *,
                           frame_px: tuple[int, int], field: str = "optics.pixel_um") -> None:
    """Refuse a calibration whose reference level's scale is not the configured scale.

    The frames of every level are resampled to the reference level's scale
    (:func:`level_magnification`); placed by ``um_per_px``, they would be misplaced by
    ``|s_ref / um_per_px - 1|`` times the distance from the optical centre: refused beyond
    :data:`MAX_SCALE_MISMATCH_PX` at the farthest frame corner (``frame_px`` = (W, H)). A
    ``calibrate lateral --reference-level`` at a level other than the one whose scale the
    configuration holds is the usual cause (issue 24).

    Raises
    ------
    CalibrationError
        Naming both values and their fields, and the level the configured scale belongs to.
    """
    s_ref = 0.5 * (lateral.um_per_px_x + lateral.um_per_px_y)
    p = float(um_per_px)
    cx, cy = lateral.optical_centre_px
    w, h = frame_px
    reach = math.hypot(max(cx, w - 1 - cx), max(cy, h - 1 - cy))
    off = s_ref / p - 1.0
    if abs(off) * reach <= MAX_SCALE_MISMATCH_PX:
        return
    slope = 0.5 * (lateral.slope_x_per_level + lateral.slope_y_per_level)
    where = "" if slope == 0 else (
        f" (this calibration has {p:g} µm/px at level "
        f"{lateral.reference_level + (p - s_ref) / slope:.1f})")
    raise CalibrationError(
        f"{field} = {p:g} µm/px and the calibration's lateral scale at its reference level "
        f"disagree by {100 * off:+.2f} % ({abs(off) * reach:.1f} px at the frame corner): "
        f"lateral.um_per_px_x / um_per_px_y = {lateral.um_per_px_x:.5f} / "
        f"{lateral.um_per_px_y:.5f} µm/px at lateral.reference_level "
        f"{lateral.reference_level:g}; every level is resampled to that scale, so set {field} "
        f"to {s_ref:.5f} or calibrate lateral with --reference-level at the level whose scale "
        f"{field} is{where}")


def unbreathe_matrix(magnification: float, *, centre_px: tuple[float, float]) -> np.ndarray:
    """The (2, 3) map, output px -> frame px, of :func:`unbreathe_frame`."""
    if not (math.isfinite(magnification) and magnification > 0):
        raise ValueError(f"magnification must be > 0, got {magnification}")
    cx, cy = centre_px
    m = float(magnification)
    return np.array([[m, 0.0, cx * (1.0 - m)], [0.0, m, cy * (1.0 - m)]])


def unbreathe_frame(image: np.ndarray, magnification: float, *,
                    centre_px: tuple[float, float],
                    resampler: ScaleResampler | None = None,
                    buffers: tuple[np.ndarray, np.ndarray] | None = None,
                    dtype: np.dtype | type | None = None) -> np.ndarray:
    """Resample a frame of relative magnification M to the reference scale.

    ``out(u) = image(centre + (u - centre) * M)``: a point ``d`` px from the centre in the
    reference frame appears ``M d`` px from it in this frame. Same shape and dtype; pixels
    mapping outside the frame replicate its border (only for M < 1, at the frame's edge).

    The separable windowed sinc of the stack alignment
    (:func:`sffscan.stages.fields.resample.scale_warp`, 8 lobes a side, clipped to the
    frame's own range), not OpenCV's 4-lobe Lanczos: that one attenuates fine texture by an
    amount that depends on each pixel's sub-pixel phase (a moire over the frame, different
    at every level, which a focus measure reads as focus), and its 8 x 8 taps cost 60-70 ms a
    1280 x 1024 frame against 6-8 ms (bench/bench_frame_optics.py, 2026-12-03, AMD EPYC VM).
    ``resampler``: prepared for this magnification and the frame's shape
    (:func:`unbreathe_resampler`), reused over the frames of a level; ``buffers``: its work
    arrays (:meth:`~sffscan.stages.fields.resample.ScaleResampler.buffers`), reused over
    every frame; ``dtype``: of the result, for a frame of integers held in a float array
    (:func:`flat_field_into`'s), default ``image``'s.
    """
    img = np.asarray(image)
    mat = unbreathe_matrix(magnification, centre_px=centre_px)
    if magnification == 1.0:
        return img if dtype is None else img.astype(dtype)
    return scale_warp(img, mat, resampler=resampler, buffers=buffers, dtype=dtype)


def unbreathe_resampler(shape: tuple[int, int], magnification: float, *,
                        centre_px: tuple[float, float]) -> ScaleResampler:
    """:func:`unbreathe_frame`'s resampling of (H, W) frames, prepared once (float32)."""
    return ScaleResampler(shape, unbreathe_matrix(magnification, centre_px=centre_px))


def flat_field(image: np.ndarray, illumination: np.ndarray, *, max_value: float) -> np.ndarray:
    """A frame divided by the relative illumination (vignetting removed), same dtype.

    Integer frames are rounded and clipped to ``max_value``.
    """
    img = np.asarray(image)
    out = flat_field_into(img, illumination, np.empty(img.shape, np.float32),
                          max_value=max_value)
    return out.astype(img.dtype)


def flat_field_into(image: np.ndarray, illumination: np.ndarray, out: np.ndarray, *,
                    max_value: float) -> np.ndarray:
    """:func:`flat_field`'s values, in float32, written into ``out`` (float32, the frame's
    shape; returned): a caller that resamples the frame next reads them from there."""
    img = np.asarray(image)
    if img.shape != illumination.shape:
        raise CalibrationError(f"vignetting calibrated on {illumination.shape[::-1]} px frames; "
                               f"this frame is {img.shape[::-1]} px")
    np.divide(img, illumination, out=out, dtype=np.float32)
    if np.issubdtype(img.dtype, np.integer):
        np.rint(out, out=out)
        np.clip(out, 0, max_value, out=out)
    return out


def curvature_at(fit: FieldCurvatureFit, u: np.ndarray, v: np.ndarray) -> np.ndarray:
    """What a flat reference reads at frame pixel (u, v) minus its reading at the centre, µm.

    ``u``, ``v`` broadcast together (frame px, fractional allowed); float32 out.
    """
    cx, cy = fit.centre_px
    du = np.asarray(u, dtype=np.float64) - cx
    dv = np.asarray(v, dtype=np.float64) - cy
    _, cu, cv, cuu, cuv, cvv = fit.coefficients_um
    return (cu * du + cv * dv + cuu * du * du + cuv * du * dv + cvv * dv * dv).astype(np.float32)


def applied(cal: Calibration) -> list[str]:
    """Names of the corrections a calibration provides (for the mosaic's attributes)."""
    out = []
    if cal.z_response is not None:
        out.append("z_response")
    if cal.lateral is not None:
        out.append("magnification_per_level")
    if cal.field_curvature is not None:
        out.append("field_curvature")
    if cal.vignetting is not None:
        out.append("vignetting")
    return out


# ---------------------------------------------------------------------- stationary fields


def correct_field(result: FieldResult, fit: FieldCurvatureFit) -> FieldResult:
    """A stationary field's heights with the field curvature removed (both height maps)."""
    corr = curvature_correction(fit, result.height_um.shape)
    return replace(result, height_um=(result.height_um - corr).astype(np.float32),
                   raw_height_um=(result.raw_height_um - corr).astype(np.float32))


@dataclass(frozen=True)
class StackCorrection:
    """A calibration applied to stationary stacks (``stack``, ``stopgo``).

    Frame k of a stack is taken at focus level k of the calibrated lens. ``um_per_px`` is
    the scale the heights are stored at (``--pixel-um``): with ``lateral``, a calibration
    whose reference level has another scale is refused (:func:`check_configured_scale`);
    None does not check.
    """

    calibration: Calibration
    um_per_px: float | None = None

    def frames(self, stack: np.ndarray, *, max_value: float | None = None) -> np.ndarray:
        """Every frame flat-fielded (``vignetting``) and resampled to the reference level's
        scale (``lateral``); ``max_value`` clips integer frames (default the dtype's)."""
        st = np.asarray(stack)
        vig = self.calibration.vignetting
        if vig is not None:
            top = float(np.iinfo(st.dtype).max) if max_value is None and \
                np.issubdtype(st.dtype, np.integer) else (max_value or 1.0)
            illum = illumination_map(vig)
            st = np.stack([flat_field(f, illum, max_value=top) for f in st])
        lat = self.calibration.lateral
        if lat is None:
            return st
        if self.um_per_px is not None:
            check_configured_scale(lat, self.um_per_px, frame_px=(st.shape[2], st.shape[1]),
                                   field="--pixel-um")
        mags = level_magnification(lat, np.arange(st.shape[0]))
        return np.stack([unbreathe_frame(f, float(m), centre_px=lat.optical_centre_px)
                         for f, m in zip(st, mags, strict=True)])

    def focus_heights_um(self, nominal: np.ndarray) -> np.ndarray:
        """The calibrated focus table (z response) when the calibration has one."""
        n = np.asarray(nominal).size
        if self.calibration.z_response is None:
            return np.asarray(nominal, dtype=np.float64)
        return calibrated_focus_heights(self.calibration, n)

    def field(self, result: FieldResult) -> FieldResult:
        """Field curvature removed from a reconstructed field (when ``field_curvature``)."""
        fit = self.calibration.field_curvature
        return result if fit is None else correct_field(result, fit)


# ---------------------------------------------------------------------- continuous scans


def first_view_columns(x_px: np.ndarray, levels: np.ndarray, *, width: int, margin: int,
                       n_levels: int, x_lo: int, x_hi: int) -> np.ndarray:
    """Frame column of each world column's first view at each level, (N, x_hi - x_lo) float32.

    Frames (world x of their first column ``x_px``, focus ``levels``) are taken in order;
    frame columns ``[margin, width - margin)`` enter the focus volume, which keeps the first
    observation of each (column, level). NaN where a column is never seen at a level.
    """
    out = np.full((n_levels, x_hi - x_lo), np.nan, dtype=np.float32)
    for x, k in zip(np.rint(np.asarray(x_px)).astype(np.int64), np.asarray(levels), strict=True):
        a = max(int(x) + margin, x_lo)
        b = min(int(x) + width - margin, x_hi)
        if b <= a:
            continue
        row = out[int(k), a - x_lo:b - x_lo]
        new = np.isnan(row)
        row[new] = (np.arange(a, b) - x)[new]
    return out


@dataclass(frozen=True)
class ScanCurvature:
    """Field curvature correction of a continuous scan's heights, per world pixel.

    For each pass, :func:`first_view_columns` of the planned frames; a height h (µm) is
    turned back into its focus level with the focus table, the frame column its first view
    at that level had is looked up, and ``curvature_at(column, frame row)`` is subtracted.
    """

    fit: FieldCurvatureFit
    focus_heights_um: np.ndarray
    columns: dict[int, tuple[int, np.ndarray]]  # pass -> (x_lo, (N, W) frame columns)
    pass_y_px: dict[int, int]

    @classmethod
    def from_config(cls, cfg: ScanConfig, fit: FieldCurvatureFit,
                    focus_heights_um: np.ndarray) -> ScanCurvature:
        from sffscan.pipeline.plan import plan_frames

        o = cfg.optics
        if (fit.frame_width_px, fit.frame_height_px) != (o.width_px, o.height_px):
            raise CalibrationError(
                f"field curvature calibrated on {fit.frame_width_px} x {fit.frame_height_px} "
                f"px frames; the scan's are {o.width_px} x {o.height_px}")
        per: dict[int, tuple[list[float], list[int], float]] = {}
        for pf in plan_frames(cfg):
            xs, ks, _ = per.setdefault(pf.pass_index, ([], [], float(pf.y_px)))
            xs.append(pf.x_px)
            ks.append(pf.focus_index)
        margin = cfg.processing.focus_reach_px
        columns, ys = {}, {}
        for i, (xs, ks, y) in per.items():
            x_lo = int(math.floor(min(xs))) - 1
            x_hi = int(math.ceil(max(xs))) + o.width_px + 1
            columns[i] = (x_lo, first_view_columns(np.array(xs), np.array(ks), width=o.width_px,
                                                    margin=margin, n_levels=o.n_levels,
                                                    x_lo=x_lo, x_hi=x_hi))
            ys[i] = int(round(y))
        return cls(fit=fit, focus_heights_um=np.asarray(focus_heights_um, dtype=np.float64),
                   columns=columns, pass_y_px=ys)

    def correction(self, height_um: np.ndarray, *, x0_px: int, y0_px: int,
                   pass_index: int) -> np.ndarray:
        """What to subtract from a block of heights at world (x0_px, y0_px), µm (H, W).

        0 where the height is NaN or the column's first view is unknown.
        """
        h = np.asarray(height_um, dtype=np.float64)
        t = self.focus_heights_um
        n = t.size
        lev = np.interp(h, t, np.arange(n)) if t[-1] > t[0] else \
            np.interp(h, t[::-1], np.arange(n)[::-1])
        k = np.clip(np.rint(np.nan_to_num(lev, nan=0.0)), 0, n - 1).astype(np.intp)
        x_lo, cols = self.columns[pass_index]
        xs = np.arange(h.shape[1]) + x0_px - x_lo
        inside = (xs >= 0) & (xs < cols.shape[1])
        u = np.full(h.shape, np.nan)
        u[:, inside] = cols[k[:, inside], xs[inside][None, :]]
        v = (np.arange(h.shape[0]) + y0_px - self.pass_y_px[pass_index])[:, None]
        corr = curvature_at(self.fit, u, v).astype(np.float64)
        corr[~np.isfinite(corr) | ~np.isfinite(h)] = 0.0
        return corr.astype(np.float32)
