"""Calibration routines: each a pure function on images, stacks or height maps.

They measure what a :class:`~sffscan.pipeline.metrology.calibration_model.Calibration`
file stores (``sffscan calibrate`` runs them and saves the file):

* z response -- :func:`calibrate_z`: per gauge block, the focus curve averaged over a
  central patch, its sub-level peak (:func:`peak_level`), then a linear fit of the peaks
  against the known heights (:func:`fit_z_response`): amplification coefficient a_z
  (µm per focus level), intercept, Pearson r, residuals.
* lateral scale -- :func:`lateral_scale`: µm per pixel in x and y from the outermost
  inner corners OpenCV finds on a checkerboard; :func:`calibrate_lateral` repeats it at
  several focus levels and fits the scale's linear change with the level (perspective of
  a non-telecentric objective).
* field curvature -- :func:`fit_field_curvature`: quadratic surface fitted to the height
  map of a flat reference (:func:`measure_height`).
* vignetting -- :func:`fit_vignetting`: the relative illumination of a flat reference.
* noise -- :func:`noise_by_subtraction`: ``N_M = Sq(z1 - z2) / sqrt(2)``.
"""

from __future__ import annotations

import math

import cv2
import numpy as np
from sffscan.pipeline.metrology.calibration_model import (
    CalibrationError,
    FieldCurvatureFit,
    LateralScale,
    LevelScale,
    VignettingFit,
    ZResponse,
    quadratic_terms,
)

__all__ = [
    "calibrate_lateral",
    "calibrate_z",
    "chessboard_corners",
    "fit_field_curvature",
    "fit_vignetting",
    "fit_z_response",
    "focus_volume_of",
    "lateral_scale",
    "measure_height",
    "noise_by_subtraction",
    "patch_focus_curve",
    "peak_level",
    "symmetric_peak",
]


# ---------------------------------------------------------------------- z response


def focus_volume_of(stack: np.ndarray, *, max_value: float, operator: str = "glvm",
                    window: int = 9) -> np.ndarray:
    """Focus volume of a raw stack, (N, H, W) -> (N, H, W) float32 (stages.focus_measure)."""
    from sffscan.stages.focus_measure import focus_measure, to_unit_float  # torch: load late

    frames = np.stack([to_unit_float(img, max_value=max_value) for img in np.asarray(stack)])
    return focus_measure(frames, operator=operator, window=window)


def patch_focus_curve(volume: np.ndarray, *, patch_px: int) -> np.ndarray:
    """Mean focus curve over the central ``patch_px`` x ``patch_px`` pixels, (N,) float64."""
    vol = np.asarray(volume)
    if vol.ndim != 3:
        raise ValueError(f"volume must be (N, H, W), got shape {vol.shape}")
    n, h, w = vol.shape
    if not 1 <= patch_px <= min(h, w):
        raise ValueError(f"patch_px must be in 1..{min(h, w)}, got {patch_px}")
    r0, c0 = (h - patch_px) // 2, (w - patch_px) // 2
    return vol[:, r0:r0 + patch_px, c0:c0 + patch_px].mean(axis=(1, 2), dtype=np.float64)


def symmetric_peak(curve: np.ndarray, *, half_width: int = 4) -> float:
    """Centre of symmetry of a focus curve near its maximum, in levels (resolution 0.001).

    A focus curve is symmetric about the height in focus (the blur grows with
    ``|h - z|``) but not Gaussian (it has a cusp), so 3-point fits are biased by up to
    ~0.07 level depending on the sub-level position. This finds the ``c`` within one level
    of the argmax that minimises ``sum_t (y(c + t) - y(c - t))^2`` over
    ``t = 0.25 .. half_width`` levels (y linearly interpolated): a 2-3x smaller bias on
    the simulated gauges. The half width shrinks near the ends of the curve.
    """
    y = np.asarray(curve, dtype=np.float64).reshape(-1)
    n = y.size
    if n < 3 or not np.isfinite(y).all():
        raise CalibrationError(f"focus curve must have >= 3 finite values, got {n}")
    a = int(np.argmax(y))
    k = min(half_width, a - 1, n - 2 - a)
    if k < 1:
        raise CalibrationError(f"focus peak at level {a} of {n}: too close to the end of "
                               "the focus range to locate (move the gauge or the range)")
    x = np.arange(n, dtype=np.float64)
    c = np.arange(a - 1.0, a + 1.0005, 0.001)[:, None]
    t = np.linspace(0.25, k, 4 * k)[None, :]
    err = ((np.interp(c + t, x, y) - np.interp(c - t, x, y)) ** 2).sum(axis=1)
    return float(c[int(np.argmin(err)), 0])


