"""Live view (pipeline/viz/sink.py): a saved Rerun recording read back with rerun.chunk.RrdReader.

One small simulated scan (tests/scan_helpers.py optics) is recorded with ``--viewer save``;
the test reads the .rrd back and checks the entity paths, the frames logged, and that the
last logged mosaic equals the Zarr mosaic reduced the same way.
"""

from __future__ import annotations

import io
import logging
import time
import urllib.parse
import urllib.request
from collections import defaultdict
from contextlib import redirect_stderr
from pathlib import Path
from typing import Any

import numpy as np
import pyarrow as pa
import pytest
import zarr
from rerun.chunk import RrdReader
from sffscan.pipeline.cli.main import main
from sffscan.pipeline.config import ConfigError
from sffscan.pipeline.mosaic.stage import MosaicStage
from sffscan.pipeline.mosaic.writer import MosaicWriter
from sffscan.pipeline.sim_source import simulate_frames
from sffscan.pipeline.viz.preview import (
    MosaicPreview,
    downsample_mosaic,
    point_stride,
    surface_points,
)
from sffscan.pipeline.viz.sink import VizOptions, VizSink, parse_mode, viz_sink_for
from sffscan.pipeline.wiring import ScanReport, run_scan
from sffscan.stages.messages import DepthBlock, DepthBlockHeader

from tests.scan_helpers import small_config

Rows = dict[str, list[dict[str, Any]]]


def read_rrd(path: Path) -> tuple[Rows, set[str], int]:
    """Rows of every entity (temporal rows sorted by frame then log order), the static
    entities, and the number of blueprint stores in the file."""
    reader = RrdReader(path)
    rows: Rows = defaultdict(list)
    static: set[str] = set()
    for chunk in reader.stream():
        if chunk.is_static:
            static.add(chunk.entity_path)
            continue
        batch = chunk.to_record_batch()
        columns = {}
        for name, col in zip(batch.schema.names, batch.columns, strict=True):
            if pa.types.is_timestamp(col.type) or pa.types.is_duration(col.type):
                col = col.cast(pa.int64())  # ns, as logged
            columns[name] = col.to_pylist()
        rows[chunk.entity_path].extend(dict(zip(columns, v, strict=True))
                                       for v in zip(*columns.values(), strict=True))
    for entity in rows.values():
        entity.sort(key=lambda r: (r["frame"], r["rerun.controls.RowId"]))
    return dict(rows), static, len(reader.blueprints())


def depth_image(row: dict[str, Any]) -> np.ndarray:
    fmt = row["DepthImage:format"][0]
    buf = bytes(row["DepthImage:buffer"][0])
    return np.frombuffer(buf, np.float32).reshape(fmt["height"], fmt["width"])


def gray_image(row: dict[str, Any]) -> np.ndarray:
    fmt = row["Image:format"][0]
    return np.frombuffer(bytes(row["Image:buffer"][0]), np.uint8).reshape(fmt["height"],
                                                                          fmt["width"])


def scalars(rows: Rows, path: str) -> list[float]:
    return [r["Scalars:scalars"][0] for r in rows[path]]


@pytest.fixture(scope="module")
def recorded(tmp_path_factory: pytest.TempPathFactory) -> tuple[ScanReport, VizSink, Path]:
    """A small scan recorded to an .rrd; mosaic preview cells of 7 x 7 px (not aligned with
    the 64-column depth blocks) in tiles of 100 cells, and a queue big enough that nothing
    is dropped."""
    tmp = tmp_path_factory.mktemp("viz")
    cfg = small_config()
    sink = viz_sink_for(cfg, ["save", str(tmp / "scan.rrd")],
                        options=VizOptions(capacity=100_000, mosaic_max_px=320,
                                           mosaic_every_s=0.5, tile_cells=100))
    assert isinstance(sink, VizSink)
    report = run_scan(cfg, frames=simulate_frames(cfg), output=tmp / "m.zarr", progress=False,
                      sinks=[sink])
    return report, sink, tmp / "scan.rrd"


