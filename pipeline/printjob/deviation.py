"""Deviation of a layer's scan from what should have been printed, and its verdicts.

Pixel classes (on the mosaic grid):

- *unknown*: no height (NaN, not scanned), confidence below ``min_confidence``, or an
  uncertainty (where the mosaic has one) above the tolerance: never counted as pass;
- *edge*: within ``edge_band_um`` of a step of the expected surface higher than the
  tolerance (a focus window straddling a step cannot be judged): not judged;
- *out*: ``|measured - expected| > tolerance_um``; *in* otherwise.

Out pixels are grouped into 8-connected blobs, joined through the pixels that were measured
but whose uncertainty is over the tolerance (they are not counted out; a blob's area is its
out pixels'); blobs smaller than ``min_blob_mm2`` are noise. A defect's rim and its slopes are
steps, whose height uncertainty (the curve's excess width,
:mod:`sffscan.stages.depth_uncertainty`) is large: without the joining those unknown pixels
cut one defect into pieces under ``fail_area_mm2`` (the print-job bench's blob of layer 4,
2026-12-05: 0.87 mm² out in pieces of 0.43, 0.28 and 0.16 mm², `warn`; joined, one blob of
0.87 mm², `fail`).
Each pixel belongs to the object of the expected bead on it, or, off the part, to the
nearest object within ``object_margin_um`` (material pushed off the part: a layer shift).
An object's verdict is ``fail`` when its largest blob is >= ``fail_area_mm2``, ``warn``
when its blobs total >= ``warn_area_mm2``, else ``unknown`` when more than
``max_unknown_fraction`` of its footprint's pixels (where its expected beads are, off the
edge band) are unknown, else ``pass``. The layer's verdict is
the worst of its objects' (fail > warn > unknown > pass); a failed scan is ``unknown``.
"""

from __future__ import annotations

import math
from typing import Literal

import numpy as np
from pydantic import BaseModel, ConfigDict, Field
from scipy import ndimage
from sffscan.pipeline.printjob.expected import (
    ExpectedMap,
    Grid,
    PrinterMapping,
    rasterise_expected,
)
from sffscan.pipeline.printjob.gcode import GcodeProgram

__all__ = ["LayerVerdict", "ObjectVerdict", "Tolerances", "Verdict", "compare_layer",
           "deviation_map", "failed_layer_verdict", "fit_printer_mapping", "worst"]

Verdict = Literal["pass", "warn", "fail", "unknown"]
_RANK = {"pass": 0, "unknown": 1, "warn": 2, "fail": 3}


class Tolerances(BaseModel):
    """Tolerances and actions of the verdicts (``[job.tolerances]``)."""

    model_config = ConfigDict(extra="forbid", frozen=True, allow_inf_nan=False)
    tolerance_um: float = Field(100.0, gt=0, description="|deviation| above this is out, µm")
    min_confidence: float = Field(0.05, ge=0, le=1, description="Pixels of lower confidence "
                                  "are unknown (0..1, the mosaic's confidence)")
    min_blob_mm2: float = Field(0.1, ge=0, description="Smaller out-of-tolerance blobs are "
                                "noise, mm²")
    warn_area_mm2: float = Field(0.2, ge=0, description="Out-of-tolerance area of an object "
                                 "that warns, mm²")
    fail_area_mm2: float = Field(0.5, ge=0, description="Largest blob of an object that "
                                 "fails it, mm²")
    edge_band_um: float = Field(150.0, ge=0, description="Band around expected steps that is "
                                "not judged, µm")
    object_margin_um: float = Field(2000.0, ge=0, description="Off-part pixels this close to "
                                    "an object belong to it, µm")
    max_unknown_fraction: float = Field(0.1, ge=0, le=1, description="An object with more "
                                        "unknown pixels is unknown, not pass (fraction)")
    action: Literal["none", "pause", "cancel_object"] = Field(
        "none", description="What a failing verdict asks the printer to do")


