"""Live view in Rerun: a side-branch sink that shows the scan while it runs.

One :class:`VizSink` owns one ``rerun.RecordingStream`` (never the global one) and taps the
placed frames (``registration``, or ``speed_shift`` with registration off), the focus
measure and the depth blocks; with ``wants_stats`` it also gets the pipeline's statistics.
Its input queue drops the oldest item when full (and counts the drops), so the viewer
never holds the pipeline back; the depth blocks, from which its mosaic is built, and the
statistics go last (``precious``: the oldest frames make way for them). In process mode it
stays in the main process (where its recording stream was opened) and the workers forward
it what it taps: only the focus frames it logs (``relay_keep``), the rest dropping the
newest when a channel is full, the depth blocks taking a reserve above the channel's
capacity; every drop on the way is counted as the view's (:mod:`sffscan.pipeline.scan_processes`).

Entity paths (timelines ``frame`` = frame_id and ``device_time`` = exposure time stamp):

- ``scan/camera/image``: camera frames, every ``frame_step``-th frame_id, reduced by
  ``frame_scale``, JPEG; ``scan/focus/measure``: the focus measure of the same frames
  (the columns that were measured, sqrt-scaled grey, JPEG; where the depth stage's band
  processes measure the focus, which no focus frame then carries, the view measures the
  whole frame itself, :meth:`VizSink._measure`);
- ``scan/depth/height``, ``scan/depth/confidence`` and ``scan/depth/uncertainty`` (the
  height's one-sigma uncertainty, µm): each completed depth block, reduced;
- ``scan/mosaic/height/tile_NNNN`` (µm, colour-mapped, 0 where invalid) and
  ``scan/mosaic/texture/tile_NNNN`` (all in focus), with ``scan/mosaic/fov`` (the camera's
  field of view): the growing mosaic, rebuilt from the depth blocks by the mosaic's own
  weighted blend on cells of ``factor`` x ``factor`` px, in column tiles of ``tile_cells``
  cells (each placed by a static translation); only the tiles that changed are logged, so
  the data rate does not grow with the scan's length;
- ``scan/surface/points/tile_NNNN``: the same tiles as a 3D point cloud in mm, coloured by
  texture, decimated;
- ``stats/rate/<stage>`` (items/s), ``stats/queue_fill/<stage>`` (mean fill of the stage's
  input queue), ``stats/dropped/<stage>`` (``viewer`` = what the viewer dropped) and
  ``registration/correction_px/{x,y}``; the view's own drops have a panel of their own;
- static: ``scan/calibration`` (pixel scale, focus table), ``scan/config`` (the TOML).
"""

from __future__ import annotations

import logging
import os
import socket
import sys
import time
import urllib.parse
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import rerun as rr
import rerun.blueprint as rrb
from sffscan.pipeline.config import ConfigError, ScanConfig, config_to_toml
from sffscan.pipeline.measuring import focus_heights_um
from sffscan.pipeline.plan import scan_extent_px
from sffscan.pipeline.stats import StatsSnapshot
from sffscan.pipeline.viz.preview import (
    MosaicPreview,
    logged_items,
    point_stride,
    precious_to_view,
    shown,
    surface_points,
    to_u8,
)
from sffscan.stages.focus_measure import focus_measure_raw
from sffscan.stages.messages import DepthBlock, FocusFrame, PlacedFrame
from sffscan.stages.protocol import FullPolicy, Sink, Tapped

MODES = "spawn | serve | save (with --rrd PATH) | auto | off"

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class VizOptions:
    """How much the viewer shows (the rest is decimated away to keep it light)."""

    frame_hz: float = 10.0  # camera frames logged per second of device time
    frame_scale: int = 2  # camera and focus images reduced by this
    block_scale: int = 4  # depth blocks reduced by this
    mosaic_max_px: int = 2048  # longest side of the mosaic preview
    mosaic_every_s: float = 2.0  # wall time between mosaic updates (and one at the end)
    tile_cells: int = 256  # the mosaic is logged in column tiles this wide, changed ones only
    max_points: int = 50_000  # points of the 3D surface
    capacity: int = 64  # the viewer's own queue (drop oldest); 16 at most in process mode


