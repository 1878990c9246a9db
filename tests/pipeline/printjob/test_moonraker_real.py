"""The Moonraker agent against a real Moonraker server, with a stand-in for Klippy.

Moonraker is not on PyPI: the test needs its source tree (``$SFFSCAN_MOONRAKER_SRC``,
default ``~/.cache/sffscan/moonraker-src``, a checkout of github.com/Arksine/moonraker)
and makes (once) a venv for it next to it. Klipper itself needs a microcontroller, so the
Klippy side of Moonraker's unix socket is a small stand-in that speaks Klippy's API
protocol (JSON + ``\\x03``: info, list_endpoints, objects/*, register_remote_method,
gcode/script, and ``motion_report/dump_trapq`` on the connections Moonraker opens for its
bridge websocket ``/klippysocket``) and calls the registered remote method as Klipper's
``action_call_remote_method`` does (``{"method": name, "params": {...}}``).
"""

from __future__ import annotations

import json
import os
import queue
import shutil
import socket
import subprocess
import sys
import threading
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest
from sffscan.pipeline.printjob.links_moonraker import MoonrakerAgent, ServiceBridge
from sffscan.pipeline.printjob.links_trapq import TrapqStream, bridge_url
from sffscan.pipeline.printjob.service import (
    Analysis,
    JobService,
    JobStart,
    LayerEvent,
    ScanResult,
)

from tests.venvs import make_venv

pytestmark = pytest.mark.slow

CACHE = Path(os.environ.get("SFFSCAN_CACHE", Path.home() / ".cache" / "sffscan"))
SRC = Path(os.environ.get("SFFSCAN_MOONRAKER_SRC", CACHE / "moonraker-src"))
VENV = CACHE / "moonraker-venv"


def _moonraker_python() -> Path:
    if not (SRC / "moonraker" / "server.py").exists():
        pytest.skip(f"no Moonraker source tree at {SRC} (Moonraker is not on PyPI: set "
                    "SFFSCAN_MOONRAKER_SRC to a checkout of github.com/Arksine/moonraker)")
    python = VENV / "bin" / "python"
    if python.exists():
        return python
    pip = make_venv(VENV, str(SRC), env={**os.environ, "PDM_BUILD_SCM_VERSION": "0.0.0"})
    if pip.returncode != 0:
        shutil.rmtree(VENV, ignore_errors=True)
        try:
            socket.create_connection(("pypi.org", 443), timeout=5).close()
        except OSError:
            pytest.skip("no network: cannot install Moonraker's dependencies")
        raise AssertionError(f"installing Moonraker failed:\n{pip.stderr[-3000:]}")
    return python


