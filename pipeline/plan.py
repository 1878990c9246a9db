"""Scan plan: where the stage is at every frame, and the area the mosaic must hold.

A pass moves the stage at constant speed along x over the strip
[motion.x_start_mm, motion.x_end_mm]. It starts just before the strip's first column
enters the usable part of the frame and ends once the strip's last column has been seen
at all N focus levels (plus a few frames for rounding and wobble). Passes are stepped along
y by :func:`sffscan.pipeline.config.pass_pitch_px` and alternate direction when ``serpentine``.
The lens staircase runs continuously: frame k is at focus level k mod N.
"""

from __future__ import annotations

import math
from collections.abc import Iterator
from dataclasses import dataclass

from sffscan.pipeline.config import ScanConfig, pass_pitch_px, shift_per_frame_px

PASS_GAP_S = 0.5  # time between passes (the stage returns or steps across), s


@dataclass(frozen=True, slots=True)
class PlannedFrame:
    frame_id: int
    timestamp_ns: int
    focus_index: int
    x_px: float  # commanded world x of the frame's first column, px
    y_px: float  # commanded world y of the frame's first row, px
    pass_index: int
    travel_px: float  # distance travelled since the start of the pass, px


def pass_direction(cfg: ScanConfig, pass_index: int) -> int:
    """+1 or -1: direction of travel of a pass."""
    return -1 if (cfg.motion.serpentine and pass_index % 2 == 1) else 1


def pass_bounds_px(cfg: ScanConfig, pass_index: int) -> tuple[float, float, int]:
    """First x position, last x position (px) and number of frames of one pass."""
    o, p = cfg.optics, cfg.processing
    px = o.pixel_um / 1000.0
    xs, xe = cfg.motion.x_start_mm / px, cfg.motion.x_end_mm / px
    d = shift_per_frame_px(cfg)
    m = p.edge_margin_px
    slack = 2 * (cfg.motion.wobble_along_px + 1.0)
    # +x: the strip's first column enters at the right edge; its last column must then be
    # seen N times after entering.
    start = xs - (o.width_px - m) - d - slack
    end = xe - (o.width_px - m) + (o.n_levels + 2) * d + slack
    n = int(math.ceil((end - start) / d)) + 1
    if pass_direction(cfg, pass_index) == 1:
        return start, start + (n - 1) * d, n
    # -x: mirror about the strip
    first = xe - m + d + slack
    return first, first - (n - 1) * d, n


def pass_start_px(cfg: ScanConfig, pass_index: int) -> tuple[float, float, int]:
    """World (x, y) px of a pass's first frame, and its direction of travel."""
    y0 = cfg.motion.y_start_mm * 1000.0 / cfg.optics.pixel_um
    return (pass_bounds_px(cfg, pass_index)[0], y0 + pass_index * pass_pitch_px(cfg),
            pass_direction(cfg, pass_index))


def plan_frames(cfg: ScanConfig) -> Iterator[PlannedFrame]:
    """Every frame of the scan, in acquisition order."""
    o = cfg.optics
    d = shift_per_frame_px(cfg)
    pitch = pass_pitch_px(cfg)
    y0 = cfg.motion.y_start_mm * 1000.0 / o.pixel_um
    frame_id = 0
    t_ns = 0.0
    dt_ns = 1e9 / o.fps
    for p in range(cfg.motion.passes):
        first, _, n = pass_bounds_px(cfg, p)
        sign = pass_direction(cfg, p)
        for k in range(n):
            yield PlannedFrame(frame_id, int(round(t_ns)), frame_id % o.n_levels,
                               first + sign * k * d, y0 + p * pitch, p, k * d)
            frame_id += 1
            t_ns += dt_ns
        t_ns += PASS_GAP_S * 1e9


def frame_count(cfg: ScanConfig) -> int:
    return sum(pass_bounds_px(cfg, p)[2] for p in range(cfg.motion.passes))


def scan_extent_px(cfg: ScanConfig, *, slack: int = 16) -> tuple[int, int, int, int]:
    """World pixel box (x0, y0, x1, y1) that every frame of the scan falls inside."""
    o = cfg.optics
    xs: list[float] = []
    for p in range(cfg.motion.passes):
        first, last, _ = pass_bounds_px(cfg, p)
        xs += [first, last]
    wob = cfg.motion.wobble_along_px + cfg.motion.wobble_across_px
    y_first = cfg.motion.y_start_mm * 1000.0 / o.pixel_um
    y_last = y_first + (cfg.motion.passes - 1) * pass_pitch_px(cfg)
    x0 = math.floor(min(xs) - wob) - slack
    x1 = math.ceil(max(xs) + o.width_px + wob) + slack
    y0 = math.floor(y_first - wob) - slack
    y1 = math.ceil(y_last + o.height_px + wob) + slack
    return x0, y0, x1, y1