def peak_level(stack: np.ndarray, *, max_value: float, patch_px: int = 64,
               operator: str = "glvm", window: int = 9, method: str = "symmetric") -> float:
    """Sub-level focus peak of a stack's central patch, in levels.

    The focus curves of the patch (``sffscan.stages.focus_measure``) are averaged first (one
    curve), then its peak is located: ``"symmetric"`` (default, :func:`symmetric_peak`) or
    any ``sffscan.stages.depth.depth_from_focus`` method (``"gauss3"``...).
    """
    from sffscan.stages.depth import depth_from_focus

    curve = patch_focus_curve(focus_volume_of(stack, max_value=max_value, operator=operator,
                                              window=window), patch_px=patch_px)
    if method == "symmetric":
        return symmetric_peak(curve)
    depth, _ = depth_from_focus(curve.astype(np.float32)[:, None, None], method=method,
                                median_size=1)
    return float(depth[0, 0])


def fit_z_response(peak_levels: np.ndarray, heights_um: np.ndarray) -> ZResponse:
    """Linear fit ``height = intercept + a_z * level`` of known heights on measured peaks.

    Parameters
    ----------
    peak_levels : (B,) array_like of float
        Measured peak focus level of each gauge, levels.
    heights_um : (B,) array_like of float
        Known gauge heights, µm; at least 3, not all equal. A gauge whose residual exceeds
        one focus step (the fitted µm per level) is refused: its height or stack is wrong.

    Returns
    -------
    ZResponse
        ``um_per_level`` (a_z), ``intercept_um``, Pearson r, and residuals (calibrated
        minus known height, µm).
    """
    lv = np.asarray(peak_levels, dtype=np.float64).reshape(-1)
    hz = np.asarray(heights_um, dtype=np.float64).reshape(-1)
    if lv.shape != hz.shape or lv.size < 3:
        raise CalibrationError(f"z response needs >= 3 (level, height) pairs of equal length, "
                               f"got {lv.size} levels and {hz.size} heights")
    if not (np.isfinite(lv).all() and np.isfinite(hz).all()):
        raise CalibrationError("z response: peak levels and heights must be finite")
    if np.ptp(lv) == 0 or np.ptp(hz) == 0:
        raise CalibrationError("z response: the gauges' heights (or peaks) are all equal")
    slope, intercept = np.polyfit(lv, hz, 1)
    r = float(np.corrcoef(lv, hz)[0, 1])
    resid = intercept + slope * lv - hz
    worst = int(np.argmax(np.abs(resid)))
    if abs(resid[worst]) > abs(slope):  # a gauge off the line by more than a focus step
        raise CalibrationError(
            f"z response: the gauge of {hz[worst]:g} µm lies {resid[worst]:+.1f} µm off the "
            f"fitted line, more than one focus step ({abs(slope):.1f} µm/level; r = {r:.4f}): "
            "a gauge's height or its stack is wrong")
    return ZResponse(um_per_level=float(slope), intercept_um=float(intercept),
                     pearson_r=max(-1.0, min(1.0, r)), heights_um=hz.tolist(),
                     peak_levels=lv.tolist(), residuals_um=resid.tolist())


def calibrate_z(stacks: np.ndarray, heights_um: np.ndarray, *, max_value: float,
                patch_px: int = 64, operator: str = "glvm", window: int = 9) -> ZResponse:
    """z response from gauge-block stacks: (B, N, H, W) stacks, (B,) known heights in µm."""
    stacks = np.asarray(stacks)
    if stacks.ndim != 4:
        raise CalibrationError(f"gauge stacks must be (B, N, H, W), got shape {stacks.shape}")
    peaks = [peak_level(s, max_value=max_value, patch_px=patch_px, operator=operator,
                        window=window) for s in stacks]
    return fit_z_response(np.array(peaks), np.asarray(heights_um))


# ---------------------------------------------------------------------- lateral scale