def blueprint() -> rrb.Blueprint:
    """The view layout: camera and focus, the growing mosaic and surface, the statistics."""
    return rrb.Blueprint(
        rrb.Horizontal(
            rrb.Vertical(
                rrb.Spatial2DView(origin="scan/camera", name="Camera (decimated)"),
                rrb.Spatial2DView(origin="scan/focus", name="Focus measure"),
                rrb.Spatial2DView(origin="scan/depth", contents="scan/depth/height",
                                  name="Last depth block (µm)"),
            ),
            rrb.Vertical(
                rrb.Spatial2DView(origin="scan/mosaic",
                                  contents=["scan/mosaic/height/**", "scan/mosaic/fov"],
                                  name="Mosaic height (µm) and camera view"),
                rrb.Spatial2DView(origin="scan/mosaic", contents="scan/mosaic/texture/**",
                                  name="Mosaic texture (all in focus)"),
                rrb.Spatial3DView(origin="scan/surface", name="Surface (mm)"),
                row_shares=[1, 1, 2],
            ),
            rrb.Vertical(
                rrb.TimeSeriesView(origin="stats/rate", name="Items/s per stage"),
                rrb.TimeSeriesView(origin="stats/queue_fill", name="Queue fill (mean)"),
                rrb.TimeSeriesView(origin="stats/dropped",
                                   contents=["$origin/**", "- stats/dropped/viewer"],
                                   name="Dropped between stages"),
                rrb.TimeSeriesView(origin="stats/dropped/viewer", name="Dropped by the view"),
                rrb.TimeSeriesView(origin="registration", name="Registration correction (px)"),
                row_shares=[2, 2, 2, 1, 2],
            ),
            column_shares=[1, 2, 1],
        ),
        collapse_panels=True,
    )


