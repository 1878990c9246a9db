"""Klipper's motion queue (``motion_report/dump_trapq``) through Moonraker's bridge
websocket, at its documented boundary: a local websocket server speaks Klipper's API
protocol as the bridge passes it (JSON text frames, no 0x03), answers the subscription
with the documented header and streams batches of rows; the agent stores the queue over
a layer's scan with its recording, and the recording then places its frames by it."""

from __future__ import annotations

import json
import queue
import shutil
import threading
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from sffscan.pipeline.formats.recording_motion import MotionQueueError
from sffscan.pipeline.formats.recording_reader import open_recording
from sffscan.pipeline.printjob.links_moonraker import MoonrakerAgent, ServiceBridge
from sffscan.pipeline.printjob.links_trapq import (
    HEADER,
    TrapqStream,
    attach_trapq,
    bridge_url,
)
from sffscan.pipeline.printjob.service import (
    Analysis,
    JobService,
    JobStart,
    LayerEvent,
    ScanResult,
)
from websockets.sync.server import ServerConnection, serve

from tests.pipeline.formats.test_recording_motion import recorded_scan
from tests.pipeline.printjob.test_moonraker_agent import FakeMoonraker

REGION = (30.0, 40.0)  # printer mm of the raster's start


class FakeBridge:
    """Klipper's API server as Moonraker's ``/klippysocket`` passes it through."""

    def __init__(self, *, refuse: bool = False, unavailable: int = 0) -> None:
        self.refuse = refuse
        #: handshakes answered 503 first, as Moonraker does while Klippy is not connected
        self.unavailable = unavailable
        self.batches: queue.Queue[list[Any] | None] = queue.Queue()
        self.requests: list[dict[str, Any]] = []
        self.server = serve(self._session, "127.0.0.1", 0, process_request=self._handshake)
        self.url = f"ws://127.0.0.1:{self.server.socket.getsockname()[1]}/klippysocket"
        self.thread = threading.Thread(target=self.server.serve_forever, daemon=True)
        self.thread.start()

    def _handshake(self, ws: ServerConnection, request: Any) -> Any:
        if self.unavailable > 0:
            self.unavailable -= 1
            return ws.respond(503, "Klippy Unix Connection Not Available\n")
        return None

    def _session(self, ws: ServerConnection) -> None:
        req = json.loads(ws.recv(timeout=10))
        self.requests.append(req)
        if self.refuse:
            ws.send(json.dumps({"id": req["id"], "error": {"error": "WebRequestError",
                                                           "message": "Unknown endpoint"}}))
            return
        ws.send(json.dumps({"id": req["id"], "result": {"header": HEADER}}))
        template = req["params"]["response_template"]
        while True:
            try:
                batch = self.batches.get(timeout=0.2)
            except queue.Empty:
                continue
            if batch is None:
                return
            ws.send(json.dumps({**template, "params": {"data": batch}}))

    def close(self) -> None:
        self.batches.put(None)
        self.server.shutdown()
        self.thread.join(5)


