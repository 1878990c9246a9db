"""One pair of frames of a focus stack: its ECC transform, reduced to a motion model, and
for the ``"scale"`` model its step with a variance (:mod:`sffscan.stages.fields.align`
chains the pairs and warps the frames).
"""

from __future__ import annotations

import math
from typing import Literal

import cv2
import numpy as np

__all__ = ["ECC_EPS", "ECC_ITERATIONS", "Model", "REGISTRATION_LOWPASS_PX",
           "REGISTRATION_WINDOW_PX", "coverage", "homogeneous", "invert_step", "pair_transform",
           "reduce_to_model", "registration_frame", "scale_step", "to_float"]

Model = Literal["scale", "similarity", "affine"]
ECC_ITERATIONS = 200
ECC_EPS = 1e-7
#: :func:`registration_frame`'s low-pass, a Gaussian's sigma, px
REGISTRATION_LOWPASS_PX = 2.0
#: :func:`registration_frame`'s window for the local mean and contrast, a Gaussian's sigma, px
REGISTRATION_WINDOW_PX = 16.0


def to_float(img: np.ndarray) -> np.ndarray:
    """A 2-D frame as float32 scaled to a maximum of 1 (ValueError for other shapes)."""
    a = np.asarray(img)
    if a.ndim != 2:
        raise ValueError(f"frames must be 2-D grey images, got shape {a.shape}")
    out = a.astype(np.float32)
    top = float(out.max()) if out.size else 0.0
    if top > 0:
        out *= np.float32(1.0 / top)
    return out


def registration_frame(img: np.ndarray, *, lowpass_px: float = REGISTRATION_LOWPASS_PX,
                       window_px: float = REGISTRATION_WINDOW_PX) -> np.ndarray:
    """What a focus stack's pair is registered on instead of the frames as taken: the frame
    low-passed, less its mean, divided by its local contrast.

    Where a part is tilted (or stepped), the band in focus moves across the frame from one
    focus level to the next, and with it the contrast of the texture: a frame is its
    texture times an envelope of sharpness. ECC's correlation of two such frames holds the
    product of the texture's correlation and the envelopes', so its peak is pulled toward
    the envelope's motion, the wider the texture's grain the more: a steady drift of ~0.2-0.5
    px a frame on the study's coarse-textured slopes with no breathing at all, which the
    chained transforms turn into pixels of misregistration. Dividing by the local contrast
    (the high-passed frame's RMS over a window wider than the grain, narrower than the
    envelope) flattens the envelope; the low-pass keeps the frequencies that adjacent levels
    blur least differently. The contrast is not taken below the frame's median, so flat,
    defocused regions are not raised to the noise's full contrast. The frame itself is not
    high-passed: a high-pass of a fixed width in px is not scale-covariant, and on frames
    blurred to its width it biased the breathing's scale (the plate of
    ``tests/stages/fields/test_align.py``: 0.07 % -> 1.1 % at 16 px, 0.16 % at 64 px).

    Measured (docs/depth-method-log.md, "Registration on the local contrast"), aligned /
    breathing-free twin with the default depth method: on fresh seeds 213..215 of the twenty
    families, stacks over the 1.10x alignment bar 7 -> 6 of 60 (mean 1.027 -> 1.019); on
    seeds 204..209, which it was chosen on, 10 -> 7 of 120; the plate's scale error 0.074 %
    -> 0.053 %.

    Parameters
    ----------
    img : (H, W) array of any real dtype
    lowpass_px, window_px : float, keyword-only
        Gaussian sigmas of the low-pass and of the local contrast, px.

    Returns
    -------
    (H, W) ndarray of float32; the same for the frame times a gain plus an offset.
    """
    f = to_float(img)
    if lowpass_px > 0:
        f = cv2.GaussianBlur(f, (0, 0), lowpass_px, borderType=cv2.BORDER_REFLECT_101)
    high = f - cv2.GaussianBlur(f, (0, 0), window_px, borderType=cv2.BORDER_REFLECT)
    local = np.sqrt(np.maximum(cv2.GaussianBlur(high * high, (0, 0), window_px,
                                                borderType=cv2.BORDER_REFLECT), 0.0))
    floor = np.float32(float(np.median(local)) + 1e-6)  # frames scaled to a maximum of 1
    return np.asarray((f - np.float32(f.mean())) / np.maximum(local, floor), dtype=np.float32)


