"""The ``cover`` of a mosaic: its valid heights as a fraction of what its scan's plan
measures (``sffscan batch``'s cover column)."""

from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np
import zarr

if TYPE_CHECKING:
    from sffscan.pipeline.config import ScanConfig

__all__ = ["plan_cover", "planned_box_px"]


def planned_box_px(cfg: ScanConfig) -> tuple[int, int, int, int]:
    """World px box (x0, y0, x1, y1), end-exclusive, that the scan's plan measures: the strip
    [motion.x_start_mm, motion.x_end_mm] along x; along y, the rows of the passes' frames
    within ``processing.edge_margin_px`` of their edges (:mod:`sffscan.pipeline.plan`)."""
    import math

    from sffscan.pipeline.config import pass_pitch_px

    o, m = cfg.optics, cfg.motion
    px_per_mm = 1000.0 / o.pixel_um
    edge = cfg.processing.edge_margin_px
    y_first = m.y_start_mm * px_per_mm
    y_last = y_first + (m.passes - 1) * pass_pitch_px(cfg)
    return (math.ceil(m.x_start_mm * px_per_mm), math.ceil(y_first + edge),
            math.floor(m.x_end_mm * px_per_mm), math.floor(y_last + o.height_px - edge))


def plan_cover(mosaic: str | Path, *, band_rows: int = 512) -> float | None:
    """The ``cover`` of a mosaic: its valid (finite) heights inside the box its scan's plan
    measures (:func:`planned_box_px`), as a fraction of that box's pixels (pixels of the
    box outside the mosaic count as not valid). A layer that lost pixels to a corrupt frame
    reads less than 1 (the accuracy's ``coverage`` is the finite fraction of the finite
    pixels: always 1). None if the mosaic has no readable scan configuration."""
    from pydantic import ValidationError
    from sffscan.pipeline.config import ScanConfig
    from sffscan.pipeline.mosaic.layout import mosaic_array

    group = zarr.open_group(str(mosaic), mode="r", use_consolidated=False)
    attrs = group.attrs.asdict()
    try:
        cfg = ScanConfig.model_validate(attrs.get("scan_config"))
        ox, oy = (int(v) for v in attrs["origin_px"])  # type: ignore[union-attr,arg-type]
    except (ValidationError, KeyError, TypeError, ValueError):
        return None
    x0, y0, x1, y1 = planned_box_px(cfg)
    if x1 <= x0 or y1 <= y0:
        return None
    height = mosaic_array(group, "height")
    rows, cols = height.shape
    c0, c1 = max(x0 - ox, 0), min(x1 - ox, cols)
    r0, r1 = max(y0 - oy, 0), min(y1 - oy, rows)
    valid = 0
    for b0 in range(r0, r1, band_rows):
        if c1 > c0:
            valid += int(np.isfinite(np.asarray(height[b0:min(b0 + band_rows, r1), c0:c1])).sum())
    return valid / ((x1 - x0) * (y1 - y0))
