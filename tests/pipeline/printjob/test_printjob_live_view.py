"""The live Rerun view of a print job: each layer's scan while it runs and each layer's
deviation and verdict as it comes, on the ``layer`` timeline; read back from a saved .rrd
with rerun's public reader."""

from __future__ import annotations

from collections import defaultdict
from pathlib import Path
from typing import Any

import pytest
from sffscan.pipeline.cli.main import main
from sffscan.pipeline.printjob.deviation import LayerVerdict
from sffscan.pipeline.printjob.expected import PrinterMapping
from sffscan.pipeline.printjob.jobstore import JobStore

from tests.pipeline.printjob.test_printjob_jobstore import _tiny_config, tiny_gcode


def rrd_rows(path: Path) -> dict[str, list[dict[str, Any]]]:
    """Temporal rows per entity of an .rrd (rerun's public RrdReader)."""
    import pyarrow as pa
    from rerun.chunk import RrdReader

    rows: dict[str, list[dict[str, Any]]] = defaultdict(list)
    for chunk in RrdReader(path).stream():
        if chunk.is_static:
            continue
        batch = chunk.to_record_batch()
        cols = {n: (c.cast(pa.int64()) if pa.types.is_timestamp(c.type) else c).to_pylist()
                for n, c in zip(batch.schema.names, batch.columns, strict=True)}
        rows[chunk.entity_path].extend(dict(zip(cols, v, strict=True))
                                       for v in zip(*cols.values(), strict=True))
    return dict(rows)


def test_each_layer_scan_and_verdict_are_logged_as_they_come(tmp_path: Path) -> None:
    import rerun as rr
    from sffscan.pipeline.printjob.demo import run_simulated_print
    from sffscan.pipeline.printjob.live_view import JobLiveView, job_blueprint

    gcode = tmp_path / "tiny.gcode"
    gcode.write_text(tiny_gcode(3))
    rrd = tmp_path / "job.rrd"
    views: list[JobLiveView] = []

    def view(store: JobStore) -> JobLiveView:
        rec = rr.RecordingStream("sffscan-test")
        rec.save(str(rrd), default_blueprint=job_blueprint())
        views.append(JobLiveView(store, rec))
        return views[-1]

    seen: list[tuple[int, list[int]]] = []

    def on_layer(k: int, v: LayerVerdict, timings: dict[str, float]) -> None:
        seen.append((k, list(views[0].layers_logged)))  # logged before the next layer

    verdicts = run_simulated_print(tmp_path / "job", gcode=gcode, config=_tiny_config(),
                                   mapping=PrinterMapping(offset_um=(0.0, 0.0)),
                                   layers=[0, 1], on_layer=on_layer, view=view)
    assert [v.verdict for v in verdicts] == ["pass", "pass"]
    assert seen == [(0, [0]), (1, [0, 1])]
    rows = rrd_rows(rrd)
    # the scans: camera frames and mosaic tiles of both layers, each on its layer
    cams = rows["/scan/camera/image"]
    assert {r["layer"] for r in cams} == {0, 1} and all(r["frame"] is not None for r in cams)
    tiles = [e for e in rows if e.startswith("/scan/mosaic/height/tile_")]
    assert tiles and {r["layer"] for e in tiles for r in rows[e]} == {0, 1}
    # a new layer's scan starts clean: the previous scan is cleared at its layer
    clears = [r["layer"] for r in rows["/scan"]]
    assert clears == [0, 1]
    # the verdicts and deviation maps of both layers
    texts = sorted((r["layer"], r["TextDocument:text"][0]) for r in rows["/job/verdict"])
    assert [k for k, _ in texts] == [0, 1] and all("**PASS**" in t for _, t in texts)
    assert sorted(r["layer"] for r in rows["/job/deviation"] if r.get("Image:buffer")) == [0, 1]
    labels = [r["LineStrips2D:labels"] for r in rows["/job/deviation/outlines"]]
    assert all(sorted(x) == ["left: pass", "right: pass"] for x in labels)


def test_job_demo_refuses_a_viewer_it_cannot_open(tmp_path: Path,
                                                  capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["job", "demo", "-o", str(tmp_path / "j"), "--layers", "1",
                 "--viewer", "save"]) == 2
    assert "--viewer save: give the recording's path with --rrd PATH" in capsys.readouterr().err
    assert main(["job", "demo", "-o", str(tmp_path / "j2"), "--layers", "1",
                 "--rrd", str(tmp_path / "no" / "x.rrd")]) == 2
    assert f"folder {tmp_path / 'no'} does not exist" in capsys.readouterr().err


def test_the_service_shows_each_jobs_layers_live(tmp_path: Path) -> None:
    """``sffscan serve --viewer``'s path: the job store handler's scan goes through the live
    view, and the verdict is logged when the background analysis writes it."""
    import rerun as rr
    from sffscan.pipeline.printjob.links_store import JobStoreHandler
    from sffscan.pipeline.printjob.live_view import JobLiveView, job_blueprint
    from sffscan.pipeline.printjob.service import JobEnd, JobService, JobStart, LayerEvent

    gdir = tmp_path / "gcodes"
    gdir.mkdir()
    (gdir / "tiny.gcode").write_text(tiny_gcode(3))
    rrd = tmp_path / "serve.rrd"
    rec = rr.RecordingStream("sffscan-test")
    rec.save(str(rrd), default_blueprint=job_blueprint())
    views: list[JobLiveView] = []

    def view(store: JobStore) -> JobLiveView:
        views.append(JobLiveView(store, rec, own_stream=False))
        return views[-1]

    handler = JobStoreHandler(_tiny_config(), gcode_dir=gdir, record=False, view=view,
                              mapping=PrinterMapping(offset_um=(0.0, 0.0)))
    with JobService(tmp_path / "store", handler) as svc:  # not strict: analysis behind
        svc.start_job(JobStart(job_id="j", gcode_name="tiny.gcode"))
        assert svc.layer("j", LayerEvent(layer=0, z_mm=0.2)).record.verdict == "pending"
        svc.end_job("j", JobEnd())  # waits for the verdict
        assert svc.record("j", 0).verdict == "pass"
    assert len(views) == 1 and views[0].layers_logged == [0]
    rec.flush()
    rec.disconnect()
    rows = rrd_rows(rrd)
    assert {r["layer"] for r in rows["/scan/camera/image"]} == {0}
    assert [r["layer"] for r in rows["/job/verdict"]] == [0]
    assert "**PASS**" in rows["/job/verdict"][0]["TextDocument:text"][0]