class ObjectVerdict(BaseModel):
    """Statistics and verdict of one object on one layer."""

    name: str
    verdict: Verdict
    pixels: int = Field(description="Pixels of the object's expected footprint")
    unknown_fraction: float = Field(description="Unknown fraction of the footprint's pixels "
                                    "off the edge band")
    p95_abs_um: float | None = Field(description="95th percentile of |deviation| over the "
                                     "judged pixels, µm; None without any")
    rms_um: float | None
    area_out_mm2: float = Field(description="Blobs out of tolerance, mm²")
    missing_mm2: float = Field(description="Out-of-tolerance area below the expected, mm²")
    excess_mm2: float = Field(description="Out-of-tolerance area above the expected, mm²")
    defect_area_mm2: float = Field(0.0, description="Area of the largest blob, mm²")
    defect_xy_um: tuple[float, float] | None = Field(
        None, description="Centroid of the largest blob, mosaic µm")
    defect_xy_mm: tuple[float, float] | None = Field(
        None, description="Centroid of the largest blob, printer mm")


class LayerVerdict(BaseModel):
    """The verdict of one layer (stored as ``verdict.json`` in the job store)."""

    layer: int
    z_mm: float
    verdict: Verdict
    reason: str = ""
    objects: list[ObjectVerdict] = Field(default_factory=list)
    tolerances: Tolerances = Field(default_factory=Tolerances)
    action: Literal["none", "pause", "cancel_object"] = "none"
    compute_s: float = Field(0.0, description="Time the comparison took, s")


def worst(verdicts: list[str]) -> Verdict:
    """The worst of several verdicts (fail > warn > unknown > pass); ``unknown`` if empty."""
    if not verdicts:
        return "unknown"
    top = max(verdicts, key=lambda v: _RANK[v])
    return "fail" if top == "fail" else "warn" if top == "warn" else (
        "unknown" if top == "unknown" else "pass")


def deviation_map(measured_um: np.ndarray, expected_um: np.ndarray) -> np.ndarray:
    """Measured minus expected height, µm.

    Parameters
    ----------
    measured_um, expected_um : (rows, columns) array_like of float
        Heights on the same grid, µm; NaN where not measured.

    Returns
    -------
    (rows, columns) float32, µm; NaN where the measurement is NaN.
    """
    m = np.asarray(measured_um, dtype=np.float32)
    e = np.asarray(expected_um, dtype=np.float32)
    if m.shape != e.shape:
        raise ValueError(f"measured {m.shape} and expected {e.shape} maps differ in shape")
    return m - e


def failed_layer_verdict(layer: int, z_mm: float, objects: tuple[str, ...] | list[str], *,
                         reason: str, tolerances: Tolerances | None = None) -> LayerVerdict:
    """The verdict of a layer whose scan failed or timed out: every object ``unknown``."""
    objs = [ObjectVerdict(name=n, verdict="unknown", pixels=0, unknown_fraction=1.0,
                          p95_abs_um=None, rms_um=None, area_out_mm2=0.0, missing_mm2=0.0,
                          excess_mm2=0.0) for n in objects]
    return LayerVerdict(layer=layer, z_mm=z_mm, verdict="unknown", reason=reason,
                        objects=objs, tolerances=tolerances or Tolerances())


def _regions(label: np.ndarray, margin_px: float) -> np.ndarray:
    """Each pixel's object: its own label, or the nearest labelled pixel's within margin."""
    if not (label < 0).any() or not (label >= 0).any():
        return label.astype(np.int32)
    dist, (ri, ci) = ndimage.distance_transform_edt(label < 0, return_indices=True)
    near = label[ri, ci].astype(np.int32)
    return np.where(dist <= margin_px, near, -1)


