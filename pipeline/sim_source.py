"""Simulated scanner: the default frame source (a sibling of the camera and replay sources).

Follows the scan plan (:mod:`sffscan.pipeline.plan`): for each frame, the stage is at its
commanded position plus an optional periodic wobble (along and across the motion), the
lens at the frame's focus level, and the simulated camera renders what it sees
(:func:`sffscan.stages.sim.camera.render_frame`). Headers carry the commanded position, not the
wobbly true one, as a real stage controller would. Deterministic by seed.
"""

from __future__ import annotations

import math
from collections.abc import Iterator

import numpy as np
from sffscan.pipeline.config import ScanConfig
from sffscan.pipeline.plan import PlannedFrame, plan_frames
from sffscan.stages.messages import Frame, FrameHeader
from sffscan.stages.sim.camera import Optics, render_frame
from sffscan.stages.sim.world import PlateWorld, characterisation_plate, sinusoid_world


def make_world(cfg: ScanConfig) -> PlateWorld:
    """The simulated world a configuration describes."""
    s, o = cfg.source, cfg.optics
    z_lo = o.z_min_um
    z_hi = o.z_min_um + (o.n_levels - 1) * o.z_step_um
    if s.world == "sinusoid":
        return sinusoid_world(seed=s.seed, pixel_um=o.pixel_um,
                              amplitude_um=0.35 * (z_hi - z_lo), period_px=400.0,
                              offset_um=0.5 * (z_lo + z_hi))
    return characterisation_plate(seed=s.seed, pixel_um=o.pixel_um, length_mm=s.plate_length_mm,
                                  width_mm=s.plate_width_mm, z_range_um=(z_lo, z_hi))


def make_optics(cfg: ScanConfig) -> Optics:
    o = cfg.optics
    return Optics(width=o.width_px, height=o.height_px, pixel_um=o.pixel_um,
                  psf_s0_px=o.psf_s0_px, psf_c_px_per_um=o.psf_c_px_per_um,
                  sigma_max_px=o.sigma_max_px, noise_sigma=o.noise_sigma,
                  bit_depth=o.bit_depth, magnification_per_mm=o.magnification_per_mm,
                  magnification_ref_um=o.magnification_reference_um(),
                  field_curvature_um=o.field_curvature_um, vignetting=o.vignetting,
                  blur_model=o.blur_model)


def wobble_px(cfg: ScanConfig, travel_px: float) -> tuple[float, float]:
    """Periodic stage wobble (along x, across y) after ``travel_px`` of travel, px."""
    m = cfg.motion
    if m.wobble_along_px == 0 and m.wobble_across_px == 0:
        return 0.0, 0.0
    period_px = m.wobble_period_mm * 1000.0 / cfg.optics.pixel_um
    phase = 2.0 * math.pi * travel_px / period_px
    return m.wobble_along_px * math.sin(phase), m.wobble_across_px * math.cos(phase)


def header_of(cfg: ScanConfig, pf: PlannedFrame) -> FrameHeader:
    px = cfg.optics.pixel_um
    return FrameHeader(frame_id=pf.frame_id, timestamp_ns=pf.timestamp_ns,
                       focus_index=pf.focus_index, stage_x_um=pf.x_px * px,
                       stage_y_um=pf.y_px * px, pass_index=pf.pass_index)


def simulate_frames(cfg: ScanConfig, *, world: PlateWorld | None = None) -> Iterator[Frame]:
    """Every frame of the simulated scan, rendered lazily in acquisition order."""
    world = world if world is not None else make_world(cfg)
    optics = make_optics(cfg)
    heights = cfg.optics.focus_heights_um()
    rng = np.random.default_rng(cfg.source.seed + 1)
    for pf in plan_frames(cfg):
        wx, wy = wobble_px(cfg, pf.travel_px)
        image = render_frame(world, x0=pf.x_px + wx, y0=pf.y_px + wy,
                             focus_um=heights[pf.focus_index], optics=optics, rng=rng)
        yield Frame(header_of(cfg, pf), image)
