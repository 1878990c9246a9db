"""The job service's default :class:`~.links_models.LayerHandler`: each job is a job store
(:class:`~.jobstore.JobStore`) scanned and judged layer by layer by
:class:`~.layer.LayerRunner`.

- The job's G-code is looked up by the name the printer gives (``JobStart.gcode_name``,
  its last path component only) in ``gcode_dir``. With it, a layer is scanned into the
  job store and compared with the G-code (deviation map, per-object verdicts).
- Without it (no ``gcode_dir``, or no such file), the layer is still scanned, into
  ``JOB/layer_NNNNN.zarr``, and its verdict is ``unknown`` with the reason: nothing says
  what should have been printed, and a layer is never ``pass`` without a comparison.
- With the simulated source (``source.kind = "sim"``) and a G-code, the simulator's world
  is the print itself, built from the G-code's beads up to the layer
  (:class:`~sffscan.stages.sim.print_world.PrintWorld`), as in ``sffscan job demo``.
"""

from __future__ import annotations

import logging
import threading
from collections.abc import Callable
from pathlib import Path
from typing import TYPE_CHECKING, Any

from sffscan.pipeline.config import ScanConfig
from sffscan.pipeline.printjob.deviation import Tolerances
from sffscan.pipeline.printjob.expected import PrinterMapping
from sffscan.pipeline.printjob.jobstore import JobStore
from sffscan.pipeline.printjob.layer import LayerRunner
from sffscan.pipeline.printjob.links_models import (
    Analysis,
    JobStart,
    LayerEvent,
    ScanResult,
)

if TYPE_CHECKING:
    from sffscan.pipeline.printjob.live_view import JobLiveView

log = logging.getLogger(__name__)

STORE_DIR = "job"  # the job store inside the service's job folder


class _Job:
    def __init__(self, runner: LayerRunner | None, why: str, world: Any = None,
                 live: JobLiveView | None = None) -> None:
        self.runner = runner
        self.why = why  # why there is no runner
        self.world = world
        self.live = live  # the job's live view, if one is asked for
        self.lock = threading.Lock()  # the runner's expected-map cache: one user at a time
        self.prep: dict[int, threading.Thread] = {}  # layer -> its expected map being made