def compare_layer(measured_um: np.ndarray, expected: ExpectedMap, *, grid: Grid,
                  objects: tuple[str, ...] | list[str], layer: int, z_mm: float,
                  confidence: np.ndarray | None = None, uncertainty_um: np.ndarray | None = None,
                  tolerances: Tolerances | None = None,
                  mapping: PrinterMapping | None = None) -> tuple[np.ndarray, LayerVerdict]:
    """Deviation map and verdict of one layer.

    Parameters
    ----------
    measured_um : (rows, columns) array_like of float
        The layer's scan on ``grid``, µm; NaN where not measured.
    expected : ExpectedMap
        What should have been printed up to this layer, on ``grid``.
    grid : Grid, keyword-only
        The common grid (pixel size for areas, coordinates for locations).
    objects : sequence of str, keyword-only
        Object names (the program's ``objects``: ``expected.label`` indexes them).
    layer, z_mm : int, float, keyword-only
        The layer's index and height (recorded in the verdict).
    confidence : (rows, columns) array_like of float, keyword-only
        The mosaic's confidence (0..1); pixels below ``min_confidence`` are unknown.
    uncertainty_um : (rows, columns) array_like of float, keyword-only
        A height uncertainty, µm, where the mosaic has one; above the tolerance: unknown.
    tolerances : Tolerances, keyword-only
        Tolerances and action; default :class:`Tolerances()`.
    mapping : PrinterMapping, keyword-only
        Printer -> mosaic coordinates, to report defect locations in printer mm too.

    Returns
    -------
    deviation : (rows, columns) float32
        Measured - expected, µm (NaN where not measured).
    verdict : LayerVerdict
    """
    import time

    t0 = time.perf_counter()
    tol = tolerances or Tolerances()
    dev = deviation_map(measured_um, expected.height_um)
    p = grid.pixel_um
    px_mm2 = (p / 1000.0) ** 2
    unknown = ~np.isfinite(dev)
    if confidence is not None:
        c = np.asarray(confidence, dtype=np.float32)
        unknown |= ~(c >= tol.min_confidence)
    uncertain = np.zeros(dev.shape, bool)
    if uncertainty_um is not None:
        u = np.asarray(uncertainty_um, dtype=np.float32)
        uncertain = np.isfinite(dev) & ~(u <= tol.tolerance_um)
        unknown |= uncertain
    band = math.ceil(tol.edge_band_um / p)
    e = expected.height_um
    if band > 0:
        size = 2 * band + 1
        edge = (ndimage.maximum_filter(e, size) - ndimage.minimum_filter(e, size)
                > tol.tolerance_um)
    else:
        edge = np.zeros(e.shape, bool)
    judged = ~unknown & ~edge
    adev = np.abs(np.nan_to_num(dev))
    out = judged & (adev > tol.tolerance_um)
    # blobs joined through measured, uncertain pixels; their sizes count out pixels only
    blobs, n_blobs = ndimage.label(out | (uncertain & ~edge), structure=np.ones((3, 3), bool))
    region = _regions(expected.label, tol.object_margin_um / p)
    results: list[ObjectVerdict] = []
    for k, name in enumerate(objects):
        own = expected.label == k
        n = int(own.sum())
        if n == 0:  # not printed on this layer's area (or not yet): nothing to judge
            continue
        mine = region == k  # its own pixels and the off-part ones nearest to it
        core = own & ~edge  # unscanned margins and the edge band (not judged) do not count
        if not core.any():
            core = own
        unk = float((unknown & core).sum()) / float(core.sum())
        jm = judged & mine
        vals = adev[jm]
        p95 = float(np.percentile(vals, 95)) if vals.size else None
        rms = float(np.sqrt(np.mean(dev[jm].astype(np.float64) ** 2))) if vals.size else None
        ids = blobs[out & mine]
        area_out = missing = excess = biggest = 0.0
        where = where_mm = None
        if ids.size:
            counts = np.bincount(ids, minlength=n_blobs + 1)
            keep = counts * px_mm2 >= tol.min_blob_mm2
            keep[0] = False
            kept = keep[blobs] & mine & out
            area_out = float(kept.sum()) * px_mm2
            missing = float((kept & (dev < 0)).sum()) * px_mm2
            excess = float((kept & (dev > 0)).sum()) * px_mm2
            if keep.any():
                big = int(np.argmax(np.where(keep, counts, 0)))
                biggest = float(counts[big]) * px_mm2
                ii, jj = np.nonzero((blobs == big) & mine & out)
                xy = (grid.origin_um[0] + p * float(jj.mean()),
                      grid.origin_um[1] + p * float(ii.mean()))
                where = xy
                if mapping is not None:
                    q = mapping.inverse(np.array(xy))
                    where_mm = (float(q[0]), float(q[1]))
        if biggest >= tol.fail_area_mm2:
            v: Verdict = "fail"
        elif area_out >= tol.warn_area_mm2:
            v = "warn"
        elif unk > tol.max_unknown_fraction:
            v = "unknown"
        else:
            v = "pass"
        results.append(ObjectVerdict(
            name=name, verdict=v, pixels=n, unknown_fraction=unk, p95_abs_um=p95, rms_um=rms,
            area_out_mm2=area_out, missing_mm2=missing, excess_mm2=excess,
            defect_area_mm2=biggest, defect_xy_um=where, defect_xy_mm=where_mm))
    overall = worst([r.verdict for r in results])
    reason = "; ".join(f"{r.name}: {r.verdict} ({r.area_out_mm2:.2f} mm² out of "
                       f"±{tol.tolerance_um:g} µm, {100 * r.unknown_fraction:.0f} % unknown)"
                       for r in results if r.verdict != "pass")
    if not results:
        reason = "no object on the scanned grid"
    action = tol.action if overall == "fail" else "none"
    return dev, LayerVerdict(layer=layer, z_mm=z_mm, verdict=overall, reason=reason,
                             objects=results, tolerances=tol, action=action,
                             compute_s=time.perf_counter() - t0)


