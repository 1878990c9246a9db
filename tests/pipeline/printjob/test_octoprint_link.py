"""The OctoPrint plug-in against a real OctoPrint server (from PyPI) and its Virtual Printer.

The test makes (once, then reuses; with uv, tests/venvs.py) a venv with OctoPrint under
``$SFFSCAN_CACHE`` (default ``~/.cache/sffscan/octoprint-venv``), installs the plug-in
from ``printer_links/`` into it (a copy, so that no build files land in the checkout),
starts ``octoprint serve`` on a free loopback port with a temporary basedir, connects to
``VIRTUAL`` and prints 10-layer G-code files with ``@SFFSCAN`` lines against a job
service with a light handler.
It is skipped only when that venv cannot be created because PyPI cannot be reached.
"""

from __future__ import annotations

import json
import os
import queue
import secrets
import shutil
import socket
import subprocess
import threading
import time
import urllib.request
import uuid
from collections.abc import Iterator
from pathlib import Path

import pytest
from sffscan.pipeline.printjob.links_http import ServiceServer
from sffscan.pipeline.printjob.service import (
    Analysis,
    JobEnd,
    JobService,
    JobStart,
    JobStatus,
    LayerEvent,
    ScanResult,
)

from tests.venvs import make_venv, venv_install

pytestmark = pytest.mark.slow

REPO = Path(__file__).resolve().parents[3]
PLUGIN_SRC = REPO / "printer_links" / "octoprint_sffscan"
CACHE = Path(os.environ.get("SFFSCAN_CACHE", Path.home() / ".cache" / "sffscan"))
VENV = CACHE / "octoprint-venv"
OCTOPRINT_SPEC = "octoprint>=1.10,<2"
#: the raster of a scanner on the head, sent by the plug-in while the job is held
SCAN_GCODE = "G1 X37.5 Y42.5 Z{z} F9000\nG1 X52.5 Y42.5 F900\nM400"


def _pypi_reachable() -> bool:
    try:
        with socket.create_connection(("pypi.org", 443), timeout=5):
            return True
    except OSError:
        return False


def _octoprint_venv() -> Path:
    """The cached venv; made (seconds, uv) when it lacks the marker of a finished install."""
    done = VENV / "sffscan-installed.txt"
    if done.is_file() and (VENV / "bin" / "octoprint").exists():
        return VENV
    CACHE.mkdir(parents=True, exist_ok=True)
    pip = make_venv(VENV, OCTOPRINT_SPEC)
    if pip.returncode != 0:
        shutil.rmtree(VENV, ignore_errors=True)
        if not _pypi_reachable():
            pytest.skip("no network: cannot create the OctoPrint venv (pypi.org:443 "
                        "unreachable)")
        raise AssertionError(f"pip install {OCTOPRINT_SPEC} failed:\n{pip.stderr[-3000:]}")
    done.write_text(OCTOPRINT_SPEC + "\n")
    return VENV


class CountingHandler:
    """Scans nothing; counts the layer events; fails the layers of ``fail_layers``."""

    def __init__(self) -> None:
        self.scans: list[tuple[str, int, float]] = []
        self.fail_layers: set[int] = set()
        #: set: a failing layer's analysis waits until the next layer's scan (non-strict)
        self.hold_failing: threading.Event | None = None
        self.ended: queue.Queue[tuple[str, str]] = queue.Queue()

    def scan(self, job: JobStart, event: LayerEvent, folder: Path) -> ScanResult:
        self.scans.append((job.job_id, event.layer, event.z_mm))
        if self.hold_failing is not None and event.layer - 1 in self.fail_layers:
            self.hold_failing.set()
        return ScanResult(info={"layer": event.layer})

    def analyse(self, job: JobStart, event: LayerEvent, scan: ScanResult,
                folder: Path) -> Analysis:
        if event.layer in self.fail_layers:
            if self.hold_failing is not None:
                assert self.hold_failing.wait(30)
            return Analysis(verdict="fail", reason=f"test defect: 2.5 mm gap in object A at "
                                                   f"layer {event.layer}")
        return Analysis(verdict="pass", reason="test handler")


class _EndingService(JobService):
    """Reports each job's end to the test (event-driven waits, no polling)."""

    def end_job(self, job_id: str, end: JobEnd, *, wait_s: float = 10.0) -> JobStatus:
        status = super().end_job(job_id, end, wait_s=wait_s)
        handler: CountingHandler = self.handler  # type: ignore[assignment]
        handler.ended.put((job_id, end.outcome))
        return status


def _gcode(layers: int) -> bytes:
    lines = ["; sffscan test part: 10 layers of a 5 mm square", "G90", "M82", "G92 E0",
             "G1 X10 Y10 F12000"]
    e = 0.0
    for n in range(layers):
        z = 0.2 * (n + 1)
        lines += [";LAYER_CHANGE", f";Z:{z:.2f}", f"G1 Z{z:.2f} F12000", "M400",
                  f"@SFFSCAN LAYER={n} Z={z:.2f}"]
        for x, y in ((15, 10), (15, 15), (10, 15), (10, 10)):
            e += 0.2
            lines.append(f"G1 X{x} Y{y} E{e:.3f} F12000")
    lines += ["M400", "; end"]
    return ("\n".join(lines) + "\n").encode()


