"""Comparison of two height maps: RMSE, CORR, PSNR, optional alignment, error histogram.

The metrics are :func:`pipeline.metrology.evaluate.accuracy` (SFF_NOTES section 3); this module adds
reading height maps from files, lining them up, and the histogram of the error
``estimate - reference``. Only pixels finite in both maps count; their number and the
coverage are reported, nothing is filled.

Alignment (``align``), applied to the estimate before the metrics:

- ``"none"``: as they are;
- ``"offset"``: minus the mean difference (a height offset between instruments);
- ``"plane"``: minus the least-squares plane of the difference (offset and tilt);
- ``"shift"``: first the whole-pixel lateral shift (within +-``max_shift_px``) that
  minimises the variance of the difference (an exhaustive search; phase correlation of
  smooth height maps proved unreliable: 6 px off on a stop-and-go mosaic of the simulated
  plate), applied by cropping both maps to their overlap, then ``"plane"``.

Two mosaics (Zarr groups) are lined up by their world origin first: only the world pixels
both cover are compared.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Literal

import numpy as np
from pydantic import BaseModel, ConfigDict, Field
from sffscan.pipeline.metrology.evaluate import accuracy
from sffscan.pipeline.mosaic.attrs import MosaicAttrs

__all__ = [
    "ALIGN_MODES",
    "CompareReport",
    "HeightMap",
    "compare_height_maps",
    "error_histogram",
    "fit_plane",
    "format_report",
    "overlap_by_origin",
    "overlap_uncertainty",
    "read_height_map",
    "region_mask",
]

ALIGN_MODES = ("none", "offset", "plane", "shift")


@dataclass
class HeightMap:
    """A height map read from a file: (H, W) float µm, NaN invalid; world placement if known."""

    height_um: np.ndarray
    source: str
    pixel_um: float | None = None
    origin_px: tuple[int, int] | None = None
    max_depth_um: float | None = None  # span of the focus table, when the file has one
    #: the height's uncertainty, µm, one sigma (a mosaic's ``uncertainty``), when it has one
    uncertainty_um: np.ndarray | None = None


class Histogram(BaseModel):
    model_config = ConfigDict(extra="forbid")

    edges_um: list[float] = Field(description="Bin edges of the error, µm (bins + 1 values)")
    counts: list[int] = Field(description="Pixels per bin")
    below: int = Field(ge=0, description="Pixels with an error below the first edge")
    above: int = Field(ge=0, description="Pixels with an error above the last edge")


class CompareReport(BaseModel):
    """Result of ``sffscan compare`` (written with ``--json``)."""

    model_config = ConfigDict(extra="forbid")

    format: Literal["sffscan-compare"] = "sffscan-compare"
    format_version: Literal[1] = 1
    estimate: str = Field(description="Height map compared (file)")
    reference: str = Field(description="Reference height map (file)")
    align: Literal["none", "offset", "plane", "shift"]
    shift_px: tuple[int, int] = Field(description="(x, y) shift applied to the estimate, px")
    plane_um: tuple[float, float, float] = Field(
        description="Removed a + b x + c y, µm and µm/px (zeros without alignment)")
    rmse_um: float | None = Field(description="Root-mean-square error, µm; null if no pixel")
    mean_error_um: float | None = Field(description="Mean of estimate - reference, µm")
    corr: float | None = Field(description="Pearson correlation")
    psnr_db: float | None = Field(description="PSNR with MAX_d = max_depth_um, dB")
    max_depth_um: float = Field(gt=0, description="MAX_d of the PSNR, µm")
    pixels: int = Field(ge=0, description="Pixels finite in both maps")
    coverage: float = Field(ge=0, le=1, description="pixels / pixels of the compared area")
    histogram: Histogram
    within_2sigma: float | None = Field(
        default=None, ge=0, le=1,
        description="Share of the compared pixels with a finite uncertainty of the estimate "
        "(a mosaic's 'uncertainty', one sigma) whose |estimate - reference| is at most twice "
        "it (calibrated: 0.90 .. 0.98 against a reference whose own error is small); null "
        "without an uncertainty")
    sigma_pixels: int = Field(
        default=0, ge=0, description="Compared pixels with a finite uncertainty of the estimate")


# ----------------------------------------------------------------------------- reading


def read_height_map(path: str | Path, *, array: str = "height") -> HeightMap:
    """Read a height map, µm: a mosaic / Zarr group (its ``array``), a Zarr array, ``.npy``,
    or a float TIFF.

    Raises
    ------
    ValueError
        If the file is not one of those, or the array is not 2-D (the message names the file).
    """
    p = Path(path)
    suffix = p.suffix.lower()
    if suffix == ".npy":
        z = np.load(p, allow_pickle=False)
        return HeightMap(_as_2d(z, p), str(p))
    if suffix in (".tif", ".tiff"):
        try:
            import tifffile
        except ImportError:
            raise ValueError(f"{p}: reading a TIFF height map needs the Python package "
                             "'tifffile', which is not installed here (pip install tifffile; "
                             "or give the map as .npy)") from None
        return HeightMap(_as_2d(tifffile.imread(p), p), str(p))
    if not p.exists():
        raise FileNotFoundError(f"{p}: no such file or folder")
    import zarr

    try:
        node: Any = zarr.open(str(p), mode="r")
    except Exception as err:  # noqa: BLE001 - any unreadable store is bad input
        raise ValueError(f"{p}: not a .npy, TIFF or Zarr height map ({err})") from None
    if isinstance(node, zarr.Group):
        arr = node.get(array)
        if not isinstance(arr, zarr.Array):
            raise ValueError(f"{p}: Zarr group has no array '{array}'")
        hm = HeightMap(_as_2d(np.asarray(arr[...]), p), str(p))
        if node.attrs.get("format") == "sffscan-mosaic":
            attrs = MosaicAttrs.model_validate(node.attrs.asdict())
            hm.pixel_um = attrs.pixel_um
            hm.origin_px = attrs.origin_px
            table = attrs.focus_heights_um
            if len(table) >= 2:
                hm.max_depth_um = float(max(table) - min(table))
            unc = node.get("uncertainty")
            if array == "height" and isinstance(unc, zarr.Array) and unc.shape == arr.shape:
                hm.uncertainty_um = np.asarray(unc[...], dtype=np.float64)
        return hm
    return HeightMap(_as_2d(node[...], p), str(p))


def _as_2d(z: np.ndarray, path: Path) -> np.ndarray:
    z = np.asarray(z)
    if z.ndim != 2 or not (np.issubdtype(z.dtype, np.floating) or np.issubdtype(z.dtype,
                                                                              np.integer)):
        raise ValueError(f"{path}: a height map must be a 2-D numeric array, got shape "
                         f"{z.shape} {z.dtype}")
    if z.dtype.itemsize == 1:  # 256 grey values: a photograph or a mask, not heights in µm
        raise ValueError(f"{path}: an 8-bit array ({z.dtype}) is an image, not a height map "
                         "in µm; give heights as float µm (.npy, float TIFF or a mosaic)")
    return z.astype(np.float64)


def overlap_by_origin(est: HeightMap, ref: HeightMap
                      ) -> tuple[np.ndarray, np.ndarray, tuple[int, int]]:
    """The two maps over the world pixels both cover (same-shape arrays), and the world
    (x, y) px of their element [0, 0].

    A map without a world origin must have the same shape as the other and is taken as
    covering the same pixels: the origin returned is the placed map's (or (0, 0) when
    neither is placed), so a region in world px means the same with either argument order.
    """
    e, r, origin = _overlap(est, ref)
    return est.height_um[e], ref.height_um[r], origin


def overlap_uncertainty(est: HeightMap, ref: HeightMap) -> np.ndarray | None:
    """The estimate's uncertainty (µm, one sigma) over :func:`overlap_by_origin`'s pixels;
    None where ``est`` has none."""
    if est.uncertainty_um is None:
        return None
    return est.uncertainty_um[_overlap(est, ref)[0]]


Window = tuple[slice, slice]


def _overlap(est: HeightMap, ref: HeightMap) -> tuple[Window, Window, tuple[int, int]]:
    """The windows of ``est`` and ``ref`` over the world pixels both cover, and the world
    (x, y) px of their first element (:func:`overlap_by_origin`)."""
    whole = (slice(None), slice(None))
    if est.origin_px is None or ref.origin_px is None:
        if est.height_um.shape != ref.height_um.shape:
            raise ValueError(f"{est.source} is {est.height_um.shape} and {ref.source} is "
                             f"{ref.height_um.shape}: maps without a world origin must have "
                             "the same shape")
        origin = est.origin_px or ref.origin_px or (0, 0)
        return whole, whole, (int(origin[0]), int(origin[1]))
    if est.pixel_um is not None and ref.pixel_um is not None and not math.isclose(
            est.pixel_um, ref.pixel_um, rel_tol=1e-9):
        raise ValueError(f"pixel sizes differ: {est.source} {est.pixel_um} µm, {ref.source} "
                         f"{ref.pixel_um} µm")
    (ex, ey), (rx, ry) = est.origin_px, ref.origin_px
    eh, ew = est.height_um.shape
    rh, rw = ref.height_um.shape
    x0, y0 = max(ex, rx), max(ey, ry)
    x1, y1 = min(ex + ew, rx + rw), min(ey + eh, ry + rh)
    if x1 <= x0 or y1 <= y0:
        raise ValueError(f"{est.source} and {ref.source} do not overlap in world pixels")
    return ((slice(y0 - ey, y1 - ey), slice(x0 - ex, x1 - ex)),
            (slice(y0 - ry, y1 - ry), slice(x0 - rx, x1 - rx)), (x0, y0))


def region_mask(shape: tuple[int, int], origin_px: tuple[int, int],
                region_px: tuple[int, int, int, int]) -> np.ndarray:
    """Boolean mask of the world px box (x0, y0, x1, y1) on an array placed at origin_px."""
    x0, y0, x1, y1 = region_px
    if not (x1 > x0 and y1 > y0):
        raise ValueError(f"region {region_px} must have x0 < x1 and y0 < y1")
    mask = np.zeros(shape, dtype=bool)
    ox, oy = origin_px
    mask[max(y0 - oy, 0):max(y1 - oy, 0), max(x0 - ox, 0):max(x1 - ox, 0)] = True
    if not mask.any():
        raise ValueError(f"region {region_px} lies outside the compared maps")
    return mask


# ----------------------------------------------------------------------------- alignment


def fit_plane(z: np.ndarray) -> tuple[float, float, float]:
    """Least-squares plane ``a + b x + c y`` through the finite pixels of ``z`` (x = column,
    y = row, px), in float64. Needs at least 3 finite pixels not on one line."""
    rows, cols = np.nonzero(np.isfinite(z))
    if rows.size < 3:
        raise ValueError(f"a plane needs at least 3 finite pixels, got {rows.size}")
    cx, cy = cols.mean(), rows.mean()  # centred for conditioning
    a = np.column_stack((np.ones(rows.size), cols - cx, rows - cy))
    coef, *_ = np.linalg.lstsq(a, z[rows, cols].astype(np.float64), rcond=None)
    c0, b, c = (float(v) for v in coef)
    return c0 - b * cx - c * cy, b, c


def _plane(shape: tuple[int, ...], coef: tuple[float, float, float]) -> np.ndarray:
    yy, xx = np.indices(shape, dtype=np.float64)
    return coef[0] + coef[1] * xx + coef[2] * yy


def _lateral_shift(est: np.ndarray, ref: np.ndarray, max_shift_px: int) -> tuple[int, int]:
    """Whole-pixel (x, y) shift of ``est`` relative to ``ref``: the one within
    ``+-max_shift_px`` that minimises the RMS of the offset-removed difference over the
    pixels both maps have (at least half of the smaller map's finite pixels must overlap)."""
    need = 0.5 * min(np.isfinite(est).sum(), np.isfinite(ref).sum())
    best: tuple[float, int, int] | None = None
    for sy in range(-max_shift_px, max_shift_px + 1):
        for sx in range(-max_shift_px, max_shift_px + 1):
            if abs(sx) >= ref.shape[1] or abs(sy) >= ref.shape[0]:
                continue
            e, r = _apply_shift(est, ref, sx, sy)
            d = (e - r)[np.isfinite(e) & np.isfinite(r)]
            if d.size == 0 or d.size < need:
                continue
            score = float(d.var())
            if best is None or score < best[0]:
                best = (score, sx, sy)
    if best is None:
        raise ValueError("cannot align: the maps have too few finite pixels in common")
    return best[1], best[2]


def _apply_shift(est: np.ndarray, ref: np.ndarray, sx: int, sy: int
                 ) -> tuple[np.ndarray, np.ndarray]:
    """Crop both so that est[p + s] lines up with ref[p]."""
    h, w = ref.shape
    if abs(sx) >= w or abs(sy) >= h:
        raise ValueError(f"shift ({sx}, {sy}) px leaves no overlap")
    e = est[max(sy, 0):h + min(sy, 0), max(sx, 0):w + min(sx, 0)]
    r = ref[max(-sy, 0):h + min(-sy, 0), max(-sx, 0):w + min(-sx, 0)]
    return e, r


# ----------------------------------------------------------------------------- comparison


def error_histogram(error: np.ndarray, *, bins: int = 50,
                    range_um: tuple[float, float] | None = None) -> Histogram:
    """Histogram of the finite errors. The default range is symmetric, +-(99.9th percentile
    of |error|); errors outside it are counted in ``below`` / ``above``, not dropped."""
    if bins < 1:
        raise ValueError(f"bins must be >= 1, got {bins}")
    e = error[np.isfinite(error)].astype(np.float64)
    if range_um is None:
        r = float(np.percentile(np.abs(e), 99.9)) if e.size else 1.0
        range_um = (-r, r) if r > 0 else (-1.0, 1.0)
    lo, hi = range_um
    if not hi > lo:
        raise ValueError(f"histogram range must be increasing, got {range_um}")
    counts, edges = np.histogram(e, bins=bins, range=(lo, hi))
    return Histogram(edges_um=[float(v) for v in edges], counts=[int(v) for v in counts],
                     below=int((e < lo).sum()), above=int((e > hi).sum()))


def _finite_or_none(v: float) -> float | None:
    return v if math.isfinite(v) else None


def compare_height_maps(estimate: np.ndarray, reference: np.ndarray, *, max_depth_um: float,
                        align: str = "none", bins: int = 50,
                        range_um: tuple[float, float] | None = None,
                        mask: np.ndarray | None = None, max_shift_px: int = 10,
                        names: tuple[str, str] = ("", ""),
                        sigma: np.ndarray | None = None) -> CompareReport:
    """RMSE, CORR, PSNR and the error histogram of ``estimate`` against ``reference``.

    Parameters
    ----------
    estimate, reference : (H, W) ndarray of float
        Height maps, µm, same shape; NaN = missing.
    max_depth_um : float, keyword-only
        MAX_d of the PSNR, µm (> 0).
    align : {"none", "offset", "plane", "shift"}, keyword-only
        See the module docstring.
    bins, range_um : keyword-only
        Error histogram (see :func:`error_histogram`).
    mask : (H, W) ndarray of bool, keyword-only
        Pixels to score (before a shift); coverage is the finite fraction of them.
    max_shift_px : int, keyword-only
        Largest lateral shift searched by ``align="shift"``, px.
    names : (str, str), keyword-only
        Sources, for the report.
    sigma : (H, W) ndarray of float, keyword-only
        The estimate's uncertainty, µm, one sigma (NaN: unknown), moved with it by a shift:
        the report's ``within_2sigma``. The reference's own error is not in it.

    Returns
    -------
    CompareReport
    """
    if align not in ALIGN_MODES:
        raise ValueError(f"align must be one of {ALIGN_MODES}, got {align!r}")
    if not (max_depth_um > 0 and math.isfinite(max_depth_um)):
        raise ValueError(f"max_depth_um must be > 0, got {max_depth_um}")
    est = np.asarray(estimate, dtype=np.float64)
    ref = np.asarray(reference, dtype=np.float64)
    if est.shape != ref.shape or est.ndim != 2:
        raise ValueError(f"estimate {est.shape} and reference {ref.shape} must be 2-D of the "
                         "same shape")
    sig = None if sigma is None else np.asarray(sigma, dtype=np.float64)
    if sig is not None and sig.shape != est.shape:
        raise ValueError(f"sigma shape {sig.shape} != the estimate's {est.shape}")
    area = np.ones(est.shape, dtype=bool)
    if mask is not None:
        if mask.shape != est.shape:
            raise ValueError(f"mask shape {mask.shape} != {est.shape}")
        area = np.asarray(mask, dtype=bool)
        est = np.where(area, est, np.nan)
    shift = (0, 0)
    if align == "shift":
        shift = _lateral_shift(est, ref, max_shift_px)
        area = _apply_shift(area, area, *shift)[0]
        if sig is not None:
            sig = _apply_shift(sig, sig, *shift)[0]
        est, ref = _apply_shift(est, ref, *shift)
    plane = (0.0, 0.0, 0.0)
    diff = est - ref
    if align == "offset":
        ok = np.isfinite(diff)
        if ok.any():
            plane = (float(diff[ok].mean()), 0.0, 0.0)
    elif align in ("plane", "shift"):
        plane = fit_plane(diff)
    if align != "none":
        est = est - _plane(est.shape, plane)
        diff = est - ref
    acc = accuracy(est, ref, max_depth=max_depth_um, sigma=sig)
    ok = np.isfinite(diff)
    asked = int(area.sum())
    return CompareReport(
        estimate=names[0], reference=names[1], align=align,  # type: ignore[arg-type]
        shift_px=shift, plane_um=plane,
        rmse_um=_finite_or_none(acc.rmse_um),
        mean_error_um=float(diff[ok].mean()) if ok.any() else None,
        corr=_finite_or_none(acc.corr), psnr_db=_finite_or_none(acc.psnr_db),
        max_depth_um=max_depth_um, pixels=acc.pixels,
        coverage=acc.pixels / asked if asked else 0.0,
        histogram=error_histogram(diff, bins=bins, range_um=range_um),
        within_2sigma=_finite_or_none(acc.within_2sigma), sigma_pixels=acc.sigma_pixels)


def format_report(r: CompareReport) -> str:
    """Human-readable summary with a text histogram."""
    def f(v: float | None, fmt: str) -> str:
        return "n/a" if v is None else format(v, fmt)

    lines = [f"compare {r.estimate} against {r.reference} (align: {r.align})"]
    if r.align == "shift":
        lines.append(f"  lateral shift  {r.shift_px[0]:+d}, {r.shift_px[1]:+d} px")
    if r.align != "none":
        lines.append(f"  removed plane  {r.plane_um[0]:+.3f} µm {r.plane_um[1]:+.3g} µm/px x "
                     f"{r.plane_um[2]:+.3g} µm/px y")
    lines += [f"  pixels         {r.pixels} ({100 * r.coverage:.1f} % of the compared area)",
              f"  RMSE           {f(r.rmse_um, '.3f')} µm",
              f"  mean error     {f(r.mean_error_um, '+.3f')} µm",
              f"  CORR           {f(r.corr, '.5f')}",
              f"  PSNR           {f(r.psnr_db, '.2f')} dB (MAX_d {r.max_depth_um:g} µm)"]
    if r.within_2sigma is not None:
        lines.append(f"  within 2 sigma {100 * r.within_2sigma:.1f} % of {r.sigma_pixels} px (the "
                     "estimate's uncertainty; the reference's own error not in it)")
    lines.append("  error histogram (µm):")
    h = r.histogram
    top = max(h.counts) if h.counts and max(h.counts) > 0 else 1
    if h.below:
        lines.append(f"    {'< ' + format(h.edges_um[0], '.3g'):>22s} {h.below:>9d}")
    for lo, hi, n in zip(h.edges_um[:-1], h.edges_um[1:], h.counts, strict=True):
        lines.append(f"    {lo:>10.3g} .. {hi:<8.3g} {n:>9d} {'#' * round(40 * n / top)}")
    if h.above:
        lines.append(f"    {'> ' + format(h.edges_um[-1], '.3g'):>22s} {h.above:>9d}")
    return "\n".join(lines)