class JobStoreHandler:
    """Scan with ``config``'s source; compare with the job's G-code when there is one.

    Parameters
    ----------
    config : ScanConfig
        The scan of one layer (its ``output.path`` is replaced per layer).
    gcode_dir : path-like or None, keyword-only
        Folder of the G-code files the printer prints.
    mapping : PrinterMapping, keyword-only
        Printer coordinates -> mosaic coordinates.
    tolerances : Tolerances, keyword-only
    record : bool, keyword-only
        Keep each layer's raw recording in the job store.
    view : callable, keyword-only
        ``store -> JobLiveView`` (:func:`~.live_view.shared_job_views`): each job's layers
        shown live, the scan while it runs, the deviation and verdict when written. A view
        that fails is logged and dropped; the job goes on.
    prepare_ahead : bool, keyword-only
        Rasterise each layer's expected map in a thread while the layer is scanned (the
        analysis then starts from it); False: the analysis makes it.
    """

    def __init__(self, config: ScanConfig, *, gcode_dir: str | Path | None = None,
                 mapping: PrinterMapping | None = None, tolerances: Tolerances | None = None,
                 record: bool = True,
                 view: Callable[[JobStore], JobLiveView] | None = None,
                 prepare_ahead: bool = True) -> None:
        self.view = view
        self.prepare_ahead = prepare_ahead
        self.config = config
        self.gcode_dir = None if gcode_dir is None else Path(gcode_dir)
        self.mapping = mapping or PrinterMapping()
        self.tolerances = tolerances or Tolerances()
        self.record = record
        self._jobs: dict[str, _Job] = {}
        self._lock = threading.Lock()  # scan and analysis workers share _jobs

    def _job(self, job: JobStart, folder: Path) -> _Job:
        with self._lock:
            cached = self._jobs.get(job.job_id)
            if cached is None:
                cached = self._jobs[job.job_id] = self._open(job, folder)
            return cached

    def _open(self, job: JobStart, folder: Path) -> _Job:
        path = folder / STORE_DIR
        if (path / "manifest.json").is_file():  # a resumed job
            store = JobStore.open(path)
        else:
            name = Path(job.gcode_name.replace("\\", "/")).name
            if self.gcode_dir is None or not name:
                return _Job(None, "no G-code to compare with (start 'sffscan serve' with "
                                  "--gcode-dir, and the job with its G-code's name)")
            gcode = self.gcode_dir / name
            if not gcode.is_file():
                return _Job(None, f"no G-code {name!r} in {self.gcode_dir}: nothing to "
                                  "compare the scan with")
            store = JobStore.create(path, gcode=gcode, printer=job.printer,
                                    config=self.config, mapping=self.mapping,
                                    tolerances=self.tolerances)
        world = None
        if self.config.source.kind == "sim":
            from sffscan.pipeline.printjob.demo import _world_extent
            from sffscan.stages.sim.print_world import PrintWorld

            program, mapping = store.program, store.manifest.mapping
            world = PrintWorld(program, mapping, self.config.optics.pixel_um,
                               _world_extent(program, mapping))
        live = None
        if self.view is not None:
            try:
                live = self.view(store)
            except Exception as err:  # noqa: BLE001 - the view never stops the job
                log.warning("job %s: no live view: %s", job.job_id, err)
        return _Job(LayerRunner(store), "", world, live)

    def scan(self, job: JobStart, event: LayerEvent, folder: Path) -> ScanResult:
        j = self._job(job, folder)
        if j.runner is None:
            from sffscan.api import scan

            out = folder / f"layer_{event.layer:05d}.zarr"
            report = scan(self.config, output=out, overwrite=True)
            return ScanResult(output=out, info={"frames": report.frames})
        j.runner.begin(event.layer, event.z_mm)
        # the layer's expected map, made while it is scanned (not on the printer's hold)
        if self.prepare_ahead:
            prep = threading.Thread(target=_prepare, args=(j, event.layer), daemon=True,
                                    name=f"sffscan-expected-{event.layer}")
            j.prep[event.layer] = prep
            prep.start()
        world = None if j.world is None else j.world.at_layer(event.layer)
        sinks = () if j.live is None else (j.live.scan_sink(self.config, event.layer),)
        try:
            report = j.runner.scan(event.layer, config=self.config, world=world,
                                   record=self.record, sinks=sinks)
        except Exception as err:  # the job store records the layer unknown too
            j.runner.fail(event.layer, f"the scan failed: {type(err).__name__}: {err}")
            _show(j, event.layer)
            raise
        return ScanResult(output=j.runner.store.mosaic_path(event.layer),
                          info={"frames": report.frames})

    def analyse(self, job: JobStart, event: LayerEvent, scan: ScanResult,
                folder: Path) -> Analysis:
        j = self._job(job, folder)
        if j.runner is None:
            return Analysis(verdict="unknown", reason=j.why)
        prep = j.prep.pop(event.layer, None)
        if prep is not None:
            prep.join(timeout=120.0)
        with j.lock:
            v = j.runner.analyse(event.layer)
        _show(j, event.layer)
        reason = v.reason
        if not reason:
            bad = [o for o in v.objects if o.verdict != "pass"]
            reason = "; ".join(
                f"{o.name}: {o.verdict} (p95 |dev| {o.p95_abs_um or 0:.0f} µm, missing "
                f"{o.missing_mm2:.2f} mm², excess {o.excess_mm2:.2f} mm²)" for o in bad)
        return Analysis(verdict=v.verdict, reason=reason,
                        objects={o.name: o.verdict for o in v.objects})


def _show(j: _Job, layer: int) -> None:
    """The layer's verdict into the job's live view (a failing view is logged, dropped)."""
    if j.live is None:
        return
    try:
        j.live.layer_done(layer)
    except Exception as err:  # noqa: BLE001 - the view never stops the job
        log.warning("live view: layer %d not shown (%s); the view is dropped", layer, err)
        j.live = None


def _prepare(j: _Job, layer: int) -> None:
    """Rasterise the layer's expected map ahead (:meth:`LayerRunner.prepare`); a failure
    only costs the analysis the time to make it."""
    assert j.runner is not None
    with j.lock:
        try:
            j.runner.prepare(layer)
        except Exception as err:  # noqa: BLE001 - the analysis makes it again, or says why
            log.warning("layer %d: expected map not made ahead: %s", layer, err)
