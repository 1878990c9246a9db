"""'sffscan job calibrate' and 'sffscan job reprocess' on a tiny recorded two-layer job."""

from __future__ import annotations

import json
import shutil

import pytest
from sffscan.pipeline.cli.main import main
from sffscan.pipeline.printjob.deviation import failed_layer_verdict
from sffscan.pipeline.printjob.expected import PrinterMapping
from sffscan.pipeline.printjob.jobstore import JobError, JobStore
from sffscan.pipeline.printjob.reprocess import calibrate_mapping, parse_layers, reprocess_job

from tests.pipeline.printjob.test_printjob_jobstore import _tiny_config, tiny_gcode


@pytest.fixture(scope="module")
def recorded_job(tmp_path_factory):
    """Two layers scanned (simulator) with their raw recordings; mapping the identity."""
    from sffscan.pipeline.printjob.demo import run_simulated_print

    d = tmp_path_factory.mktemp("recjob")
    gcode = d / "tiny.gcode"
    gcode.write_text(tiny_gcode(3))
    verdicts = run_simulated_print(d / "job", gcode=gcode, defects=(), config=_tiny_config(),
                                   mapping=PrinterMapping(offset_um=(0.0, 0.0)), record=True,
                                   layers=[0, 1])
    assert [v.verdict for v in verdicts] == ["pass", "pass"]
    return d / "job"


@pytest.fixture
def job(recorded_job, tmp_path):
    dst = tmp_path / "job"
    shutil.copytree(recorded_job, dst)
    return dst


def test_parse_layers() -> None:
    assert parse_layers(None, 5) is None
    assert parse_layers("1-3", 5) == [1, 2, 3]
    assert parse_layers("0,2-3", 5) == [0, 2, 3]
    with pytest.raises(JobError, match="outside"):
        parse_layers("2-9", 5)
    with pytest.raises(JobError, match="not N or A-B"):
        parse_layers("a-b", 5)


def test_calibrate_recovers_a_wrong_mapping_and_apply_stores_it(job, capsys) -> None:
    store = JobStore.open(job)
    store.update_manifest(mapping=PrinterMapping(offset_um=(300.0, -200.0)))
    # the truth is the identity (the simulated print used it); the fit is phase correlation
    # on 25 µm pixels: within 4 px of it, and the same from another start
    c = calibrate_mapping(job, layer=1)
    assert not c.applied and c.layer == 1
    assert c.change_um == pytest.approx((-300.0, 200.0), abs=100)
    store.update_manifest(mapping=PrinterMapping(offset_um=(-150.0, 250.0)))
    c2 = calibrate_mapping(job, layer=1)
    assert c2.new.offset_um == pytest.approx(c.new.offset_um, abs=25)
    store.update_manifest(mapping=PrinterMapping(offset_um=(300.0, -200.0)))
    # not stored without --apply
    assert JobStore.open(job).manifest.mapping.offset_um == (300.0, -200.0)
    assert main(["job", "calibrate", str(job), "--layer", "1", "--apply"]) == 0
    out = capsys.readouterr().out
    assert "change from the manifest's mapping" in out and "stored in the manifest" in out
    man = json.loads((job / "manifest.json").read_text())
    assert man["mapping"]["offset_um"] == pytest.approx([0.0, 0.0], abs=100)
    assert not list(job.glob(".*.tmp"))  # written atomically


def test_calibrate_errors_name_the_job_and_the_layer(job, capsys) -> None:
    assert main(["job", "calibrate", str(job), "--layer", "2"]) == 2
    assert f"{job}: layer 2 is not done" in capsys.readouterr().err
    assert main(["job", "calibrate", str(job), "--layer", "7"]) == 2
    assert "layer 7: the G-code has layers 0..2" in capsys.readouterr().err
    shutil.rmtree(JobStore.open(job).mosaic_path(1))
    assert main(["job", "calibrate", str(job), "--layer", "1"]) == 2
    assert "layer 1 has no mosaic" in capsys.readouterr().err
    # a mapping that puts the part off the scanned area: the fit fails, nothing stored
    JobStore.open(job).update_manifest(mapping=PrinterMapping(offset_um=(9e5, 9e5)),
                                       roi_um=None)
    assert main(["job", "calibrate", str(job), "--layer", "0", "--apply"]) == 2
    assert "does not overlap" in capsys.readouterr().err
    assert JobStore.open(job).manifest.mapping.offset_um == (9e5, 9e5)


