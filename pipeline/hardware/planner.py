"""Scan planning (``sffscan plan``): speeds, exposure, frames, time and passes for an area.

Two rules are compared for the same optics:

- **thesis** (per-stack, eq. 6.1-6.3): consecutive focus stacks may be translated by at
  most l = (w - w P) / 2 (w the FOV along the motion, P the overlap), so the speed is
  s = (r / N) l (:func:`sffscan.pipeline.config.max_speed_thesis_mm_s`). Only half of a stack is
  useful; passes side by side are consecutive stacks across the motion, so they are
  stepped by the same rule across: strips of u = h / 2 stepped by u (1 - P). A pass
  travels the area's length plus one stack translation l (the last stack completes).
  With the thesis' optics (FOV 11 x 9 mm, 150 fps, N = 50, P = 9.1 %) a 100 x 100 mm
  plate needs 25 passes of 7.0 s at 15.0 mm/s: 175 s, the thesis' figures.
- **sliding** (sffscan's streaming focus volume): a column needs N consecutive frames in
  the usable width, s <= usable / N * fps * pixel
  (:func:`sffscan.pipeline.config.max_speed_sliding_mm_s`); frames per pass and the pass pitch
  come from the scan plan itself (:func:`sffscan.pipeline.plan.pass_bounds_px`,
  :func:`sffscan.pipeline.config.pass_pitch_px`).

The exposure limit is pixel scale / speed (a point must not smear over a pixel,
:func:`sffscan.pipeline.hardware.lens_waveform.max_exposure_us`), and at most half a staircase step
(the trigger sits at the step's centre; :func:`pipeline.hardware.lens_waveform.exposure_window_us`).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Literal

from pydantic import ValidationError
from sffscan.pipeline.config import (
    ConfigError,
    ScanConfig,
    max_speed_sliding_mm_s,
    max_speed_thesis_mm_s,
    pass_pitch_px,
    usable_width_px,
)
from sffscan.pipeline.hardware.lens_waveform import exposure_window_us, max_exposure_us
from sffscan.pipeline.plan import PASS_GAP_S, pass_bounds_px


class PlanError(ConfigError):
    """An impossible scan request; the message gives the reason."""


@dataclass(frozen=True)
class RulePlan:
    """The scan of an area under one speed rule (times in s, speeds in mm/s)."""

    rule: str
    max_speed_mm_s: float
    speed_mm_s: float
    max_exposure_us: float  # min(pixel scale / speed, half a staircase step)
    pass_length_mm: float
    frames_per_pass: int
    pass_time_s: float
    pass_pitch_mm: float
    passes: int
    scan_time_s: float  # passes x pass time
    refused: str | None = None  # why this rule cannot scan at the requested speed

    @property
    def total_time_s(self) -> float:
        """Scan time plus the stage's turn between passes (pipeline.plan.PASS_GAP_S each)."""
        return self.scan_time_s + (self.passes - 1) * PASS_GAP_S


@dataclass(frozen=True)
class ScanPlan:
    fov_mm: tuple[float, float]  # (along the motion, across), mm
    fov_px: tuple[int, int]
    fps: float
    n_levels: int
    overlap: float
    pixel_um: float
    area_mm: tuple[float, float]  # (along, across), mm
    exposure_window_us: float
    thesis: RulePlan
    sliding: RulePlan


def _passes(area: float, strip: float, pitch: float) -> int:
    """Passes of width ``strip`` stepped by ``pitch`` that cover ``area`` (same unit)."""
    if area <= strip:
        return 1
    return 1 + math.ceil((area - strip) / pitch - 1e-9)


def _config(fov_px: tuple[int, int], *, fps: float, n_levels: int, overlap: float,
            pixel_um: float, area_mm: tuple[float, float], speed: float, window: int,
            operator: str, registration: bool) -> ScanConfig:
    try:
        return ScanConfig.model_validate({
            "optics": {"width_px": fov_px[0], "height_px": fov_px[1], "pixel_um": pixel_um,
                       "n_levels": n_levels, "fps": fps},
            "motion": {"speed_mm_s": speed, "x_start_mm": 0.0, "x_end_mm": area_mm[0],
                       "pass_overlap": overlap},
            "processing": {"window": window, "focus_operator": operator,
                           "registration": registration},
        })
    except ValidationError as err:
        e = err.errors()[0]
        raise PlanError(f"{'.'.join(str(p) for p in e['loc'])}: {e['msg']}") from None


