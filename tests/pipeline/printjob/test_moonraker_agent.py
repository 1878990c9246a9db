"""The Moonraker agent at Moonraker's documented JSON-RPC boundary, and the Klipper macros.

Klipper needs a microcontroller, so nothing here runs Klipper: a local websocket server
speaks Moonraker's agent protocol (identify, register_remote_method, the remote-method
notification, printer.gcode.script, connection.send_event, notify_history_changed), and
the shipped macros are rendered with Jinja2 under Klipper's delimiters and parsing rules.
``tests/pipeline/printjob/test_moonraker_real.py`` runs the agent against a real Moonraker server.
"""

from __future__ import annotations

import ast
import configparser
import json
import queue
import re
import threading
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import jinja2
import pytest
from sffscan.pipeline.printjob.links_moonraker import MoonrakerAgent, ServiceBridge
from sffscan.pipeline.printjob.service import (
    Analysis,
    JobService,
    JobStart,
    LayerEvent,
    ScanResult,
)
from websockets.sync.server import ServerConnection, serve

MACROS = Path(__file__).resolve().parents[3] / "printer_links" / "klipper" / "sffscan.cfg"


class FailingHandler:
    def __init__(self, fail: set[int]) -> None:
        self.fail = fail
        self.events: list[LayerEvent] = []

    def scan(self, job: JobStart, event: LayerEvent, folder: Path) -> ScanResult:
        self.events.append(event)
        return ScanResult()

    def analyse(self, job: JobStart, event: LayerEvent, scan: ScanResult,
                folder: Path) -> Analysis:
        if event.layer in self.fail:
            return Analysis(verdict="fail", reason="blob of 0.6 mm on object B")
        return Analysis(verdict="pass")


class FakeMoonraker:
    """Moonraker's side of the agent protocol; the test drives the notifications."""

    def __init__(self) -> None:
        self.received: queue.Queue[dict[str, Any]] = queue.Queue()
        self.outgoing: queue.Queue[dict[str, Any] | None] = queue.Queue()
        self.server = serve(self._session, "127.0.0.1", 0)
        self.url = f"ws://127.0.0.1:{self.server.socket.getsockname()[1]}/websocket"
        self.thread = threading.Thread(target=self.server.serve_forever, daemon=True)
        self.thread.start()

    def _session(self, ws: ServerConnection) -> None:
        stop = threading.Event()

        def pump() -> None:  # test -> agent notifications
            while not stop.is_set():
                try:
                    msg = self.outgoing.get(timeout=0.2)
                except queue.Empty:
                    continue
                if msg is None:
                    ws.close()
                    return
                ws.send(json.dumps(msg))

        t = threading.Thread(target=pump, daemon=True)
        t.start()
        try:
            for raw in ws:
                msg = json.loads(raw)
                self.received.put(msg)
                if "id" in msg:
                    result: Any = "ok"
                    if msg["method"] == "server.connection.identify":
                        result = {"connection_id": 1234}
                    ws.send(json.dumps({"jsonrpc": "2.0", "result": result, "id": msg["id"]}))
        finally:
            stop.set()
            t.join(5)

    def next(self, method: str, timeout_s: float = 10) -> dict[str, Any]:
        while True:
            msg = self.received.get(timeout=timeout_s)
            if msg.get("method") == method:
                return msg

    def close(self) -> None:
        self.server.shutdown()
        self.thread.join(5)


@pytest.fixture
def moonraker() -> Iterator[FakeMoonraker]:
    fake = FakeMoonraker()
    yield fake
    fake.close()