def test_recording_entity_paths_and_frames(recorded: tuple[ScanReport, VizSink, Path]) -> None:
    report, sink, rrd = recorded
    rows, static, blueprints = read_rrd(rrd)
    assert sink.factor == 7
    assert blueprints == 1
    for path in ["/scan/camera/image", "/scan/focus/measure", "/scan/depth/height",
                 "/scan/depth/confidence", "/scan/mosaic/height/tile_0000",
                 "/scan/mosaic/texture/tile_0003", "/scan/mosaic/fov",
                 "/scan/surface/points/tile_0002", "/registration/correction_px/x",
                 "/registration/correction_px/y", "/stats/dropped/viewer"]:
        assert path in rows, f"{path} missing; logged: {sorted(rows)}"
    for stage in ["source", "registration", "focus_measure", "depth", "mosaic"]:
        assert f"/stats/rate/{stage}" in rows
    assert {"/scan/calibration", "/scan/config", "/scan/surface"} <= static
    # nothing dropped, so every frame_id that is a multiple of the step was logged, once
    viewer_queue = [q for q in report.result.queues if q.name.endswith("->viewer")][0]
    assert viewer_queue.dropped == 0 and viewer_queue.policy == "drop_oldest"
    n = report.frames
    assert sink.frame_step == 15  # 150 fps / 10 Hz
    logged = [r["frame"] for r in rows["/scan/camera/image"]]
    assert logged == list(range(0, n, 15))
    assert [r["frame"] for r in rows["/scan/focus/measure"]] == logged
    # the registration correction of every frame, on the frame timeline
    assert [r["frame"] for r in rows["/registration/correction_px/x"]] == list(range(n))
    # device time: frame_id / fps
    t = np.array([r["device_time"] for r in rows["/scan/camera/image"]])
    np.testing.assert_allclose(np.diff(t), 15 / 150.0 * 1e9, rtol=1e-6)
    # each depth block once
    depth_items = [s for s in report.result.stages if s.name == "depth"][0].items_out
    assert len(rows["/scan/depth/height"]) == depth_items
    assert scalars(rows, "/stats/dropped/viewer")[-1] == 0.0


def tiles(rows: Rows, prefix: str) -> dict[int, dict[str, Any]]:
    """The last logged row of each mosaic tile ``{prefix}/tile_NNNN``."""
    return {int(path.rsplit("_", 1)[1]): entity[-1] for path, entity in rows.items()
            if path.startswith(prefix + "/tile_")}


