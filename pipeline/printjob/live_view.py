"""A print job watched live in Rerun: each layer's scan as it runs, and each layer's
deviation map and verdict as soon as they are written.

One :class:`JobLiveView` owns one ``rerun.RecordingStream`` for the whole job (never the
global one). Everything it logs carries the ``layer`` sequence timeline:

- ``scan/...``: the layer's scan, from the live-view sink of a single scan
  (:class:`~sffscan.pipeline.viz.sink.VizSink`: camera, focus, depth blocks, the growing
  mosaic, statistics; timelines ``frame`` and ``device_time`` too), cleared at the start of
  each layer so a layer never shows the tiles of the one before;
- ``job/deviation``, ``job/deviation_um``, ``job/deviation/outlines``, ``job/verdict``:
  the layer's comparison with the G-code (:func:`~.viewer.log_layer`), logged by
  :meth:`JobLiveView.layer_done` from whichever thread finished the analysis;
- static ``job/manifest``.

``sffscan job demo --viewer MODE`` (``spawn``, ``serve``, ``save`` with ``--rrd PATH``)
opens one; the scan's own :func:`~sffscan.pipeline.viz.sink.open_recording` connects it.
"""

from __future__ import annotations

import threading
from collections.abc import Callable
from typing import Any

import rerun as rr
import rerun.blueprint as rrb
from sffscan.pipeline.config import ScanConfig
from sffscan.pipeline.printjob.jobstore import JobStore
from sffscan.pipeline.printjob.viewer import TIMELINE, log_layer, log_manifest
from sffscan.pipeline.viz.sink import VizOptions, VizSink, open_recording

__all__ = ["JobLiveView", "LayerScanSink", "job_blueprint", "open_job_view",
           "shared_job_views"]


def job_blueprint() -> rrb.Blueprint:
    """The job's layout: the layer's camera and growing mosaic, its deviation map with the
    objects' outlines, the verdict."""
    return rrb.Blueprint(
        rrb.Horizontal(
            rrb.Vertical(
                rrb.Spatial2DView(origin="scan/camera", name="Camera (decimated)"),
                rrb.Spatial2DView(origin="scan/mosaic",
                                  contents=["scan/mosaic/height/**", "scan/mosaic/fov"],
                                  name="Layer scan: mosaic height (µm)"),
            ),
            rrb.Vertical(
                rrb.Spatial2DView(origin="job/deviation", name="Deviation from the G-code"),
                rrb.TextDocumentView(origin="job/verdict", name="Verdict"),
                row_shares=[3, 2],
            ),
            column_shares=[1, 1],
        ),
        rrb.TimePanel(timeline=TIMELINE),
        collapse_panels=True,
    )


class LayerScanSink(VizSink):
    """The live-view sink of one layer's scan inside a job's recording: its items carry the
    ``layer`` time, and closing it leaves the job's stream open."""

    def __init__(self, cfg: ScanConfig, rec: rr.RecordingStream, *, layer: int,
                 options: VizOptions | None = None) -> None:
        self.layer = layer
        super().__init__(cfg, rec, options=options)

    def process(self, item: Any) -> tuple[()]:
        self.rec.set_time(TIMELINE, sequence=self.layer)  # this sink's thread's clock
        return super().process(item)

    def finish(self) -> tuple[()]:
        self.rec.set_time(TIMELINE, sequence=self.layer)
        return super().finish()

    def close(self, *, failed: bool) -> None:
        self.rec.flush()  # the job's stream stays open for the next layer

    def release(self) -> None:
        return None


class JobLiveView:
    """One Rerun recording for a whole job, logged while it runs.

    Parameters
    ----------
    store : JobStore
        The job.
    rec : rerun.RecordingStream
        Where to log (connected by the caller: saved, spawned or served).
    options : VizOptions, keyword-only
        How much of each scan to show.
    limit_um : float, keyword-only, optional
        |deviation| where the colour map saturates, µm; default 5 x the job's tolerance.
    own_stream : bool, keyword-only
        :meth:`close` disconnects ``rec`` (False: the stream is shared with later jobs, as
        in ``sffscan serve --viewer``; close only flushes).
    """

    def __init__(self, store: JobStore, rec: rr.RecordingStream, *,
                 options: VizOptions | None = None, limit_um: float | None = None,
                 own_stream: bool = True) -> None:
        self.store, self.rec = store, rec
        self.own_stream = own_stream
        self.options = options
        self.limit_um = limit_um
        self.layers_logged: list[int] = []
        self._lock = threading.Lock()  # layer_done may come from an analysis worker
        log_manifest(store, rec, limit_um=limit_um)

    def scan_sink(self, cfg: ScanConfig, layer: int) -> LayerScanSink:
        """The sink that shows layer ``layer``'s scan (pass it to the scan's ``sinks``);
        what the previous layer's scan showed is cleared at this layer."""
        self.rec.set_time(TIMELINE, sequence=layer)
        self.rec.log("scan", rr.Clear(recursive=True))
        return LayerScanSink(cfg, self.rec, layer=layer, options=self.options)

    def layer_done(self, layer: int) -> None:
        """Log the layer's verdict and deviation map (written by the analysis)."""
        with self._lock:
            log_layer(self.store, layer, self.rec, limit_um=self.limit_um)
            self.rec.flush()
            self.layers_logged.append(layer)

    def close(self) -> None:
        self.rec.flush()
        if self.own_stream:
            self.rec.disconnect()


def open_job_view(store: JobStore, mode: list[str], *,
                  options: VizOptions | None = None) -> JobLiveView:
    """A :class:`JobLiveView` connected as the ``--viewer`` words ``mode`` ask (``spawn``,
    ``serve``, ``auto``, or ``["save", PATH]``; see
    :func:`~sffscan.pipeline.viz.sink.open_recording`, whose ``ConfigError`` names a bad
    mode, file or port). A served view's address is logged."""
    rec, _ = open_recording(mode, layout=job_blueprint())
    return JobLiveView(store, rec, options=options)


def shared_job_views(mode: list[str], *, options: VizOptions | None = None
                     ) -> Callable[[JobStore], JobLiveView]:
    """``store -> JobLiveView`` for a service: one viewer (opened now, as ``mode`` asks)
    that every job of the service logs into, one after the other."""
    rec, _ = open_recording(mode, layout=job_blueprint())

    def view(store: JobStore) -> JobLiveView:
        return JobLiveView(store, rec, options=options, own_stream=False)

    return view
