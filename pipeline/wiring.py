"""Wiring: a scan configuration becomes a running pipeline, a mosaic and a summary.

    source -> speed_shift -> registration -> focus_measure -> depth -> mosaic
           q1            q2              q3               q4       q5

Every queue ``q*`` is bounded (``processing.queue_capacity``) and blocks when full, so no
frame is ever dropped; the summary reports the drops counted anyway (0).
"""

from __future__ import annotations

import time
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from sffscan.pipeline.completeness import FrameAccount
from sffscan.pipeline.config import ScanConfig
from sffscan.pipeline.measuring import focus_heights_um, measure_stages
from sffscan.pipeline.metrology.correction_stages import (
    corrections_applied,
    optics_correction_stages,
)
from sffscan.pipeline.metrology.evaluate import (
    SIM_TRUTH,
    Accuracy,
    mosaic_accuracy,
    store_accuracy,
    uncertainty_line,
)
from sffscan.pipeline.mosaic.stage import MosaicStage
from sffscan.pipeline.mosaic.writer import MosaicWriter
from sffscan.pipeline.plan import frame_count, pass_start_px, scan_extent_px
from sffscan.pipeline.progress import ScanProgress as Progress
from sffscan.pipeline.runtime import Pipeline
from sffscan.pipeline.scan_processes import process_placement, use_processes
from sffscan.pipeline.stats import PipelineResult
from sffscan.stages.frame_source import FrameBuffers, SourceStage
from sffscan.stages.messages import Frame
from sffscan.stages.protocol import Sink, Stage
from sffscan.stages.speed_shift import SpeedShiftStage


def build_stages(cfg: ScanConfig, frames: Iterator[Frame], writer: MosaicWriter, *,
                 buffers: FrameBuffers | None = None) -> list[Stage]:
    """The scan's stages, source to mosaic; ``buffers``: where the source's frames are
    decoded (:class:`~sffscan.stages.frame_source.FrameBuffers`; default ``frames``'
    own, if it has any)."""
    o, m = cfg.optics, cfg.motion
    x0, y0, x1, y1 = (v * o.pixel_um for v in scan_extent_px(cfg))
    # the calibration's magnification per level and field curvature (issue 14)
    optics_pre, optics_post = optics_correction_stages(cfg, focus_heights_um(cfg))
    stages: list[Stage] = [
        SourceStage(frames, shape=(o.height_px, o.width_px), dtype=o.dtype, n_levels=o.n_levels,
                    max_value=int(o.max_value), passes=m.passes, area_um=(x0, y0, x1, y1),
                    buffers=buffers),
        *optics_pre,
        SpeedShiftStage(pixel_um=o.pixel_um, speed_mm_s=m.speed_mm_s,
                        pass_start=lambda i: pass_start_px(cfg, i)),
    ]
    stages += [
        *measure_stages(cfg),
        *optics_post,
        MosaicStage(writer),
    ]
    return stages


def open_writer(cfg: ScanConfig, *, path: str | Path | None = None,
                overwrite: bool | None = None) -> MosaicWriter:
    x0, y0, x1, y1 = scan_extent_px(cfg)
    o, p = cfg.optics, cfg.processing
    return MosaicWriter(
        path if path is not None else cfg.output.path,
        origin_px=(x0, y0), shape=(y1 - y0, x1 - x0), pixel_um=o.pixel_um,
        chunk_px=cfg.output.chunk_px,
        overwrite=cfg.output.overwrite if overwrite is None else overwrite,
        attrs={
            "processing": {"focus_operator": p.focus_operator, "window": p.window,
                           "depth_method": p.depth_method, "median_size": p.median_size,
                           "registration": p.registration,
                           "registration_scale": p.registration_scale, "backend": p.backend,
                           "calibration": p.calibration,
                           "calibration_applied": corrections_applied(cfg)},
            "focus_heights_um": focus_heights_um(cfg),
            "scan_config": cfg.model_dump(mode="json"),
        },
    )


@dataclass
class ScanReport:
    config: ScanConfig
    output: Path
    frames: int
    result: PipelineResult
    accuracy: Accuracy | None = None
    extras: dict[str, Any] = field(default_factory=dict)