def fit_printer_mapping(measured_um: np.ndarray, program: GcodeProgram, grid: Grid, *,
                        layer: int = 0, initial: PrinterMapping | None = None,
                        confidence: np.ndarray | None = None,
                        min_confidence: float = 0.05) -> PrinterMapping:
    """Fit the printer -> mosaic translation from a scan of a printed layer.

    The expected map of layers ``<= layer`` under ``initial`` is phase-correlated with the
    measured map (:func:`sffscan.stages.phase_correlation.phase_correlate`, the
    registration's: each map's mean removed before the Hann window, the cross-power
    spectrum weighted to a Gaussian peak); the translation found is added to ``initial``'s
    offset (its rotation is kept). The scan must cover the printed layer and ``initial``
    must be within a quarter of the grid of the truth. A peak that unrelated maps would
    reach (:func:`~sffscan.stages.phase_correlation.is_significant`) is refused: no fit.
    (``cv2.phaseCorrelate``, used before, weighs every frequency alike and found a peak
    2.2 mm off on a tiny simulated job whose depth method changed, with a response of
    0.03; this one found the same offset within 0.6 px on both height maps.)

    Parameters
    ----------
    measured_um : (rows, columns) array_like of float
        Scan of the layer (the first layer, or a printed fiducial), µm; NaN allowed.
    program : GcodeProgram
        The print.
    grid : Grid
        The scan's grid.
    layer : int, keyword-only
        Last layer the scan shows.
    initial : PrinterMapping, keyword-only
        Starting guess; default the identity.
    confidence : (rows, columns) array_like of float, keyword-only
        Pixels below ``min_confidence`` are ignored (set to the median height).

    Returns
    -------
    PrinterMapping

    Raises
    ------
    ValueError
        No valid measured pixel, or no significant correlation peak (its height and the
        runner-up's named).
    """
    from sffscan.stages.phase_correlation import is_significant, phase_correlate

    m0 = initial or PrinterMapping()
    exp = rasterise_expected(program, grid, upto_layer=layer, mapping=m0).height_um
    meas = np.asarray(measured_um, dtype=np.float64).copy()
    bad = ~np.isfinite(meas)
    if confidence is not None:
        bad |= ~(np.asarray(confidence) >= min_confidence)
    if bad.all():
        raise ValueError("fit_printer_mapping: no valid measured pixel")
    meas[bad] = np.median(meas[~bad])
    c = phase_correlate(exp.astype(np.float32), meas.astype(np.float32))
    if not is_significant(c, exp.shape):
        raise ValueError(f"no significant correlation peak between the expected and the "
                         f"measured layer (peak {c.peak:.3f}, runner-up {c.runner_up:.3f})")
    sx, sy = c.sx, c.sy
    p = grid.pixel_um
    return PrinterMapping(offset_um=(m0.offset_um[0] + sx * p, m0.offset_um[1] + sy * p),
                          rotation_deg=m0.rotation_deg)