def plan_scan(*, fov_mm: tuple[float, float], fps: float, n_levels: int, overlap: float,
              pixel_um: float, area_mm: tuple[float, float] = (100.0, 100.0),
              direction: Literal["x", "y"] = "x", speed_mm_s: float | None = None,
              window: int = 9, operator: str = "glvm", registration: bool = True) -> ScanPlan:
    """Plan the scan of ``area_mm`` under both rules.

    Parameters
    ----------
    fov_mm : (float, float)
        Field of view (width along the camera's x, height along its y), mm.
    fps : float
        Frame rate, frames/s.
    n_levels : int
        Focus levels N.
    overlap : float
        Overlap P, fraction in [0, 1): between focus stacks (thesis) and between passes.
    pixel_um : float
        Object-side pixel scale, µm/px.
    area_mm : (float, float)
        Area to cover, (along the motion, across), mm.
    direction : {"x", "y"}
        Camera axis the motion runs along.
    speed_mm_s : float, optional
        Requested speed; default: each rule's maximum.
    window, operator, registration
        Processing that sets the frame margins of the sliding rule.
    """
    if not 0.0 <= overlap < 1.0:
        raise PlanError(f"overlap = {overlap:g}: must lie in [0, 1)")
    for name, value in (("FOV width", fov_mm[0]), ("FOV height", fov_mm[1]),
                        ("pixel scale", pixel_um), ("frame rate", fps)):
        if not 0 < value < math.inf:  # inf, nan, 0 or below
            raise PlanError(f"{name} = {value:g}: FOV, pixel scale and frame rate must be "
                            "finite and > 0")
    if not (0 < area_mm[0] < math.inf and 0 < area_mm[1] < math.inf):
        raise PlanError(f"area {area_mm[0]:g} x {area_mm[1]:g} mm: both sides must be finite "
                        "and > 0")
    if speed_mm_s is not None and not 0 < speed_mm_s < math.inf:
        raise PlanError(f"speed = {speed_mm_s:g} mm/s: must be finite and > 0")
    along, across = (fov_mm[0], fov_mm[1]) if direction == "x" else (fov_mm[1], fov_mm[0])
    fov_px = (round(along * 1000.0 / pixel_um), round(across * 1000.0 / pixel_um))
    base = _config(fov_px, fps=fps, n_levels=n_levels, overlap=overlap, pixel_um=pixel_um,
                   area_mm=area_mm, speed=1.0, window=window, operator=operator,
                   registration=registration)
    if usable_width_px(base) < n_levels:
        raise PlanError(f"the FOV along the motion ({along:g} mm = {fov_px[0]} px) leaves "
                        f"{usable_width_px(base):.0f} px after the focus-window margins: "
                        f"fewer than N = {n_levels} levels, no speed can work")
    thesis = _thesis_plan(along, across, fps=fps, n_levels=n_levels, overlap=overlap,
                          pixel_um=pixel_um, area_mm=area_mm, speed=speed_mm_s,
                          vmax=max_speed_thesis_mm_s(base, overlap=overlap))
    sliding = _sliding_plan(base, area_mm=area_mm, speed=speed_mm_s, window=window,
                            operator=operator, registration=registration)
    if thesis.refused and sliding.refused:
        raise PlanError(sliding.refused)
    return ScanPlan((along, across), fov_px, fps, n_levels, overlap, pixel_um, area_mm,
                    exposure_window_us(fps), thesis, sliding)


def _max_exposure(pixel_um: float, speed: float, fps: float) -> float:
    """Longest exposure, µs: no smear over a pixel, and within half a staircase step."""
    return min(max_exposure_us(pixel_um, speed), exposure_window_us(fps))


