"""A sensor pixel's aperture in an aligned stack, and the noise floor it moves.

A pixel integrates the light over its area (a box; 100 % fill factor assumed). Under focus
breathing, frame k shows the world magnified ``s_k`` against the reference frame, so its
pixels are ``1 / s_k`` reference px wide: once resampled onto the reference grid its texture
is attenuated by a box of another width, less for the magnified frames, and a focus measure
favours them (on the synthetic families with 1.2 %/frame breathing, rendered finer and
integrated per pixel: up to 1.11x the depth RMSE of the same stacks without breathing, with
the true transforms; bench/align_families_results.md). :func:`equalise_aperture` gives each
resampled frame the reference pixel's box.

That filter also changes each frame's sensor noise (white in the frame's own pixels) by a
different gain, up to +-16 % in variance for 25 % of breathing: a tilt of the focus curves'
noise floor that moves the peak of every weakly textured pixel toward the frames whose noise
grew (measured: 1.07x -> 1.53x the depth RMSE of the breathing-free stack, on a stack with
heavy noise, tests/stages/fields/test_align_breathing.py). :func:`noise_floor_offsets`
measures, for each frame, what the equalisation adds to a focus measure of white noise, so that
the focus volume can take it off (:func:`stack_noise_floor` for a whole stack, given to
:func:`~sffscan.stages.fields.stationary.reconstruct_field` as ``noise_floor``).
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import cv2
import numpy as np

if TYPE_CHECKING:
    from sffscan.stages.fields.align import Alignment

__all__ = ["APERTURE_TAPS", "aperture_kernel", "equalise_aperture", "noise_floor_offsets",
           "noise_sigma", "stack_noise_floor"]

# Immerkaer's noise kernel (difference of two Laplacians): zero response to any plane,
# sum of squares 36.
_NOISE_KERNEL = np.array([[1, -2, 1], [-2, 4, -2], [1, -2, 1]], np.float64)
APERTURE_TAPS = 8
"""Half-length of :func:`aperture_kernel` (``2 APERTURE_TAPS + 1`` weights): its response is
within 0.2 % of the box ratio up to 0.45 cycles/px for scales 0.887 and 1.127 (+-12 %)."""
NOISE_PATCH_PX = 256
"""Side of the white-noise patch :func:`noise_floor_offsets` warps (its mean is what counts)."""


def aperture_kernel(scale: float, *, taps: int = APERTURE_TAPS) -> np.ndarray:
    """1-D filter that gives a resampled frame the reference pixel's aperture.

    A sensor pixel integrates the light over its area (a box, 100 % fill factor). A frame
    magnified by ``scale`` against the reference (``matrix`` maps reference px to its px with
    this factor) has pixels ``1 / scale`` reference px wide: once resampled onto the
    reference grid, its texture is less attenuated (``scale > 1``) or more (``< 1``) than the
    reference frame's, by the ratio of two box responses, and a focus measure then favours
    the magnified frames. This kernel's response is that ratio,
    ``sinc(f) / sinc(f / scale)`` for ``|f| <= 1/2`` cycles/px (the box of the reference
    pixel over the frame's), sampled on ``2 taps + 1`` px and Lanczos-windowed, sum 1.

    Returns a float64 array of ``2 taps + 1`` weights; ``[1]`` for ``scale == 1`` (the
    reference frame is left exactly as it is).
    """
    if not scale > 0:
        raise ValueError(f"scale must be > 0, got {scale}")
    if scale == 1.0:
        return np.ones(1)
    f = np.linspace(-0.5, 0.5, 4097)
    gain = np.sinc(f) / np.sinc(f / scale)
    n = np.arange(-taps, taps + 1)
    # h[n] = integral of gain(f) cos(2 pi f n) df over one period (gain is even)
    h = np.trapezoid(gain[None, :] * np.cos(2 * np.pi * f[None, :] * n[:, None]), f, axis=1)
    h *= np.sinc(n / (taps + 1))
    return np.asarray(h / h.sum(), dtype=np.float64)


def equalise_aperture(image: np.ndarray, scale_x: float, scale_y: float, *,
                      taps: int = APERTURE_TAPS) -> np.ndarray:
    """A frame already resampled onto the reference grid, given the reference pixel's
    aperture (:func:`aperture_kernel` along each axis; borders replicated).

    ``image``: (H, W) float array; returns a new float64 array of its shape.
    """
    kx = aperture_kernel(scale_x, taps=taps)
    ky = aperture_kernel(scale_y, taps=taps)
    img = np.asarray(image, dtype=np.float64)
    if kx.size == 1 and ky.size == 1:
        return img.copy()
    return np.asarray(cv2.sepFilter2D(img, cv2.CV_64F, kx, ky,
                                      borderType=cv2.BORDER_REPLICATE))


def noise_sigma(image: np.ndarray) -> float:
    """Standard deviation of a frame's white sensor noise, in the image's units.

    Immerkaer's estimator ("Fast noise variance estimation", CVIU 64, 1996: a kernel blind
    to planes, whose response to white noise has variance 36 sigma^2) made robust to texture
    and edges with the median of the absolute response (``1.4826 * median / 6``, a Gaussian's
    sigma from its median absolute deviation).

    ``image``: (H, W) array, H, W >= 3. Returns a float >= 0.
    """
    img = np.asarray(image, dtype=np.float64)
    if img.ndim != 2 or min(img.shape) < 3:
        raise ValueError(f"noise_sigma needs an (H, W) image with H, W >= 3, got {img.shape}")
    r = cv2.filter2D(img, cv2.CV_64F, _NOISE_KERNEL)[1:-1, 1:-1]
    return float(1.4826 * np.median(np.abs(r)) / 6.0)


def noise_floor_offsets(alignment: Alignment, *, sigma: float, operator: str = "glvm",
                        window: int = 9, seed: int = 0) -> np.ndarray:
    """What the aperture equalisation adds to a focus measure of each frame's sensor noise.

    A patch of white noise (``sigma``, the frames' noise in unit-float, from
    :func:`noise_sigma`) is warped as each frame was (its scale about the patch centre),
    with and without :func:`equalise_aperture`; offset k is the difference of the focus
    measure's means over the two. A quadratic focus measure (GLVM, gradient and Laplacian
    energies) of a frame is its texture's plus its noise's: subtracting the offset from level
    k of the focus volume of a stack aligned with ``aperture=True`` gives every level the
    noise floor the resampling alone leaves (the same for every frame, within a few %).

    Parameters
    ----------
    alignment : Alignment
        The transforms the stack was aligned with (:func:`~sffscan.stages.fields.align.
        align_stack`).
    sigma : float, keyword-only
        Sensor noise, unit-float (0..1 full scale), >= 0.
    operator, window : keyword-only
        The focus measure the stack is measured with.
    seed : int, keyword-only
        The noise patch's seed (the same patch for every frame).

    Returns
    -------
    (N,) float64 array, in the focus measure's units; zeros when ``sigma`` is 0.
    """
    from sffscan.stages.fields.resample import warp_frame
    from sffscan.stages.focus_measure import focus_measure

    if not sigma >= 0:
        raise ValueError(f"sigma must be >= 0, got {sigma}")
    n = alignment.matrices.shape[0]
    if sigma == 0:
        return np.zeros(n)
    p = NOISE_PATCH_PX
    noise = np.random.default_rng(seed).normal(0.0, sigma, (p, p))
    c = np.array([(p - 1) / 2.0, (p - 1) / 2.0])
    inner = max(window, 8) + 8  # the warp's and the measure's reach from the patch border
    out = np.empty(n)
    for k, m in enumerate(alignment.matrices):
        a = np.asarray(m, dtype=np.float64)[:, :2]
        centred = np.hstack([a, (c - a @ c)[:, None]])
        pair = np.stack([warp_frame(noise, centred, aperture=ap) for ap in (True, False)])
        vol = focus_measure(pair.astype(np.float32), operator=operator, window=window)
        means = np.asarray(vol[:, inner:-inner, inner:-inner], np.float64).mean(axis=(1, 2))
        out[k] = means[0] - means[1]
    return out


def stack_noise_floor(stack: np.ndarray, alignment: Alignment, *, operator: str = "glvm",
                      window: int = 9, max_value: float | None = None) -> tuple[np.ndarray, float]:
    """:func:`noise_floor_offsets` of a stack as taken (before alignment): its sensor noise
    is the median of its frames' :func:`noise_sigma`, in unit-float (``max_value`` as in
    :func:`~sffscan.stages.fields.stationary.reconstruct_field`).

    Returns the (N,) offsets and the noise sigma (unit-float).
    """
    from sffscan.stages.fields.stationary import default_max_value

    st = np.asarray(stack)
    full = float(max_value) if max_value is not None else default_max_value(st.dtype)
    sigma = float(np.median([noise_sigma(f) for f in st])) / full
    return noise_floor_offsets(alignment, sigma=sigma, operator=operator, window=window), sigma
