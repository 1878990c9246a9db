"""A simulated print: the world's height built from a G-code's beads, with injected defects.

A :class:`PrintWorld` has the interface the simulated camera uses (``pixel_um``,
``height_um``, ``texture``), like :class:`~sffscan.stages.sim.world.PlateWorld`, so
:func:`sffscan.stages.sim.scanner.simulate_frames` scans it unchanged. Its surface is the
top of the beads of layers ``0 .. layer`` (:meth:`PrintWorld.at_layer`), rasterised with
the same bead model the expected map uses
(:func:`sffscan.pipeline.printjob.expected.rasterise_expected`), plus a small random bead
height jitter, plus the defects whose layer has been reached:

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
from sffscan.pipeline.printjob.expected import (
    ExpectedMap,
    Grid,
    PrinterMapping,
    rasterise_expected,
)
from sffscan.pipeline.printjob.gcode import GcodeProgram
from sffscan.stages.sim.world import PlateWorld

__all__ = ["DefectKind", "PrintDefect", "PrintWorld"]

DefectKind = Literal["gap", "blob", "lifted_corner", "layer_shift", "missing_object"]
PERSISTENT = ("lifted_corner", "layer_shift", "missing_object")


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

    program: GcodeProgram
    mapping: PrinterMapping
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
        out = rasterise_expected(c["program"], self.grid, upto_layer=upto, mapping=self.mapping,
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
