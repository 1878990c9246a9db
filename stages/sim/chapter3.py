"""The thesis' chapter-3 simulation: a stationary stack with a known surface.

60 images of 300 x 300 px, focus levels 100 µm apart, a sinusoidal surface with a fine
(1-2 px) texture, like the texture image of the thesis' simulation tool, and Gaussian noise
of a given variance added to the images in 0..1 (the thesis: 0.005). Used by
``sffscan study --chapter3`` and by the tests of the depth methods.
"""

from __future__ import annotations

import dataclasses

import numpy as np
from sffscan.stages.sim.camera import Optics, render_stack
from sffscan.stages.sim.world import sinusoid_world

N_LEVELS, SIZE_PX, STEP_UM = 60, 300, 100.0


def chapter3_stack(*, noise: float = 0.0, seed: int = 5
                   ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The chapter-3 stack, its focus table and its true surface.

    Parameters
    ----------
    noise : float, keyword-only
        Variance of the Gaussian noise added to the 0..1 images; 0 = none.
    seed : int, keyword-only
        Seed of the noise.

    Returns
    -------
    images : (60, 300, 300) ndarray of float32
        The stack, 0..1 (plus noise).
    heights_um : (60,) ndarray of float64
        Height in focus at each level, µm (0, 100, ... 5900).
    truth_um : (300, 300) ndarray of float32
        The true surface height, µm.
    """
    optics = Optics(width=SIZE_PX, height=SIZE_PX, pixel_um=8.5, noise_sigma=0.0,
                    bit_depth=10)
    heights = np.arange(N_LEVELS) * STEP_UM
    world = dataclasses.replace(
        sinusoid_world(seed=3, pixel_um=8.5, amplitude_um=0.35 * heights[-1], period_px=150.0,
                       offset_um=0.5 * heights[-1]), texture_scales_px=(1.0, 2.0))
    images = render_stack(world, x0=0.0, y0=0.0, focus_heights_um=heights, optics=optics,
                          rng=None).astype(np.float32) / 1023.0
    if noise > 0:
        images = with_noise(images, variance=noise, seed=seed)
    return images, heights, world.height_um(0.0, 0.0, SIZE_PX, SIZE_PX)


def with_noise(images: np.ndarray, *, variance: float, seed: int = 5) -> np.ndarray:
    """``images`` plus Gaussian noise of ``variance`` (float32, the same shape), from a
    generator seeded with ``seed``."""
    rng = np.random.default_rng(seed)
    return images + rng.normal(0.0, np.sqrt(variance), images.shape).astype(np.float32)
