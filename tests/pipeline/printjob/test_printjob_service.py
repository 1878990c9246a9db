"""The job service: holds, timeouts, verdicts, restart, and its HTTP front."""

from __future__ import annotations

import json
import threading
import urllib.error
import urllib.request
from pathlib import Path

import pytest
from sffscan.pipeline.printjob.links_http import ServiceServer, is_loopback_host
from sffscan.pipeline.printjob.service import (
    STATE_FILE,
    Analysis,
    JobEnd,
    JobService,
    JobStart,
    LayerEvent,
    ScanResult,
    ServiceError,
    read_state,
    write_state,
)


class Handler:
    """Scans write a small file; verdicts from ``verdicts`` (default pass); gates block."""

    def __init__(self) -> None:
        self.scanned: list[int] = []
        self.analysed: list[int] = []
        self.verdicts: dict[int, str] = {}
        self.scan_gate: threading.Event | None = None
        self.analysis_gate: threading.Event | None = None
        self.scan_error: Exception | None = None
        self.analysis_started = threading.Event()

    def scan(self, job: JobStart, event: LayerEvent, folder: Path) -> ScanResult:
        if self.scan_gate is not None:
            assert self.scan_gate.wait(10)
        if self.scan_error is not None:
            raise self.scan_error
        self.scanned.append(event.layer)
        out = folder / f"layer_{event.layer:05d}.txt"
        out.write_text(str(event.z_mm))
        return ScanResult(output=out)

    def analyse(self, job: JobStart, event: LayerEvent, scan: ScanResult,
                folder: Path) -> Analysis:
        self.analysis_started.set()
        if self.analysis_gate is not None:
            assert self.analysis_gate.wait(10)
        assert scan.output is not None and scan.output.exists()
        self.analysed.append(event.layer)
        v = self.verdicts.get(event.layer, "pass")
        return Analysis(verdict=v, reason=f"{v} by the test", objects={"A": v})  # type: ignore[arg-type]


def _event(n: int) -> LayerEvent:
    return LayerEvent(layer=n, z_mm=0.2 * (n + 1))


def test_non_strict_layer_returns_after_the_scan_and_the_verdict_follows(tmp_path: Path) -> None:
    h = Handler()
    h.analysis_gate = threading.Event()
    with JobService(tmp_path, h) as svc:
        svc.start_job(JobStart(job_id="j1"))
        reply = svc.layer("j1", _event(0))
        assert reply.record.scan == "done" and reply.record.verdict == "pending"
        assert reply.record.output == "layer_00000.txt"
        h.analysis_gate.set()
        status = svc.end_job("j1", JobEnd(), wait_s=10)  # waits for the pending verdict
        assert status.pending == [] and status.counts == {"pass": 1}
        assert svc.record("j1", 0).objects == {"A": "pass"}
    state = read_state(tmp_path / "j1" / STATE_FILE)
    assert state.status == "ended" and state.layers[0].verdict == "pass"


def test_strict_waits_for_the_verdict_and_alerts_list_failed_layers(tmp_path: Path) -> None:
    h = Handler()
    h.verdicts = {1: "fail"}
    with JobService(tmp_path, h, strict=True) as svc:
        svc.start_job(JobStart(job_id="j"))
        assert svc.layer("j", _event(0)).record.verdict == "pass"
        reply = svc.layer("j", _event(1))
        assert reply.record.verdict == "fail" and reply.record.reason == "fail by the test"
        reply = svc.layer("j", _event(2))
        assert [r.layer for r in reply.alerts] == [1]