class FakeKlippy:
    """Klippy's side of Moonraker's unix socket: enough of its API for Moonraker to be
    ready, and the remote-method calls of the macro."""

    def __init__(self, path: Path) -> None:
        self.path = path
        self.requests: queue.Queue[dict[str, Any]] = queue.Queue()
        self.remote_methods: set[str] = set()
        #: rows streamed to a ``motion_report/dump_trapq`` subscriber (Klipper's format)
        self.trapq_rows: list[list[Any]] = [
            [100.0, 2.0, 0.0, 0.0, [10.0, 10.0, 1.2], [0.0, 0.0, 0.0]],
            [102.0, 1.0, 15.0, 0.0, [10.0, 10.0, 1.2], [1.0, 0.0, 0.0]]]
        self._conn: socket.socket | None = None
        self._bridges: list[socket.socket] = []
        self._send_lock = threading.Lock()
        self._listener = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
        self._listener.bind(str(path))
        self._listener.listen(4)
        self._listener.settimeout(1.0)  # wakes to see the listener closed
        self._thread = threading.Thread(target=self._serve, daemon=True)
        self._thread.start()

    def _serve(self) -> None:
        """The first connection is Moonraker's own; later ones are its bridge websockets'
        (one unix connection per ``/klippysocket`` client)."""
        while True:
            try:
                conn, _ = self._listener.accept()
            except TimeoutError:  # idle for a while (a slow test before): keep accepting
                continue
            except OSError:  # the listener was closed
                return
            if self._conn is None:
                self._conn = conn
            else:
                self._bridges.append(conn)
            threading.Thread(target=self._read, args=(conn,), daemon=True).start()

    def _read(self, conn: socket.socket) -> None:
        buf = b""
        while True:
            try:
                data = conn.recv(65536)
            except OSError:
                return
            if not data:
                return
            buf += data
            while b"\x03" in buf:
                raw, buf = buf.split(b"\x03", 1)
                self._answer(json.loads(raw), conn)

    def _result(self, method: str, params: dict[str, Any]) -> Any:
        if method == "info":
            return {"state": "ready", "state_message": "Printer is ready",
                    "software_version": "fake-klippy", "hostname": "test",
                    "klipper_path": str(self.path.parent), "python_path": sys.executable,
                    "app": "Klipper"}
        if method == "list_endpoints":
            return {"endpoints": ["info", "objects/list", "objects/query",
                                  "objects/subscribe", "gcode/script"]}
        if method == "objects/list":
            return {"objects": ["webhooks", "print_stats", "gcode_move", "pause_resume",
                                "display_status"]}
        if method in ("objects/query", "objects/subscribe"):
            objs = params.get("objects") or {}
            status: dict[str, Any] = {k: {} for k in objs}
            if "webhooks" in status:
                status["webhooks"] = {"state": "ready", "state_message": "Printer is ready"}
            return {"eventtime": time.monotonic(), "status": status}
        if method == "register_remote_method":
            self.remote_methods.add(params["remote_method"])
        return {}

    def _answer(self, req: dict[str, Any], conn: socket.socket) -> None:
        self.requests.put(req)
        params = req.get("params") or {}
        if req.get("method") == "motion_report/dump_trapq":  # Klipper's API_Server.md
            self.send({"id": req.get("id"), "result": {"header": [
                "time", "duration", "start_velocity", "acceleration", "start_position",
                "direction"]}}, conn)
            self.send({**params.get("response_template", {}),
                       "params": {"data": self.trapq_rows}}, conn)
            return
        self.send({"id": req.get("id"), "result": self._result(req.get("method", ""), params)},
                  conn)

    def send(self, msg: dict[str, Any], conn: socket.socket | None = None) -> None:
        conn = conn or self._conn
        assert conn is not None
        with self._send_lock:
            conn.sendall(json.dumps(msg).encode() + b"\x03")

    def wait_for(self, method: str, timeout_s: float, **match: Any) -> dict[str, Any]:
        deadline = time.monotonic() + timeout_s
        while True:
            left = deadline - time.monotonic()
            if left <= 0:
                raise AssertionError(f"Moonraker never sent {method} {match} to Klippy")
            try:
                req = self.requests.get(timeout=left)
            except queue.Empty:
                continue
            params = req.get("params") or {}
            if req.get("method") == method and all(params.get(k) == v
                                                   for k, v in match.items()):
                return req

    def close(self) -> None:
        for s in (self._conn, self._listener, *self._bridges):
            if s is not None:
                s.close()
        self._thread.join(5)


class Handler:
    def __init__(self) -> None:
        self.layers: list[int] = []

    def scan(self, job: JobStart, event: LayerEvent, folder: Path) -> ScanResult:
        self.layers.append(event.layer)
        return ScanResult()

    def analyse(self, job: JobStart, event: LayerEvent, scan: ScanResult,
                folder: Path) -> Analysis:
        if event.layer == 3:
            return Analysis(verdict="fail", reason="layer shift of 0.8 mm")
        return Analysis(verdict="pass")


@pytest.fixture
def real_moonraker(tmp_path: Path) -> Iterator[tuple[str, FakeKlippy, Path]]:
    python = _moonraker_python()
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    data = tmp_path / "printer_data"
    (data / "config").mkdir(parents=True)
    sock = Path(f"/tmp/sffscan-klippy-{os.getpid()}-{port}.sock")  # short: AF_UNIX limit
    klippy = FakeKlippy(sock)
    conf = data / "config" / "moonraker.conf"
    conf.write_text(f"[server]\nhost: 127.0.0.1\nport: {port}\nklippy_uds_address: {sock}\n\n"
                    "[machine]\nprovider: none\n\n"
                    "[authorization]\ntrusted_clients:\n    127.0.0.0/8\n")
    log = tmp_path / "moonraker.log"
    with open(log, "w") as out:
        proc = subprocess.Popen([str(python), "-m", "moonraker", "-d", str(data), "-c",
                                 str(conf), "-n"], stdout=out, stderr=subprocess.STDOUT,
                                cwd=SRC)
    try:
        yield f"ws://127.0.0.1:{port}/websocket", klippy, log
    finally:
        proc.terminate()
        try:
            proc.wait(20)
        except subprocess.TimeoutExpired:  # pragma: no cover
            proc.kill()
            proc.wait(10)
        klippy.close()
        sock.unlink(missing_ok=True)


