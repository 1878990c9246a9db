"""A print job in the Rerun viewer: a ``layer`` timeline of deviation maps and verdicts.

``log_job(job, rec)`` logs, for every done layer at time ``layer`` = its index (a sequence
timeline):

- ``job/deviation``: the deviation map as an RGB image in the report's diverging colour map
  (:func:`~sffscan.pipeline.printjob.report.deviation_colours`: the tolerance band grey,
  missing material blue, excess red, no measurement dark slate);
- ``job/deviation/outlines``: the objects' outlines (line strips in the image's pixel
  coordinates, labelled with the object names, coloured by their verdict);
- ``job/verdict``: the layer's and each object's verdict and statistics as Markdown text;
- ``job/deviation_um``: the deviation itself (a depth image, µm, meter 1) to read values.

Static: ``job/manifest`` (Markdown). ``save_job_rrd(job, path)`` writes it to an ``.rrd``.
"""

from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np
from sffscan.pipeline.printjob.deviation import LayerVerdict
from sffscan.pipeline.printjob.jobstore import JobError, JobStore
from sffscan.pipeline.printjob.report import deviation_colours, layer_deviation

if TYPE_CHECKING:
    import rerun as rr

__all__ = ["TIMELINE", "log_job", "log_layer", "log_manifest", "save_job_rrd",
           "verdict_markdown"]

TIMELINE = "layer"
_VERDICT_RGB = {"pass": (26, 152, 80), "warn": (224, 138, 0), "fail": (215, 48, 39),
                "unknown": (107, 123, 134)}


def verdict_markdown(v: LayerVerdict, n_layers: int) -> str:
    """A layer's verdict and its objects' statistics as Markdown."""
    lines = [f"## Layer {v.layer + 1}/{n_layers} (index {v.layer}), z {v.z_mm:.2f} mm: "
             f"**{v.verdict.upper()}**", ""]
    if v.reason:
        lines += [v.reason, ""]
    lines += ["| object | verdict | p95 \\|dev\\| µm | out of tol. mm² | missing mm² | "
              "excess mm² | largest defect (printer mm) |", "|---|---|---|---|---|---|---|"]
    for o in v.objects:
        p95 = "–" if o.p95_abs_um is None else f"{o.p95_abs_um:.0f}"
        where = "–" if o.defect_xy_mm is None else (
            f"({o.defect_xy_mm[0]:.1f}, {o.defect_xy_mm[1]:.1f})")
        lines.append(f"| {o.name} | {o.verdict} | {p95} | {o.area_out_mm2:.2f} | "
                     f"{o.missing_mm2:.2f} | {o.excess_mm2:.2f} | {where} |")
    return "\n".join(lines)


def _limit(store: JobStore, limit_um: float | None) -> tuple[float, float]:
    tol = store.manifest.tolerances.tolerance_um
    return tol, 5.0 * tol if limit_um is None else float(limit_um)


def log_manifest(store: JobStore, rec: rr.RecordingStream, *,
                 limit_um: float | None = None) -> None:
    """``job/manifest`` (static Markdown): the job, its G-code, objects and tolerance."""
    import rerun as rr

    man = store.manifest
    tol, lim = _limit(store, limit_um)
    rec.log("job/manifest", rr.TextDocument(
        f"# Print job {man.job_id}\n\nprinter {man.printer or 'not named'}; G-code "
        f"`{man.gcode_sha256}`; {len(man.layer_z_mm)} layers; objects "
        f"{', '.join(man.objects)}; tolerance ±{tol:g} µm; colours saturate at ±{lim:g} µm",
        media_type=rr.MediaType.MARKDOWN), static=True)


def log_layer(store: JobStore, layer: int, rec: rr.RecordingStream, *,
              limit_um: float | None = None) -> None:
    """Log one done layer at time ``layer`` (the calling thread's clock): its verdict, its
    deviation map (RGB and µm) and the objects' outlines; a layer without a deviation map
    (failed scan) clears the image."""
    import rerun as rr

    tol, lim = _limit(store, limit_um)
    v = store.read_verdict(layer)
    rec.set_time(TIMELINE, sequence=layer)
    rec.log("job/verdict", rr.TextDocument(verdict_markdown(v, len(store.manifest.layer_z_mm)),
                                           media_type=rr.MediaType.MARKDOWN))
    got = layer_deviation(store, layer)
    if got is None:
        rec.log("job/deviation", rr.Clear(recursive=True))
        rec.log("job/deviation_um", rr.Clear(recursive=False))
        return
    dev, outlines = got
    rec.log("job/deviation", rr.Image(deviation_colours(dev, tolerance_um=tol, limit_um=lim)))
    rec.log("job/deviation_um", rr.DepthImage(np.nan_to_num(dev, nan=0.0), meter=1.0))
    per = {o.name: o.verdict for o in v.objects}
    names = list(outlines)
    strips = [np.vstack([outlines[m], outlines[m][:1]]) + 0.5 for m in names]
    rec.log("job/deviation/outlines", rr.LineStrips2D(
        strips, labels=[f"{Path(m).stem}: {per.get(m, '?')}" for m in names],
        colors=[_VERDICT_RGB.get(per.get(m, "unknown"), (0, 0, 0)) for m in names],
        radii=rr.Radius.ui_points(1.5)))


def open_job(job_path: str | Path) -> JobStore:
    try:
        return JobStore.open(job_path)
    except OSError as err:
        raise JobError(f"{job_path}: not a readable job folder ({err})") from None


def log_job(job_path: str | Path, rec: rr.RecordingStream, *,
            limit_um: float | None = None) -> list[int]:
    """Log a job's done layers to a Rerun recording on the ``layer`` timeline.

    Parameters
    ----------
    job_path : path-like
        A job folder.
    rec : rerun.RecordingStream
        Where to log (never the global stream).
    limit_um : float, keyword-only, optional
        |deviation| where the colour map saturates, µm; default 5 x the job's tolerance.

    Returns
    -------
    list of int
        The layers logged (the done ones), increasing.

    Raises
    ------
    JobError
        Not a job folder (the path is named).
    """
    store = open_job(job_path)
    log_manifest(store, rec, limit_um=limit_um)
    done = store.done_layers()
    for k in done:
        log_layer(store, k, rec, limit_um=limit_um)
    return done


def save_job_rrd(job_path: str | Path, rrd_path: str | Path, *,
                 limit_um: float | None = None) -> list[int]:
    """Write a job's ``layer`` timeline (:func:`log_job`) to an ``.rrd`` file; returns the
    layers logged."""
    import rerun as rr

    rec = rr.RecordingStream("sffscan-job")
    rec.save(str(rrd_path))
    try:
        return log_job(job_path, rec, limit_um=limit_um)
    finally:
        rec.flush(timeout_sec=30.0)
        rec.disconnect()
