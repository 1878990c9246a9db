"""The service's default handler (job store + LayerRunner) and ``sffscan serve``."""

from __future__ import annotations

import json
import os
import re
import signal
import subprocess
import sys
import urllib.request
from pathlib import Path

import pytest
from sffscan.pipeline.config import config_from_dict, config_to_toml
from sffscan.pipeline.printjob import demo
from sffscan.pipeline.printjob.jobstore import JobStore
from sffscan.pipeline.printjob.links_store import STORE_DIR, JobStoreHandler
from sffscan.pipeline.printjob.service import JobEnd, JobService, JobStart, LayerEvent

ROOT = Path(__file__).resolve().parents[3]


def tiny_config() -> object:
    """160 x 64 px of 17 µm, N = 10, over 8 mm of the plate: about 100 frames."""
    return config_from_dict({
        "source": {"world": "plate", "plate_length_mm": 12.0, "plate_width_mm": 2.0},
        "optics": {"width_px": 160, "height_px": 64, "pixel_um": 17.0, "n_levels": 10},
        "motion": {"x_start_mm": 1.0, "x_end_mm": 9.0},
        "processing": {"block_columns": 32, "registration_scale": 2},
        "output": {"chunk_px": 64},
    }, origin="test")


def test_without_gcode_the_layer_is_scanned_and_unknown(tmp_path: Path) -> None:
    handler = JobStoreHandler(tiny_config(), gcode_dir=tmp_path / "gcodes")  # type: ignore[arg-type]
    (tmp_path / "gcodes").mkdir()
    with JobService(tmp_path / "store", handler, strict=True) as svc:
        svc.start_job(JobStart(job_id="j", gcode_name="/sd/cube.gcode"))
        rec = svc.layer("j", LayerEvent(layer=0, z_mm=0.2)).record
        assert (rec.scan, rec.verdict) == ("done", "unknown")
        assert "no G-code 'cube.gcode'" in rec.reason
        assert rec.output == "layer_00000.zarr"
        assert (tmp_path / "store" / "j" / "layer_00000.zarr" / "zarr.json").is_file()


@pytest.mark.slow
def test_with_the_gcode_a_layer_is_judged_in_the_job_store(tmp_path: Path) -> None:
    """The demo plate's first layer, simulated from its G-code, through the service."""
    handler = JobStoreHandler(demo.demo_config(), gcode_dir=demo.demo_gcode().parent,
                              mapping=demo.DEMO_MAPPING, record=False)
    with JobService(tmp_path, handler, strict=True, scan_timeout_s=300,
                    verdict_timeout_s=120) as svc:
        svc.start_job(JobStart(job_id="plate", gcode_name="demo_plate.gcode"))
        rec = svc.layer("plate", LayerEvent(layer=0, z_mm=0.2)).record
        svc.end_job("plate", JobEnd())
    assert rec.verdict == "pass", rec.reason
    assert set(rec.objects) == {"box_a.stl", "cylinder_b.stl", "box_c.stl", "cylinder_d.stl"}
    store = JobStore.open(tmp_path / "plate" / STORE_DIR)
    assert store.done_layers() == [0]
    assert store.read_verdict(0).verdict == "pass"


def test_serve_command_end_to_end_and_clean_stop(tmp_path: Path) -> None:
    cfg = tmp_path / "scan.toml"
    cfg.write_text(config_to_toml(tiny_config()))  # type: ignore[arg-type]
    proc = subprocess.Popen([sys.executable, "-m", "sffscan", "serve", "--config", str(cfg),
                             "--store", str(tmp_path / "jobs"), "--port", "0", "--strict"],
                            cwd=ROOT, stderr=subprocess.PIPE, text=True)
    try:
        assert proc.stderr is not None
        line = proc.stderr.readline()
        match = re.search(r"listening on (http://127\.0\.0\.1:\d+)", line)
        assert match, line
        url = match.group(1)

        def post(path: str, body: dict) -> dict:
            req = urllib.request.Request(url + path, data=json.dumps(body).encode(),
                                         method="POST")
            with urllib.request.urlopen(req, timeout=120) as resp:
                return json.loads(resp.read())

        assert post("/jobs", {"job_id": "cli"})["status"] == "open"
        rec = post("/jobs/cli/layers", {"layer": 0, "z_mm": 0.2})["record"]
        assert rec["scan"] == "done" and rec["verdict"] == "unknown"
        assert post("/jobs/cli/end", {"outcome": "completed"})["counts"] == {"unknown": 1}
        proc.send_signal(signal.SIGTERM)
        _, err = proc.communicate(timeout=30)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.communicate(timeout=10)
    assert proc.returncode == 0
    assert "sffscan serve: stopped" in err


def test_serve_refuses_beyond_loopback_without_a_token(tmp_path: Path) -> None:
    r = subprocess.run([sys.executable, "-m", "sffscan", "serve", "--host", "0.0.0.0",
                        "--port", "0", "--store", str(tmp_path / "jobs")], cwd=ROOT,
                       capture_output=True, text=True, timeout=60,
                       env={k: v for k, v in os.environ.items() if k != "SFFSCAN_TOKEN"})
    assert r.returncode == 2
    assert "beyond loopback) without a bearer token" in r.stderr


def test_the_expected_map_is_made_while_the_layer_is_scanned(tmp_path: Path,
                                                             monkeypatch: pytest.MonkeyPatch
                                                             ) -> None:
    """The handler rasterises a layer's expected map in its own thread during the scan, so
    the analysis after the scan starts from it (issue 25's verdict latency)."""
    import threading

    from sffscan.pipeline.printjob.expected import PrinterMapping
    from sffscan.pipeline.printjob.layer import LayerRunner

    from tests.pipeline.printjob.test_printjob_jobstore import _tiny_config, tiny_gcode

    calls: list[tuple[int, str, bool]] = []
    original = LayerRunner.prepare

    def prepare(self: LayerRunner, layer: int) -> bool:
        done = original(self, layer)
        calls.append((layer, threading.current_thread().name, done))
        return done

    monkeypatch.setattr(LayerRunner, "prepare", prepare)
    from sffscan.pipeline.printjob import layer as layer_module

    rasterised: list[int] = []
    raster = layer_module.rasterise_expected

    def counted(*args: object, **kwargs: object) -> object:
        rasterised.append(int(kwargs["upto_layer"]))  # type: ignore[call-overload]
        return raster(*args, **kwargs)  # type: ignore[arg-type]

    monkeypatch.setattr(layer_module, "rasterise_expected", counted)
    gdir = tmp_path / "gcodes"
    gdir.mkdir()
    (gdir / "tiny.gcode").write_text(tiny_gcode(3))
    handler = JobStoreHandler(_tiny_config(), gcode_dir=gdir, record=False,
                              mapping=PrinterMapping(offset_um=(0.0, 0.0)))
    with JobService(tmp_path / "store", handler, strict=True) as svc:
        svc.start_job(JobStart(job_id="j", gcode_name="tiny.gcode"))
        for k in (0, 1):
            assert svc.layer("j", LayerEvent(layer=k, z_mm=0.2 * (k + 1))).record.verdict \
                == "pass"
    # each layer's map is made ahead (layer 0 on the grid its configuration gives the
    # mosaic), and the analysis uses it: one rasterisation per layer, none after the scan
    assert calls == [(0, "sffscan-expected-0", True), (1, "sffscan-expected-1", True)]
    assert rasterised == [0, 1]