def test_reprocess_replaces_verdicts_and_reports_failures_and_skips(job, capsys) -> None:
    store = JobStore.open(job)
    # pretend layer 0 had been judged unknown (e.g. a timeout) and layer 1's mapping was
    # wrong: the reprocess recomputes both from the recordings
    store.finish_layer(0, failed_layer_verdict(0, 0.2, store.manifest.objects, reason="x"))
    old_dev = store.deviation_path(1).stat().st_mtime_ns
    rows = reprocess_job(job)
    assert [(r.layer, r.status, r.old, r.new) for r in rows] == [
        (0, "done", "unknown", "pass"), (1, "done", "pass", "pass")]
    assert store.read_verdict(0).verdict == "pass"
    assert store.deviation_path(1).stat().st_mtime_ns != old_dev
    assert store.mosaic_path(0).is_dir()
    assert not [p for p in store.layer_dir(0).iterdir() if p.name.startswith(".")]
    # a layer without a recording is skipped; a broken recording fails and keeps its verdict
    shutil.rmtree(store.recording_path(0))
    rec1 = store.recording_path(1)
    (rec1 / "zarr.json").write_text("{ not json")
    store.finish_layer(1, failed_layer_verdict(1, 0.4, store.manifest.objects, reason="old"))
    assert main(["job", "reprocess", str(job), "--layers", "0-1"]) == 1
    cap = capsys.readouterr()
    assert "skipped" in cap.out and "no recording.zarr" in cap.out
    assert "unknown -> (kept)" in cap.out
    assert f"{job}: layer 1: reprocessing failed, its old verdict kept" in cap.err
    v1 = store.read_verdict(1)
    assert v1.verdict == "unknown" and v1.reason == "old"
    assert store.mosaic_path(1).is_dir()
    assert not [p for p in store.layer_dir(1).iterdir() if p.name.startswith(".")]
    assert main(["job", "reprocess", str(job), "--layers", "5"]) == 2
    assert "outside the job's layers 0..2" in capsys.readouterr().err


def test_batch_reprocesses_a_job_folder_in_place(job, capsys, tmp_path) -> None:
    store = JobStore.open(job)
    store.finish_layer(1, failed_layer_verdict(1, 0.4, store.manifest.objects, reason="x"))
    assert main(["batch", str(job), "--method", "gauss3"]) == 0
    out = capsys.readouterr().out
    assert "unknown -> pass" in out and "2 done, 0 skipped, 0 failed" in out
    assert store.read_verdict(1).verdict == "pass"
    assert main(["batch", str(job), "-o", str(tmp_path / "out")]) == 2
    assert "is a job folder" in capsys.readouterr().err
    assert main(["batch", str(tmp_path / "none*.zarr")]) == 2  # recordings still need -o
    assert "-o/--output is required" in capsys.readouterr().err


def test_calibrate_printer_is_the_same_command(job, capsys) -> None:
    """``sffscan calibrate printer`` (where the calibrations are) runs ``job calibrate``."""
    JobStore.open(job).update_manifest(mapping=PrinterMapping(offset_um=(300.0, -200.0)))
    assert main(["calibrate", "printer", str(job), "--layer", "1"]) == 0
    via_calibrate = capsys.readouterr().out
    assert main(["job", "calibrate", str(job), "--layer", "1"]) == 0
    assert capsys.readouterr().out == via_calibrate
    assert "change from the manifest's mapping" in via_calibrate
    assert JobStore.open(job).manifest.mapping.offset_um == (300.0, -200.0)  # no --apply
    assert main(["calibrate", "printer", str(job), "--layer", "2"]) == 2
    assert f"{job}: layer 2 is not done" in capsys.readouterr().err
