"""What should have been printed: expected height maps from the G-code and from the model.

Grid and coordinates: a :class:`Grid` is the mosaic's pixel grid: pixel (row i, column j)
has its centre at ``(origin_um[0] + j * pixel_um, origin_um[1] + i * pixel_um)`` µm in
mosaic coordinates (those of :func:`sffscan.open_mosaic`'s ``x`` and ``y``). Printer
coordinates (mm, the G-code's) map to mosaic coordinates with a :class:`PrinterMapping`.

Bead model (G-code): a move of length L that extrudes e mm of filament of diameter D lays a
bead of cross-section ``A = e * pi D^2 / 4 / L`` (mm^2). With the layer height h (the
layer's z minus the previous layer's) the bead is Slic3r's stadium: a rectangle with
semicircular sides, width ``w = A / h + h (1 - pi / 4)``, its top flat at the layer's z and
its sides rounded (radius h / 2). The expected height at a point is the highest bead top
covering it (0, the bed, elsewhere).

Model (STL, 3MF): the part truncated at the layer's z, seen from above: vertical rays cast
with trimesh give the solid's intervals along each pixel's column, and the expected height
is the highest solid point at or below z.
"""

from __future__ import annotations

import math
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np
from pydantic import BaseModel, ConfigDict, Field
from sffscan.pipeline.printjob.gcode import GcodeProgram
from sffscan.stages.sim.print_world import ExpectedMap, Grid, bead_width_mm, rasterise_beads

if TYPE_CHECKING:
    import trimesh

__all__ = ["ExpectedMap", "Grid", "ModelUnitsError", "PrinterMapping", "bead_width_mm",
           "load_model", "model_top_surface", "rasterise_expected"]


class ModelUnitsError(ValueError):
    """A model whose size does not match the G-code's (metres, inches...)."""


class PrinterMapping(BaseModel):
    """Printer coordinates (mm) -> mosaic coordinates (µm): a rotation, then a translation.

    ``mosaic_um = R(rotation_deg) @ (printer_mm * 1000) + offset_um``.
    """

    model_config = ConfigDict(extra="forbid", frozen=True, allow_inf_nan=False)
    offset_um: tuple[float, float] = Field((0.0, 0.0), description="Translation (x, y), µm")
    rotation_deg: float = Field(0.0, ge=-360, le=360,
                                description="Rotation of the printer axes in the mosaic, deg")

    def apply(self, xy_mm: np.ndarray) -> np.ndarray:
        """(..., 2) printer mm -> (..., 2) mosaic µm, float64."""
        a = math.radians(self.rotation_deg)
        c, s = math.cos(a), math.sin(a)
        p = np.asarray(xy_mm, dtype=np.float64) * 1000.0
        x = c * p[..., 0] - s * p[..., 1] + self.offset_um[0]
        y = s * p[..., 0] + c * p[..., 1] + self.offset_um[1]
        return np.stack([x, y], axis=-1)

    def inverse(self, xy_um: np.ndarray) -> np.ndarray:
        """(..., 2) mosaic µm -> (..., 2) printer mm, float64."""
        a = math.radians(self.rotation_deg)
        c, s = math.cos(a), math.sin(a)
        q = np.asarray(xy_um, dtype=np.float64)
        dx, dy = q[..., 0] - self.offset_um[0], q[..., 1] - self.offset_um[1]
        return np.stack([c * dx + s * dy, -s * dx + c * dy], axis=-1) / 1000.0


def rasterise_expected(program: GcodeProgram, grid: Grid, *, upto_layer: int,
                       mapping: PrinterMapping | None = None, base: ExpectedMap | None = None,
                       exclude: np.ndarray | None = None,
                       shift_mm: np.ndarray | None = None) -> ExpectedMap:
    """Expected height map of the extrusion of layers ``<= upto_layer``.

    Parameters
    ----------
    program : GcodeProgram
        The print's moves (:func:`sffscan.pipeline.printjob.gcode.read_gcode`).
    grid : Grid
        Output grid, mosaic coordinates.
    upto_layer : int, keyword-only
        Last layer included (0-based; ``program.n_layers - 1`` for the whole part).
    mapping : PrinterMapping, keyword-only
        Printer -> mosaic coordinates; default the identity (printer mm * 1000 = µm).
    base : ExpectedMap, keyword-only
        A map of the same grid with layers ``<= base.upto_layer`` already rasterised (and
        the same mapping): only the later layers are added (a copy; ``base`` is unchanged).
    exclude : (M,) bool ndarray, keyword-only
        Moves to leave out (the simulator's defects).
    shift_mm : (M, 2) float ndarray, keyword-only
        Per-move XY offsets, mm, added before the mapping (the simulator's layer shifts).

    Returns
    -------
    ExpectedMap

    Notes
    -----
    The bead model itself is :func:`sffscan.stages.sim.print_world.rasterise_beads`, which
    the simulated print's world uses too.
    """
    return rasterise_beads(program, grid, upto_layer=upto_layer,
                           mapping=mapping or PrinterMapping(), base=base, exclude=exclude,
                           shift_mm=shift_mm)


# ---------------------------------------------------------------------------- the model


