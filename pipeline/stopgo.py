"""Stop-and-go measurement: a grid of stationary fields stitched into one mosaic (SFF_NOTES 5).

The stages move the part to each field of a grid, stop, and the camera takes a whole focus
stack there. Each field is reconstructed on its own (:func:`.stationary.reconstruct_field`)
and placed in world pixels by its stage position; neighbouring fields overlap by
``overlap_px`` and are blended into the same Zarr mosaic format as the continuous scan
(:class:`sffscan.pipeline.mosaic.writer.MosaicWriter`), so every tool that reads a scan mosaic
reads this one.

Placement: the stage position is the world position of the field's first pixel (column 0,
row 0), µm, as in the frame headers of a scan; it is rounded to the nearest world pixel
(error <= 0.5 px; the stage's own accuracy is the limit).

Blending: a field contributes ``height * w`` and ``w`` with
``w = max(confidence, 1e-3) * feather``, where ``feather`` rises linearly from the field's
edges over ``overlap_px`` px (``min(1, (d + 0.5) / overlap_px)``, d the distance to the
nearest edge in px), so that across an overlap band the two fields cross-fade instead of
leaving a seam. Height and texture are the weighted means; confidence is the largest.

The camera is a :class:`FieldCamera` protocol; :class:`SimFieldCamera` is its simulated
sibling (the scanner's simulator, standing still).
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Protocol

import numpy as np
from sffscan.pipeline import locks
from sffscan.pipeline.metrology.optics_correction import StackCorrection, applied
from sffscan.pipeline.mosaic.writer import MosaicWriter
from sffscan.stages.fields.stationary import FieldResult, StackSettings, reconstruct_field
from sffscan.stages.mosaic import MIN_WEIGHT
from sffscan.stages.sim.camera import Optics, render_stack
from sffscan.stages.sim.world import PlateWorld

__all__ = [
    "FieldCamera",
    "FieldPosition",
    "SimFieldCamera",
    "StopAndGoReport",
    "feather_weights",
    "plan_grid",
    "run_stop_and_go",
    "stitch_field",
]


class FieldCamera(Protocol):
    """Takes a focus stack with the stages at one position."""

    @property
    def pixel_um(self) -> float: ...

    @property
    def field_px(self) -> tuple[int, int]:
        """(width, height) of a field, px."""
        ...

    @property
    def focus_heights_um(self) -> np.ndarray: ...

    @property
    def max_value(self) -> float: ...

    def acquire(self, *, stage_x_um: float, stage_y_um: float) -> np.ndarray:
        """(N, H, W) stack, one image per focus height, the field's first pixel at the stage
        position (world µm)."""
        ...


@dataclass
class SimFieldCamera:
    """Simulated field camera: :func:`sffscan.stages.sim.camera.render_stack` of a simulated world.

    Parameters
    ----------
    world : PlateWorld
        The simulated world.
    optics : Optics
        Camera and lens (its width x height is the field).
    focus_heights : (N,) ndarray of float
        Heights in focus, µm.
    seed : int
        Seed of the sensor noise (one generator for the whole grid).
    """

    world: PlateWorld
    optics: Optics
    focus_heights: np.ndarray
    seed: int = 0

    def __post_init__(self) -> None:
        self._rng = np.random.default_rng(self.seed)

    @property
    def pixel_um(self) -> float:
        return self.optics.pixel_um

    @property
    def field_px(self) -> tuple[int, int]:
        return self.optics.width, self.optics.height

    @property
    def focus_heights_um(self) -> np.ndarray:
        return np.asarray(self.focus_heights, dtype=np.float64)

    @property
    def max_value(self) -> float:
        return float(self.optics.max_value)

    def acquire(self, *, stage_x_um: float, stage_y_um: float) -> np.ndarray:
        return render_stack(self.world, x0=stage_x_um / self.pixel_um,
                            y0=stage_y_um / self.pixel_um,
                            focus_heights_um=self.focus_heights_um, optics=self.optics,
                            rng=self._rng)


@dataclass(frozen=True)
class FieldPosition:
    """One field of the grid: its index (column, row) and stage position, µm."""

    ix: int
    iy: int
    stage_x_um: float
    stage_y_um: float


def _axis_starts(start_px: int, length_px: int, field: int, overlap: int) -> list[int]:
    """First pixels of the fields that cover [start, start + length) with >= overlap px."""
    if length_px <= field:
        return [start_px]
    pitch = field - overlap
    n = 1 + math.ceil((length_px - field) / pitch)
    # spread evenly: the last field ends exactly at the end of the range
    step = (length_px - field) / (n - 1)
    return [start_px + int(round(i * step)) for i in range(n)]


def plan_grid(*, x_um: tuple[float, float], y_um: tuple[float, float], field_px: tuple[int, int],
              pixel_um: float, overlap_px: int = 150) -> list[FieldPosition]:
    """Serpentine grid of fields covering a rectangle with at least ``overlap_px`` overlap.

    Parameters
    ----------
    x_um, y_um : (float, float)
        World extent to cover, µm (start < end).
    field_px : (int, int)
        Field (width, height), px.
    pixel_um : float
        Pixel scale, µm/px.
    overlap_px : int
        Least overlap between neighbouring fields, px (thesis: 150); fields are spread evenly,
        so the actual overlap may be larger.

    Returns
    -------
    list of FieldPosition
        Row by row, alternating direction (serpentine), positions on whole pixels.
    """
    w, h = (int(v) for v in field_px)
    if w < 1 or h < 1:
        raise ValueError(f"field_px must be positive, got {field_px}")
    if not (pixel_um > 0 and math.isfinite(pixel_um)):
        raise ValueError(f"pixel_um must be > 0, got {pixel_um}")
    if not 0 <= overlap_px < min(w, h):
        raise ValueError(f"overlap_px must be in [0, {min(w, h)}), got {overlap_px}")
    if not (x_um[1] > x_um[0] and y_um[1] > y_um[0]):
        raise ValueError(f"area must have start < end, got x {x_um}, y {y_um}")
    x0, x1 = math.floor(x_um[0] / pixel_um), math.ceil(x_um[1] / pixel_um)
    y0, y1 = math.floor(y_um[0] / pixel_um), math.ceil(y_um[1] / pixel_um)
    xs = _axis_starts(x0, x1 - x0, w, overlap_px)
    ys = _axis_starts(y0, y1 - y0, h, overlap_px)
    out = []
    for iy, ypx in enumerate(ys):
        cols = list(enumerate(xs)) if iy % 2 == 0 else list(enumerate(xs))[::-1]
        for ix, xpx in cols:
            out.append(FieldPosition(ix, iy, xpx * pixel_um, ypx * pixel_um))
    return out


def feather_weights(shape: tuple[int, int], *, overlap_px: int) -> np.ndarray:
    """Blending ramp of a field: ``min(1, (d + 0.5) / overlap_px)``, d = px to the nearest edge.

    Returns
    -------
    (H, W) float32 in (0, 1]; all ones for ``overlap_px`` 0.
    """
    h, w = shape
    if overlap_px <= 0:
        return np.ones(shape, dtype=np.float32)
    dy = np.minimum(np.arange(h), np.arange(h)[::-1]) + 0.5
    dx = np.minimum(np.arange(w), np.arange(w)[::-1]) + 0.5
    ramp_y = np.minimum(1.0, dy / overlap_px)
    ramp_x = np.minimum(1.0, dx / overlap_px)
    return (ramp_y[:, None] * ramp_x[None, :]).astype(np.float32)


def stitch_field(writer: MosaicWriter, result: FieldResult, *, x0_px: int, y0_px: int,
                 feather: np.ndarray) -> int:
    """Blend one reconstructed field into the mosaic at world pixel (x0_px, y0_px).

    Returns the number of valid (finite-height) pixels of the field.
    """
    valid = np.isfinite(result.height_um)
    w = np.where(valid, np.maximum(result.confidence, MIN_WEIGHT) * feather, 0.0)
    sums = {
        "height": np.where(valid, result.height_um, 0.0) * w,
        "texture": np.where(valid, result.texture, 0.0) * w,
        "weight": w,
        "confidence": np.where(valid, result.confidence, 0.0),
    }
    if result.uncertainty_um is not None:  # else unknown (NaN) in the mosaic
        sums["uncertainty"] = np.where(valid, result.uncertainty_um, 0.0) * w
    writer.write_region(x0_px, y0_px, sums)
    return int(valid.sum())


@dataclass
class StopAndGoReport:
    fields: int
    valid_pixels: int
    seconds: float
    path: Path


def grid_extent_px(positions: Sequence[FieldPosition], *, pixel_um: float,
                   field_px: tuple[int, int]) -> tuple[int, int, int, int]:
    """World px box (x0, y0, x1, y1) covered by the fields."""
    xs = [int(round(p.stage_x_um / pixel_um)) for p in positions]
    ys = [int(round(p.stage_y_um / pixel_um)) for p in positions]
    return min(xs), min(ys), max(xs) + field_px[0], max(ys) + field_px[1]


def run_stop_and_go(camera: FieldCamera, positions: Sequence[FieldPosition], output: str | Path,
                    *, settings: StackSettings | None = None, overlap_px: int = 150,
                    chunk_px: int = 256, overwrite: bool = False,
                    progress: Callable[[int, int, float], None] | None = None,
                    correction: StackCorrection | None = None) -> StopAndGoReport:
    """Acquire, reconstruct and stitch every field of a grid into a Zarr mosaic.

    The mosaic's status is ``writing`` while fields arrive, ``complete`` at the end, and
    ``failed`` if a field fails (the fields already stitched stay in the mosaic).

    Parameters
    ----------
    camera : FieldCamera
        Takes the stack at each position.
    positions : sequence of FieldPosition
        The grid (see :func:`plan_grid`).
    output : str or Path
        Zarr v3 group to write.
    settings : StackSettings, keyword-only
        Reconstruction settings of every field.
    overlap_px : int, keyword-only
        Width of the blending ramp, px (normally the grid's overlap).
    chunk_px, overwrite : keyword-only
        As for :class:`sffscan.pipeline.mosaic.writer.MosaicWriter`.
    progress : callable(done, total, elapsed_s), keyword-only
        Called after each field.
    correction : StackCorrection, keyword-only
        A calibration applied to every field: vignetting and magnification per level in
        the frames, the z response in the focus table, the field curvature in the heights.

    Raises
    ------
    LockHeld
        Another writer (a scan, a stack, another stop-and-go run) holds ``output``'s lock
        (:mod:`sffscan.pipeline.locks`); nothing is acquired.
    FileExistsError
        ``output`` exists and ``overwrite`` is false (or it is not a mosaic).
    """
    if not positions:
        raise ValueError("positions: the grid has no fields")
    settings = settings or StackSettings()
    px = camera.pixel_um
    x0, y0, x1, y1 = grid_extent_px(positions, pixel_um=px, field_px=camera.field_px)
    table = camera.focus_heights_um if correction is None else \
        correction.focus_heights_um(camera.focus_heights_um)
    processing = {"mode": "stop-and-go", **settings.as_dict(), "overlap_px": overlap_px,
                  "calibration_applied": [] if correction is None else
                  applied(correction.calibration),
                  "fields": [[p.ix, p.iy, p.stage_x_um, p.stage_y_um] for p in positions]}
    with locks.claim_mosaic(output, overwrite=overwrite):  # one writer a mosaic
        writer = MosaicWriter(output, origin_px=(x0, y0), shape=(y1 - y0, x1 - x0),
                              pixel_um=px, chunk_px=chunk_px, overwrite=overwrite,
                              attrs={"processing": processing,
                                     "focus_heights_um": [float(v) for v in table]})
        return _stitch_fields(camera, positions, writer, table=table, settings=settings,
                              overlap_px=overlap_px, progress=progress,
                              correction=correction)


def _stitch_fields(camera: FieldCamera, positions: Sequence[FieldPosition],
                   writer: MosaicWriter, *, table: np.ndarray, settings: StackSettings,
                   overlap_px: int, progress: Callable[[int, int, float], None] | None,
                   correction: StackCorrection | None) -> StopAndGoReport:
    """:func:`run_stop_and_go`'s fields, each acquired, reconstructed and stitched."""
    px = camera.pixel_um
    feather = feather_weights((camera.field_px[1], camera.field_px[0]), overlap_px=overlap_px)
    start = time.perf_counter()
    valid = done = 0
    try:
        for pos in positions:
            stack = camera.acquire(stage_x_um=pos.stage_x_um, stage_y_um=pos.stage_y_um)
            try:
                if correction is not None:
                    stack = correction.frames(stack, max_value=camera.max_value)
                result = reconstruct_field(stack, focus_heights_um=table,
                                           settings=settings, max_value=camera.max_value)
                if correction is not None:
                    result = correction.field(result)
            except ValueError as err:
                raise ValueError(f"field ({pos.ix}, {pos.iy}) at stage ({pos.stage_x_um:g}, "
                                 f"{pos.stage_y_um:g}) µm: {err}") from None
            if result.height_um.shape != feather.shape:
                raise ValueError(f"field ({pos.ix}, {pos.iy}): stack of {result.height_um.shape} "
                                 f"px, expected {feather.shape}")
            valid += stitch_field(writer, result, x0_px=int(round(pos.stage_x_um / px)),
                                  y0_px=int(round(pos.stage_y_um / px)), feather=feather)
            done += 1
            if progress is not None:
                progress(done, len(positions), time.perf_counter() - start)
    except BaseException:
        writer.set_status("failed", valid_pixels=valid, blocks=done)
        raise
    writer.set_status("complete", valid_pixels=valid, blocks=done)
    return StopAndGoReport(done, valid, time.perf_counter() - start, writer.path)