class OctoPrint:
    """A running ``octoprint serve`` whose console lines are read by a thread."""

    def __init__(self, venv: Path, basedir: Path, port: int, apikey: str) -> None:
        self.url = f"http://127.0.0.1:{port}"
        self.apikey = apikey
        self.basedir = basedir
        self.lines: queue.Queue[str] = queue.Queue(maxsize=100_000)
        self.proc = subprocess.Popen(
            [str(venv / "bin" / "octoprint"), "serve", "--basedir", str(basedir),
             "--host", "127.0.0.1", "--port", str(port), "--iknowwhatimdoing"],
            stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True,
            env={**os.environ, "PYTHONUNBUFFERED": "1"})
        self._reader = threading.Thread(target=self._read, daemon=True)
        self._reader.start()

    def _read(self) -> None:
        assert self.proc.stdout is not None
        for line in self.proc.stdout:
            try:
                self.lines.put_nowait(line.rstrip())
            except queue.Full:  # pragma: no cover - the test reads them all
                pass

    def wait_line(self, needle: str, timeout_s: float) -> str:
        deadline = time.monotonic() + timeout_s
        while True:
            left = deadline - time.monotonic()
            if left <= 0:
                raise AssertionError(f"OctoPrint never said {needle!r} within {timeout_s} s;"
                                     f" log:\n{self.log_tail()}")
            try:
                line = self.lines.get(timeout=left)
            except queue.Empty:
                continue
            if needle in line:
                return line

    def log_tail(self) -> str:
        log = self.basedir / "logs" / "octoprint.log"
        return log.read_text(errors="replace")[-4000:] if log.exists() else "(no log)"

    def api(self, method: str, path: str, body: dict | None = None,
            raw: bytes | None = None, content_type: str = "application/json") -> object:
        data = raw if raw is not None else (None if body is None else json.dumps(body).encode())
        req = urllib.request.Request(self.url + path, data=data, method=method)
        req.add_header("X-Api-Key", self.apikey)
        if data is not None:
            req.add_header("Content-Type", content_type)
        with urllib.request.urlopen(req, timeout=30) as resp:
            text = resp.read().decode()
        return json.loads(text) if text else None

    def upload_and_print(self, name: str, gcode: bytes) -> None:
        boundary = uuid.uuid4().hex
        parts = [f'--{boundary}\r\nContent-Disposition: form-data; name="file"; '
                 f'filename="{name}"\r\nContent-Type: application/octet-stream\r\n\r\n'.encode()
                 + gcode + b"\r\n"]
        for k, v in (("select", "true"), ("print", "true")):
            parts.append(f'--{boundary}\r\nContent-Disposition: form-data; name="{k}"\r\n\r\n'
                         f"{v}\r\n".encode())
        self.api("POST", "/api/files/local", raw=b"".join(parts) + f"--{boundary}--\r\n".encode(),
                 content_type=f"multipart/form-data; boundary={boundary}")

    def state(self) -> str:
        job = self.api("GET", "/api/job")
        assert isinstance(job, dict)
        return str(job["state"])

    def close(self) -> None:
        self.proc.terminate()
        try:
            self.proc.wait(30)
        except subprocess.TimeoutExpired:  # pragma: no cover
            self.proc.kill()
            self.proc.wait(10)
        self._reader.join(10)
        assert self.proc.stdout is not None
        self.proc.stdout.close()


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def _write_config(basedir: Path, service_url: str, apikey: str) -> None:
    basedir.mkdir(parents=True)
    config = {
        "server": {"firstRun": False, "onlineCheck": {"enabled": False},
                   "pluginBlacklist": {"enabled": False}},
        "serial": {"autoconnect": False, "log": True},
        "plugins": {
            "_disabled": ["announcements", "softwareupdate", "discovery", "errortracking",
                          "tracking", "pluginmanager", "backup", "achievements",
                          "health_check", "gcodeviewer"],
            "virtual_printer": {"enabled": True, "throttle": 0.001},
            "sffscan": {"service_url": service_url, "strict": True, "on_fail": "pause",
                        "timeout_s": 60, "scan_gcode": SCAN_GCODE},
        },
    }
    # JSON is YAML: OctoPrint reads both files as written
    (basedir / "config.yaml").write_text(json.dumps(config, indent=1))
    users = {"_version": 2,
             "sffscan-test": {"password": "$argon2id$unusable", "active": True,
                              "groups": ["admins", "users"], "permissions": [],
                              "apikey": apikey, "settings": {}}}
    (basedir / "users.yaml").write_text(json.dumps(users, indent=1))


