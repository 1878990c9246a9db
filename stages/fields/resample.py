"""Band-limited resampling of a frame by a scale and shift (no rotation): a separable
windowed sinc; :func:`warp_frame`, any affine map onto the reference grid.

Why not :func:`cv2.warpAffine` with ``INTER_LANCZOS4`` for focus breathing: an 8-tap kernel
attenuates a frame's finest texture by an amount that depends on the sub-pixel phase of
each output pixel, and a frame magnified by ``s`` runs through every phase (a moiré of
period ``1 / |s - 1|`` px). The reference frame of an aligned stack is not resampled at
all, so after alignment it is the sharpest frame of the stack: a focus measure then pulls
heights toward its level (measured on the synthetic families with 1.2 %/frame breathing,
:func:`sffscan.stages.sim.families.family_stack`: up to 1.20 x the RMSE of the same stack
without breathing with the true transforms, the alignment's estimate being right to 0.1 %;
docs/depth-study.md). A Lanczos kernel of :data:`TAPS` lobes on each side keeps the passband
flat almost to the Nyquist frequency, so that every frame keeps its texture.

A scale-and-shift map is separable (``x' = s_x x + t_x``, ``y' = s_y y + t_y``): two sparse
1-D resampling matrices, one per axis, each row ``2 TAPS`` weights (borders replicated).
"""

from __future__ import annotations

import math

import cv2
import numpy as np
import scipy.sparse
from sffscan.stages.fields.aperture import equalise_aperture

__all__ = ["TAPS", "is_separable", "resample_matrix", "scale_warp", "warp_frame"]

TAPS = 8
"""Lobes of the Lanczos (windowed sinc) kernel on each side: 16 weights per output pixel
and axis; pixels within ``TAPS`` px of the frame's border see its replicated edge."""


def is_separable(matrix: np.ndarray, *, tol: float = 1e-12) -> bool:
    """Whether an affine (2, 3) map has no rotation or shear (a scale and shift per axis)."""
    m = np.asarray(matrix, dtype=np.float64)
    return abs(float(m[0, 1])) <= tol and abs(float(m[1, 0])) <= tol


def resample_matrix(n_out: int, n_in: int, scale: float, shift: float, *, taps: int = TAPS
                    ) -> scipy.sparse.csr_matrix:
    """Sparse (n_out, n_in) matrix ``R`` with ``(R f)[i] = f(scale * i + shift)``.

    Lanczos-``taps`` weights, normalised to sum 1 per row (a constant stays constant), input
    indices outside ``0 .. n_in - 1`` clamped (replicated border). An integer position gets
    the single weight 1: an identity map is exact.
    """
    x = scale * np.arange(n_out, dtype=np.float64) + shift
    base = np.floor(x).astype(np.intp)
    offs = np.arange(-taps + 1, taps + 1)
    idx = base[:, None] + offs[None, :]
    d = x[:, None] - idx
    w = np.sinc(d) * np.sinc(d / taps)
    w[np.abs(d) >= taps] = 0.0
    w /= w.sum(axis=1, keepdims=True)
    rows = np.repeat(np.arange(n_out), offs.size)
    cols = np.clip(idx, 0, n_in - 1).ravel()
    return scipy.sparse.csr_matrix((w.ravel(), (rows, cols)), shape=(n_out, n_in))


def scale_warp(image: np.ndarray, matrix: np.ndarray, *, taps: int = TAPS,
               aperture: bool = False) -> np.ndarray:
    """``out(x, y) = image(matrix [x, y, 1])`` for a map without rotation or shear.

    Parameters
    ----------
    image : (H, W) array of uint8, uint16 or float
    matrix : (2, 3) array_like
        Output px -> image px; ``matrix[0, 1] == matrix[1, 0] == 0``.
    taps : int, keyword-only
        Kernel lobes per side.
    aperture : bool, keyword-only
        Also give the result the reference pixel's aperture
        (:func:`~sffscan.stages.fields.aperture.equalise_aperture`).

    Returns
    -------
    (H, W) array of ``image``'s dtype, clipped to the image's own range (the sinc's ringing
    must not push a 10-bit frame past its full scale; integers rounded).

    Raises
    ------
    ValueError
        If the map rotates or shears.
    """
    img = np.asarray(image)
    m = np.asarray(matrix, dtype=np.float64)
    if not is_separable(m):
        raise ValueError(f"scale_warp needs a map without rotation or shear, got {m.tolist()}")
    h, w = img.shape
    rx = resample_matrix(w, w, m[0, 0], m[0, 2], taps=taps)
    ry = resample_matrix(h, h, m[1, 1], m[1, 2], taps=taps)
    out = np.asarray(ry @ (rx @ img.astype(np.float64).T).T)
    if aperture:
        out = equalise_aperture(out, float(m[0, 0]), float(m[1, 1]))
    lo, hi = float(img.min()), float(img.max())
    np.clip(out, lo, hi, out=out)
    if np.issubdtype(img.dtype, np.integer):
        np.rint(out, out=out)
    return out.astype(img.dtype)


def warp_frame(image: np.ndarray, matrix: np.ndarray, *, aperture: bool = True) -> np.ndarray:
    """Frame resampled onto the reference grid: ``out(x) = image(matrix [x, 1])``.

    :func:`scale_warp` for a scale and shift, else OpenCV's Lanczos; with ``aperture``, given
    the reference pixel's aperture (:mod:`~sffscan.stages.fields.aperture`; for a rotation
    or shear, with the magnification ``sqrt |det|``). Returns an array of ``image``'s shape
    and dtype, clipped to the frame's own range (the kernel's ringing must not push a 10-bit
    frame past its full scale); pixels mapping outside the frame replicate its border
    (:func:`~sffscan.stages.fields.align.align_stack` reports them as not valid).
    """
    if is_separable(matrix):
        return scale_warp(image, matrix, aperture=aperture)
    img = np.asarray(image)
    h, w = img.shape
    m = np.asarray(matrix, dtype=np.float64)
    out = cv2.warpAffine(img.astype(np.float64), m, (w, h),
                         flags=cv2.INTER_LANCZOS4 | cv2.WARP_INVERSE_MAP,
                         borderMode=cv2.BORDER_REPLICATE)
    if aperture:
        s = math.sqrt(abs(float(np.linalg.det(m[:, :2]))))
        out = equalise_aperture(out, s, s)
    np.clip(out, float(img.min()), float(img.max()), out=out)
    if np.issubdtype(img.dtype, np.integer):
        np.rint(out, out=out)
    return out.astype(img.dtype)