def chessboard_corners(image: np.ndarray, *, squares: tuple[int, int]) -> np.ndarray:
    """Inner corners of a checkerboard, (ny - 1, nx - 1, 2) float64 (x, y) px, row by row.

    Uses ``cv2.findChessboardCornersSB`` (sub-pixel accurate), falling back to
    ``cv2.findChessboardCorners`` + ``cv2.cornerSubPix``. Raises :class:`CalibrationError`
    when the pattern is not found.
    """
    img = np.asarray(image)
    if img.ndim != 2:
        raise CalibrationError(f"checkerboard image must be 2-D grey, got shape {img.shape}")
    if img.dtype != np.uint8:
        top = float(img.max()) if img.size else 0.0
        img = cv2.convertScaleAbs(img, alpha=255.0 / top if top > 0 else 1.0)
    pattern = (int(squares[0]) - 1, int(squares[1]) - 1)
    ok, corners = cv2.findChessboardCornersSB(img, pattern)
    if not ok:
        ok, corners = cv2.findChessboardCorners(img, pattern)
        if ok:
            crit = (cv2.TERM_CRITERIA_EPS + cv2.TERM_CRITERIA_MAX_ITER, 50, 1e-3)
            corners = cv2.cornerSubPix(img, corners, (5, 5), (-1, -1), crit)
    if not ok or corners is None:
        raise CalibrationError(f"checkerboard of {pattern[0]} x {pattern[1]} inner corners "
                               "not found in the image")
    return np.asarray(corners, dtype=np.float64).reshape(pattern[1], pattern[0], 2)


def lateral_scale(image: np.ndarray, *, squares: tuple[int, int], square_um: float
                  ) -> tuple[float, float]:
    """µm per pixel along x and y from a checkerboard's outermost inner corners.

    Along x: the known distance ``(nx - 2) * square_um`` between the first and last corner
    of each corner row over their pixel distance, averaged over the rows; along y likewise
    over the columns. The board should be aligned with the frame (within a few degrees).
    """
    g = chessboard_corners(image, squares=squares)
    nx, ny = g.shape[1], g.shape[0]
    dx = np.linalg.norm(g[:, -1] - g[:, 0], axis=-1).mean()
    dy = np.linalg.norm(g[-1] - g[0], axis=-1).mean()
    return float((nx - 1) * square_um / dx), float((ny - 1) * square_um / dy)


def calibrate_lateral(images: np.ndarray, *, levels: np.ndarray, squares: tuple[int, int],
                      square_um: float, reference_level: float | None = None) -> LateralScale:
    """Per-level lateral scale from checkerboard images at several focus levels.

    Parameters
    ----------
    images : (K, H, W) array
        One board image per focus level (board in focus).
    levels : (K,) array_like of float
        Focus level of each image.
    squares, square_um
        Board geometry: squares along x, y; square side in µm.
    reference_level : float or None
        Level the stored scales refer to; default the mean of ``levels``.

    Returns
    -------
    LateralScale
        Linear fit of the scale against the level (slope 0 for a single image), the
        frame centre as optical centre, and each measurement.
    """
    imgs = np.asarray(images)
    if imgs.ndim == 2:
        imgs = imgs[None]
    lv = np.asarray(levels, dtype=np.float64).reshape(-1)
    if imgs.ndim != 3 or lv.size != imgs.shape[0]:
        raise CalibrationError(f"need one level per image, got {lv.size} levels for "
                               f"images of shape {imgs.shape}")
    ref = float(lv.mean()) if reference_level is None else float(reference_level)
    sx, sy = np.array([lateral_scale(im, squares=squares, square_um=square_um)
                       for im in imgs]).T
    if lv.size >= 2 and np.ptp(lv) > 0:
        kx, bx = np.polyfit(lv - ref, sx, 1)
        ky, by = np.polyfit(lv - ref, sy, 1)
    else:
        kx, bx, ky, by = 0.0, float(sx.mean()), 0.0, float(sy.mean())
    h, w = imgs.shape[1:]
    return LateralScale(um_per_px_x=float(bx), um_per_px_y=float(by), reference_level=ref,
                        slope_x_per_level=float(kx), slope_y_per_level=float(ky),
                        optical_centre_px=((w - 1) / 2.0, (h - 1) / 2.0),
                        per_level=[LevelScale(level=float(a), um_per_px_x=float(b),
                                              um_per_px_y=float(c))
                                   for a, b, c in zip(lv, sx, sy, strict=True)])


# ------------------------------------------------------------ curvature, vignetting, noise


def measure_height(stack: np.ndarray, *, focus_heights_um: np.ndarray, max_value: float,
                   operator: str = "glvm", window: int = 9, method: str = "spc",
                   median_size: int = 11) -> tuple[np.ndarray, np.ndarray]:
    """Height map (µm) and depth (levels) of one stationary stack, (H, W) float32 each."""
    from sffscan.stages.depth import depth_from_focus, levels_to_height

    vol = focus_volume_of(stack, max_value=max_value, operator=operator, window=window)
    depth, _ = depth_from_focus(vol, method=method, median_size=median_size,
                                spread_size=window)
    return levels_to_height(depth, focus_heights_um=focus_heights_um), depth


