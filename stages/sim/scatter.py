"""The simulated camera's blur with the light scattered from each world point
(``Optics.blur_model = "scatter"``), beside :mod:`sffscan.stages.sim.camera`'s gathered one.

:func:`sffscan.stages.sim.camera._blur` gathers: each image pixel takes the texture blurred
by the sigma of its own height (the bank level bracketing it). Optics image a surface without
occlusion the other way: each world point spreads its light over its own circle of
confusion, so a defocused neighbour's light spills over a focused pixel and the light is
conserved. Here each bank level blurs the texture's *share* at that level (the same
interpolation weights, linear in the bank coordinate, summing to 1 at every point) and the
levels are summed; the world points of the texture's margin take part with their own
heights. Slower than gathering (one blur of a weighted texture per bank level in use).
"""

from __future__ import annotations

import math

import cv2
import numpy as np

__all__ = ["scatter_blur"]


def scatter_blur(tex: np.ndarray, sigma_ext: np.ndarray, margin: int,
                 shape: tuple[int, int], bank: np.ndarray) -> np.ndarray:
    """The frame's reflectance with each texture point's light spread by its own blur.

    Parameters
    ----------
    tex : (He, We) ndarray of float32
        The texture window, ``margin`` px beyond the frame on the left and top (He, We
        divisible by 8).
    sigma_ext : (He, We) ndarray of float32
        Each texture point's PSF sigma, px (the camera's law at its height).
    margin : int
        Px of the window before the frame's first row and column.
    shape : (int, int)
        The frame's (H, W).
    bank : (L,) ndarray of float
        The bank's sigmas (:func:`sffscan.stages.sim.camera.blur_bank_sigmas`).

    Returns
    -------
    (H, W) ndarray of float32
    """
    from sffscan.stages.sim.camera import _factor, _gauss, _level_coordinate, _upsample_variance

    h, w = shape
    he, we = tex.shape
    u = np.clip(_level_coordinate(sigma_ext), 0.0, np.float32(len(bank) - 1))
    lo = np.minimum(np.floor(u).astype(np.intp), len(bank) - 2)
    t = (u - lo).astype(np.float32)
    out = np.zeros((he, we), np.float32)
    for level in range(int(lo.min()), int(lo.max()) + 2):
        share = np.where(lo == level, 1.0 - t, 0.0) + np.where(lo == level - 1, t, 0.0)
        if not share.any():
            continue
        src = (tex * share).astype(np.float32)
        s = float(bank[level])
        d = _factor(s)
        if s == 0:
            out += src
        elif d == 1:
            out += _gauss(src, s)
        else:  # as the bank's large sigmas: on an area-downsampled copy, upsampled
            small = cv2.resize(src, (we // d, he // d), interpolation=cv2.INTER_AREA)
            s_small = math.sqrt(s * s - (d * d - 1) / 12.0 - _upsample_variance(d)) / d
            out += cv2.resize(_gauss(small, s_small), (we, he), interpolation=cv2.INTER_LINEAR)
    return np.ascontiguousarray(out[margin:margin + h, margin:margin + w])
