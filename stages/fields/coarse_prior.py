"""Two-step scanning: a coarse height map bounds the focus levels to acquire and process.

A coarse prior (a laser-line scan, a height map rendered from the CAD model, or the
previous layer's mosaic) gives, for each field, the range of heights it can hold; only the
focus levels inside that range plus a margin (the coarse method's uncertainty) and a few
pad levels (so that every focus curve keeps its peak and flanks inside the acquired set)
are acquired and processed (SFF_NOTES.md section 5: 43 % fewer images in the thesis).

* :class:`CoarsePrior` -- a coarse height map on a grid of world pixels, with its uncertainty.
* :func:`level_range` -- focus levels covering a height interval, margin and pad included.
* :func:`field_levels` -- the levels to acquire for one stationary field.
* :func:`reconstruct_levels` -- height of a field from the frames of a subset of levels
  (``stages.focus_measure`` and ``stages.depth``; curves are the acquired levels only).
* The scan's side (the staircase a continuous scan can run, the configuration that runs it,
  the previous layer's mosaic as the prior: ``sffscan restrict``) is
  :mod:`sffscan.pipeline.restrict`.

Missing prior data (NaN) is never guessed: a field that touches it gets the full range.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from sffscan.stages.depth import depth_from_focus, levels_to_height
from sffscan.stages.focus_measure import focus_measure, to_unit_float
from sffscan.stages.sim.camera import Optics
from sffscan.stages.sim.world import PlateWorld

__all__ = [
    "CoarsePrior",
    "field_levels",
    "level_range",
    "reconstruct_levels",
    "simulated_prior",
    "TwoStepResult",
    "two_step_fields",
]


@dataclass(frozen=True)
class CoarsePrior:
    """A coarse height map over the world.

    Parameters
    ----------
    heights_um : (R, C) float array
        Coarse heights, µm; NaN where the coarse method has nothing.
    origin_px : (x, y)
        World pixel of element [0, 0]'s centre.
    step_px : float
        World pixels between grid elements (> 0); element [r, c] stands for world pixel
        ``origin + (c, r) * step``, i.e. the cell ``+- step / 2`` around it.
    uncertainty_um : float
        The coarse method's uncertainty, µm (>= 0): the margin added to every range.
    """

    heights_um: np.ndarray
    origin_px: tuple[float, float] = (0.0, 0.0)
    step_px: float = 1.0
    uncertainty_um: float = 0.0

    def __post_init__(self) -> None:
        h = np.asarray(self.heights_um, dtype=np.float32)
        if h.ndim != 2 or h.size == 0:
            raise ValueError(f"prior.heights_um must be a non-empty 2-D map, got {h.shape}")
        if not (math.isfinite(self.step_px) and self.step_px > 0):
            raise ValueError(f"prior.step_px must be > 0, got {self.step_px}")
        if not (math.isfinite(self.uncertainty_um) and self.uncertainty_um >= 0):
            raise ValueError(f"prior.uncertainty_um must be >= 0, got {self.uncertainty_um}")
        object.__setattr__(self, "heights_um", h)

    def range_um(self, x0: float, y0: float, x1: float, y1: float) -> tuple[float, float] | None:
        """(lowest, highest) prior height over the world px box [x0, x1) x [y0, y1).

        Every grid cell that overlaps the box counts. None when the box reaches outside
        the map or touches a NaN cell: the prior does not know that field.
        """
        ox, oy = self.origin_px
        s = self.step_px
        c0 = math.floor((x0 - ox) / s + 0.5)
        c1 = math.ceil((x1 - 1 - ox) / s - 0.5)
        r0 = math.floor((y0 - oy) / s + 0.5)
        r1 = math.ceil((y1 - 1 - oy) / s - 0.5)
        rows, cols = self.heights_um.shape
        if c0 < 0 or r0 < 0 or c1 >= cols or r1 >= rows or c1 < c0 or r1 < r0:
            return None
        cell = self.heights_um[r0:r1 + 1, c0:c1 + 1]
        if not np.isfinite(cell).all():
            return None
        return float(cell.min()), float(cell.max())


def level_range(z_lo_um: float, z_hi_um: float, *, focus_heights_um: np.ndarray,
                margin_um: float, pad_levels: int = 8) -> np.ndarray:
    """Indices of the focus levels covering ``[z_lo - margin, z_hi + margin]``, padded.

    Parameters
    ----------
    z_lo_um, z_hi_um : float
        Height interval the field holds, µm.
    focus_heights_um : (N,) array_like of float
        Heights in focus at the levels, strictly increasing, µm.
    margin_um : float, keyword-only
        Added on both sides (the coarse method's uncertainty), µm.
    pad_levels : int, keyword-only
        Levels added beyond the interval on each side, so that a surface at either end
        still has its focus peak with flanks inside the acquired set (>= 1). Default 8:
        the phase methods (PC, SPC) use the whole curve, and on a smooth surface their
        RMSE from a subset is within 2 % of the full range's with 8 pad levels (+10 % with
        5, +35 % with 3); local methods (gauss3, argmax) need only 1-2.

    Returns
    -------
    (M,) int ndarray of consecutive level indices, M >= 3, clipped to 0..N-1.
    """
    z = np.asarray(focus_heights_um, dtype=np.float64).reshape(-1)
    if z.size < 3 or not (np.diff(z) > 0).all():
        raise ValueError("focus_heights_um must hold >= 3 strictly increasing heights")
    if not (math.isfinite(z_lo_um) and math.isfinite(z_hi_um) and z_hi_um >= z_lo_um):
        raise ValueError(f"need finite z_lo_um <= z_hi_um, got {z_lo_um}, {z_hi_um}")
    if not margin_um >= 0 or pad_levels < 1:
        raise ValueError(f"margin_um must be >= 0 and pad_levels >= 1, got "
                         f"{margin_um}, {pad_levels}")
    n = z.size
    lo = int(np.searchsorted(z, z_lo_um - margin_um, side="right")) - 1  # level at or below
    hi = int(np.searchsorted(z, z_hi_um + margin_um, side="left"))  # level at or above
    lo, hi = max(0, lo - pad_levels), min(n - 1, hi + pad_levels)
    while hi - lo < 2:  # at least 3 levels for a depth estimate
        lo, hi = max(0, lo - 1), min(n - 1, hi + 1)
    return np.arange(lo, hi + 1)


def field_levels(prior: CoarsePrior, *, x0: float, y0: float, width: int, height: int,
                 focus_heights_um: np.ndarray, pad_levels: int = 8) -> np.ndarray:
    """Focus levels to acquire for the field whose top-left world pixel is (x0, y0).

    The field's prior range plus ``prior.uncertainty_um`` and ``pad_levels``; all levels
    where the prior does not cover the field.
    """
    n = np.size(focus_heights_um)
    r = prior.range_um(x0, y0, x0 + width, y0 + height)
    if r is None:
        return np.arange(n)
    return level_range(r[0], r[1], focus_heights_um=focus_heights_um,
                       margin_um=prior.uncertainty_um, pad_levels=pad_levels)


def reconstruct_levels(frames: np.ndarray, levels: np.ndarray, *, focus_heights_um: np.ndarray,
                       max_value: float, operator: str = "glvm", window: int = 9,
                       method: str = "spc", median_size: int = 11
                       ) -> tuple[np.ndarray, np.ndarray]:
    """Height map of a field from the frames of a subset of consecutive focus levels.

    Parameters
    ----------
    frames : (M, H, W) array
        The acquired frames, one per entry of ``levels``.
    levels : (M,) int array
        Their focus levels, consecutive and increasing, M >= 3.
    focus_heights_um : (N,) array_like of float
        The full focus table, µm.
    max_value, operator, window, method, median_size
        As in the scan: full scale of the frames, focus operator and window, depth method.

    Returns
    -------
    height_um : (H, W) float32
    confidence : (H, W) float32
    """
    lv = np.asarray(levels).reshape(-1)
    fr = np.asarray(frames)
    if fr.ndim != 3 or fr.shape[0] != lv.size:
        raise ValueError(f"need one frame per level: frames {fr.shape}, {lv.size} levels")
    if lv.size < 3 or not (np.diff(lv) == 1).all():
        raise ValueError("levels must be >= 3 consecutive increasing indices")
    table = np.asarray(focus_heights_um, dtype=np.float64)
    if lv[0] < 0 or lv[-1] >= table.size:
        raise ValueError(f"levels must lie in 0..{table.size - 1}, got {lv[0]}..{lv[-1]}")
    vol = focus_measure(np.stack([to_unit_float(f, max_value=max_value) for f in fr]),
                        operator=operator, window=window)
    if method in ("pc", "spc") and lv.size < table.size:
        # Phase methods treat the curve as circular: on a subset whose two ends both hold
        # focus (a pixel straddling an edge), the phase would wrap to the far end. Place
        # the acquired levels at their indices in the full-length curve; the levels the
        # prior rules out hold the pixel's floor (its smallest acquired value: out of
        # focus, by the prior's bound), so the circle is the full range's.
        full = np.empty((table.size,) + vol.shape[1:], dtype=np.float32)
        full[:] = vol.min(axis=0)
        full[lv] = vol
        depth, conf = depth_from_focus(full, method=method, median_size=median_size,
                                       spread_size=window)
        return levels_to_height(depth, focus_heights_um=table), conf
    depth, conf = depth_from_focus(vol, method=method, median_size=median_size,
                                   spread_size=window)
    return levels_to_height(depth, focus_heights_um=table[lv]), conf


def simulated_prior(true_height_um: np.ndarray, *, step_px: int, uncertainty_um: float,
                    origin_px: tuple[float, float] = (0.0, 0.0),
                    rng: np.random.Generator) -> CoarsePrior:
    """A coarse measurement of a known surface (a stand-in for a laser-line scan).

    Samples ``true_height_um`` every ``step_px`` pixels (the sample at the cell centre),
    adds Gaussian noise of ``uncertainty_um / 2`` (so the margin is 2 sigma), and records
    ``uncertainty_um`` as the prior's uncertainty.

    Parameters
    ----------
    true_height_um : (H, W) array
        The surface, world px box starting at ``origin_px``.
    step_px : int
        Lateral resolution of the coarse method, px (>= 1).
    """
    if step_px < 1:
        raise ValueError(f"step_px must be >= 1, got {step_px}")
    z = np.asarray(true_height_um, dtype=np.float64)
    half = step_px // 2
    grid = z[half::step_px, half::step_px]
    grid = grid + rng.normal(0.0, uncertainty_um / 2.0, grid.shape)
    return CoarsePrior(grid.astype(np.float32), (origin_px[0] + half, origin_px[1] + half),
                       float(step_px), uncertainty_um)


@dataclass(frozen=True)
class TwoStepResult:
    """Outcome of :func:`two_step_fields` (frames counted, heights over field interiors)."""

    frames_full: int
    frames_prior: int
    height_full_um: np.ndarray
    height_prior_um: np.ndarray
    truth_um: np.ndarray
    levels_per_field: tuple[int, ...]

    @property
    def frames_saved(self) -> float:
        """Fraction of frames the prior saves, 0..1."""
        return 1.0 - self.frames_prior / self.frames_full


def two_step_fields(world: PlateWorld, *, optics: Optics, region_px: tuple[int, int, int, int],
                    focus_heights_um: np.ndarray, prior: CoarsePrior, operator: str = "glvm",
                    window: int = 9, method: str = "spc", median_size: int = 11,
                    pad_levels: int = 8, seed: int = 0) -> TwoStepResult:
    """Stop-and-go fields over a simulated region, full range against the prior's levels.

    The fields' interiors (the focus window's and median filter's reach left out) tile
    ``region_px`` = (x0, y0, x1, y1) world px. Each field's full stack is rendered once;
    the two-step measurement uses only the frames of the prior's levels (the same frames a
    camera triggered at those levels would take), and both are processed identically.
    """
    from sffscan.stages.sim.camera import render_stack

    x0, y0, x1, y1 = region_px
    m = window // 2 + median_size // 2 + 1
    step_x, step_y = optics.width - 2 * m, optics.height - 2 * m
    if step_x < 1 or step_y < 1:
        raise ValueError("optics too small for the focus window and median margins")
    heights = np.asarray(focus_heights_um, dtype=np.float64)
    rng = np.random.default_rng(seed)
    full = np.full((y1 - y0, x1 - x0), np.nan, np.float32)
    part = np.full_like(full, np.nan)
    n_full = n_prior = 0
    per_field = []
    for fy in range(y0 - m, y1 - m, step_y):
        for fx in range(x0 - m, x1 - m, step_x):
            stack = render_stack(world, x0=float(fx), y0=float(fy), focus_heights_um=heights,
                                 optics=optics, rng=rng)
            lv = field_levels(prior, x0=fx, y0=fy, width=optics.width, height=optics.height,
                              focus_heights_um=heights, pad_levels=pad_levels)
            kw = dict(focus_heights_um=heights, max_value=float(optics.max_value),
                      operator=operator, window=window, method=method, median_size=median_size)
            h_full, _ = reconstruct_levels(stack, np.arange(heights.size), **kw)  # type: ignore[arg-type]
            h_part, _ = reconstruct_levels(stack[lv], lv, **kw)  # type: ignore[arg-type]
            n_full += heights.size
            n_prior += lv.size
            per_field.append(int(lv.size))
            w, h = min(step_x, x1 - fx - m), min(step_y, y1 - fy - m)
            r, c = fy + m - y0, fx + m - x0
            full[r:r + h, c:c + w] = h_full[m:m + h, m:m + w]
            part[r:r + h, c:c + w] = h_part[m:m + h, m:m + w]
    truth = world.height_um(float(x0), float(y0), x1 - x0, y1 - y0)
    return TwoStepResult(n_full, n_prior, full, part, truth, tuple(per_field))