def _refusal(rule: str, speed: float, vmax: float) -> str:
    return (f"speed {speed:g} mm/s exceeds the {rule} limit {vmax:.2f} mm/s")


def _thesis_plan(along: float, across: float, *, fps: float, n_levels: int, overlap: float,
                 pixel_um: float, area_mm: tuple[float, float], speed: float | None,
                 vmax: float) -> RulePlan:
    s = vmax if speed is None else speed
    refused = _refusal("thesis per-stack", s, vmax) if s > vmax * (1 + 1e-9) else None
    stack_l = along * (1.0 - overlap) / 2.0  # eq. 6.2
    length = area_mm[0] + stack_l
    strip = across / 2.0
    pitch = strip * (1.0 - overlap)
    passes = _passes(area_mm[1], strip, pitch)
    pass_time = length / s
    return RulePlan("thesis", vmax, s, _max_exposure(pixel_um, s, fps), length,
                    math.ceil(pass_time * fps), pass_time, pitch, passes, passes * pass_time,
                    refused)


def _sliding_plan(base: ScanConfig, *, area_mm: tuple[float, float], speed: float | None,
                  window: int, operator: str, registration: bool) -> RulePlan:
    vmax = max_speed_sliding_mm_s(base)
    s = vmax if speed is None else speed
    refused = _refusal("sliding-window", s, vmax) if s > vmax * (1 + 1e-9) else None
    o = base.optics
    cfg = base.model_copy(update={"motion": base.motion.model_copy(
        update={"speed_mm_s": min(s, vmax)})})
    first, last, frames = pass_bounds_px(cfg, 0)
    px_mm = o.pixel_um / 1000.0
    strip = (o.height_px - 2 * cfg.processing.edge_margin_px) * px_mm
    pitch = pass_pitch_px(cfg) * px_mm
    passes = _passes(area_mm[1], strip, pitch)
    pass_time = frames / o.fps
    return RulePlan("sliding", vmax, s, _max_exposure(o.pixel_um, s, o.fps),
                    abs(last - first) * px_mm, frames, pass_time, pitch, passes,
                    passes * pass_time, refused)


def format_plan(plan: ScanPlan) -> str:
    """The plan as the table ``sffscan plan`` prints."""
    a, c = plan.fov_mm
    lines = [
        f"optics      FOV {a:g} mm along the motion x {c:g} mm across "
        f"({plan.fov_px[0]} x {plan.fov_px[1]} px of {plan.pixel_um:g} µm), {plan.fps:g} fps, "
        f"N = {plan.n_levels}, overlap {plan.overlap * 100:g} %",
        f"area        {plan.area_mm[0]:g} mm along x {plan.area_mm[1]:g} mm across",
        f"exposure    at most {plan.exposure_window_us:.0f} µs after the trigger (half a "
        "staircase step)",
        "rule                       thesis (per stack)   sliding window (sffscan)",
    ]
    rows = [
        ("max speed, mm/s", "{:.2f}", "max_speed_mm_s"),
        ("speed, mm/s", "{:.2f}", "speed_mm_s"),
        ("max exposure, µs", "{:.0f}", "max_exposure_us"),
        ("pass length, mm", "{:.1f}", "pass_length_mm"),
        ("frames per pass", "{:d}", "frames_per_pass"),
        ("time per pass, s", "{:.2f}", "pass_time_s"),
        ("pass pitch, mm", "{:.2f}", "pass_pitch_mm"),
        ("passes", "{:d}", "passes"),
        ("scan time, s", "{:.1f}", "scan_time_s"),
        ("with turns, s", "{:.1f}", "total_time_s"),
    ]
    for label, fmt, attr in rows:
        cells = []
        for rp in (plan.thesis, plan.sliding):
            cells.append("-" if rp.refused and attr not in ("max_speed_mm_s", "speed_mm_s")
                         else fmt.format(getattr(rp, attr)))
        lines.append(f"  {label:<24} {cells[0]:>18}   {cells[1]:>18}")
    for rp in (plan.thesis, plan.sliding):
        if rp.refused:
            lines.append(f"{rp.rule}: refused: {rp.refused}")
    return "\n".join(lines)
