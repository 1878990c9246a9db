"""Accuracy of a height map against a reference: RMSE, CORR, PSNR (SFF_NOTES section 3),
and how well its height uncertainty describes its errors.

RMSE = sqrt(mean((D_hat - D)^2)); CORR = Pearson correlation of D_hat and D;
PSNR = 20 log10(MAX_d) - 10 log10(mean((D_hat - D)^2)), MAX_d the largest representable
depth (the span of the focus-level table). Only pixels where both maps are finite count.
Where the map has a one-sigma uncertainty (a mosaic's ``uncertainty``), the share of the
compared pixels with a finite sigma whose |D_hat - D| <= 2 sigma (issue 24's calibration
bar: 0.90 .. 0.98). The mosaic is compared band by band, so memory stays bounded for any
mosaic size.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Protocol

import numpy as np
import zarr
from pydantic import ValidationError
from sffscan.pipeline.mosaic.attrs import MosaicAccuracy, MosaicAttrs
from sffscan.pipeline.mosaic.layout import mosaic_array, present_arrays


class HeightWorld(Protocol):
    def height_um(self, x0: float, y0: float, width: int, height: int) -> np.ndarray: ...


@dataclass
class Accuracy:
    rmse_um: float
    corr: float
    psnr_db: float
    pixels: int
    coverage: float  # finite fraction of the pixels asked about
    within_2sigma: float = math.nan  # share of the sigma_pixels with |error| <= 2 sigma
    sigma_pixels: int = 0  # compared pixels with a finite uncertainty


class _Moments:
    """Streaming sums for RMSE and Pearson correlation."""

    def __init__(self) -> None:
        self.n = 0
        self.asked = 0
        self.se = self.sx = self.sy = self.sxx = self.syy = self.sxy = 0.0
        self.rated = self.within = 0

    def add(self, est: np.ndarray, ref: np.ndarray, asked: np.ndarray | None = None,
            sigma: np.ndarray | None = None) -> None:
        ok = np.isfinite(est) & np.isfinite(ref)
        self.asked += int(ok.size if asked is None else asked.sum())
        if asked is not None:
            ok &= asked
        x = est[ok].astype(np.float64)
        y = ref[ok].astype(np.float64)
        if sigma is not None:
            s = np.asarray(sigma, np.float64)[ok]
            rated = np.isfinite(s)
            self.rated += int(rated.sum())
            self.within += int((np.abs(x - y)[rated] <= 2.0 * s[rated]).sum())
        self.n += x.size
        self.se += float(((x - y) ** 2).sum())
        self.sx += float(x.sum())
        self.sy += float(y.sum())
        self.sxx += float((x * x).sum())
        self.syy += float((y * y).sum())
        self.sxy += float((x * y).sum())

    def result(self, max_depth: float) -> Accuracy:
        if self.n == 0:
            return Accuracy(math.nan, math.nan, math.nan, 0, 0.0)
        mse = self.se / self.n
        cov = self.sxy / self.n - (self.sx / self.n) * (self.sy / self.n)
        vx = self.sxx / self.n - (self.sx / self.n) ** 2
        vy = self.syy / self.n - (self.sy / self.n) ** 2
        corr = cov / math.sqrt(vx * vy) if vx > 0 and vy > 0 else math.nan
        psnr = 20 * math.log10(max_depth) - 10 * math.log10(mse) if mse > 0 else math.inf
        cover = self.n / self.asked if self.asked else 0.0
        within = self.within / self.rated if self.rated else math.nan
        return Accuracy(math.sqrt(mse), corr, psnr, self.n, cover, within, self.rated)


def accuracy(estimate: np.ndarray, reference: np.ndarray, *, max_depth: float,
             mask: np.ndarray | None = None, sigma: np.ndarray | None = None) -> Accuracy:
    """RMSE, CORR and PSNR of ``estimate`` against ``reference`` (same shape and unit).

    Parameters
    ----------
    estimate, reference : ndarray, (H, W)
        Height maps, same unit (µm here); NaN marks missing pixels.
    max_depth : float
        MAX_d of the PSNR, same unit.
    mask : ndarray of bool, optional
        Pixels to score; coverage is the finite fraction of them.
    sigma : ndarray, (H, W), optional
        The estimate's one-sigma uncertainty, same unit (NaN: unknown): ``within_2sigma``
        is the share of the scored pixels with a finite sigma whose error is at most
        2 sigma (NaN without any).
    """
    if estimate.shape != reference.shape:
        raise ValueError(f"estimate shape {estimate.shape} != reference shape {reference.shape}")
    if sigma is not None and np.shape(sigma) != estimate.shape:
        raise ValueError(f"sigma shape {np.shape(sigma)} != estimate shape {estimate.shape}")
    mom = _Moments()
    mom.add(estimate, reference, mask, sigma)
    return mom.result(max_depth)


def mosaic_accuracy(path: str | Path, world: HeightWorld, *, max_depth: float,
                    region_px: tuple[int, int, int, int] | None = None,
                    band_rows: int = 256) -> Accuracy:
    """Compare a mosaic's ``height`` with the true surface of a simulated world, and its
    ``uncertainty`` (where the mosaic has one) with the errors.

    ``region_px`` = (x0, y0, x1, y1) world px limits the score to that box (coverage is
    then the finite fraction of it); by default every finite mosaic pixel counts.
    """
    group = zarr.open_group(str(path), mode="r", use_consolidated=False)
    height = mosaic_array(group, "height")
    sigma = (mosaic_array(group, "uncertainty") if "uncertainty" in present_arrays(group)
             else None)
    ox, oy = MosaicAttrs.model_validate(group.attrs.asdict()).origin_px
    rows, cols = height.shape
    c0, c1, r0, r1 = 0, cols, 0, rows
    if region_px is not None:
        c0, r0 = max(region_px[0] - ox, 0), max(region_px[1] - oy, 0)
        c1, r1 = min(region_px[2] - ox, cols), min(region_px[3] - oy, rows)
    mom = _Moments()
    for b0 in range(r0, r1, band_rows):
        b1 = min(b0 + band_rows, r1)
        est = np.asarray(height[b0:b1, c0:c1])
        ref = world.height_um(ox + c0, oy + b0, c1 - c0, b1 - b0)
        asked = np.ones(est.shape, bool) if region_px is not None else np.isfinite(est)
        mom.add(est, ref, asked, None if sigma is None else np.asarray(sigma[b0:b1, c0:c1]))
    return mom.result(max_depth)


#: the ``truth`` of an accuracy against the simulator's world
SIM_TRUTH = "the simulation's true surface"


def uncertainty_line(within_2sigma: float, pixels: int, *, truth: str) -> str:
    """The summary line of an uncertainty scored against ``truth`` (what a scan, ``info``
    and ``stopgo`` print): the share within 2 sigma and the band it is calibrated to."""
    return (f"uncertainty {100 * within_2sigma:.1f} % of {pixels} px within 2 sigma of "
            f"{truth} (calibrated: 90-98 %)")


def _finite(v: float, lo: float = -math.inf, hi: float = math.inf) -> float | None:
    return min(max(float(v), lo), hi) if math.isfinite(v) else None


def store_accuracy(mosaic: str | Path, acc: Accuracy, *, truth: str) -> MosaicAccuracy:
    """Store ``acc`` (of :func:`~sffscan.pipeline.metrology.evaluate.mosaic_accuracy`) in the
    mosaic's attributes (``accuracy``), validated with the other attributes; returns it."""
    group = zarr.open_group(str(mosaic), mode="r+", use_consolidated=False)
    stored = MosaicAccuracy(truth=truth, rmse_um=_finite(acc.rmse_um, 0.0),
                            corr=_finite(acc.corr, -1.0, 1.0), psnr_db=_finite(acc.psnr_db),
                            pixels=acc.pixels, coverage=min(max(acc.coverage, 0.0), 1.0),
                            within_2sigma=_finite(acc.within_2sigma, 0.0, 1.0),
                            sigma_pixels=acc.sigma_pixels)
    value = stored.model_dump(mode="json")
    MosaicAttrs.model_validate({**group.attrs.asdict(), "accuracy": value})  # still valid
    group.update_attributes({"accuracy": value})
    return stored


def stored_accuracy(attrs: dict[str, Any]) -> MosaicAccuracy | None:
    """The accuracy a mosaic's attributes hold; None if not stored (or unreadable: a mosaic
    made before it was stored, or by a later version)."""
    raw = attrs.get("accuracy")
    if raw is None:
        return None
    try:
        return MosaicAccuracy.model_validate(raw)
    except ValidationError:
        return None
