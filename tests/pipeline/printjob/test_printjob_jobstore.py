"""Job store: manifest, atomic layers, restart, refused layer events; a 3-layer simulated job."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest
from sffscan.pipeline.printjob.deviation import failed_layer_verdict
from sffscan.pipeline.printjob.expected import Grid, PrinterMapping
from sffscan.pipeline.printjob.gcode import GcodeError
from sffscan.pipeline.printjob.jobstore import JobError, JobStore, LayerOrderError

import sffscan


def tiny_gcode(layers: int = 3) -> str:
    """Two 2.4 x 2.4 mm squares of parallel 0.4 mm lines, objects 'left' and 'right'."""
    e = ((0.4 - 0.2) * 0.2 + math.pi * 0.01) * 2.4 / (math.pi * 1.75**2 / 4)
    out = ["G21", "G90", "M83"]
    for k in range(layers):
        out.append(f"G1 Z{0.2 * (k + 1):.1f}")
        for name, x0 in (("left", 1.0), ("right", 5.0)):
            out.append(f"EXCLUDE_OBJECT_START NAME={name}")
            for j in range(7):
                y = 1.0 + 0.4 * j
                out += [f"G1 X{x0:.2f} Y{y:.2f}", f"G1 X{x0 + 2.4:.2f} Y{y:.2f} E{e:.5f}"]
            out.append(f"EXCLUDE_OBJECT_END NAME={name}")
    return "\n".join(out) + "\n"


@pytest.fixture
def gcode(tmp_path):
    f = tmp_path / "tiny.gcode"
    f.write_text(tiny_gcode())
    return f


def test_manifest_hashes_and_a_bad_gcode_creates_nothing(tmp_path, gcode) -> None:
    s = JobStore.create(tmp_path / "job", gcode=gcode, printer="sim",
                        mapping=PrinterMapping(offset_um=(5.0, 6.0)))
    man = json.loads((tmp_path / "job" / "manifest.json").read_text())
    assert man["layer_z_mm"] == [0.2, 0.4, 0.6] and man["objects"] == ["left", "right"]
    assert len(man["gcode_sha256"]) == 64 and man["mapping"]["offset_um"] == [5.0, 6.0]
    assert JobStore.open(tmp_path / "job").manifest == s.manifest
    bad = tmp_path / "bad.gcode"
    bad.write_text("G1 Z0.2\nG1 X1 Y1 E1\nG1 X2 Y2 E1..5\n")
    with pytest.raises(GcodeError, match="line 3"):
        JobStore.create(tmp_path / "job2", gcode=bad)
    assert not (tmp_path / "job2").exists()
    with pytest.raises(JobError, match="not empty"):
        JobStore.create(tmp_path / "job", gcode=gcode)
    # a changed G-code copy is refused on reopening
    (tmp_path / "job" / "job.gcode").write_text(tiny_gcode(2))
    with pytest.raises(JobError, match="sha256"):
        JobStore.open(tmp_path / "job")
    with pytest.raises(JobError, match="not a job folder"):
        JobStore.open(tmp_path)


def test_layer_events_out_of_order_repeated_or_at_a_wrong_z_are_refused(tmp_path, gcode) -> None:
    s = JobStore.create(tmp_path / "job", gcode=gcode)
    s.begin_layer(0, 0.2)
    s.finish_layer(0, failed_layer_verdict(0, 0.2, ["left", "right"], reason="test"))
    with pytest.raises(LayerOrderError, match="repeated"):
        s.begin_layer(0, 0.2)
    with pytest.raises(LayerOrderError, match="z = 0.5 mm"):
        s.begin_layer(1, 0.5)
    s.begin_layer(2, 0.6)  # skipping a layer is allowed (every n-th layer)
    with pytest.raises(LayerOrderError, match="out of order"):
        s.begin_layer(1, 0.4)
    with pytest.raises(LayerOrderError, match="layers 0..2"):
        s.begin_layer(7)
    assert s.done_layers() == [0]


def test_restart_redoes_an_unfinished_layer_and_keeps_the_done_ones(tmp_path, gcode) -> None:
    s = JobStore.create(tmp_path / "job", gcode=gcode)
    for k in (0, 1):
        s.begin_layer(k)
        grid = Grid((0.0, 0.0), 100.0, (4, 5))
        s.write_deviation(k, np.full((4, 5), float(k), np.float32), grid)
        s.finish_layer(k, failed_layer_verdict(k, 0.2 * (k + 1), ["left"], reason="x"))
    d = s.begin_layer(2)
    (d / "partial.tmp").write_text("crash here")  # the service dies mid-layer
    s2 = JobStore.open(tmp_path / "job")  # restart
    assert s2.done_layers() == [0, 1]
    assert s2.read_verdict(1).reason == "x"
    d2 = s2.begin_layer(2)  # not done: begun again, the partial folder cleared
    assert not (d2 / "partial.tmp").exists()
    assert not list((tmp_path / "job").rglob("*.tmp"))


def test_a_three_layer_simulated_job_end_to_end(tmp_path, gcode) -> None:
    from sffscan.pipeline.printjob.demo import run_simulated_print
    from sffscan.stages.sim.print_world import PrintDefect

    cfg = _tiny_config()
    blob = PrintDefect("blob", 2, "right", (6.2, 2.2), size_mm=0.8, height_um=400.0)
    seen = []
    verdicts = run_simulated_print(tmp_path / "job", gcode=gcode, defects=(blob,), config=cfg,
                                   mapping=PrinterMapping(offset_um=(0.0, 0.0)), record=True,
                                   on_layer=lambda k, v, t: seen.append(k))
    assert seen == [0, 1, 2]
    assert [v.verdict for v in verdicts] == ["pass", "pass", "fail"]
    right = verdicts[2].objects[1]
    assert right.name == "right" and right.verdict == "fail"
    assert right.defect_xy_mm == pytest.approx((6.2, 2.2), abs=0.3)
    assert verdicts[2].objects[0].verdict == "pass"
    store = JobStore.open(tmp_path / "job")
    assert all(store.recording_path(k).is_dir() and store.mosaic_path(k).is_dir()
               for k in range(3))  # each layer keeps its raw frames, for 'sffscan replay'
    ds = sffscan.open_job(tmp_path / "job")
    assert ds.sizes["layer"] == 3 and list(ds["verdict"].values) == ["pass", "pass", "fail"]
    np.testing.assert_allclose(ds["z_mm"].values, [0.2, 0.4, 0.6])
    dev = ds["deviation"].sel(layer=2).sel(x=6200.0, y=2200.0, method="nearest")
    assert float(dev) == pytest.approx(400.0, abs=80)  # the blob's top
    # rerunning the job resumes: nothing is scanned again
    again = []
    run_simulated_print(tmp_path / "job", gcode=gcode, defects=(blob,), config=cfg,
                        on_layer=lambda k, v, t: again.append(k))
    assert again == []


def test_a_missing_or_failed_scan_is_unknown_never_pass(tmp_path) -> None:
    from sffscan.pipeline.printjob.layer import LayerRunner

    gcode = tmp_path / "six.gcode"
    gcode.write_text(tiny_gcode(6))
    store = JobStore.create(tmp_path / "job", gcode=gcode)
    runner = LayerRunner(store, warm=False)
    runner.begin(0, 0.2)
    v = runner.analyse(0)  # the scan never wrote its mosaic
    assert v.verdict == "unknown" and "no readable mosaic" in v.reason
    assert store.done_layers() == [0] and store.read_verdict(0).verdict == "unknown"
    runner.begin(1, 0.4)
    d = runner.scan(1, config=_tiny_config(), frames=iter(()))  # no frame at all
    assert store.mosaic_path(1).is_dir() and d.frames == 0
    v = runner.analyse(1)
    assert v.verdict == "unknown" and "100 % unknown" in v.reason  # nothing measured
    import zarr

    zarr.open_group(str(store.mosaic_path(1)), mode="r+").attrs["status"] = "failed"
    v = runner.analyse(1)  # a stage failed mid-scan
    assert v.verdict == "unknown" and "not 'complete'" in v.reason
    v = runner.fail(2, "scan timed out after 60 s")  # a timeout releases the printer
    assert v.verdict == "unknown" and store.done_layers() == [0, 1, 2]
    # a restart while layer 3's analysis ran and layer 4 was being scanned
    store.begin_layer(3)
    store.begin_layer(4)
    again = LayerRunner(JobStore.open(tmp_path / "job"), warm=False)
    (v3,) = again.recover()  # layer 3 finished (no mosaic: unknown), layer 4 left to redo
    assert v3.layer == 3 and v3.verdict == "unknown"
    assert again.store.done_layers() == [0, 1, 2, 3]
    again.begin(4)  # the next event for layer 4 redoes it


def _tiny_config():
    from sffscan.pipeline.printjob.demo import demo_config

    return demo_config(frame_px=(160, 176), x_mm=(0.6, 7.8), y_start_mm=0.3, passes=1,
                       optics={"n_levels": 12, "z_min_um": -400.0, "z_step_um": 150.0})


def test_cli_job_show(tmp_path, gcode, capsys) -> None:
    from sffscan.pipeline.cli.main import main

    s = JobStore.create(tmp_path / "job", gcode=gcode, printer="sim")
    s.begin_layer(0)
    s.finish_layer(0, failed_layer_verdict(0, 0.2, ["left", "right"], reason="timeout"))
    assert main(["job", "show", str(tmp_path / "job")]) == 0
    out = capsys.readouterr().out
    assert "1 of 3 layers done" in out and "UNKNOWN" in out and "left:unknown" in out
    assert main(["job", "show", str(tmp_path)]) == 2
    assert "not a job folder" in capsys.readouterr().err
