"""Real-lens effects of the simulated objective: focus breathing, field curvature, vignetting.

All three are centred on the optical centre, the frame centre ``((W - 1) / 2, (H - 1) / 2)``,
and use the normalised squared radius ``rho2 = ((u - cx)^2 + (v - cy)^2) / (cx^2 + cy^2)``
(0 at the centre, 1 at the frame corner):

* **Magnification change with focus** (a non-telecentric objective, "focus breathing"):
  ``M(f) = 1 + magnification_per_mm * (f - magnification_ref_um) / 1000``. Frame pixel
  (u, v) sees the world point ``centre + (u - cx, v - cy) / M`` px from the optical axis,
  so the object-side pixel scale at focus f is ``pixel_um / M(f)``.
* **Field curvature**: the surface of best focus lies ``field_curvature_um * rho2`` µm above
  the nominal focus height (positive: the corners focus higher).
* **Vignetting**: the illumination is multiplied by ``1 - vignetting * rho2``.

The functions here are the pure pieces :mod:`sffscan.stages.sim.camera` composes; the
calibration (:mod:`sffscan.pipeline.metrology.calibration_fit`) measures the same quantities.
"""

from __future__ import annotations

import math

import cv2
import numpy as np

__all__ = [
    "LANCZOS_REACH_PX",
    "breathing_pad_px",
    "curvature_map_um",
    "radius2_map",
    "scale_about_centre",
    "vignetting_map",
]

LANCZOS_REACH_PX = 4  # cv2.INTER_LANCZOS4 reads 4 px on each side


def radius2_map(shape: tuple[int, int], *, scale: float = 1.0, pad: int = 0) -> np.ndarray:
    """Normalised squared radius from the frame centre, (H + 2 pad, W + 2 pad) float32.

    Parameters
    ----------
    shape : (H, W)
        Frame shape, px; the centre is ``((W - 1) / 2, (H - 1) / 2)`` and the corner has 1.
    scale : float
        Magnification: element (i, j) of a window ``pad`` px larger than the frame on each
        side maps to frame pixel ``centre + (j - pad - cx, i - pad - cy) * scale`` (the
        world grid seen by a frame of magnification ``scale``); 1 = the frame grid.
    pad : int
        Extra px on each side.
    """
    h, w = shape
    cx, cy = (w - 1) / 2.0, (h - 1) / 2.0
    u = (np.arange(w + 2 * pad, dtype=np.float64) - pad - cx) * scale
    v = (np.arange(h + 2 * pad, dtype=np.float64) - pad - cy) * scale
    r2 = (u * u)[None, :] + (v * v)[:, None]
    return (r2 / max(cx * cx + cy * cy, 1e-12)).astype(np.float32)


def curvature_map_um(shape: tuple[int, int], *, field_curvature_um: float, scale: float = 1.0,
                     pad: int = 0) -> np.ndarray:
    """Height of the surface of best focus above the nominal focus, µm, (H+2pad, W+2pad) float32.

    ``field_curvature_um * rho2`` (see :func:`radius2_map` for ``scale`` and ``pad``).
    """
    return radius2_map(shape, scale=scale, pad=pad) * np.float32(field_curvature_um)


def vignetting_map(shape: tuple[int, int], *, vignetting: float) -> np.ndarray:
    """Relative illumination ``1 - vignetting * rho2`` over the frame, (H, W) float32."""
    if not 0.0 <= vignetting < 1.0:
        raise ValueError(f"vignetting must be in [0, 1), got {vignetting}")
    out = radius2_map(shape)
    out *= np.float32(-vignetting)
    out += np.float32(1.0)
    return out


def breathing_pad_px(shape: tuple[int, int], magnification: float) -> int:
    """Extra world px on each side a frame of magnification M needs around the frame grid.

    A frame of magnification ``M < 1`` sees ``(1 / M - 1) * max(W, H) / 2`` px beyond the
    unit grid on each side; the interpolation reads 4 more.
    """
    if not (math.isfinite(magnification) and magnification > 0):
        raise ValueError(f"magnification must be > 0, got {magnification}")
    h, w = shape
    over = max(0.0, 1.0 / magnification - 1.0) * max(w, h) / 2.0
    return int(math.ceil(over)) + LANCZOS_REACH_PX + 1


def scale_about_centre(img: np.ndarray, magnification: float, *, out_shape: tuple[int, int],
                       pad: int = 0, interpolation: int = cv2.INTER_LANCZOS4) -> np.ndarray:
    """Magnify an image about the centre of its central ``out_shape`` window.

    ``out[v, u] = img[pad + cy + (v - cy) / M, pad + cx + (u - cx) / M]`` with
    ``(cx, cy) = ((W - 1) / 2, (H - 1) / 2)`` of ``out_shape = (H, W)``: what a lens of
    magnification M (relative) shows of the unit-magnification image ``img``, which holds
    ``pad`` px of context on each side. ``M = 1 / s`` undoes a magnification ``s``.

    Parameters
    ----------
    img : (H + 2 pad, W + 2 pad) float32 (or any dtype cv2.warpAffine takes)
    magnification : float
        Relative magnification M > 0.
    out_shape : (H, W)
    pad : int
    interpolation : cv2 flag
        Default Lanczos (8 x 8 taps): a band-limited image keeps its sharpness whatever
        the sub-pixel phase, so the focus measure is not modulated by the warp.

    Returns
    -------
    (H, W) array of ``img``'s dtype; pixels mapping outside ``img`` replicate its border.
    """
    h, w = out_shape
    if img.shape[0] != h + 2 * pad or img.shape[1] != w + 2 * pad:
        raise ValueError(f"image of shape {img.shape} is not out_shape {out_shape} + 2 * {pad}")
    if not (math.isfinite(magnification) and magnification > 0):
        raise ValueError(f"magnification must be > 0, got {magnification}")
    cx, cy = (w - 1) / 2.0, (h - 1) / 2.0
    k = 1.0 / magnification
    mat = np.array([[k, 0.0, pad + cx - k * cx], [0.0, k, pad + cy - k * cy]])
    return cv2.warpAffine(img, mat, (w, h), flags=interpolation | cv2.WARP_INVERSE_MAP,
                          borderMode=cv2.BORDER_REPLICATE)