def fit_field_curvature(height_um: np.ndarray, *, margin_px: int = 0) -> FieldCurvatureFit:
    """Quadratic surface fitted (least squares) to the height map of a flat reference.

    Parameters
    ----------
    height_um : (H, W) array of float
        Measured heights of a flat reference over the whole frame, µm; NaN pixels are
        left out of the fit.
    margin_px : int
        Frame border left out (the focus window's and median filter's reach), px.

    Returns
    -------
    FieldCurvatureFit
        Coefficients in µm with u, v in px from the frame centre ((W - 1) / 2, (H - 1) / 2).
    """
    z = np.asarray(height_um, dtype=np.float64)
    if z.ndim != 2:
        raise CalibrationError(f"reference height map must be (H, W), got shape {z.shape}")
    h, w = z.shape
    cx, cy = (w - 1) / 2.0, (h - 1) / 2.0
    vv, uu = np.mgrid[0:h, 0:w].astype(np.float64)
    keep = np.isfinite(z)
    if margin_px > 0:
        inner = np.zeros_like(keep)
        inner[margin_px:h - margin_px, margin_px:w - margin_px] = True
        keep &= inner
    if keep.sum() < 6:
        raise CalibrationError("field curvature: fewer than 6 valid reference pixels")
    a = quadratic_terms(uu[keep] - cx, vv[keep] - cy)
    coef, *_ = np.linalg.lstsq(a, z[keep], rcond=None)
    rms = float(np.sqrt(np.mean((a @ coef - z[keep]) ** 2)))
    return FieldCurvatureFit(frame_width_px=w, frame_height_px=h, centre_px=(cx, cy),
                             coefficients_um=tuple(float(c) for c in coef),  # type: ignore[arg-type]
                             rms_residual_um=rms)


def fit_vignetting(stack: np.ndarray, *, margin_px: int = 0) -> VignettingFit:
    """Relative illumination of the frame from a focus stack of a flat, evenly lit reference.

    The mean of the stack's frames (texture averages out over the defocused frames and
    the fit), fitted by least squares with a quadratic surface in the frame coordinates,
    then divided by its value at the frame centre.

    Parameters
    ----------
    stack : (N, H, W) array of uint8, uint16 or float
    margin_px : int
        Frame border left out, px.

    Returns
    -------
    VignettingFit
    """
    st = np.asarray(stack)
    if st.ndim != 3:
        raise CalibrationError(f"flat reference stack must be (N, H, W), got shape {st.shape}")
    mean = st.mean(axis=0, dtype=np.float64)
    h, w = mean.shape
    cx, cy = (w - 1) / 2.0, (h - 1) / 2.0
    step = max(1, min(h, w) // 128)  # a few thousand samples are plenty for 6 coefficients
    vv, uu = np.mgrid[margin_px:h - margin_px:step, margin_px:w - margin_px:step]
    z = mean[vv, uu]
    if z.size < 6 or not np.isfinite(z).all():
        raise CalibrationError("vignetting: too few valid pixels in the flat reference")
    a = quadratic_terms((uu - cx).ravel().astype(np.float64), (vv - cy).ravel().astype(np.float64))
    coef, *_ = np.linalg.lstsq(a, z.ravel(), rcond=None)
    if not coef[0] > 0:
        raise CalibrationError("vignetting: the flat reference is dark at the frame centre")
    coef = coef / coef[0]
    corners = quadratic_terms(np.array([-cx, cx, -cx, cx]), np.array([-cy, -cy, cy, cy])) @ coef
    return VignettingFit(frame_width_px=w, frame_height_px=h, centre_px=(cx, cy),
                         coefficients=tuple(float(c) for c in coef),  # type: ignore[arg-type]
                         corner_loss=float(1.0 - corners.mean()))


def noise_by_subtraction(z1: np.ndarray, z2: np.ndarray) -> float:
    """Measurement noise ``N_M = Sq(z1 - z2) / sqrt(2)`` of two back-to-back measurements.

    Sq is the RMS of the difference after removing its mean, over the pixels finite in both
    maps (µm in, µm out). Raises :class:`CalibrationError` on a shape mismatch or when no
    pixel is valid in both.
    """
    a, b = np.asarray(z1, dtype=np.float64), np.asarray(z2, dtype=np.float64)
    if a.shape != b.shape:
        raise CalibrationError(f"noise: height maps differ in shape: {a.shape} and {b.shape}")
    d = (a - b)[np.isfinite(a) & np.isfinite(b)]
    if d.size < 2:
        raise CalibrationError("noise: fewer than 2 pixels valid in both height maps")
    return float(np.sqrt(np.mean((d - d.mean()) ** 2)) / math.sqrt(2.0))