@pytest.fixture
def octoprint_setup(tmp_path: Path) -> Iterator[tuple[OctoPrint, CountingHandler]]:
    venv = _octoprint_venv()
    src = tmp_path / "plugin-src"
    shutil.copytree(PLUGIN_SRC, src, ignore=shutil.ignore_patterns("build", "*.egg-info",
                                                                     "__pycache__"))
    done = venv_install(venv, "--no-deps", "--reinstall", str(src), timeout=300)
    assert done.returncode == 0, done.stderr[-3000:]
    handler = CountingHandler()
    service = _EndingService(tmp_path / "store", handler, scan_timeout_s=30,
                             verdict_timeout_s=30)
    server = ServiceServer(service, port=0).start()
    apikey = secrets.token_hex(16).upper()
    _write_config(tmp_path / "octoprint", server.url, apikey)
    octo = OctoPrint(venv, tmp_path / "octoprint", _free_port(), apikey)
    try:
        octo.wait_line("Listening on", timeout_s=120)
        yield octo, handler
    finally:
        octo.close()
        server.close()


def test_octoprint_virtual_printer_scans_every_layer_and_pauses_on_fail(
        octoprint_setup: tuple[OctoPrint, CountingHandler]) -> None:
    octo, handler = octoprint_setup
    octo.api("POST", "/api/connection", {"command": "connect", "port": "VIRTUAL",
                                         "baudrate": 115200})
    octo.wait_line('to "Operational"', timeout_s=60)

    # 1. a 10-layer job: 10 scans, the job completes
    octo.upload_and_print("part10.gcode", _gcode(10))
    job_id, outcome = handler.ended.get(timeout=90)
    assert outcome == "completed"
    assert [n for j, n, _ in handler.scans if j == job_id] == list(range(10))
    assert [round(z, 2) for j, _, z in handler.scans if j == job_id] == [
        round(0.2 * (n + 1), 2) for n in range(10)]
    # the plug-in reports the job's end when OctoPrint says it is done; OctoPrint is then
    # still 'Finishing' for a moment (seen on a loaded 2-core VM)
    octo.wait_line('from "Finishing" to "Operational"', timeout_s=30)
    assert octo.state() == "Operational"
    # the scan moves went out while the job was held: each between its layer's Z move and
    # the next layer's (serial.log holds what OctoPrint sent to the printer)
    sent = [ln.split("Send: ", 1)[1] for ln in
            (octo.basedir / "logs" / "serial.log").read_text().splitlines() if "Send: " in ln]
    raster = [i for i, ln in enumerate(sent) if "G1 X52.5 Y42.5 F900" in ln]
    layer_z = [next(i for i, ln in enumerate(sent) if f"G1 Z{0.2 * (n + 1):.2f} F12000" in ln)
               for n in range(10)]
    assert len(raster) == 10
    assert all(a < r < b for a, r, b in zip(layer_z, raster, layer_z[1:] + [len(sent)],
                                               strict=True))

    # 2. layer 4 fails, on_fail = pause: the job pauses at layer 4 and says why
    handler.fail_layers = {4}
    octo.upload_and_print("part10-defect.gcode", _gcode(10))
    line = octo.wait_line("sffscan: pause the print", timeout_s=90)
    assert "layer 4 verdict fail: test defect: 2.5 mm gap in object A" in line
    deadline = time.monotonic() + 20
    while octo.state() != "Paused":  # the pause is asked right after the log line
        assert time.monotonic() < deadline, f"not paused: {octo.state()}"
        time.sleep(0.2)
    second = [n for j, n, _ in handler.scans if j != job_id]
    assert second == [0, 1, 2, 3, 4]  # nothing scanned (nor printed) past the failed layer
    assert "layer 4 verdict fail" in (octo.basedir / "logs" / "octoprint.log").read_text()
    octo.api("POST", "/api/job", {"command": "cancel"})
    _, outcome = handler.ended.get(timeout=60)
    assert outcome == "cancelled"

    # 3. not strict: the print goes on after layer 4's scan (its analysis ends during layer
    # 5's scan); the failure comes back with layer 5's or 6's answer (alerts): pause there
    octo.api("POST", "/api/settings", {"plugins": {"sffscan": {"strict": False}}})
    handler.hold_failing = threading.Event()
    before = len(handler.scans)
    octo.upload_and_print("part10-defect-lenient.gcode", _gcode(10))
    line = octo.wait_line("sffscan: pause the print", timeout_s=90)
    assert "layer 4 verdict fail" in line
    deadline = time.monotonic() + 20
    while octo.state() != "Paused":
        assert time.monotonic() < deadline, f"not paused: {octo.state()}"
        time.sleep(0.2)
    assert [n for _, n, _ in handler.scans[before:]] in ([0, 1, 2, 3, 4, 5],
                                                         [0, 1, 2, 3, 4, 5, 6])
    octo.api("POST", "/api/job", {"command": "cancel"})
    assert handler.ended.get(timeout=60)[1] == "cancelled"