def load_model(path: str | Path) -> trimesh.Trimesh:
    """Read an STL/3MF/OBJ model as one mesh (a scene's meshes concatenated)."""
    import trimesh

    p = Path(path)
    if not p.is_file():
        raise FileNotFoundError(f"{p}: model file not found")
    try:
        loaded = trimesh.load(str(p), force="mesh")
    except Exception as err:  # trimesh raises many kinds on bad files
        raise ValueError(f"{p}: cannot read the model: {err}") from None
    if not isinstance(loaded, trimesh.Trimesh) or len(loaded.faces) == 0:
        raise ValueError(f"{p}: no triangles in the model")
    return loaded


def _check_units(size_mm: np.ndarray, gcode_size_mm: np.ndarray, name: str) -> None:
    ratio = float(np.max(size_mm) / max(float(np.max(gcode_size_mm)), 1e-9))
    if 0.5 <= ratio <= 2.0:
        return
    guess = ""
    if 1e-4 < ratio < 4e-3:
        guess = " (it looks like metres: scale it by 1000)"
    elif 0.02 < ratio < 0.08:
        guess = " (it looks like inches: scale it by 25.4)"
    elif 400 < ratio < 4000:
        guess = " (it looks like micrometres: scale it by 0.001)"
    raise ModelUnitsError(
        f"{name}: the model is {np.max(size_mm):g} units across but the G-code's extrusion "
        f"is {np.max(gcode_size_mm):g} mm across (ratio {ratio:.3g}){guess}; give the model "
        "in millimetres")


def model_top_surface(mesh: trimesh.Trimesh, grid: Grid, *, z_mm: float,
                      program: GcodeProgram | None = None,
                      placement_mm: tuple[float, float, float] | None = None,
                      mapping: PrinterMapping | None = None, name: str = "model") -> np.ndarray:
    """Expected top surface of the model printed up to height ``z_mm``, by ray casting.

    Parameters
    ----------
    mesh : trimesh.Trimesh
        The part (watertight), model units must be mm.
    grid : Grid
        Output grid, mosaic coordinates.
    z_mm : float, keyword-only
        Height the part is printed to, mm (a layer's z).
    program : GcodeProgram, keyword-only
        The sliced program: its extrusion's extent checks the model's units, and, without
        ``placement_mm``, places the model (XY centre on the extrusion's centre, bottom on
        the bed).
    placement_mm : (float, float, float), keyword-only
        Translation from model to printer coordinates, mm.
    mapping : PrinterMapping, keyword-only
        Printer -> mosaic coordinates; default the identity.
    name : str, keyword-only
        Model name for messages.

    Returns
    -------
    (rows, columns) float32, µm: the highest solid point at or below ``z_mm`` above each
    pixel centre (0 where the column misses the part).

    Raises
    ------
    ModelUnitsError
        The model's size differs from the G-code's by more than 2x (the message guesses the
        unit).
    """
    lo, hi = mesh.bounds
    if program is not None:
        x0, y0, x1, y1 = program.extent_mm()
        _check_units(hi[:2] - lo[:2], np.array([x1 - x0, y1 - y0]), name)
        if placement_mm is None:
            cx, cy = (x0 + x1) / 2, (y0 + y1) / 2
            placement_mm = (cx - (lo[0] + hi[0]) / 2, cy - (lo[1] + hi[1]) / 2, -lo[2])
    off = np.asarray(placement_mm if placement_mm is not None else (0.0, 0.0, 0.0))
    m = mapping or PrinterMapping()
    xs, ys = grid.xy_um()
    gx, gy = np.meshgrid(xs, ys)
    pts_mm = m.inverse(np.stack([gx.ravel(), gy.ravel()], axis=1)) - off[:2]
    inside = ((pts_mm[:, 0] >= lo[0]) & (pts_mm[:, 0] <= hi[0]) & (pts_mm[:, 1] >= lo[1])
              & (pts_mm[:, 1] <= hi[1]))
    out = np.zeros(gx.size, np.float32)
    ray = np.flatnonzero(inside)
    if ray.size:
        top = hi[2] + 1.0
        origins = np.column_stack([pts_mm[ray], np.full(ray.size, top)])
        dirs = np.tile([0.0, 0.0, -1.0], (ray.size, 1))
        loc, which, _ = mesh.ray.intersects_location(origins, dirs, multiple_hits=True)
        zc = z_mm - off[2]
        best = np.zeros(ray.size)
        order = np.lexsort((-loc[:, 2], which))  # per ray, hits from the top down
        which, hz = which[order], loc[order, 2]
        starts = np.flatnonzero(np.r_[True, which[1:] != which[:-1]])
        ends = np.r_[starts[1:], which.size]
        for s, e in zip(starts, ends, strict=True):
            zs = np.unique(np.round(hz[s:e], 9))[::-1]  # dedupe edge hits, top down
            for k in range(0, zs.size - 1, 2):  # (entry, exit) pairs of the solid
                z_in, z_out = zs[k], zs[k + 1]
                if z_out <= zc:
                    best[which[s]] = min(z_in, zc) + off[2]
                    break
        out[ray] = np.maximum(best, 0.0) * 1000.0
    return out.reshape(grid.shape)