def homogeneous(m: np.ndarray) -> np.ndarray:
    """A (2, 3) affine matrix as (3, 3)."""
    return np.vstack([m, [0.0, 0.0, 1.0]])


def pair_transform(template: np.ndarray, image: np.ndarray, *, init: np.ndarray | None = None,
                   levels: int | None = None, gauss_size: int = 5) -> tuple[np.ndarray, float]:
    """Affine transform ``A`` with ``image(A [x, y, 1]) ~ template(x, y)`` (ECC, coarse to fine).

    Parameters
    ----------
    template, image : (H, W) arrays of the same shape (any real dtype)
    init : (2, 3) float, optional
        Starting transform at full resolution; default the identity.
    levels : int, optional
        Pyramid levels (halvings); default so that the coarsest image is about 128 px.
    gauss_size : int
        ECC's Gaussian pre-filter size (odd px), applied to both images at every level.

    Returns
    -------
    A : (2, 3) float64
    correlation : float
        ECC's correlation coefficient at full resolution.

    Raises ValueError when ECC does not converge (featureless or unrelated images).
    """
    t, im = to_float(template), to_float(image)
    if t.shape != im.shape:
        raise ValueError(f"images differ in shape: {t.shape} and {im.shape}")
    if levels is None:
        levels = max(0, int(math.floor(math.log2(min(t.shape) / 128.0))))
    pyr_t, pyr_i = [t], [im]
    for _ in range(levels):
        pyr_t.append(cv2.pyrDown(pyr_t[-1]))
        pyr_i.append(cv2.pyrDown(pyr_i[-1]))
    warp = (np.eye(2, 3) if init is None else np.asarray(init, dtype=np.float64)).copy()
    warp = warp.astype(np.float32)
    f = 2.0 ** levels
    warp[:, 2] /= f
    crit = (cv2.TERM_CRITERIA_EPS | cv2.TERM_CRITERIA_COUNT, ECC_ITERATIONS, ECC_EPS)
    rho = 0.0
    for lev in range(levels, -1, -1):
        try:
            # the stubs lack the (mask None, gaussFiltSize) overload the library has
            rho, warp = cv2.findTransformECC(  # type: ignore[call-overload]
                pyr_t[lev], pyr_i[lev], warp, cv2.MOTION_AFFINE, crit, None, gauss_size)
        except cv2.error as err:
            raise ValueError(f"ECC alignment did not converge at pyramid level {lev}: "
                             f"{str(err).strip().splitlines()[-1]}") from None
        if lev > 0:
            warp[:, 2] *= 2.0
    return warp.astype(np.float64), float(rho)


def reduce_to_model(a: np.ndarray, shape: tuple[int, int], model: Model
            ) -> tuple[np.ndarray, float, np.ndarray, float]:
    """Project an affine transform onto the model, about the frame centre."""
    h, w = shape
    c = np.array([(w - 1) / 2.0, (h - 1) / 2.0])
    lin = a[:, :2]
    shift = lin @ c + a[:, 2] - c  # where the centre goes, minus the centre
    if model == "affine":
        s = math.sqrt(abs(float(np.linalg.det(lin))))
        rot = math.degrees(math.atan2(lin[1, 0] - lin[0, 1], lin[0, 0] + lin[1, 1]))
        m = a.copy()
    else:
        # closest similarity (least squares): [[p, -q], [q, p]]
        p = 0.5 * (lin[0, 0] + lin[1, 1])
        q = 0.5 * (lin[1, 0] - lin[0, 1])
        if model == "scale":
            q = 0.0
        new = np.array([[p, -q], [q, p]])
        s = math.hypot(p, q)
        rot = math.degrees(math.atan2(q, p))
        m = np.hstack([new, (c + shift - new @ c)[:, None]])
    # a reference point d px from the centre appears s * d px from it in the frame: s is the
    # frame's magnification relative to the reference
    return m, s, shift, rot