def test_agent_identifies_registers_and_answers_each_layer(moonraker: FakeMoonraker,
                                                           tmp_path: Path) -> None:
    handler = FailingHandler({2})
    with JobService(tmp_path, handler, strict=True) as service:
        bridge = ServiceBridge(service)
        finished: list[str] = []

        def on_finished(outcome: str) -> None:
            finished.append(outcome)
            bridge.end(outcome)

        agent = MoonrakerAgent(moonraker.url, on_layer=bridge.layer, on_finished=on_finished)
        stop = threading.Event()
        runner = threading.Thread(target=agent.run, args=(stop,), daemon=True)
        runner.start()
        ident = moonraker.next("server.connection.identify")
        assert ident["params"]["type"] == "agent" and ident["params"]["client_name"] == "sffscan"
        reg = moonraker.next("connection.register_remote_method")
        assert reg["params"] == {"method_name": "sffscan_layer"}

        scripts = []
        for n in range(4):
            moonraker.outgoing.put({"jsonrpc": "2.0", "method": "sffscan_layer", "params": {
                "layer": n, "z": 0.2 * (n + 1), "filename": "gcodes/cube v2.gcode",
                "region": [10.0, 10.0, 40.0, 30.0], "speed": 15.0}})
            scripts.append(moonraker.next("printer.gcode.script")["params"]["script"])
            event = moonraker.next("connection.send_event")
            assert event["params"]["event"] == "sffscan_verdict"
            assert event["params"]["data"]["layer"] == n
        assert scripts == ["SFFSCAN_DONE ACTION=NONE"] * 2 + [
            'SFFSCAN_DONE ACTION=PAUSE REASON="layer 2 verdict fail: blob of 0.6 mm on '
            'object B"', "SFFSCAN_DONE ACTION=NONE"]  # layer 2's failure acted on once
        assert [e.region_mm for e in handler.events] == [(10.0, 10.0, 40.0, 30.0)] * 4
        job_id = bridge.job_id
        assert job_id is not None and job_id.startswith("cube-v2.gcode-")

        moonraker.outgoing.put({"jsonrpc": "2.0", "method": "notify_history_changed",
                                "params": [{"action": "finished",
                                            "job": {"status": "completed"}}]})
        moonraker.outgoing.put(None)  # then Moonraker goes away: the agent returns
        runner.join(10)
        assert not runner.is_alive()
        stop.set()
        assert finished == ["completed"]
        status = service.status(job_id)
        assert status.status == "ended" and status.counts == {"pass": 3, "fail": 1}


def test_agent_refused_layer_answers_so_the_macro_releases(moonraker: FakeMoonraker,
                                                           tmp_path: Path) -> None:
    with JobService(tmp_path, FailingHandler(set())) as service:
        bridge = ServiceBridge(service, actions={"unknown": "pause"})
        agent = MoonrakerAgent(moonraker.url, on_layer=bridge.layer)
        stop = threading.Event()
        runner = threading.Thread(target=agent.run, args=(stop,), daemon=True)
        runner.start()
        moonraker.next("connection.register_remote_method")
        moonraker.outgoing.put({"jsonrpc": "2.0", "method": "sffscan_layer",
                                "params": {"layer": 0, "filename": "a.gcode"}})  # no z
        script = moonraker.next("printer.gcode.script")["params"]["script"]
        assert script.startswith("SFFSCAN_DONE ACTION=PAUSE REASON=")
        assert "'z'" in script
        stop.set()
        runner.join(10)
        assert not runner.is_alive()


# --- the macros, rendered as Klipper renders them -------------------------------------


def _klipper_sections() -> configparser.RawConfigParser:
    # Klipper's own parser settings (klippy/configfile.py)
    cp = configparser.RawConfigParser(strict=False, inline_comment_prefixes=(";", "#"))
    cp.read_string(MACROS.read_text())
    return cp


def _variables(cp: configparser.RawConfigParser, section: str) -> dict[str, Any]:
    return {k[len("variable_"):]: ast.literal_eval(v) for k, v in cp.items(section)
            if k.startswith("variable_")}


def _render(cp: configparser.RawConfigParser, section: str, context: dict[str, Any]) -> list[str]:
    env = jinja2.Environment("{%", "%}", "{", "}")  # Klipper's gcode_macro delimiters
    text = env.from_string(cp.get(section, "gcode")).render(**context)
    return [line.strip() for line in text.splitlines() if line.strip()]