def test_agent_through_a_real_moonraker(real_moonraker: tuple[str, FakeKlippy, Path],
                                        tmp_path: Path) -> None:
    url, klippy, log = real_moonraker
    # Moonraker connects to Klippy and becomes ready (it subscribes to the webhooks)
    klippy.wait_for("objects/subscribe", timeout_s=60)
    handler = Handler()
    with JobService(tmp_path / "store", handler, strict=True) as service:
        bridge = ServiceBridge(service)
        agent = MoonrakerAgent(url, on_layer=bridge.layer, timeout_s=20)
        stop = threading.Event()
        errors: list[BaseException] = []

        def run() -> None:
            deadline = time.monotonic() + 60
            while not stop.is_set():  # Moonraker's websocket opens after its start-up
                try:
                    agent.run(stop)
                    return
                except OSError as err:
                    if time.monotonic() > deadline:
                        errors.append(err)
                        return
                    stop.wait(0.5)
                except BaseException as err:  # noqa: B036 - reported to the test
                    errors.append(err)
                    return

        runner = threading.Thread(target=run, daemon=True)
        runner.start()
        try:
            klippy.wait_for("register_remote_method", timeout_s=60,
                            remote_method="sffscan_layer")
            scripts = []
            for n in range(5):
                klippy.send({"method": "sffscan_layer", "params": {
                    "layer": n, "z": round(0.2 * (n + 1), 2), "filename": "cube.gcode",
                    "region": [10.0, 10.0, 40.0, 30.0], "speed": 15.0}})
                req = klippy.wait_for("gcode/script", timeout_s=30)
                scripts.append(req["params"]["script"])
        finally:
            stop.set()
            runner.join(15)
        assert not errors, errors
        assert handler.layers == [0, 1, 2, 3, 4]
        assert scripts[:3] == ["SFFSCAN_DONE ACTION=NONE"] * 3
        assert scripts[3] == ('SFFSCAN_DONE ACTION=PAUSE REASON="layer 3 verdict fail: layer '
                              'shift of 0.8 mm"')
        assert scripts[4] == "SFFSCAN_DONE ACTION=NONE"
    assert "sffscan" in log.read_text(errors="replace")  # Moonraker logged the agent
    # the motion queue through Moonraker's bridge websocket (its own unix connection)
    stream = TrapqStream(bridge_url(url), timeout_s=20).start()
    try:
        req = klippy.wait_for("motion_report/dump_trapq", timeout_s=20, name="toolhead")
        assert req["params"]["response_template"] == {"q": "sffscan_trapq"}
        assert stream.wait_until(103.0, timeout_s=20)
        assert stream.rows() == klippy.trapq_rows
    finally:
        stream.close()
    assert "Bridge Socket Opened" in log.read_text(errors="replace")


def test_serve_command_runs_the_agent(real_moonraker: tuple[str, FakeKlippy, Path],
                                      tmp_path: Path) -> None:
    """``sffscan serve --moonraker``: a layer called by the macro is scanned (simulator, no
    G-code: verdict unknown, action none) and answered through Moonraker."""
    from sffscan.pipeline.config import config_from_dict, config_to_toml

    url, klippy, _ = real_moonraker
    cfg = tmp_path / "scan.toml"
    cfg.write_text(config_to_toml(config_from_dict({
        "source": {"world": "plate", "plate_length_mm": 12.0, "plate_width_mm": 2.0},
        "optics": {"width_px": 160, "height_px": 64, "pixel_um": 17.0, "n_levels": 10},
        "motion": {"x_start_mm": 1.0, "x_end_mm": 9.0},
        "processing": {"block_columns": 32, "registration_scale": 2},
        "output": {"chunk_px": 64}}, origin="test")))
    root = Path(__file__).resolve().parents[3]
    proc = subprocess.Popen([sys.executable, "-m", "sffscan", "serve", "--config", str(cfg),
                             "--store", str(tmp_path / "jobs"), "--port", "0",
                             "--moonraker", url], cwd=root, stderr=subprocess.PIPE, text=True)
    try:
        try:
            klippy.wait_for("register_remote_method", timeout_s=90,
                            remote_method="sffscan_layer")
            # as long as the registration may take: the service warms its analysis up
            # (dask, distributed) while it connects, slow on a loaded machine
            klippy.wait_for("motion_report/dump_trapq", timeout_s=90, name="toolhead")
        except AssertionError as exc:  # say what the service said
            proc.kill()
            _, err = proc.communicate(timeout=10)
            raise AssertionError(f"{exc}; sffscan serve's stderr:\n{err}") from None
        klippy.send({"method": "sffscan_layer", "params": {"layer": 0, "z": 0.2,
                                                           "filename": "cube.gcode"}})
        req = klippy.wait_for("gcode/script", timeout_s=120)
        assert req["params"]["script"] == "SFFSCAN_DONE ACTION=NONE"
        proc.terminate()
        _, err = proc.communicate(timeout=30)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.communicate(timeout=10)
    assert proc.returncode == 0, err
    states = list((tmp_path / "jobs").glob("cube.gcode-*/service_state.json"))
    assert len(states) == 1
    state = json.loads(states[0].read_text())
    assert state["layers"]["0"]["verdict"] == "unknown"
    assert "no G-code" in state["layers"]["0"]["reason"]