def scale_step(template: np.ndarray, image: np.ndarray, a: np.ndarray
                ) -> tuple[np.ndarray, np.ndarray]:
    """A pair's ``(log s, shift x, shift y)`` about the frame centre (:func:`reduce_to_model`) and
    each one's variance (Cramér-Rao: the residual variance times its correlation area, over
    the sum of the frames' shared squared derivatives along the parameter)."""
    t, im = to_float(template), to_float(image)
    h, w = t.shape
    m, s, shift, _ = reduce_to_model(a, (h, w), "scale")
    t = cv2.GaussianBlur(t, (5, 5), 0)
    wi = cv2.warpAffine(cv2.GaussianBlur(im, (5, 5), 0), m, (w, h),
                        flags=cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP)
    ok = coverage(m, (h, w), 2.0)
    ok[:2], ok[-2:], ok[:, :2], ok[:, -2:] = False, False, False, False
    if ok.sum() < 64:
        return np.array([math.log(s), *shift]), np.full(3, np.inf)
    tv, wv = t[ok].astype(np.float64), wi[ok].astype(np.float64)
    # the photometric fit ECC makes implicitly: least squares wv ~ gain tv + offset, in
    # closed form (np.polyfit's Vandermonde lstsq took 0.3 s a 2048 x 1536 pair)
    tm, wm = float(tv.mean()), float(wv.mean())
    dt = tv - tm
    gain = float(np.dot(dt, wv - wm)) / max(float(np.dot(dt, dt)), 1e-300)
    offset = wm - gain * tm
    res = np.zeros((h, w))
    res[ok] = wv - (gain * tv + offset)
    var_r = float(np.mean(res[ok] ** 2))
    # correlation of the residual between neighbours: its correlation area (Gaussian model)
    r1 = float(np.sum(res[:, 1:] * res[:, :-1]) / max(np.sum(res[:, 1:] ** 2), 1e-30))
    r1 = min(max(r1, 0.01), 0.99)
    area = max(1.0, 4.0 * math.pi * (-1.0 / (4.0 * math.log(r1))))
    # the derivatives of both frames multiplied: their noise is independent, so the sums
    # hold the structure the frames share, not the noise (a blurred, noisy pair tells little)
    # pixel coordinates about the centre, broadcast (a row and a column, not two planes)
    xx = np.arange(w, dtype=np.float64)[None, :] - (w - 1) / 2.0
    yy = np.arange(h, dtype=np.float64)[:, None] - (h - 1) / 2.0
    d = []
    for img in (t, wi):
        gx = cv2.Sobel(img, cv2.CV_64F, 1, 0, ksize=3) / 8.0
        gy = cv2.Sobel(img, cv2.CV_64F, 0, 1, ksize=3) / 8.0
        d.append((gx * xx + gy * yy, gx, gy))
    info = gain * np.array([max(0.0, float(np.sum((a * b)[ok])))
                            for a, b in zip(*d, strict=True)])
    var = np.where(info > 0, var_r * area / np.maximum(info, 1e-300), np.inf)
    return np.array([math.log(s), *shift]), var


def invert_step(step: np.ndarray) -> np.ndarray:
    """The inverse of a scale step: ``x' = c + s (x - c) + t`` -> ``x = c + (x' - c - t) / s``."""
    s = math.exp(step[0])
    return np.array([-step[0], -step[1] / s, -step[2] / s])


def coverage(matrix: np.ndarray, shape: tuple[int, int], inset: float) -> np.ndarray:
    """(H, W) bool: the reference pixels that ``matrix`` (reference px -> frame px) maps
    into the frame, at least ``inset`` px inside its edges."""
    h, w = shape
    xx = np.arange(w, dtype=np.float64)[None, :]  # broadcast: the same values, no planes
    yy = np.arange(h, dtype=np.float64)[:, None]
    x = matrix[0, 0] * xx + matrix[0, 1] * yy + matrix[0, 2]
    y = matrix[1, 0] * xx + matrix[1, 1] * yy + matrix[1, 2]
    return (x >= inset) & (x <= w - 1 - inset) & (y >= inset) & (y <= h - 1 - inset)
