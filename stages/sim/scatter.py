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
from collections.abc import Callable

import cv2
import numpy as np

__all__ = ["scatter_blur", "scatter_levels"]


def scatter_levels(tex: np.ndarray, lower: np.ndarray, weight: np.ndarray,
                   blur: Callable[[np.ndarray, int], np.ndarray], *,
                   dtype: type[np.floating] = np.float32) -> np.ndarray:
    """The sum over a blur bank's levels of ``blur(share, level)``, ``share`` the texture's
    part at that level: each point's weight ``1 - weight`` at its ``lower`` level and
    ``weight`` at the next (summing to 1). One home for the families' scatter
    (:func:`sffscan.stages.sim.families.family_stack`) and the camera's (:func:`scatter_blur`).

    Parameters
    ----------
    tex : (H, W) ndarray of float32
    lower : (H, W) ndarray of int
        Each point's lower bank level.
    weight : (H, W) ndarray of float
        The next level's weight, 0..1.
    blur : callable
        ``blur(image float32, level)``: the image blurred by the bank's level.
    dtype : keyword-only
        The sum's dtype.
    """
    out = np.zeros(tex.shape, dtype)
    for level in range(int(lower.min()), int(lower.max()) + 2):
        share = np.where(lower == level, 1.0 - weight, 0.0) + np.where(lower == level - 1,
                                                                       weight, 0.0)
        if share.any():
            out += blur((tex * share).astype(np.float32), level)
    return out


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

    def blurred(src: np.ndarray, level: int) -> np.ndarray:
        s = float(bank[level])
        d = _factor(s)
        if s == 0:
            return src
        if d == 1:
            return _gauss(src, s)
        # as the bank's large sigmas: on an area-downsampled copy, upsampled
        small = cv2.resize(src, (we // d, he // d), interpolation=cv2.INTER_AREA)
        s_small = math.sqrt(s * s - (d * d - 1) / 12.0 - _upsample_variance(d)) / d
        return cv2.resize(_gauss(small, s_small), (we, he), interpolation=cv2.INTER_LINEAR)

    out = scatter_levels(tex, lo, (u - lo).astype(np.float32), blurred)
    return np.ascontiguousarray(out[margin:margin + h, margin:margin + w])