def run_scan(cfg: ScanConfig, *, frames: Iterator[Frame], output: str | Path | None = None,
             overwrite: bool | None = None, progress: bool = True,
             sinks: list[Sink] | None = None, writer: MosaicWriter | None = None,
             account: FrameAccount | None = None) -> ScanReport:
    """Run the whole pipeline over ``frames``; the mosaic goes to ``output`` (or into an
    already open ``writer``, e.g. one reopened to resume); ``sinks`` (recorder, viewer) tap
    the stages they name. With ``account``, the frames taken are counted and the mosaic is
    ``complete`` only if every expected frame was (else ``incomplete``)."""
    if writer is None:
        writer = open_writer(cfg, path=output, overwrite=overwrite)
    # the source's FrameBuffers (a replay, a camera, the simulator), kept through the count
    buffers = getattr(frames, "buffers", None)
    if account is not None:
        frames = account.count(frames)
        writer.account = account.status
    stages = build_stages(cfg, frames, writer, buffers=buffers)
    prog = Progress(frame_count(cfg)) if progress else None
    placement = (process_placement(cfg, stages, sinks=list(sinks or []))
                 if use_processes(cfg, list(sinks or [])) else None)
    pipe = Pipeline(stages, capacity=cfg.processing.queue_capacity, on_progress=prog,
                    sinks=sinks, placement=placement)
    try:
        result = pipe.run()
    finally:
        if prog is not None:
            prog.close()
    return ScanReport(cfg, writer.path, result.stages[0].frames, result)


def evaluate_sim(report: ScanReport, world: Any) -> Accuracy:
    """Accuracy of a simulated scan's mosaic against the world's true surface; also stored in
    the mosaic's attributes (``accuracy``), so it travels with the mosaic."""
    o = report.config.optics
    t0 = time.perf_counter()
    acc = mosaic_accuracy(report.output, world, max_depth=(o.n_levels - 1) * o.z_step_um)
    store_accuracy(report.output, acc, truth=SIM_TRUTH)
    report.extras["evaluation_s"] = time.perf_counter() - t0
    report.accuracy = acc
    return acc


def format_summary(report: ScanReport) -> str:
    r = report.result
    lines = [
        f"mosaic      {report.output}",
        f"frames      {report.frames} in {r.wall_s:.1f} s: "
        f"{report.frames / r.wall_s if r.wall_s else 0:.1f} frames/s end to end",
        f"dropped     {r.dropped} frames",
        "stage             in     out  busy s   cpu s    in/s (own busy time)",
    ]
    for s in r.stages:
        lines.append(f"  {s.name:<14} {s.frames:>6}  {s.items_out:>6}  {s.busy_s:6.2f}"
                     f"  {s.cpu_s:6.2f}  {s.frames_per_s:9.1f}  {s.unit}")
    lines.append("queue                       capacity  when full    max fill  mean fill  dropped")
    for q in r.queues:
        lines.append(f"  {q.name:<26} {q.capacity:>8}  {q.policy:<11} {q.max_fill:>8}"
                     f"  {q.mean_fill:>9.2f}  {q.dropped:>7}")
    for name, extra in r.extras.items():
        waited = extra.get("pipeline_waited_s", 0) if extra else 0
        if waited:
            lines.append(f"WARNING     the sink '{name}' fell behind and held the pipeline back "
                         f"{waited:.2f} s in all")
        if extra:
            lines.append(f"{name:<12} " + ", ".join(f"{k} {v}" for k, v in extra.items()))
    if report.accuracy is not None:
        a = report.accuracy
        lines.append(f"accuracy    RMSE {a.rmse_um:.1f} µm, CORR {a.corr:.4f}, "
                     f"PSNR {a.psnr_db:.1f} dB over {a.pixels} valid pixels "
                     "(against the simulation's true surface)")
        if a.sigma_pixels:
            lines.append(uncertainty_line(a.within_2sigma, a.sigma_pixels, truth="the truth"))
    return "\n".join(lines)
