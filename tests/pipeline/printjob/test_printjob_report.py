"""HTML job report: every layer and object with its verdict, layers not done, bad folders,
the colour map's neutral tolerance band. A tiny job store written directly (no scan)."""

from __future__ import annotations

import base64
import re
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import pytest
from sffscan.pipeline.cli.main import main
from sffscan.pipeline.printjob.deviation import LayerVerdict, ObjectVerdict, failed_layer_verdict
from sffscan.pipeline.printjob.expected import Grid
from sffscan.pipeline.printjob.jobstore import JobError, JobStore
from sffscan.pipeline.printjob.report import (
    NEUTRAL_RGB,
    NODATA_RGB,
    deviation_colours,
    write_report,
)

from tests.pipeline.printjob.test_printjob_jobstore import tiny_gcode
from tests.pipeline.printjob.test_printjob_live_view import rrd_rows

GRID = Grid((0.0, 0.0), 100.0, (40, 80))  # 8 x 4 mm, the tiny G-code's two squares


def _objects(verdicts: dict[str, str]) -> list[ObjectVerdict]:
    return [ObjectVerdict(name=n, verdict=v, pixels=500, unknown_fraction=0.01,  # type: ignore[arg-type]
                          p95_abs_um=250.0 if v == "fail" else 12.0, rms_um=8.0,
                          area_out_mm2=1.5 if v == "fail" else 0.0, missing_mm2=0.0,
                          excess_mm2=1.5 if v == "fail" else 0.0,
                          defect_xy_mm=(2.0, 2.0) if v == "fail" else None)
            for n, v in verdicts.items()]


@pytest.fixture
def job(tmp_path: Path) -> Path:
    """Layers 0 (pass) and 2 (left fails, with a blob in its deviation) done; layer 1 not."""
    g = tmp_path / "tiny.gcode"
    g.write_text(tiny_gcode(4))
    s = JobStore.create(tmp_path / "job", gcode=g, printer="sim-test")
    dev = np.random.default_rng(0).normal(0, 10, GRID.shape).astype(np.float32)
    s.begin_layer(0, 0.2)
    s.write_deviation(0, dev, GRID)
    s.finish_layer(0, LayerVerdict(layer=0, z_mm=0.2, verdict="pass",
                                   objects=_objects({"left": "pass", "right": "pass"})))
    s.begin_layer(2, 0.6)
    blob = dev.copy()
    blob[10:20, 15:25] = 400.0
    s.write_deviation(2, blob, GRID)
    s.finish_layer(2, LayerVerdict(layer=2, z_mm=0.6, verdict="fail",
                                   reason="left: fail (1.50 mm² out)",
                                   objects=_objects({"left": "fail", "right": "pass"})))
    s.begin_layer(3, 0.8)  # a scan that failed: unknown, no deviation map
    s.finish_layer(3, failed_layer_verdict(3, 0.8, ["left", "right"], reason="scan timed out"))
    return tmp_path / "job"


def _figures(text: str) -> list[np.ndarray]:
    out = []
    for b64 in re.findall(r'alt="deviation map of layer \d+" src="data:image/png;base64,'
                          r'([A-Za-z0-9+/=]+)"', text):
        img = cv2.imdecode(np.frombuffer(base64.b64decode(b64), np.uint8), cv2.IMREAD_COLOR)
        assert img is not None
        out.append(np.asarray(img)[..., ::-1])
    return out


def test_the_report_has_every_layer_and_object_with_its_verdict(job: Path) -> None:
    out = write_report(job)
    assert out == job / "report.html"
    text = out.read_text(encoding="utf-8")
    assert "sim-test" in text and JobStore.open(job).manifest.gcode_sha256 in text
    for k, verdict in ((0, "pass"), (2, "fail"), (3, "unknown")):
        row = re.search(rf'<tr data-layer="{k}">(.*?)</tr>', text)
        assert row is not None, k
        assert f">{verdict}</span>" in row.group(1)
        sec = re.search(rf'<section class="layer" id="layer-{k:04d}">(.*?)</section>', text)
        assert sec is not None, k
        assert f">{verdict}</span></h3>" in sec.group(1)
    sec2 = re.search(r'id="layer-0002">(.*?)</section>', text)
    assert sec2 is not None
    for name, v in (("left", "fail"), ("right", "pass")):
        assert re.search(rf"<td>{name}</td><td><span[^>]*>{v}</span>", sec2.group(1)), name
    assert "(2.0, 2.0) mm" in sec2.group(1) and "<td>250</td>" in sec2.group(1)
    assert "scan timed out" in text and "no deviation map" in text
    # two figures (layers 0 and 2); layer 2's shows its +400 µm blob in red, layer 0 none
    figs = _figures(text)
    assert len(figs) == 2
    red = [int(((f[..., 0] > 150) & (f[..., 2] < 100)).sum()) for f in figs]
    assert red[0] == 0 and red[1] > 100
    # colour bar labels in µm, no external resource
    assert "+100 µm" in text and "−500 µm" in text
    assert not re.search(r'(src|href)="(http|file|/)', text)


