"""The OpenCV CPU front ends of GLVM and TENV: the torch definitions of :mod:`.toolbox` with
OpenCV's separable filters, on 2-D float32 arrays (no torch).

The scan's CPU path measures every frame here (about 15x faster than the torch
definition on the CPU); the torch definition is the reference, and the two agree to float32
round-off (``tests/stages/test_focus_measure.py``: 1e-6 of the map's largest value against a
float64 reference). Definitions (``box_k`` = mean over k x k with replicated borders,
MATLAB ``imfilter(I, fspecial('average', k), 'replicate')``; images scaled to 0..1):

* GLVM, modified grey-level variance: ``fm = box_k((I - box_k(I))**2)``;
* TENV, Tenengrad variance: ``G = Gx**2 + Gy**2`` of the unnormalised 3 x 3 Sobel
  (replicated borders), ``fm = stdfilt(G, ones(k))**2``, the sample variance of G over
  k x k (1 / (k^2 - 1)) with mirrored borders, as the toolbox computes it.
"""

from __future__ import annotations

import cv2
import numpy as np
from sffscan.stages.operators import check_window

__all__ = ["box_kernel", "check_image", "glvm_cv", "tenv_cv"]

_REPLICATE = cv2.BORDER_REPLICATE
_MIRROR = cv2.BORDER_REFLECT  # MATLAB's 'symmetric': mirrored including the edge pixel


def check_image(image: np.ndarray) -> np.ndarray:
    """A 2-D floating image (scaled to 0..1) as contiguous float32; ValueError otherwise."""
    image = np.asarray(image)
    if image.ndim != 2:
        raise ValueError(f"image must be 2-D (H, W), got shape {image.shape}")
    if not np.issubdtype(image.dtype, np.floating):
        raise ValueError(
            f"image must be floating (scaled to 0..1, see to_unit_float), got dtype {image.dtype}"
        )
    return np.ascontiguousarray(image, dtype=np.float32)


def box_kernel(window: int) -> np.ndarray:
    """The 1-D factor of the k x k mean: ``k`` weights ``1 / k``, float32."""
    return np.full(window, 1.0 / window, np.float32)


def glvm_cv(image: np.ndarray, *, window: int = 9, raw: np.ndarray | None = None,
            max_value: float = 1.0) -> np.ndarray:
    """GLVM with OpenCV: ``mu = box_k(I)``, ``fm = box_k((I - mu)**2)``.

    The local mean is ``cv2.boxFilter``; the second mean is separable (the k weights of
    :func:`box_kernel` down and across, ``cv2.sepFilter2D``); replicated borders. Given the
    raw integer image that ``image`` was scaled from, the local mean is box filtered from
    it instead (OpenCV reads uint8 / uint16 at a half or a quarter of float32's memory
    traffic) and scaled while it is subtracted: what the scan does for every frame, the
    same to float32 round-off.

    Parameters
    ----------
    image : (H, W) ndarray of float
        Image scaled to 0..1 (converted to float32).
    window : int, keyword-only
        Odd window size k >= 3, px. Default 9.
    raw : (H, W) ndarray of uint8 or uint16, optional, keyword-only
        The raw image, ``image == raw / max_value``; contiguous reads fastest.
    max_value : float, keyword-only
        Full scale of ``raw`` (255, 1023, ...); unused without ``raw``.

    Returns
    -------
    (H, W) ndarray of float32
        Focus measure, units of intensity squared.
    """
    window = check_window(window)
    img = check_image(image)
    scale = 1.0
    source = img
    if raw is not None:
        if raw.shape != img.shape:
            raise ValueError(f"raw must have the image's shape {img.shape}, got {raw.shape}")
        source, scale = raw, 1.0 / float(max_value)
    ksize = (window, window)
    mu = cv2.boxFilter(source, cv2.CV_32F, ksize, normalize=True, borderType=_REPLICATE)
    d = cv2.scaleAdd(mu, -scale, img)
    cv2.multiply(d, d, dst=d)
    kernel = box_kernel(window)
    return cv2.sepFilter2D(d, cv2.CV_32F, kernel, kernel, borderType=_REPLICATE)


def tenv_cv(image: np.ndarray, *, window: int = 9) -> np.ndarray:
    """TENV with OpenCV: the sample variance of the Sobel energy over k x k.

    ``cv2.Sobel(ksize=3)`` (unnormalised, replicated borders; its sign is the opposite of
    MATLAB's, which squaring removes), then the sample variance of G from
    ``cv2.sqrBoxFilter`` and ``cv2.boxFilter`` with mirrored borders (MATLAB's
    'symmetric'), times n / (n - 1), clamped at 0.

    Parameters
    ----------
    image : (H, W) ndarray of float
        Image scaled to 0..1 (converted to float32).
    window : int, keyword-only
        Odd window size k >= 3, px. Default 9.

    Returns
    -------
    (H, W) ndarray of float32
        Focus measure, units of intensity^4 (the Sobel gain of 4 per axis is kept).
    """
    window = check_window(window)
    img = check_image(image)
    gx = cv2.Sobel(img, cv2.CV_32F, 1, 0, ksize=3, borderType=_REPLICATE)
    gy = cv2.Sobel(img, cv2.CV_32F, 0, 1, ksize=3, borderType=_REPLICATE)
    g = gx * gx
    g += gy * gy
    ksize = (window, window)
    mean = cv2.boxFilter(g, cv2.CV_32F, ksize, normalize=True, borderType=_MIRROR)
    fm = cv2.sqrBoxFilter(g, cv2.CV_32F, ksize, normalize=True, borderType=_MIRROR)
    np.subtract(fm, mean * mean, out=fm)
    n = window * window
    np.multiply(fm, np.float32(n / (n - 1)), out=fm)
    return np.maximum(fm, 0.0, out=fm)