def test_scan_timeout_releases_the_hold_as_unknown_and_a_busy_scanner_skips(
        tmp_path: Path) -> None:
    h = Handler()
    h.scan_gate = threading.Event()
    with JobService(tmp_path, h, scan_timeout_s=0.2) as svc:
        svc.start_job(JobStart(job_id="j"))
        rec = svc.layer("j", _event(0)).record
        assert (rec.scan, rec.verdict) == ("timeout", "unknown")
        assert "not done within 0.2 s" in rec.reason
        rec = svc.layer("j", _event(1)).record
        assert (rec.scan, rec.verdict) == ("skipped", "unknown")
        assert "busy with layer 0" in rec.reason
        h.scan_gate.set()
    assert h.analysed == []  # a timed-out scan is never analysed into a pass


def test_strict_verdict_timeout_is_unknown_and_a_late_verdict_is_marked(tmp_path: Path) -> None:
    h = Handler()
    h.analysis_gate = threading.Event()
    with JobService(tmp_path, h, strict=True, verdict_timeout_s=0.2) as svc:
        svc.start_job(JobStart(job_id="j"))
        rec = svc.layer("j", _event(0)).record
        assert rec.verdict == "unknown" and "not ready within 0.2 s" in rec.reason
        h.analysis_gate.set()
        svc.end_job("j", JobEnd(), wait_s=10)
        late = svc.record("j", 0)
        assert (late.verdict, late.late) == ("pass", True)


def test_failed_scan_is_unknown_never_pass(tmp_path: Path) -> None:
    h = Handler()
    h.scan_error = RuntimeError("camera lost")
    with JobService(tmp_path, h, strict=True) as svc:
        svc.start_job(JobStart(job_id="j"))
        rec = svc.layer("j", _event(0)).record
        assert (rec.scan, rec.verdict) == ("failed", "unknown")
        assert rec.reason == "scan failed: RuntimeError: camera lost"
    assert h.analysed == []


def test_out_of_order_refused_repeated_answered_without_a_new_scan(tmp_path: Path) -> None:
    h = Handler()
    with JobService(tmp_path, h, strict=True) as svc:
        svc.start_job(JobStart(job_id="j"))
        svc.layer("j", _event(0))
        svc.layer("j", _event(2))
        with pytest.raises(ServiceError, match="layer 1 arrived after layer 2") as err:
            svc.layer("j", _event(1))
        assert err.value.status == 409
        again = svc.layer("j", _event(2))
        assert again.repeated and again.record.verdict == "pass"
        assert h.scanned == [0, 2]
        with pytest.raises(ServiceError, match="'j' is still open"):
            svc.start_job(JobStart(job_id="other"))
        svc.end_job("j", JobEnd(outcome="cancelled"))
        with pytest.raises(ServiceError, match="has ended"):
            svc.layer("j", _event(3))


def test_analysis_queue_full_is_unknown(tmp_path: Path) -> None:
    h = Handler()
    h.analysis_gate = threading.Event()
    with JobService(tmp_path, h, analysis_queue=1) as svc:
        svc.start_job(JobStart(job_id="j"))
        verdicts = [svc.layer("j", _event(0)).record]
        assert h.analysis_started.wait(10)  # layer 0 is in the worker, out of the queue
        verdicts += [svc.layer("j", _event(n)).record for n in (1, 2)]
        # layer 0 is in the worker, layer 1 waits in the queue, layer 2 finds it full
        assert verdicts[2].verdict == "unknown"
        assert verdicts[2].reason == "analysis queue full (1 layers waiting)"
        h.analysis_gate.set()