@pytest.fixture(scope="module")
def recorded(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return recorded_scan(tmp_path_factory.mktemp("trapq"), x_end_mm=3.0)


def raster_rows(rec: Path, *, t0_s: float = 500.0) -> list[list[Any]]:
    """The printer's queue of the recorded scan: the head stands at the region's start,
    then moves as the headers say (one constant-velocity segment per pass), then stands."""
    r = open_recording(rec)
    m = {k: v[r.order] for k, v in r.meta.items()}
    t = t0_s + (m["timestamp_ns"] - m["timestamp_ns"][0]) * 1e-9
    xy = (np.c_[m["stage_x_um"], m["stage_y_um"]] - [m["stage_x_um"][0], m["stage_y_um"][0]]
          ) / 1000.0 + REGION
    points = [(t0_s - 2.0, xy[0])]
    for p in np.unique(m["pass_index"]):
        k = np.flatnonzero(m["pass_index"] == p)
        points += [(t[k[0]], xy[k[0]]), (t[k[-1]], xy[k[-1]])]
    points += [(points[-1][0] + 1.0, points[-1][1])]
    rows: list[list[Any]] = []
    for (ta, a), (tb, b) in zip(points[:-1], points[1:], strict=True):
        dist = float(np.hypot(*(b - a)))
        d = (b - a) / dist if dist else np.zeros(2)
        rows.append([ta, tb - ta, dist / (tb - ta), 0.0, [a[0], a[1], 1.2],
                     [d[0], d[1], 0.0]])
    return rows


def test_bridge_url_is_beside_the_agent_websocket() -> None:
    assert bridge_url("ws://pi.local:7125/websocket") == "ws://pi.local:7125/klippysocket"


def test_the_stream_collects_batches_and_the_queue_goes_into_the_recording(
        recorded: Path, tmp_path: Path) -> None:
    rec = tmp_path / "rec.zarr"
    shutil.copytree(recorded, rec)
    want = [f.header for f in open_recording(rec).frames()]
    rows = raster_rows(rec)
    bridge = FakeBridge()
    stream = TrapqStream(bridge.url, timeout_s=5).start()
    try:
        assert bridge.requests[0]["method"] == "motion_report/dump_trapq"
        assert bridge.requests[0]["params"]["name"] == "toolhead"
        bridge.batches.put(rows[:2])
        bridge.batches.put(rows[1:3])  # a row sent again (Klipper's batch overlap)
        assert stream.wait_until(rows[2][0] + rows[2][1], timeout_s=5)

        def rest() -> None:  # the last rows come while attach_trapq waits for them
            bridge.batches.put(rows[3:])

        timer = threading.Timer(0.3, rest)
        timer.start()
        motion = attach_trapq(rec, stream, region_start_mm=REGION, timeout_s=5)
        timer.join()
    finally:
        stream.close()
        bridge.close()
    assert motion.clock.print_time_s_at == 500.0 and motion.clock.how.startswith("trigger")
    r = open_recording(rec)
    assert r.attrs.format_version == 5 and r.motion == motion
    got = [f.header for f in r.frames()]
    # the queue places every frame where the headers did, within the simulator's whole-ns
    # time stamps (0.5 ns at 15 mm/s: 0.0075 µm)
    for g, w in zip(got, want, strict=True):
        assert g.stage_x_um == pytest.approx(w.stage_x_um, abs=0.01)
        assert g.stage_y_um == pytest.approx(w.stage_y_um, abs=0.01)


def test_no_rows_in_time_and_a_refused_subscription_are_errors(recorded: Path,
                                                               tmp_path: Path) -> None:
    rec = tmp_path / "rec.zarr"
    shutil.copytree(recorded, rec)
    refusing = FakeBridge(refuse=True)
    try:
        with pytest.raises(MotionQueueError, match="Unknown endpoint"):
            TrapqStream(refusing.url, timeout_s=5).start()
    finally:
        refusing.close()
    rows = raster_rows(rec)
    bridge = FakeBridge()
    stream = TrapqStream(bridge.url, timeout_s=5).start()
    try:
        with pytest.raises(MotionQueueError, match="no row of the motion queue"):
            attach_trapq(rec, stream, region_start_mm=REGION, timeout_s=0.2)
        half = [rows[1][0], rows[1][1] / 2, *rows[1][2:]]
        bridge.batches.put([rows[0], half])  # the raster starts, the rest never comes
        assert stream.wait_until(half[0] + half[1], timeout_s=5)
        with pytest.raises(MotionQueueError, match="did not reach the last frame"):
            attach_trapq(rec, stream, region_start_mm=REGION, timeout_s=0.3)
        with pytest.raises(MotionQueueError, match="raster's start is not in the queue"):
            attach_trapq(rec, stream, region_start_mm=(0.0, 0.0), timeout_s=0.3)
    finally:
        stream.close()
        bridge.close()
    assert open_recording(rec).attrs.format_version == 4  # nothing written


class RecordingHandler:
    """Scans by copying a recording into the layer's folder."""

    def __init__(self, recording: Path) -> None:
        self.recording = recording

    def scan(self, job: JobStart, event: LayerEvent, folder: Path) -> ScanResult:
        layer = folder / "job" / f"layer_{event.layer:05d}"
        layer.mkdir(parents=True)
        shutil.copytree(self.recording, layer / "recording.zarr")
        return ScanResult(output=layer / "mosaic.zarr")

    def analyse(self, job: JobStart, event: LayerEvent, scan: ScanResult,
                folder: Path) -> Analysis:
        return Analysis(verdict="pass")


@pytest.fixture
def moonraker() -> Iterator[FakeMoonraker]:
    fake = FakeMoonraker()
    yield fake
    fake.close()


def test_agent_stores_the_queue_with_each_layers_recording(
        recorded: Path, moonraker: FakeMoonraker, tmp_path: Path) -> None:
    rows = raster_rows(recorded)
    bridge = FakeBridge()
    store = tmp_path / "store"
    with JobService(store, RecordingHandler(recorded)) as service:
        link = ServiceBridge(service)
        agent = MoonrakerAgent(moonraker.url, on_layer=link.layer, trapq_url=bridge.url,
                               recording_of=link.recording_of, timeout_s=5)
        stop = threading.Event()
        runner = threading.Thread(target=agent.run, args=(stop,), daemon=True)
        runner.start()
        moonraker.next("connection.register_remote_method")
        bridge.batches.put([[1.0, 2.0, 0.0, 0.0, [0, 0, 0], [0, 0, 0]]])  # before: cleared
        moonraker.outgoing.put({"jsonrpc": "2.0", "method": "sffscan_layer", "params": {
            "layer": 0, "z": 0.2, "filename": "part.gcode",
            "region": [*REGION, 60.0, 50.0], "speed": 15.0}})
        # the macro's moves come after its call: the queue streams them while it scans
        timer = threading.Timer(0.5, lambda: bridge.batches.put(rows))
        timer.start()
        assert moonraker.next("printer.gcode.script")["params"]["script"] == \
            "SFFSCAN_DONE ACTION=NONE"
        moonraker.next("connection.send_event")
        # a layer without its raster in the queue: scanned, its recording left as it was
        moonraker.outgoing.put({"jsonrpc": "2.0", "method": "sffscan_layer", "params": {
            "layer": 1, "z": 0.4, "filename": "part.gcode",
            "region": [0.0, 0.0, 60.0, 50.0], "speed": 15.0}})
        timer.join()
        timer = threading.Timer(0.5, lambda: bridge.batches.put(rows))
        timer.start()
        moonraker.next("connection.send_event")
        moonraker.outgoing.put(None)
        runner.join(15)
        stop.set()
        timer.join()
        assert not runner.is_alive()
        job = store / str(link.job_id) / "job"
    bridge.close()
    r0 = open_recording(job / "layer_00000" / "recording.zarr")
    assert r0.attrs.format_version == 5 and r0.motion is not None
    assert r0.motion.clock.print_time_s_at == 500.0
    assert r0.motion.start_s >= 497.0  # the row streamed before the call was cleared
    assert open_recording(job / "layer_00001" / "recording.zarr").attrs.format_version == 4
    assert any("layer 1: no motion queue stored" in n and "raster's start" in n
               for n in agent.trapq_notes)


def test_agent_without_a_bridge_scans_as_before(recorded: Path, moonraker: FakeMoonraker,
                                                tmp_path: Path) -> None:
    with JobService(tmp_path, RecordingHandler(recorded)) as service:
        link = ServiceBridge(service)
        agent = MoonrakerAgent(moonraker.url, on_layer=link.layer, timeout_s=2,
                               trapq_url="ws://127.0.0.1:9/klippysocket",
                               recording_of=link.recording_of)
        stop = threading.Event()
        runner = threading.Thread(target=agent.run, args=(stop,), daemon=True)
        runner.start()
        moonraker.next("connection.register_remote_method")
        moonraker.outgoing.put({"jsonrpc": "2.0", "method": "sffscan_layer", "params": {
            "layer": 0, "z": 0.2, "filename": "part.gcode", "region": [*REGION, 60, 50]}})
        assert moonraker.next("printer.gcode.script")["params"]["script"] == \
            "SFFSCAN_DONE ACTION=NONE"
        moonraker.next("connection.send_event")
        moonraker.outgoing.put(None)
        runner.join(15)
        stop.set()
    assert any("no motion queue from ws://127.0.0.1:9/klippysocket" in n
               for n in agent.trapq_notes)


def test_stream_reconnects_while_moonraker_answers_503() -> None:
    """Moonraker refuses the bridge (HTTP 503) while Klippy is not connected: a stream with
    ``retry_s`` tries again until it is answered; one without says why at once (it used to
    die in its thread with a traceback, and the agent never asked again)."""
    bridge = FakeBridge(unavailable=2)
    try:
        stream = TrapqStream(bridge.url, timeout_s=5.0, retry_s=0.05).start()
        try:
            assert bridge.unavailable == 0 and len(bridge.requests) == 1
            bridge.batches.put([[1.0, 1.0, 0.0, 0.0, [0.0, 0.0, 0.0], [1.0, 0.0, 0.0]]])
            assert stream.wait_until(2.0, timeout_s=5.0)
        finally:
            stream.close()
    finally:
        bridge.close()
    bridge = FakeBridge(unavailable=1)
    try:
        with pytest.raises(MotionQueueError, match="503"):
            TrapqStream(bridge.url, timeout_s=5.0).start()
        assert bridge.requests == []
    finally:
        bridge.close()