def test_layer_macro_calls_the_agent_rasters_at_scan_speed_and_holds() -> None:
    cp = _klipper_sections()
    v = _variables(cp, "gcode_macro SFFSCAN_LAYER")
    v["trigger_pin"] = "sffscan_trigger"
    calls: list[tuple[str, dict[str, Any]]] = []

    def remote(name: str, **kw: Any) -> str:
        calls.append((name, kw))
        return ""

    printer = {"gcode_macro SFFSCAN_LAYER": v,
               "print_stats": {"state": "printing", "filename": "cube.gcode"},
               "gcode_move": {"gcode_position": {"z": 1.2}}}
    lines = _render(cp, "gcode_macro SFFSCAN_LAYER", {
        "printer": printer, "params": {"LAYER": "5"},
        "action_call_remote_method": remote})
    assert calls == [("sffscan_layer", {"layer": 5, "z": 1.2, "filename": "cube.gcode",
                                        "region": [10.0, 10.0, 40.0, 30.0], "speed": 15.0})]
    # the trigger is set after the travel has ended (M400) and cleared after the raster
    i_on, i_off = lines.index("SET_PIN PIN=sffscan_trigger VALUE=1"), lines.index(
        "SET_PIN PIN=sffscan_trigger VALUE=0")
    assert lines[i_on - 1] == "M400" and lines[i_off - 1] == "M400"
    raster = lines[i_on + 1:i_off - 1]
    # 20 mm across at 8 mm per pass: 3 serpentine passes at 15 mm/s (F900)
    assert raster == ["G1 X40.0 F900.0", "G1 Y18.0 F9000.0", "G1 X10.0 F900.0",
                      "G1 Y26.0 F9000.0", "G1 X40.0 F900.0"]
    assert lines[-2:] == ["PAUSE", "UPDATE_DELAYED_GCODE ID=_SFFSCAN_WAIT DURATION=0.5"]
    assert "SET_GCODE_VARIABLE MACRO=SFFSCAN_LAYER VARIABLE=busy VALUE=True" in lines
    # not printing: nothing at all
    printer["print_stats"] = {"state": "standby", "filename": ""}
    assert _render(cp, "gcode_macro SFFSCAN_LAYER", {
        "printer": printer, "params": {}, "action_call_remote_method": remote}) == []


def test_done_and_wait_macros_release_keep_paused_or_time_out() -> None:
    cp = _klipper_sections()
    done = _render(cp, "gcode_macro SFFSCAN_DONE",
                   {"params": {"ACTION": "PAUSE", "REASON": "layer 2 verdict fail: gap"}})
    assert "SET_GCODE_VARIABLE MACRO=SFFSCAN_LAYER VARIABLE=keep_paused VALUE=True" in done
    assert 'RESPOND TYPE=error MSG="sffscan: print paused: layer 2 verdict fail: gap"' in done
    assert "CANCEL_PRINT" in _render(cp, "gcode_macro SFFSCAN_DONE",
                                     {"params": {"ACTION": "CANCEL"}})

    v = _variables(cp, "gcode_macro SFFSCAN_LAYER")
    paused = {"state": "paused"}

    def wait(**state: Any) -> list[str]:
        printer = {"gcode_macro SFFSCAN_LAYER": {**v, **state}, "print_stats": paused}
        return _render(cp, "delayed_gcode _SFFSCAN_WAIT", {"printer": printer})

    assert wait(busy=True, wait_loops=3) == [
        "SET_GCODE_VARIABLE MACRO=SFFSCAN_LAYER VARIABLE=wait_loops VALUE=4",
        "UPDATE_DELAYED_GCODE ID=_SFFSCAN_WAIT DURATION=0.5"]
    assert wait(busy=False, keep_paused=False) == ["RESUME"]
    assert wait(busy=False, keep_paused=True) == []
    timeout = wait(busy=True, wait_loops=119)  # 120 x 0.5 s = the 60 s release timeout
    assert re.match(r'RESPOND TYPE=error MSG="sffscan: no answer within 60.0 s', timeout[0])
    assert timeout[-1] == "RESUME"
