"""The whole-curve centroid's departure from its curve's phase
(``curve_shape.centroid_departure``): known answers on curves built from a peak and a
floor, and the uncertainty that carries it."""

from __future__ import annotations

import numpy as np
from sffscan.stages.curve_shape import centroid_departure
from sffscan.stages.depth import depth_from_focus, focus_sums
from sffscan.stages.depth_uncertainty import height_uncertainty_um

N = 40
LEVELS = np.arange(N, dtype=np.float64)


def _curves(peaks: list[float], floors: list[float], sigma: float = 2.0) -> np.ndarray:
    """(N, len(floors), len(peaks)) float32: a Gaussian peak (height 1) on each floor."""
    g = np.exp(-0.5 * ((LEVELS[:, None] - np.asarray(peaks)[None]) / sigma) ** 2)
    return (g[:, None, :] + np.asarray(floors)[None, :, None]).astype(np.float32)


def _departure(vol: np.ndarray, depth: np.ndarray) -> np.ndarray:
    sums = focus_sums(vol)
    return centroid_departure(depth, sums[1], sums[2], vol.shape[0])


def test_the_departure_is_the_floor_s_pull_on_even_curves() -> None:
    """On a Gaussian peak (even, away from the ends) the phase is the peak whatever the
    floor: the departure is the centroid's error, which grows with the floor; without a
    floor, none."""
    peaks = [8.0, 12.5, 19.5, 27.0, 31.0]
    floors = [0.0, 0.01, 0.05, 0.2]
    vol = _curves(peaks, floors)
    c = depth_from_focus(vol, method="centroid")[0]
    dep = _departure(vol, c)
    assert dep.dtype == np.float32 and dep.shape == c.shape
    np.testing.assert_allclose(dep, np.abs(c - np.asarray(peaks)[None]), atol=2e-3)
    np.testing.assert_allclose(dep[0], 0.0, atol=2e-3)
    assert (np.diff(dep[:, [0, 1, 3, 4]], axis=0) > 0.1).all()  # more floor, more pull
    np.testing.assert_allclose(dep[:, 2], 0.0, atol=2e-3)  # 19.5: the middle, no pull


def test_the_departure_is_measured_on_the_circle_of_levels() -> None:
    """A peak at an end, the phase across it (N - 0.3 for -0.3): the distance the short way
    round, at most N / 2; a missing depth departs by nothing."""
    re = np.array([[np.cos(2 * np.pi * 0.3 / N), 1.0]], np.float32)  # phase -0.3 levels
    im = np.array([[np.sin(2 * np.pi * 0.3 / N), 0.0]], np.float32)
    c = np.array([[1.2, np.nan]], np.float32)
    dep = centroid_departure(c, re, im, N)
    np.testing.assert_allclose(dep, [[1.5, 0.0]], atol=1e-4)
    far = centroid_departure(np.array([[N / 2 - 0.3]], np.float32), re[:, :1], im[:, :1], N)
    assert float(far[0, 0]) == np.float32(N / 2)


def test_the_centroid_uncertainty_holds_its_departure() -> None:
    """``height_uncertainty_um`` of the centroid adds the departure in quadrature: at least
    the departure (µm) and, on these curves, twice it covers every error; other methods
    do not add it."""
    peaks = [8.0, 12.5, 27.0, 31.0]
    vol = np.repeat(np.repeat(_curves(peaks, [0.1]), 12, axis=1), 3, axis=2)
    c = depth_from_focus(vol, method="centroid")[0]
    step = 25.0
    kw = {"n_levels": N, "focus_heights_um": step * LEVELS, "window": 3}
    sums, low = focus_sums(vol), vol.min(axis=0)
    u = height_uncertainty_um(c, sums, low, method="centroid", **kw)
    dep = _departure(vol, c)
    err = np.abs(c - np.repeat(peaks, 3)[None, :])
    assert (err > 1.0).all()  # the floor pulls every curve by more than a level
    assert (u >= step * dep - 1e-3).all()
    assert (err <= 2.0 * u / step).all()
    other = height_uncertainty_um(c, sums, low, method="argmax", **kw)
    assert (other < step * dep).any()
