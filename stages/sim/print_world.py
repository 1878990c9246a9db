"""A simulated print: the world's height built from a G-code's beads, with injected defects.

A :class:`PrintWorld` has the interface the simulated camera uses (``pixel_um``,
``height_um``, ``texture``), like :class:`~sffscan.stages.sim.world.PlateWorld`, so
:func:`sffscan.pipeline.sim_source.simulate_frames` scans it unchanged. Its surface is the
top of the beads of layers ``0 .. layer`` (:meth:`PrintWorld.at_layer`), rasterised by
:func:`rasterise_beads` (the bead model, defined here and used by the expected map of
:mod:`sffscan.pipeline.printjob.expected` too: stages compute, pipeline runs), plus a
small random bead height jitter, plus the defects whose layer has been reached:

- ``gap`` (under-extrusion): the layer's material is missing in a disc of diameter
  ``size_mm`` (the previous layer shows); the next layer bridges it (transient);
- ``blob``: a Gaussian bump of ``height_um`` with sigma ``size_mm / 2`` on that layer only
  (the next layer's nozzle flattens it);
- ``lifted_corner``: from the layer on, the object's corner nearest ``xy_mm`` rises by
  ``height_um``, falling linearly to 0 at ``size_mm`` from the corner (warping; persists);
- ``layer_shift``: from the layer on, every move is offset by ``shift_mm`` (persists);
- ``missing_object``: from the layer on, the object is not printed (persists).

Coordinates: world µm = ``mapping.apply(printer mm)``; world pixel (x, y) is centred at
(x * pixel_um, y * pixel_um) µm, as in :mod:`sffscan.stages.sim.world`. The heights are one
raster over ``extent_um`` (outside it: the bed, 0 µm), sampled bilinearly.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field, replace
from typing import Any, Literal

import cv2
import numpy as np
from sffscan.stages.sim.world import PlateWorld

__all__ = ["DefectKind", "ExpectedMap", "Grid", "PrintDefect", "PrintWorld", "bead_width_mm",
           "rasterise_beads"]

DefectKind = Literal["gap", "blob", "lifted_corner", "layer_shift", "missing_object"]
PERSISTENT = ("lifted_corner", "layer_shift", "missing_object")


# ------------------------------------------------------------------ the bead model
# (shared with the expected map: sffscan.pipeline.printjob.expected re-exports these)

@dataclass(frozen=True)
class Grid:
    """A pixel grid in mosaic coordinates.

    Parameters
    ----------
    origin_um : (float, float)
        Centre of pixel (0, 0), (x, y) µm.
    pixel_um : float
        Pixel size, µm/px.
    shape : (int, int)
        (rows, columns).
    """

    origin_um: tuple[float, float]
    pixel_um: float
    shape: tuple[int, int]

    def __post_init__(self) -> None:
        if not (math.isfinite(self.pixel_um) and self.pixel_um > 0):
            raise ValueError(f"Grid.pixel_um must be > 0, got {self.pixel_um}")
        if len(self.shape) != 2 or min(self.shape) < 1:
            raise ValueError(f"Grid.shape must be two positive sizes, got {self.shape}")

    @classmethod
    def of_dataset(cls, ds: Any) -> Grid:
        """The grid of an xarray Dataset with ``x`` and ``y`` pixel-centre coordinates (µm),
        as :func:`sffscan.open_mosaic` returns."""
        x, y = np.asarray(ds["x"]), np.asarray(ds["y"])
        p = float(x[1] - x[0]) if x.size > 1 else float(ds.attrs["pixel_um"])
        return cls((float(x[0]), float(y[0])), p, (int(y.size), int(x.size)))

    def xy_um(self) -> tuple[np.ndarray, np.ndarray]:
        """Pixel-centre coordinates: (columns,) x and (rows,) y, µm."""
        return (self.origin_um[0] + self.pixel_um * np.arange(self.shape[1]),
                self.origin_um[1] + self.pixel_um * np.arange(self.shape[0]))


@dataclass
class ExpectedMap:
    """An expected top surface on a grid.

    Attributes
    ----------
    height_um : (rows, columns) float32
        Expected height, µm (0 = the bed).
    label : (rows, columns) int16
        Object of the highest bead at each pixel (index into the program's ``objects``);
        -1 where no labelled bead lies.
    upto_layer : int
        Layers ``0 .. upto_layer`` are included (-1: none).
    """

    height_um: np.ndarray
    label: np.ndarray
    upto_layer: int


def bead_width_mm(e_mm: np.ndarray, length_mm: np.ndarray, layer_height_mm: np.ndarray, *,
                  filament_diameter_mm: float) -> np.ndarray:
    """Width of the stadium bead a move lays, mm (see the module's bead model).

    Parameters
    ----------
    e_mm, length_mm, layer_height_mm : array_like of float
        Filament extruded (mm), move length (mm, > 0) and layer height (mm, > 0).
    filament_diameter_mm : float, keyword-only
        Filament diameter, mm.

    Returns
    -------
    ndarray of float64, mm
    """
    area = np.asarray(e_mm) * math.pi * filament_diameter_mm**2 / 4.0 / np.asarray(length_mm)
    h = np.asarray(layer_height_mm, dtype=np.float64)
    return area / h + h * (1.0 - math.pi / 4.0)


def rasterise_beads(program: Any, grid: Grid, *, upto_layer: int, mapping: Any = None,
                    base: ExpectedMap | None = None, exclude: np.ndarray | None = None,
                    shift_mm: np.ndarray | None = None) -> ExpectedMap:
    """Expected height map of the extrusion of layers ``<= upto_layer``.

    Parameters
    ----------
    program : GcodeProgram
        The print's moves (any object with ``start``, ``end``, ``z_mm``, ``e_mm``,
        ``layer``, ``object_id``, ``layer_height_mm()`` and ``filament_diameter_mm`` as
        :class:`sffscan.pipeline.printjob.gcode.GcodeProgram` has).
    grid : Grid
        Output grid, mosaic coordinates.
    upto_layer : int, keyword-only
        Last layer included (0-based; ``program.n_layers - 1`` for the whole part).
    mapping : PrinterMapping, keyword-only
        Printer -> mosaic coordinates (an object with ``apply((..., 2) mm) -> µm``); default
        the identity (printer mm * 1000 = µm).
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
    """
    def apply(xy_mm: np.ndarray) -> np.ndarray:
        return xy_mm * 1000.0 if mapping is None else np.asarray(mapping.apply(xy_mm))

    if base is not None:
        if base.height_um.shape != grid.shape:
            raise ValueError(f"base map shape {base.height_um.shape} != grid {grid.shape}")
        height, label, first = base.height_um.copy(), base.label.copy(), base.upto_layer + 1
    else:
        height = np.zeros(grid.shape, np.float32)
        label = np.full(grid.shape, -1, np.int16)
        first = 0
    if upto_layer < first:
        return ExpectedMap(height, label, max(upto_layer, first - 1))
    sel = (program.layer >= first) & (program.layer <= upto_layer)
    if exclude is not None:
        sel &= ~exclude
    idx = np.flatnonzero(sel)
    a_mm, b_mm = program.start[idx], program.end[idx]
    if shift_mm is not None:
        a_mm, b_mm = a_mm + shift_mm[idx], b_mm + shift_mm[idx]
    length = np.hypot(*(b_mm - a_mm).T)
    h_mm = program.layer_height_mm()[program.layer[idx]]
    w_mm = bead_width_mm(program.e_mm[idx], np.maximum(length, 1e-6), h_mm,
                         filament_diameter_mm=program.filament_diameter_mm)
    a = apply(a_mm)
    b = apply(b_mm)
    p = grid.pixel_um
    ox, oy = grid.origin_um
    ny, nx = grid.shape
    for k in range(idx.size):
        half = w_mm[k] * 500.0
        hh = h_mm[k] * 500.0  # half the layer height, µm
        top = program.z_mm[idx[k]] * 1000.0
        flat = max(half - hh, 0.0)
        (ax, ay), (bx, by) = a[k], b[k]
        j0 = max(0, math.floor((min(ax, bx) - half - ox) / p))
        j1 = min(nx, math.ceil((max(ax, bx) + half - ox) / p) + 1)
        i0 = max(0, math.floor((min(ay, by) - half - oy) / p))
        i1 = min(ny, math.ceil((max(ay, by) + half - oy) / p) + 1)
        if j0 >= j1 or i0 >= i1:
            continue
        rows, cols = _capsule_pixels(ax, ay, bx, by, half, grid, i0, i1, j0, j1)
        if rows.size == 0:
            continue
        xs = ox + p * cols - ax
        ys = oy + p * rows - ay
        dx, dy = bx - ax, by - ay
        ll = dx * dx + dy * dy
        t = np.clip((xs * dx + ys * dy) / ll, 0.0, 1.0) if ll > 0 else 0.0
        d = np.hypot(xs - t * dx, ys - t * dy)
        edge = np.clip(d - flat, 0.0, None)
        z = (top - hh + np.sqrt(np.clip(hh * hh - edge * edge, 0.0, None))).astype(np.float32)
        up = (d <= half) & (z > height[rows, cols])
        height[rows[up], cols[up]] = z[up]
        label[rows[up], cols[up]] = program.object_id[idx[k]]
    return ExpectedMap(height, label, upto_layer)


def _capsule_pixels(ax: float, ay: float, bx: float, by: float, half: float, grid: Grid,
                    i0: int, i1: int, j0: int, j1: int) -> tuple[np.ndarray, np.ndarray]:
    """Row and column indices of the pixels of box [i0, i1) x [j0, j1) whose centres lie
    in the band of half-width ``half`` (µm) around segment a-b, per row (a superset of the
    capsule; the caller tests the distance)."""
    p = grid.pixel_um
    ox, oy = grid.origin_um
    rows = np.arange(i0, i1)
    lo = np.full(rows.size, j0, dtype=np.int64)
    hi = np.full(rows.size, j1 - 1, dtype=np.int64)
    dx, dy = bx - ax, by - ay
    if abs(dy) > 1e-9:
        y = oy + p * rows
        xc = ax + (y - ay) * dx / dy
        reach = half * math.hypot(dx, dy) / abs(dy) + p
        lo = np.maximum(lo, np.ceil((xc - reach - ox) / p).astype(np.int64))
        hi = np.minimum(hi, np.floor((xc + reach - ox) / p).astype(np.int64))
    counts = np.clip(hi - lo + 1, 0, None)
    total = int(counts.sum())
    if total == 0:
        return np.empty(0, np.int64), np.empty(0, np.int64)
    r = np.repeat(rows, counts)
    starts = np.repeat(np.cumsum(counts) - counts, counts)
    c = np.repeat(lo, counts) + (np.arange(total) - starts)
    return r, c


# ------------------------------------------------------------------ the simulated print

@dataclass(frozen=True)
class PrintDefect:
    """A defect injected into a simulated print.

    Parameters
    ----------
    kind : {"gap", "blob", "lifted_corner", "layer_shift", "missing_object"}
    layer : int
        Layer where it appears (0-based).
    object : str
        Object it belongs to (for ``layer_shift``, the object it is judged on; the shift
        moves every object).
    xy_mm : (float, float)
        Printer position, mm (gap and blob centre; the corner nearest it lifts).
    size_mm : float
        Gap diameter, blob 2 sigma, or lifted corner radius, mm.
    height_um : float
        Blob height or corner lift, µm.
    shift_mm : (float, float)
        Layer shift, mm.
    """

    kind: DefectKind
    layer: int
    object: str = ""
    xy_mm: tuple[float, float] = (0.0, 0.0)
    size_mm: float = 2.0
    height_um: float = 400.0
    shift_mm: tuple[float, float] = (1.0, 0.0)


@dataclass
class PrintWorld:
    """The simulated print at one layer (see the module docstring).

    Parameters
    ----------
    program : GcodeProgram
        The print's G-code.
    mapping : PrinterMapping
        Printer mm -> world µm.
    pixel_um : float
        World pixel, µm/px (the optics').
    extent_um : (float, float, float, float)
        World region (x0, y0, x1, y1) µm where the heights are rasterised.
    defects : tuple of PrintDefect
        Injected defects.
    seed : int
        Texture and bead jitter seed.
    bead_jitter_um : float
        Std of a random per-move bead height change, µm (0: the ideal beads).
    layer : int
        Current layer (-1: the empty bed); :meth:`at_layer` gives another.
    """

    program: Any
    mapping: Any
    pixel_um: float
    extent_um: tuple[float, float, float, float]
    defects: tuple[PrintDefect, ...] = ()
    seed: int = 0
    bead_jitter_um: float = 3.0
    layer: int = -1
    #: the beads stacked so far, shared by the copies :meth:`at_layer` makes (same defects)
    cache: dict[str, Any] = field(default_factory=dict, repr=False, compare=False)
    _raster: np.ndarray | None = field(default=None, init=False, repr=False)
    _texture: PlateWorld | None = field(default=None, init=False, repr=False)

    def __post_init__(self) -> None:
        names = set(self.program.objects)
        for d in self.defects:
            if d.kind not in ("layer_shift",) and d.object not in names:
                raise ValueError(f"defect {d.kind} at layer {d.layer}: unknown object "
                                 f"{d.object!r} (objects: {sorted(names)})")
            if not 0 <= d.layer < self.program.n_layers:
                raise ValueError(f"defect {d.kind}: layer {d.layer} outside 0.."
                                 f"{self.program.n_layers - 1}")

    # ------------------------------------------------------------------ layout
    @property
    def grid(self) -> Grid:
        """The raster's grid (world µm)."""
        x0, y0, x1, y1 = self.extent_um
        p = self.pixel_um
        gx0, gy0 = math.floor(x0 / p) * p, math.floor(y0 / p) * p
        return Grid((gx0, gy0), p, (math.ceil((y1 - gy0) / p) + 1,
                                    math.ceil((x1 - gx0) / p) + 1))

    def at_layer(self, layer: int, *, defects: tuple[PrintDefect, ...] | None = None
                 ) -> PrintWorld:
        """The same print after layer ``layer`` (optionally with other defects)."""
        if defects is None or defects == self.defects:
            return replace(self, layer=layer)
        return replace(self, layer=layer, defects=defects, cache={})

    # ------------------------------------------------------------------ heights
    def _moves(self) -> tuple[np.ndarray, np.ndarray]:
        """Moves left out and per-move offsets of all defects (those of a later layer only
        touch moves not printed yet, so every layer's stack is a prefix of one sequence)."""
        prog = self.program
        exclude = np.zeros(prog.layer.size, bool)
        shift = np.zeros((prog.layer.size, 2))
        for d in self.defects:
            if d.kind == "missing_object":
                k = prog.objects.index(d.object)
                exclude |= (prog.object_id == k) & (prog.layer >= d.layer)
            elif d.kind == "layer_shift":
                shift[prog.layer >= d.layer] += d.shift_mm
        return exclude, shift

    def true_heights(self) -> np.ndarray:
        """(rows, columns) float32 heights over :attr:`grid`, µm (cached)."""
        if self._raster is not None:
            return self._raster
        prog, grid, k = self.program, self.grid, self.layer
        if k < 0:
            self._raster = np.zeros(grid.shape, np.float32)
            return self._raster
        below = self._stack(k - 1)
        top = self._stack(k)
        shift = self.cache["moves"][1]
        h = top.height_um
        xs, ys = grid.xy_um()
        gx, gy = np.meshgrid(xs, ys)
        for d in self.defects:
            if d.kind == "gap" and d.layer == k:
                c = self.mapping.apply(np.array(d.xy_mm) + shift[prog.layer == k][:1].sum(0))
                disc = np.hypot(gx - c[0], gy - c[1]) <= d.size_mm * 500.0
                h = np.where(disc, below.height_um, h)
            elif d.kind == "blob" and d.layer == k:
                c = self.mapping.apply(np.array(d.xy_mm))
                s = d.size_mm * 500.0
                h = h + d.height_um * np.exp(-((gx - c[0]) ** 2 + (gy - c[1]) ** 2) / (2 * s * s))
            elif d.kind == "lifted_corner" and d.layer <= k:
                obj = top.label == prog.objects.index(d.object)
                if obj.any():
                    c = self.mapping.apply(np.array(d.xy_mm))
                    ii, jj = np.nonzero(obj)
                    dist = np.hypot(gx[ii, jj] - c[0], gy[ii, jj] - c[1])
                    corner = np.argmin(dist)
                    cx, cy = gx[ii[corner], jj[corner]], gy[ii[corner], jj[corner]]
                    r = np.hypot(gx - cx, gy - cy)
                    lift = d.height_um * np.clip(1.0 - r / (d.size_mm * 1000.0), 0.0, None)
                    h = np.where(obj, h + lift, h)
        self._raster = np.ascontiguousarray(h, dtype=np.float32)
        return self._raster

    def _stack(self, upto: int) -> ExpectedMap:
        """The beads of layers <= upto (incremental over the cached stacks)."""
        c = self.cache
        if "moves" not in c:
            prog = self.program
            if self.bead_jitter_um > 0:
                rng = np.random.default_rng([self.seed, 0xB3AD])
                jitter = rng.normal(0.0, self.bead_jitter_um / 1000.0, prog.layer.size)
                prog = replace(prog, z_mm=prog.z_mm + jitter)
            c["moves"] = self._moves()
            c["program"] = prog
            c["stacks"] = {}
        stacks: dict[int, ExpectedMap] = c["stacks"]
        if upto in stacks:
            return stacks[upto]
        lower = [k for k in stacks if k < upto]
        base = stacks[max(lower)] if lower else None
        exclude, shift = c["moves"]
        out = rasterise_beads(c["program"], self.grid, upto_layer=upto, mapping=self.mapping,
                                 exclude=exclude, shift_mm=shift, base=base)
        stacks[upto] = out
        for k in sorted(stacks)[:-3]:  # keep a few: the scan goes up layer by layer
            if k != upto:
                del stacks[k]
        return out

    def height_um(self, x0: float, y0: float, width: int, height: int) -> np.ndarray:
        """True surface height over a window of world pixels (as PlateWorld.height_um).

        Returns
        -------
        (height, width) float32, µm: the height at world pixels (x0 + i, y0 + j).
        """
        r = self.true_heights()
        g = self.grid
        p = self.pixel_um
        # raster pixel coordinates of the window's centre (getRectSubPix: bilinear)
        cx = (x0 * p - g.origin_um[0]) / p + (width - 1) / 2.0
        cy = (y0 * p - g.origin_um[1]) / p + (height - 1) / 2.0
        big = np.zeros((r.shape[0] + 2, r.shape[1] + 2), np.float32)  # a bed border
        big[1:-1, 1:-1] = r
        out = cv2.getRectSubPix(big, (int(width), int(height)), (cx + 1.0, cy + 1.0))
        return np.asarray(out, dtype=np.float32)

    # ------------------------------------------------------------------ texture
    def texture(self, x0: float, y0: float, width: int, height: int) -> np.ndarray:
        """Reflectance over a window of world pixels (a PlateWorld's random texture)."""
        if self._texture is None:
            self._texture = PlateWorld(seed=self.seed, pixel_um=self.pixel_um)
        return self._texture.texture(x0, y0, width, height)

    def defect_region(self, defect: PrintDefect, *, tolerance_um: float) -> np.ndarray:
        """(rows, columns) bool over :attr:`grid`: where ``defect`` changes the surface at
        its layer by more than ``tolerance_um`` (the truth a detection is scored against)."""
        at = self.at_layer(defect.layer)
        without = self.at_layer(defect.layer,
                                defects=tuple(d for d in self.defects if d != defect))
        return np.abs(at.true_heights() - without.true_heights()) > tolerance_um