def test_logged_mosaic_equals_zarr(recorded: tuple[ScanReport, VizSink, Path]) -> None:
    report, sink, rrd = recorded
    rows, static, _ = read_rrd(rrd)
    g = zarr.open_group(str(report.output), mode="r")
    assert g.attrs["status"] == "complete"
    want_h, want_t = downsample_mosaic(np.asarray(g["height"]), np.asarray(g["texture"]),
                                       np.asarray(g["weight"]), factor=sink.factor)
    # the last logged version of every tile, put together (tiles of 100 cells)
    t = sink.opt.tile_cells
    h_tiles, t_tiles = tiles(rows, "/scan/mosaic/height"), tiles(rows, "/scan/mosaic/texture")
    assert sorted(h_tiles) == sorted(t_tiles) == list(range(-(-want_h.shape[1] // t)))
    assert {f"/scan/mosaic/height/tile_{k:04d}" for k in h_tiles} <= static  # placement
    got_h = np.concatenate([depth_image(h_tiles[k]) for k in sorted(h_tiles)], axis=1)
    got_t = np.concatenate([gray_image(t_tiles[k]) for k in sorted(t_tiles)], axis=1)
    assert got_h.shape == want_h.shape
    assert np.isfinite(want_h).mean() > 0.5 and (want_h[np.isfinite(want_h)] > 0).all()
    assert np.array_equal(got_h == 0, np.isnan(want_h))  # invalid cells are logged as 0
    # float32 rounding of the Zarr's per-pixel blend: 1e-5 relative of heights < 10 mm
    np.testing.assert_allclose(got_h, np.nan_to_num(want_h), atol=0.05)
    want_t8 = np.clip(np.nan_to_num(want_t) * 255 + 0.5, 0, 255).astype(np.int16)
    assert np.abs(got_t.astype(np.int16) - want_t8).max() <= 1
    # only changed tiles are logged: fewer tile images than updates x tiles
    logged = sum(len(rows[f"/scan/mosaic/height/tile_{k:04d}"]) for k in h_tiles)
    assert logged == sink.tiles_logged < sink.mosaics_logged * len(h_tiles)
    # the 3D points of the last tiles: heights in mm within the mosaic's, at most 50 000
    pts = [p for k, row in tiles(rows, "/scan/surface/points").items()
           for p in row["Points3D:positions"]]
    assert 0 < len(pts) <= 50_000
    z = np.array([p[2] for p in pts])
    assert np.nanmin(want_h) / 1000 - 1e-3 <= z.min() and z.max() <= np.nanmax(want_h) / 1000 + 1e-3


def test_preview_blends_like_the_mosaic_stage(tmp_path: Path) -> None:
    """Overlapping blocks of two passes, one at a NaN hole: preview == reduced Zarr."""
    rng = np.random.default_rng(3)
    writer = MosaicWriter(tmp_path / "m.zarr", origin_px=(100, 50), shape=(40, 90), pixel_um=10.0,
                          chunk_px=32)
    stage = MosaicStage(writer)
    preview = MosaicPreview(origin_px=(100, 50), shape=(40, 90), factor=5)
    for pass_index, (x0, y0) in enumerate([(103, 51), (133, 51), (120, 63), (170, 63)]):
        h = rng.uniform(0, 5000, (30, 33)).astype(np.float32)
        h[:9, :6] = np.nan  # the first block's cells (0, 0) get nothing
        block = DepthBlock(DepthBlockHeader(x0_px=x0, y0_px=y0, width_px=33, height_px=30,
                                            pass_index=pass_index // 2, complete_columns=33,
                                            incomplete_columns=0),
                           h, rng.uniform(0, 1, h.shape).astype(np.float32),
                           rng.uniform(0, 1, h.shape).astype(np.float32))
        list(stage.process(block))
        preview.add(block)
    list(stage.finish())
    stage.close(failed=False)
    g = zarr.open_group(str(tmp_path / "m.zarr"), mode="r")
    want_h, want_t = downsample_mosaic(np.asarray(g["height"]), np.asarray(g["texture"]),
                                       np.asarray(g["weight"]), factor=5)
    got_h, got_t = preview.images()
    # grown past the initial 40 x 90 px; the Zarr grows by whole chunks (32 px): NaN there
    assert got_h.shape == (9, 21) and want_h.shape == (9, 26)
    assert np.isnan(want_h[:, 21:]).all()
    want_h, want_t = want_h[:, :21], want_t[:, :21]
    np.testing.assert_allclose(got_h, want_h, atol=0.02, equal_nan=True)
    np.testing.assert_allclose(got_t, want_t, atol=1e-5, equal_nan=True)
    assert np.isnan(got_h[0, 0]) and np.isfinite(got_h[1, 1])


def test_surface_points_known_answer() -> None:
    h = np.array([[1000.0, np.nan], [2000.0, 3000.0]], np.float32)
    t = np.array([[0.0, 0.5], [1.0, 0.5]], np.float32)
    pos, col = surface_points(h, t, pixel_um=10.0, factor=4, origin_px=(100, 200), stride=1)
    # cell (i, j) centre: world px origin + (j + 0.5) * 4 - 0.5 -> mm at 10 µm/px
    np.testing.assert_allclose(pos, [[1.015, 2.015, 1.0], [1.015, 2.055, 2.0],
                                     [1.055, 2.055, 3.0]], atol=1e-6)
    assert col[:, 0].tolist() == [0, 255, 128]
    assert point_stride(10_000, 2500) == 2 and point_stride(10_001, 2500) == 3
    pos, _ = surface_points(np.zeros((100, 100), np.float32), np.zeros((100, 100), np.float32),
                            pixel_um=1.0, factor=1, origin_px=(0, 0), stride=2)
    assert len(pos) == 2500


def test_viewer_mode_words(tmp_path: Path) -> None:
    assert parse_mode(["spawn"]) == ("spawn", None)
    assert parse_mode(["save", str(tmp_path / "a.rrd")]) == ("save", tmp_path / "a.rrd")
    for bad in (["save"], ["bogus"], ["serve", "x"], ["save", str(tmp_path / "no" / "a.rrd")]):
        with pytest.raises(ConfigError, match="--viewer"):
            parse_mode(bad)
    err = io.StringIO()
    with redirect_stderr(err):
        code = main(["demo", "-o", str(tmp_path / "d.zarr"), "--viewer", "bogus", "-q"])
    assert code == 2 and "--viewer bogus" in err.getvalue()
    # an existing file is replaced only when it is a Rerun recording (its file magic)
    old = tmp_path / "old.rrd"
    old.write_bytes(b"RRF2" + bytes(12))
    assert parse_mode(["save", str(old)]) == ("save", old)
    image = tmp_path / "im_01.png"
    image.write_bytes(b"\x89PNG the user's image")
    with pytest.raises(ConfigError, match="exists and is not a Rerun recording"):
        parse_mode(["save", str(image)])
    with redirect_stderr(io.StringIO()) as err:
        code = main(["demo", "-o", str(tmp_path / "e.zarr"), "-q", "--rrd", str(image)])
    assert code == 2 and "not a Rerun recording" in err.getvalue()
    assert image.read_bytes() == b"\x89PNG the user's image"


def test_spawn_without_a_display_is_refused(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.delenv("DISPLAY", raising=False)
    monkeypatch.delenv("WAYLAND_DISPLAY", raising=False)
    monkeypatch.setattr("sys.platform", "linux")
    with pytest.raises(ConfigError, match="--viewer spawn: no display"):
        viz_sink_for(small_config(), ["spawn"])


class SlowViz(VizSink):
    """A viewer that cannot keep up (30 ms per item)."""

    def process(self, item: Any) -> tuple[()]:
        time.sleep(0.03)
        return super().process(item)


def test_slow_viewer_drops_oldest_and_shows_the_count(tmp_path: Path) -> None:
    import rerun as rr

    cfg = small_config(motion={"x_start_mm": 2.0, "x_end_mm": 8.0})
    rec = rr.RecordingStream("sffscan-test")
    rec.save(str(tmp_path / "slow.rrd"))
    sink = SlowViz(cfg, rec, options=VizOptions(capacity=4))
    report = run_scan(cfg, frames=simulate_frames(cfg), output=tmp_path / "m.zarr",
                      progress=False, sinks=[sink])
    q = [q for q in report.result.queues if q.name.endswith("->viewer")][0]
    assert q.dropped > 0  # it fell behind, and the scan went on without it
    assert all(s.frames == report.frames for s in report.result.stages[:4])
    g = zarr.open_group(str(report.output), mode="r")
    assert g.attrs["status"] == "complete"
    rows, _, _ = read_rrd(tmp_path / "slow.rrd")
    # the last statistics reach the viewer after the last drop: it shows the final count
    assert scalars(rows, "/stats/dropped/viewer")[-1] == q.dropped
    assert report.result.extras["viewer"]["dropped_by_viewer"] == q.dropped


@pytest.mark.parametrize("mode", [["serve"], ["auto"]])
def test_serve_mode_serves_the_web_viewer_on_loopback(mode: list[str],
                                                      monkeypatch: pytest.MonkeyPatch,
                                                      caplog: pytest.LogCaptureFixture) -> None:
    """``serve`` (and ``auto`` without a display) log the web viewer's address; it answers."""
    monkeypatch.delenv("DISPLAY", raising=False)
    monkeypatch.delenv("WAYLAND_DISPLAY", raising=False)
    monkeypatch.setattr("sys.platform", "linux")
    cfg = small_config()
    with caplog.at_level(logging.INFO, logger="sffscan"):
        sink = viz_sink_for(cfg, mode)
    try:
        lines = [r.getMessage() for r in caplog.records if "live view" in r.getMessage()]
        assert len(lines) == 1 and lines[0].startswith("live view at http://127.0.0.1:")
        url = lines[0].split(" at ", 1)[1]
        assert "?url=rerun%2Bhttp%3A%2F%2F127.0.0.1%3A" in url
        with urllib.request.urlopen(url.split("?", 1)[0], timeout=10) as resp:
            assert resp.status == 200
            assert b"rerun" in resp.read().lower()
        # the scan's data (gRPC) is served on loopback only, not to the network
        grpc = urllib.parse.unquote(url.split("?url=", 1)[1])
        grpc_port = int(grpc.rsplit(":", 1)[1].split("/", 1)[0])
        if Path("/proc/net/tcp").exists():
            assert listening_addresses(grpc_port) == {"127.0.0.1"}
    finally:
        sink.close(failed=False)


def test_demo_shows_the_live_view_by_default(tmp_path: Path,
                                             monkeypatch: pytest.MonkeyPatch) -> None:
    seen: list[tuple[Any, str]] = []

    def fake_viewer_sink(cfg: Any, viewer: Any, *, default: str, rrd: Any = None) -> None:
        seen.append((viewer, default))
        raise ConfigError("stop here")

    monkeypatch.setattr("sffscan.pipeline.cli.main.viewer_sink", fake_viewer_sink)
    with redirect_stderr(io.StringIO()):
        assert main(["demo", "-o", str(tmp_path / "d.zarr"), "-q"]) == 2
        assert main(["demo", "-o", str(tmp_path / "d.zarr"), "-q", "--viewer", "off"]) == 2
    assert seen == [(None, "auto"), ("off", "auto")]


class _Terminal(io.StringIO):
    def isatty(self) -> bool:
        return True


def test_served_view_stays_until_enter_in_a_terminal(monkeypatch: pytest.MonkeyPatch,
                                                     tmp_path: Path) -> None:
    """After a scan run from a terminal, ``serve`` keeps the view until Enter (asked by the
    command line after the summary, :func:`hold_views`); the recording is flushed and
    closed after that."""
    import rerun as rr
    from sffscan.pipeline.cli.common import hold_views

    rec = rr.RecordingStream("sffscan-test")
    rec.save(str(tmp_path / "w.rrd"))
    sink = VizSink(small_config(), rec, wait_at_end="http://127.0.0.1:1/?url=x")
    stdin = _Terminal("\n")
    monkeypatch.setattr("sys.stdin", stdin)
    err = io.StringIO()
    with redirect_stderr(err):
        sink.close(failed=False)
        assert sink.waiting and stdin.tell() == 0  # still served, nothing asked yet
        hold_views([sink])
    assert "stays at http://127.0.0.1:1/?url=x until you press Enter" in err.getvalue()
    assert stdin.tell() == 1  # the Enter was read
    assert not sink.waiting
    _, static, _ = read_rrd(tmp_path / "w.rrd")
    assert "/scan/calibration" in static


def test_served_view_summary_comes_before_the_wait(monkeypatch: pytest.MonkeyPatch,
                                                  tmp_path: Path) -> None:
    """``--viewer serve`` from a terminal: the progress line is ended, the summary printed,
    and only then does the command wait for Enter."""
    import rerun as rr
    from sffscan.pipeline.cli.common import run_and_report

    cfg = small_config(motion={"x_start_mm": 2.0, "x_end_mm": 6.0},
                       output={"path": str(tmp_path / "m.zarr")})
    rec = rr.RecordingStream("sffscan-test")
    rec.save(str(tmp_path / "s.rrd"))
    sink = VizSink(cfg, rec, wait_at_end="http://127.0.0.1:1/?url=x")
    screen = _Terminal()  # stdout and stderr on one terminal, as a user sees them
    stdin = _Terminal("\n")
    monkeypatch.setattr("sys.stdin", stdin)
    monkeypatch.setattr("sys.stdout", screen)
    monkeypatch.setattr("sys.stderr", screen)
    assert run_and_report(cfg, simulate_frames(cfg), world=None, progress=True,
                          sinks=[sink]) == 0
    text = screen.getvalue()
    summary = text.index("mosaic      ")
    wait = text.index("until you press Enter")
    assert summary < wait and stdin.tell() == 1
    assert "\r" in text[:summary] and text[:summary].endswith("\n")  # the bar's line ended
    assert "\r" not in text[summary:]


def test_downsample_mosaic_known_answer() -> None:
    """The reference the read-back test compares with, against a plain loop over cells."""
    rng = np.random.default_rng(5)
    h = rng.uniform(0, 900, (11, 14))
    h[rng.uniform(size=h.shape) < 0.3] = np.nan
    h[:3, :3] = np.nan  # one cell with no valid pixel
    t, w = rng.uniform(0, 1, h.shape), rng.uniform(0.01, 2, h.shape)
    got_h, got_t = downsample_mosaic(h, t, w, factor=3)
    assert got_h.shape == got_t.shape == (4, 5) and got_h.dtype == np.float32
    for i in range(4):
        for j in range(5):
            cell = (slice(3 * i, 3 * i + 3), slice(3 * j, 3 * j + 3))
            ok = np.isfinite(h[cell])
            if not ok.any():
                assert np.isnan(got_h[i, j]) and np.isnan(got_t[i, j])
                continue
            ww = w[cell][ok]
            assert got_h[i, j] == pytest.approx((ww * h[cell][ok]).sum() / ww.sum(), rel=1e-6)
            assert got_t[i, j] == pytest.approx((ww * t[cell][ok]).sum() / ww.sum(), rel=1e-6)
    assert np.isnan(got_h[0, 0])


def static_row(path: Path, entity: str) -> dict[str, Any]:
    """The static row logged at ``entity`` (one chunk)."""
    rows = [c.to_record_batch().to_pylist()[0] for c in RrdReader(path).stream()
            if c.is_static and c.entity_path == entity
            and "focus_heights_um" in c.to_record_batch().schema.names]
    assert len(rows) == 1
    return rows[0]


def test_calibrated_focus_table_is_shown(tmp_path: Path) -> None:
    """With a calibration, the view's focus table and colour range are the calibrated
    heights the depth stage uses, not the nominal optics table."""
    import rerun as rr
    from sffscan.pipeline.measuring import focus_heights_um
    from sffscan.pipeline.metrology.calibration_model import (
        Calibration,
        ZResponse,
        save_calibration,
    )

    z = ZResponse(um_per_level=150.0, intercept_um=2000.0, pearson_r=1.0,
                  heights_um=[2000.0, 9350.0], peak_levels=[0.0, 49.0], residuals_um=[0.0, 0.0])
    cal = save_calibration(Calibration(description="test", z_response=z), tmp_path / "cal.json")
    cfg = small_config(processing={"calibration": str(cal)})
    want = focus_heights_um(cfg)
    assert want[0] == 2000.0 and want != cfg.optics.focus_heights_um()
    rec = rr.RecordingStream("sffscan-test")
    rec.save(str(tmp_path / "c.rrd"))
    sink = VizSink(cfg, rec)
    sink.close(failed=False)
    assert sink.depth_range == (min(want), max(want))
    assert static_row(tmp_path / "c.rrd", "/scan/calibration")["focus_heights_um"] == want


@pytest.mark.parametrize("where", ["dir", "unwritable"])
def test_viewer_save_to_an_unusable_path_exits_2(tmp_path: Path, where: str) -> None:
    """``--viewer save --rrd PATH`` where PATH is a folder or cannot be created: exit 2,
    named."""
    path = tmp_path if where == "dir" else Path("/proc/sffscan-test.rrd")
    err = io.StringIO()
    with redirect_stderr(err):
        code = main(["demo", "-o", str(tmp_path / "d.zarr"), "-q", "--viewer", "save",
                     "--rrd", str(path)])
    # named by its option: the run path's output check ("--rrd PATH: is a folder, ...")
    # or the viewer's ("--viewer save --rrd PATH: ...")
    assert code == 2 and f"--rrd {path}" in err.getvalue()


def listening_addresses(port: int) -> set[str]:
    """IPv4 addresses this machine listens on at TCP ``port`` (Linux /proc/net/tcp)."""
    out = set()
    for line in Path("/proc/net/tcp").read_text().splitlines()[1:]:
        local, state = line.split()[1], line.split()[3]
        addr, hexport = local.split(":")
        if state == "0A" and int(hexport, 16) == port:
            out.add(".".join(str(int(addr[i:i + 2], 16)) for i in (6, 4, 2, 0)))
    return out


def jpeg_shape(row: dict[str, Any], component: str = "EncodedImage:blob") -> tuple[int, ...]:
    import cv2

    blob = np.frombuffer(bytes(row[component][0]), np.uint8)
    return tuple(cv2.imdecode(blob, cv2.IMREAD_UNCHANGED).shape)


def test_focus_images_keep_the_frame_shape(recorded: tuple[ScanReport, VizSink, Path]) -> None:
    """The focus measure covers only the columns that can still add to the volume; it is
    logged on the frame's full width (columns placed at col0, the rest 0) so the viewer gets
    one image size (Rerun treats a compressed image stream that changes size as an error)."""
    _, _, rrd = recorded
    rows, _, _ = read_rrd(rrd)
    camera = {jpeg_shape(r) for r in rows["/scan/camera/image"]}
    focus = {jpeg_shape(r) for r in rows["/scan/focus/measure"]}
    assert len(camera) == 1 and focus == camera


def test_blueprint_shows_the_views_own_drops_apart() -> None:
    """The view's own drop count has a view of its own (a legend of six queues is cut)."""
    import rerun.blueprint as rrb
    from sffscan.pipeline.viz.sink import blueprint

    views: list[Any] = []

    def walk(node: Any) -> None:
        if isinstance(node, rrb.TimeSeriesView):
            views.append(node)
        for child in getattr(node, "contents", None) or []:
            if not isinstance(child, str):
                walk(child)

    walk(blueprint().root_container)
    own = [v for v in views if "stats/dropped/viewer" in str(v.origin) + str(v.contents)
           and "- stats/dropped/viewer" not in v.contents]
    assert len(own) == 1 and str(own[0].origin) == "stats/dropped/viewer"
    others = [v for v in views if str(v.origin) == "stats/dropped"]
    assert len(others) == 1 and "- stats/dropped/viewer" in others[0].contents


@pytest.mark.parametrize(("processing", "measures"), [
    ({"workers": 2, "bands": "threads"}, True), ({"workers": 2, "bands": "processes"}, True),
    ({"workers": 1}, False), ({"workers": 2, "backend": "torch"}, False)])
def test_band_workers_view_measures_the_frames_it_shows(tmp_path: Path, processing: dict,
                                                       measures: bool) -> None:
    """Where the depth stage's band workers measure the focus (more than one, in threads or
    processes, the OpenCV backend), no focus frame reaches the view: it measures the frames
    it shows itself (the whole frame, the focus stage's measure); otherwise it waits for the
    focus frames."""
    import cv2
    import rerun as rr
    from sffscan.pipeline.viz.preview import to_u8
    from sffscan.stages.focus_measure import focus_measure_raw
    from sffscan.stages.messages import PlacedFrame
    from sffscan.stages.protocol import Tapped

    cfg = small_config(processing=processing)
    rec = rr.RecordingStream("sffscan-test")
    rec.save(str(tmp_path / "b.rrd"))
    sink = VizSink(cfg, rec)
    assert sink.measures_focus == measures
    frame = next(iter(simulate_frames(cfg)))
    assert frame.header.frame_id % sink.frame_step == 0
    sink.process(Tapped("registration", PlacedFrame(frame.header, frame.image, (0.0, 0.0),
                                                    (0, 0))))
    sink.close(failed=False)
    rec.flush()
    rows, _, _ = read_rrd(tmp_path / "b.rrd")
    if not measures:
        assert "/scan/focus/measure" not in rows
        return
    (row,) = rows["/scan/focus/measure"]
    got = cv2.imdecode(np.frombuffer(bytes(row["EncodedImage:blob"][0]), np.uint8),
                       cv2.IMREAD_UNCHANGED)
    _, fm = focus_measure_raw(frame.image, max_value=cfg.optics.max_value,
                              operator=cfg.processing.focus_operator, window=cfg.processing.window)
    root = np.sqrt(np.maximum(fm, 0.0))
    want = to_u8(root, scale=255.0 / float(root.max()), reduce=sink.opt.frame_scale)
    assert got.shape == want.shape
    # the same image up to JPEG's loss (quality 80: ~2 grey levels on average)
    assert np.abs(got.astype(float) - want).mean() < 0.05 * want.mean()
    assert np.corrcoef(got.ravel(), want.ravel())[0, 1] > 0.98
