"""Two-step scanning, the scan's side: the focus levels a continuous scan needs from a coarse
prior (:class:`sffscan.stages.fields.coarse_prior.CoarsePrior`), the configuration that runs
only those levels, and the previous layer's mosaic as the prior (``sffscan restrict``).

* :func:`scan_level_range` -- the one staircase a continuous scan can run over the area of
  its passes, :func:`strip_level_range` over the strip it must measure;
* :func:`restrict_scan` -- the configuration that runs it (fewer levels, so a higher speed
  limit);
* :func:`prior_from_mosaic` -- the previous layer's mosaic as the prior.
"""

from __future__ import annotations

import math

import numpy as np
from sffscan.pipeline.config import ScanConfig, config_from_dict
from sffscan.pipeline.plan import pass_bounds_px, pass_start_px, scan_extent_px
from sffscan.stages.fields.coarse_prior import CoarsePrior, field_levels


def scan_level_range(cfg: ScanConfig, prior: CoarsePrior, *, pad_levels: int = 8,
                     pass_index: int | None = None) -> np.ndarray:
    """Focus levels a continuous scan (or one of its passes) needs, from the prior.

    The lens runs one staircase for a whole pass, so the range is that of everything the
    pass's frames see (``sffscan.pipeline.plan``), or of the whole scan when ``pass_index`` is None.
    """
    heights = np.asarray(cfg.optics.focus_heights_um())
    if pass_index is None:
        x0, y0, x1, y1 = scan_extent_px(cfg, slack=0)
    else:
        if not 0 <= pass_index < cfg.motion.passes:
            raise ValueError(f"pass_index must be in 0..{cfg.motion.passes - 1}, "
                             f"got {pass_index}")
        first, last, _ = pass_bounds_px(cfg, pass_index)
        y_first = pass_start_y_px(cfg, pass_index)
        x0, x1 = math.floor(min(first, last)), math.ceil(max(first, last) + cfg.optics.width_px)
        y0, y1 = math.floor(y_first), math.ceil(y_first + cfg.optics.height_px)
    return field_levels(prior, x0=x0, y0=y0, width=x1 - x0, height=y1 - y0,
                        focus_heights_um=heights, pad_levels=pad_levels)


def prior_from_mosaic(path: str, *, uncertainty_um: float,
                      pixel_um: float | None = None) -> CoarsePrior:
    """The previous layer's mosaic (an sffscan mosaic Zarr group) as a prior.

    Its ``height`` array on its own world pixels; NaN (unmeasured) stays NaN, so a field or
    scan that touches it gets the full range. ``pixel_um``, when given, must equal the
    mosaic's pixel scale (world pixels are only comparable at the same scale).
    """
    import zarr
    from sffscan.pipeline.mosaic.layout import mosaic_array
    from sffscan.pipeline.mosaic.reader import read_mosaic_attrs

    try:
        group = zarr.open_group(str(path), mode="r")
    except Exception as exc:  # noqa: BLE001 - anything that is not a readable group
        raise ValueError(f"{path}: not a readable Zarr group ({exc})") from exc
    attrs = read_mosaic_attrs(group, path)
    if pixel_um is not None and not math.isclose(attrs.pixel_um, pixel_um, rel_tol=1e-9):
        raise ValueError(f"{path}: mosaic pixel_um {attrs.pixel_um:g} differs from the "
                         f"scan's optics.pixel_um {pixel_um:g}")
    heights = np.asarray(mosaic_array(group, "height")[:])
    ox, oy = attrs.origin_px
    return CoarsePrior(heights, origin_px=(float(ox), float(oy)), step_px=1.0,
                       uncertainty_um=uncertainty_um)


def strip_level_range(cfg: ScanConfig, prior: CoarsePrior, *,
                      pad_levels: int = 8) -> np.ndarray:
    """Focus levels a continuous scan needs to measure its planned strip, from the prior.

    The strip is what the scan must cover completely: x from ``motion.x_start_mm`` to
    ``motion.x_end_mm``, y over every pass inside the frame margins. The lens runs one
    staircase for the scan, so this is one consecutive range of levels; all levels when the
    prior does not cover the strip or has NaN in it.
    """
    o, m = cfg.optics, cfg.motion
    margin = cfg.processing.edge_margin_px
    x0 = math.ceil(m.x_start_mm * 1000.0 / o.pixel_um)
    x1 = math.floor(m.x_end_mm * 1000.0 / o.pixel_um)
    y0 = math.floor(pass_start_px(cfg, 0)[1]) + margin
    y1 = math.ceil(pass_start_px(cfg, m.passes - 1)[1]) + o.height_px - margin
    return field_levels(prior, x0=x0, y0=y0, width=x1 - x0, height=y1 - y0,
                        focus_heights_um=np.asarray(o.focus_heights_um()),
                        pad_levels=pad_levels)


def pass_start_y_px(cfg: ScanConfig, pass_index: int) -> float:
    return pass_start_px(cfg, pass_index)[1]


def restrict_scan(cfg: ScanConfig, levels: np.ndarray) -> ScanConfig:
    """The scan configuration whose staircase runs only ``levels`` (consecutive).

    ``optics.z_min_um`` moves to the first level's height and ``optics.n_levels`` becomes
    the count; the speed limit (``sffscan.pipeline.config.max_speed_sliding_mm_s``) grows as N
    shrinks. The result is validated like any configuration.
    """
    lv = np.asarray(levels).reshape(-1)
    if lv.size < 3 or not (np.diff(lv) == 1).all() or lv[0] < 0 \
            or lv[-1] >= cfg.optics.n_levels:
        raise ValueError(f"levels must be >= 3 consecutive indices in 0..{cfg.optics.n_levels - 1}")
    data = cfg.model_dump()
    data["optics"]["z_min_um"] = cfg.optics.z_min_um + int(lv[0]) * cfg.optics.z_step_um
    data["optics"]["n_levels"] = int(lv.size)
    return config_from_dict(data, origin="restricted scan")