def test_restart_mid_job_resumes_from_the_state_file(tmp_path: Path) -> None:
    h = Handler()
    with JobService(tmp_path, h, strict=True) as svc:
        svc.start_job(JobStart(job_id="j", gcode_name="part.gcode"))
        for n in range(3):
            svc.layer("j", _event(n))
    # the service died with layer 2's verdict pending and layer 3's scan running
    path = tmp_path / "j" / STATE_FILE
    state = read_state(path)
    state.layers[2] = state.layers[2].model_copy(update={"verdict": "pending"})
    state.layers[3] = state.layers[2].model_copy(update={"layer": 3, "scan": "running",
                                                         "output": None})
    write_state(path, state)

    h2 = Handler()
    with JobService(tmp_path, h2, strict=True) as svc:
        with pytest.raises(ServiceError, match="start it again"):
            svc.status("j")
        status = svc.start_job(JobStart(job_id="j"))
        assert status.resumed and status.layers_done == [0, 1, 2, 3]
        rec3 = svc.record("j", 3)
        assert rec3.verdict == "unknown" and "stopped during" in rec3.reason
        assert svc.layer("j", _event(1)).repeated
        assert svc.layer("j", _event(4)).record.verdict == "pass"
        svc.end_job("j", JobEnd(), wait_s=10)
        assert svc.record("j", 2).verdict == "pass"  # the cut analysis ran again
    assert h2.scanned == [4] and sorted(h2.analysed) == [2, 4]


def _post(url: str, body: object, token: str | None = None) -> tuple[int, dict]:
    req = urllib.request.Request(url, data=json.dumps(body).encode(), method="POST")
    req.add_header("Content-Type", "application/json")
    if token:
        req.add_header("Authorization", f"Bearer {token}")
    try:
        with urllib.request.urlopen(req, timeout=10) as resp:
            return resp.status, json.loads(resp.read())
    except urllib.error.HTTPError as err:
        return err.code, json.loads(err.read())


def test_http_front_end_to_end_and_errors_name_the_field(tmp_path: Path) -> None:
    h = Handler()
    h.verdicts = {1: "fail"}
    with ServiceServer(JobService(tmp_path, h, strict=True), port=0) as server:
        url = server.url
        assert _post(url + "/jobs", {"job_id": "web"})[0] == 200
        code, body = _post(url + "/jobs/web/layers", {"layer": 0, "z_mm": 0.2})
        assert code == 200 and body["record"]["verdict"] == "pass"
        code, body = _post(url + "/jobs/web/layers", {"layer": 1, "z_mm": 0.4,
                                                      "objects": [{"name": "A", "polygon_mm":
                                                                   [[0, 0], [5, 0], [5, 5]]}]})
        assert body["record"]["verdict"] == "fail"
        code, body = _post(url + "/jobs/web/layers", {"layer": -1, "z_mm": 0.2})
        assert code == 400 and body["error"].startswith("layer:")
        code, body = _post(url + "/jobs/web/layers", {"layer": 5, "z_mm": 1,
                                                      "region_mm": [5, 0, 1, 1]})
        assert code == 400 and "region_mm" in body["error"]
        code, body = _post(url + "/jobs/web/layers", {"layer": 0, "z_mm": 0.2, "speed": 3})
        assert code == 400 and "speed" in body["error"]
        assert _post(url + "/jobs/nojob/layers", {"layer": 0, "z_mm": 0.2})[0] == 404
        with urllib.request.urlopen(url + "/jobs/web/layers/1", timeout=10) as resp:
            assert json.loads(resp.read())["objects"] == {"A": "fail"}
        code, body = _post(url + "/jobs/web/end", {"outcome": "completed"})
        assert body["counts"] == {"pass": 1, "fail": 1}


def test_http_token_required_and_no_bind_beyond_loopback_without_one(tmp_path: Path) -> None:
    assert is_loopback_host("127.0.0.5") and is_loopback_host("::1")
    assert not is_loopback_host("0.0.0.0") and not is_loopback_host("192.168.1.2")
    svc = JobService(tmp_path, Handler())
    with pytest.raises(ValueError, match="beyond loopback"):
        ServiceServer(svc, host="0.0.0.0", port=0)
    token = "t" * 32
    with ServiceServer(svc, port=0, token=token) as server:
        code, body = _post(server.url + "/jobs", {"job_id": "x"})
        assert code == 401 and "token" in body["error"]
        assert _post(server.url + "/jobs", {"job_id": "x"}, token="u" * 32)[0] == 401
        assert _post(server.url + "/jobs", {"job_id": "x"}, token=token)[0] == 200