class VizSink(Sink):
    """Logs what the pipeline does into ``rec``; see the module docstring for the paths."""

    name = "viewer"
    policy = FullPolicy.DROP_OLDEST
    wants_stats = True

    def __init__(self, cfg: ScanConfig, rec: rr.RecordingStream, *,
                 options: VizOptions | None = None, wait_at_end: str | None = None) -> None:
        self.cfg, self.rec = cfg, rec
        self.opt = options or VizOptions()
        self.capacity = self.opt.capacity
        self.wait_at_end = wait_at_end  # an address to keep serving at, until Enter
        placed = "registration" if cfg.processing.registration else "speed_shift"
        self.taps = (placed, "focus_measure", "depth")
        o = cfg.optics
        self.frame_step = max(1, round(o.fps / self.opt.frame_hz))
        #: no focus frames come (the depth stage's band workers measure the focus): the view
        #: measures the frames it shows (one in ``frame_step``, in the view's own thread)
        self.measures_focus = cfg.processing.bands_measure()
        #: what the view uses, selected where the stages run (process mode)
        self.relay_keep = (logged_items, {"frame_step": self.frame_step})
        #: the depth blocks (a lost one leaves a hole in the mosaic) and the statistics are
        #: dropped last
        self.precious = precious_to_view
        x0, y0, x1, y1 = scan_extent_px(cfg)
        self.factor = max(1, -(-max(x1 - x0, y1 - y0) // self.opt.mosaic_max_px))
        self.preview = MosaicPreview(origin_px=(x0, y0), shape=(y1 - y0, x1 - x0),
                                     factor=self.factor, tile=self.opt.tile_cells)
        self._stride = point_stride(self.preview.shape[0] * self.preview.shape[1],
                                    self.opt.max_points)
        self._tiles_placed: set[int] = set()
        # the table the depth stage uses: calibrated where a calibration is given
        self.focus_heights = focus_heights_um(cfg)
        self.depth_range = (min(self.focus_heights), max(self.focus_heights))
        self.frames_logged = 0
        self.mosaics_logged = 0
        self.tiles_logged = 0
        self.viewer_dropped = 0
        self._now: tuple[int, int] | None = None  # (frame_id, timestamp_ns) last seen
        self._last_mosaic = time.perf_counter()
        self._prev: dict[str, tuple[float, float, float]] = {}
        self._styled: set[str] = set()
        self._log_static()

    # -- logging helpers ---------------------------------------------------------------
    def _log_static(self) -> None:
        o, rec, heights = self.cfg.optics, self.rec, self.focus_heights
        table = "\n".join(f"| {i} | {z:g} |" for i, z in enumerate(heights))
        source = self.cfg.processing.calibration or "nominal optics"
        rec.log("scan/calibration", rr.TextDocument(
            f"pixel scale {o.pixel_um:g} µm/px, {o.width_px} x {o.height_px} px, {o.fps:g} fps, "
            f"N = {o.n_levels} levels\n\nmosaic preview: 1 cell = {self.factor} x "
            f"{self.factor} px; camera frames every {self.frame_step}th\n\n"
            f"| level | height in focus, µm ({source}) |\n|---|---|\n{table}",
            media_type="text/markdown"), static=True)
        rec.log("scan/calibration", rr.AnyValues(pixel_um=o.pixel_um, fps=o.fps,
                                                 mosaic_factor=self.factor,
                                                 focus_heights_um=heights),
                static=True)
        rec.log("scan/config", rr.TextDocument(config_to_toml(self.cfg)), static=True)
        rec.log("scan/surface", rr.ViewCoordinates.RIGHT_HAND_Z_UP, static=True)

    def _set_time(self, at: tuple[int, int] | None = None) -> None:
        """Log at frame ``at`` = (frame_id, timestamp_ns), by default the newest frame seen."""
        at = at if at is not None else self._now
        if at is not None:
            self.rec.set_time("frame", sequence=at[0])
            self.rec.set_time("device_time", duration=np.timedelta64(at[1], "ns"))

    def _scalar(self, path: str, value: float, label: str) -> None:
        if path not in self._styled:
            self.rec.log(path, rr.SeriesLines(names=label), static=True)
            self._styled.add(path)
        self.rec.log(path, rr.Scalars(value))

    # -- items ---------------------------------------------------------------------------
    def process(self, item: Any) -> tuple[()]:
        if isinstance(item, StatsSnapshot):
            self._stats(item)
        elif isinstance(item, Tapped):
            payload = item.item
            if isinstance(payload, PlacedFrame):
                self._placed(payload)
            elif isinstance(payload, FocusFrame):
                self._focus(payload)
            elif isinstance(payload, DepthBlock):
                self._block(payload)
        waited = time.perf_counter() - self._last_mosaic
        if self.preview.dirty and waited >= self.opt.mosaic_every_s:
            self._mosaic()
        return ()

    def _placed(self, p: PlacedFrame) -> None:
        hdr = p.header
        self._now = (hdr.frame_id, hdr.timestamp_ns)
        self._set_time()
        if self.cfg.processing.registration:
            self._scalar("registration/correction_px/x", p.correction_px[0], "x (along)")
            self._scalar("registration/correction_px/y", p.correction_px[1], "y (across)")
        if hdr.frame_id % self.frame_step:
            return
        scale = 255.0 / self.cfg.optics.max_value
        img = to_u8(p.image, scale=scale, reduce=self.opt.frame_scale)
        self.rec.log("scan/camera/image", rr.Image(img, color_model="L").compress(jpeg_quality=80))
        ox, oy = self.preview.origin
        f, (h, w) = self.factor, p.image.shape
        self.rec.log("scan/mosaic/fov", rr.Boxes2D(
            mins=[(p.offset_px[0] - ox) / f, (p.offset_px[1] - oy) / f], sizes=[w / f, h / f],
            labels=f"frame {hdr.frame_id}, level {hdr.focus_index}", colors=(255, 64, 64)))
        self.frames_logged += 1
        if self.measures_focus:
            self._measure(p)

    def _measure(self, p: PlacedFrame) -> None:
        """The focus measure of a whole frame, as the focus stage measures it
        (:func:`~sffscan.stages.focus_measure.focus_measure_raw`), logged as a focus frame."""
        c = self.cfg.processing
        image01, fm = focus_measure_raw(p.image, max_value=self.cfg.optics.max_value,
                                        operator=c.focus_operator, window=c.window)
        self._focus(FocusFrame(p, image01, fm, 0))

    def _focus(self, ff: FocusFrame) -> None:
        hdr = ff.placed.header
        if hdr.frame_id % self.frame_step or ff.focus.size == 0:
            return
        self._set_time((hdr.frame_id, hdr.timestamp_ns))  # behind the newest placed frame
        # on the frame's full width (only columns col0.. were measured): one image size
        root = np.zeros(ff.placed.image.shape, np.float32)
        root[:, ff.col0:ff.col0 + ff.focus.shape[1]] = np.sqrt(np.maximum(ff.focus, 0.0))
        peak = float(root.max())
        img = to_u8(root, scale=255.0 / peak if peak > 0 else 0.0, reduce=self.opt.frame_scale)
        self.rec.log("scan/focus/measure",
                     rr.Image(img, color_model="L").compress(jpeg_quality=80))
        self._set_time()

    def _block(self, b: DepthBlock) -> None:
        self.preview.add(b)
        s = self.opt.block_scale
        self.rec.log("scan/depth/height", rr.DepthImage(
            shown(b.height_um[::s, ::s]), meter=1e6, colormap="turbo",
            depth_range=self.depth_range))
        self.rec.log("scan/depth/confidence",
                     rr.Image(to_u8(b.confidence[::s, ::s], scale=255.0, reduce=1),
                              color_model="L"))
        if b.uncertainty_um is not None:  # µm, one sigma, 0 where invalid
            self.rec.log("scan/depth/uncertainty", rr.DepthImage(
                shown(b.uncertainty_um[::s, ::s]), meter=1e6, colormap="viridis"))

    def _mosaic(self) -> None:
        """Log the mosaic tiles that changed since the last time (image and 3D points)."""
        t, f, (ox, oy) = self.opt.tile_cells, self.factor, self.preview.origin
        for k in self.preview.take_dirty():
            name = f"tile_{k:04d}"
            if k not in self._tiles_placed:  # where the tile lies in the preview, once
                for kind in ("height", "texture"):
                    self.rec.log(f"scan/mosaic/{kind}/{name}",
                                 rr.Transform3D(translation=[k * t, 0.0, 0.0]), static=True)
                self._tiles_placed.add(k)
            height, texture = self.preview.images(k)
            self.rec.log(f"scan/mosaic/height/{name}", rr.DepthImage(
                shown(height), meter=1e6, colormap="turbo", depth_range=self.depth_range))
            self.rec.log(f"scan/mosaic/texture/{name}",
                         rr.Image(to_u8(texture, scale=255.0, reduce=1), color_model="L"))
            pos, col = surface_points(height, texture, pixel_um=self.cfg.optics.pixel_um,
                                      factor=f, origin_px=(ox + k * t * f, oy),
                                      stride=self._stride)
            self.rec.log(f"scan/surface/points/{name}", rr.Points3D(pos, colors=col,
                                                                     radii=-2.0))
            self.tiles_logged += 1
        self._last_mosaic = time.perf_counter()
        self.mosaics_logged += 1

    def _stats(self, snap: StatsSnapshot) -> None:
        if self._now is None:  # shown on the frame timeline: wait for the first frame
            return
        self._set_time()
        for s in snap.stages:
            prev = self._prev.get("stage:" + s.name, (0.0, 0.0, 0.0))
            dt = snap.elapsed_s - prev[0]
            if dt > 0 and s.name != self.name:
                self._scalar(f"stats/rate/{s.name}", (s.frames - prev[1]) / dt,
                             f"{s.name} ({s.unit}/s)")
            self._prev["stage:" + s.name] = (snap.elapsed_s, float(s.frames), 0.0)
        for q in snap.queues:
            into = q.name.rsplit("->", 1)[-1]
            prev = self._prev.get("queue:" + q.name, (0.0, 0.0, 0.0))
            puts = q.puts - prev[1]
            if puts > 0:
                self._scalar(f"stats/queue_fill/{into}", (q.fill_sum - prev[2]) / puts,
                             f"into {into} (of {q.capacity})")
            label = "dropped by the view" if into == self.name else f"dropped before {into}"
            self._scalar(f"stats/dropped/{into}", float(q.dropped), label)
            if into == self.name:
                self.viewer_dropped = q.dropped
            self._prev["queue:" + q.name] = (snap.elapsed_s, float(q.puts), float(q.fill_sum))

    def finish(self) -> tuple[()]:
        self._set_time()
        if self.preview.dirty:
            self._mosaic()
        return ()

    #: True after :meth:`close` when a served view stays up after a successful scan run
    #: from a terminal: it is served until :meth:`release` (the command line waits for
    #: Enter after printing the summary, :func:`sffscan.pipeline.cli.common.hold_views`).
    waiting = False

    def close(self, *, failed: bool) -> None:
        self.rec.flush()
        if self.wait_at_end and not failed and sys.stdin.isatty():
            self.waiting = True  # still served; release() ends it
            return
        self.rec.disconnect()

    def release(self) -> None:
        """Stop serving a view kept up by :meth:`close` (``waiting``)."""
        if self.waiting:
            self.waiting = False
            self.rec.disconnect()

    def extra_stats(self) -> dict[str, int]:
        return {"frames_logged": self.frames_logged, "mosaic_updates": self.mosaics_logged,
                "mosaic_tiles_logged": self.tiles_logged,
                "dropped_by_viewer": self.viewer_dropped}


# -- opening a viewer ------------------------------------------------------------------------
def native_viewer_possible() -> bool:
    """True where a native window can open (a display on Linux; always on macOS/Windows)."""
    if sys.platform.startswith("linux"):
        return bool(os.environ.get("DISPLAY") or os.environ.get("WAYLAND_DISPLAY"))
    return True


def free_port(preferred: int, *, host: str = "127.0.0.1") -> int:
    """``preferred`` if it can be bound at ``host``, else a free port there."""
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        try:
            s.bind((host, preferred))
            return preferred
        except OSError:
            s.bind((host, 0))
            return int(s.getsockname()[1])


def web_viewer_url(grpc_url: str, *, web_port: int) -> str:
    """The address a browser opens to watch ``grpc_url`` in the web viewer."""
    return f"http://127.0.0.1:{web_port}/?url={urllib.parse.quote(grpc_url, safe='')}"


def _is_rrd(path: Path) -> bool:
    """A Rerun recording file: it starts with Rerun's file magic ``RRF`` (then the version
    of its encoding; ``RRF2`` in rerun-sdk 0.41)."""
    try:
        with open(path, "rb") as f:
            return f.read(3) == b"RRF"
    except OSError:
        return False


def parse_mode(mode: list[str]) -> tuple[str, Path | None]:
    """Check the viewer words (``--viewer MODE``, and ``--rrd PATH`` as ``["save", PATH]``):
    ("spawn" | "serve" | "auto", None) or ("save", path)."""
    if mode and mode[0] == "save":
        if len(mode) != 2:
            raise ConfigError("--viewer save: give the recording's path with --rrd PATH")
        path = Path(mode[1])
        if not path.parent.is_dir():
            raise ConfigError(f"--viewer save --rrd {path}: folder {path.parent} does not "
                              "exist")
        if path.is_dir():
            raise ConfigError(f"--viewer save --rrd {path}: is a folder; give an .rrd file "
                              "name")
        if path.is_file() and not _is_rrd(path):  # an image, a configuration: never replaced
            raise ConfigError(f"--viewer save --rrd {path}: exists and is not a Rerun "
                              "recording; refusing to overwrite it, choose another path")
        return "save", path
    if len(mode) == 1 and mode[0] in ("spawn", "serve", "auto"):
        return mode[0], None
    raise ConfigError(f"--viewer {' '.join(mode)}: expected one of {MODES}")


def open_recording(mode: list[str], *, layout: rrb.Blueprint | None = None
                   ) -> tuple[rr.RecordingStream, str | None]:
    """A new recording stream connected as the ``--viewer`` words ``mode`` ask, and the web
    viewer's address when it serves one (logged, INFO). ``layout``: the view's blueprint
    (default :func:`blueprint`, a single scan's)."""
    kind, path = parse_mode(mode)
    if kind == "auto":
        kind = "spawn" if native_viewer_possible() else "serve"
    elif kind == "spawn" and not native_viewer_possible():
        raise ConfigError("--viewer spawn: no display to open the native viewer on (neither "
                          "DISPLAY nor WAYLAND_DISPLAY is set); use '--viewer serve' or "
                          "'--viewer save PATH'")
    rec = rr.RecordingStream("sffscan")
    bp = layout if layout is not None else blueprint()
    words = f"--viewer {mode[0]}" + (f" --rrd {path}" if path is not None else "")
    try:  # Rerun reports an unusable file, port or viewer as RuntimeError
        if kind == "save":
            rec.save(str(path), default_blueprint=bp)
            return rec, None
        if kind == "spawn":
            rec.spawn(port=free_port(9876), default_blueprint=bp)
            return rec, None
        # the scan's data on loopback only (the web viewer's page, which holds no data,
        # listens on all interfaces: rerun-sdk 0.41's serve_web_viewer takes no address)
        server = rr.GrpcServerSink(bind_ip="127.0.0.1", port=free_port(9876))
        rec.set_sinks(server, default_blueprint=bp)
        grpc_url = server.uri
        web_port = free_port(9090, host="0.0.0.0")
        rr.serve_web_viewer(web_port=web_port, open_browser=False, connect_to=grpc_url)
    except RuntimeError as err:
        rec.disconnect()
        raise ConfigError(f"{words}: {err}") from err
    address = web_viewer_url(grpc_url, web_port=web_port)
    log.info("live view at %s", address)
    return rec, address


def viz_sink_for(cfg: ScanConfig, mode: list[str], *,
                 options: VizOptions | None = None) -> Sink:
    """The live-view sink for the ``--viewer`` words ``mode``, its viewer opened.

    ``spawn`` starts the native viewer; ``serve`` serves the web viewer on this machine
    (ports 9876 gRPC / 9090 http, or free ones), prints its address and, after the scan,
    keeps serving until Enter when run from a terminal; ``save PATH`` writes an .rrd
    recording; ``auto`` spawns where a native window can open, else serves.
    """
    rec, address = open_recording(mode)
    return VizSink(cfg, rec, options=options, wait_at_end=address)