def test_a_layer_without_a_verdict_is_marked_not_done(job: Path, tmp_path: Path) -> None:
    text = write_report(job, tmp_path / "r.html").read_text(encoding="utf-8")
    row = re.search(r'<tr class="notdone" data-layers="1-1">(.*?)</tr>', text)
    assert row is not None and ">not done</span>" in row.group(1)
    assert 'data-layer="1"' not in text and 'id="layer-0001"' not in text
    assert "3 of 4 layers done" in text


def test_a_folder_that_is_not_a_job_exits_2_naming_it(tmp_path: Path,
                                                      capsys: pytest.CaptureFixture[str]) -> None:
    (tmp_path / "notajob").mkdir()
    with pytest.raises(JobError, match="notajob"):
        write_report(tmp_path / "notajob")
    assert main(["job", "report", str(tmp_path / "notajob")]) == 2
    err = capsys.readouterr().err
    assert str(tmp_path / "notajob") in err and "not a job folder" in err
    assert not (tmp_path / "notajob" / "report.html").exists()


def test_the_cli_writes_the_report(job: Path, tmp_path: Path,
                                   capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["job", "report", str(job), "-o", str(tmp_path / "x.html")]) == 0
    assert (tmp_path / "x.html").read_text(encoding="utf-8").startswith("<!DOCTYPE html>")
    assert str(tmp_path / "x.html") in capsys.readouterr().out
    assert main(["job", "report", str(job), "-o", str(tmp_path / "x.html")]) == 0  # again
    # never over a file that is not a report, nor into a layer's recording or mosaic
    notes = tmp_path / "notes.html"
    notes.write_text("<html>the user's page</html>")
    assert main(["job", "report", str(job), "-o", str(notes)]) == 2
    assert "is not an sffscan job report" in capsys.readouterr().err
    assert notes.read_text() == "<html>the user's page</html>"
    store = next(job.rglob("zarr.json")).parent
    assert main(["job", "report", str(job), "-o", str(store / "r.html")]) == 2
    assert "inside the Zarr store" in capsys.readouterr().err
    assert not (store / "r.html").exists()


def test_the_tolerance_band_is_neutral_and_the_sides_diverge() -> None:
    d = np.array([[0.0, 50.0, -99.9, 100.0, -100.0, 101.0, -101.0, 500.0, -500.0, 2000.0,
                   np.nan]])
    c = deviation_colours(d, tolerance_um=100.0, limit_um=500.0)
    assert c.shape == (1, 11, 3) and c.dtype == np.uint8
    for i in range(5):  # 0 µm and |dev| <= tolerance
        assert tuple(c[0, i]) == NEUTRAL_RGB, d[0, i]
    r, g, b = (c[0, :, j].astype(int) for j in range(3))
    assert r[5] > b[5] and b[6] > r[6]  # just out: light red (excess) / light blue (missing)
    assert tuple(c[0, 7]) == tuple(c[0, 9])  # saturated beyond the limit
    assert r[7] > 3 * b[7] and b[8] > 3 * r[8]
    assert r[7] < r[5] and b[8] < b[6]  # darker further out
    assert tuple(c[0, 10]) == NODATA_RGB
    with pytest.raises(ValueError, match="limit_um"):
        deviation_colours(d, tolerance_um=100.0, limit_um=50.0)


def _rrd_rows(path: Path) -> dict[str, list[dict[str, Any]]]:
    """Temporal rows per entity of an .rrd (test_printjob_live_view's reader), by layer."""
    rows = rrd_rows(path)
    for r in rows.values():
        r.sort(key=lambda x: x["layer"])
    return rows


def test_the_rerun_layer_timeline_has_each_layer_map_and_verdict(job: Path,
                                                                 tmp_path: Path) -> None:
    from sffscan.pipeline.printjob.viewer import save_job_rrd

    assert save_job_rrd(job, tmp_path / "j.rrd") == [0, 2, 3]
    rows = _rrd_rows(tmp_path / "j.rrd")
    assert [r["layer"] for r in rows["/job/verdict"]] == [0, 2, 3]
    texts = [r["TextDocument:text"][0] for r in rows["/job/verdict"]]
    assert "**PASS**" in texts[0] and "**FAIL**" in texts[1] and "**UNKNOWN**" in texts[2]
    assert "| left | fail | 250 |" in texts[1] and "scan timed out" in texts[2]
    imgs = [r for r in rows["/job/deviation"] if r.get("Image:buffer")]
    assert [r["layer"] for r in imgs] == [0, 2]
    fmt = imgs[1]["Image:format"][0]
    img = np.frombuffer(bytes(imgs[1]["Image:buffer"][0]), np.uint8).reshape(
        fmt["height"], fmt["width"], 3)
    dev = JobStore.open(job).deviation_path(2)
    import zarr

    want = deviation_colours(np.asarray(zarr.open_array(str(dev), mode="r")[...]),
                             tolerance_um=100.0, limit_um=500.0)
    assert np.array_equal(img, want)
    assert tuple(img[15, 20]) != NEUTRAL_RGB and tuple(img[35, 70]) == NEUTRAL_RGB
    # layer 3 (failed scan, no map) clears the image instead of showing layer 2's
    assert any(r["layer"] == 3 for r in rows["/job/deviation"] if not r.get("Image:buffer"))
    outl = rows["/job/deviation/outlines"]
    assert [r["layer"] for r in outl] == [0, 2]
    assert sorted(outl[1]["LineStrips2D:labels"]) == ["left: fail", "right: pass"]
