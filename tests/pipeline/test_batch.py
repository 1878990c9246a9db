"""``sffscan batch``: four small recordings on a 2-worker LocalCluster, one corrupt: three
complete mosaics, one reported failure, exit 1; a rerun skips the three."""

from __future__ import annotations

import csv
import shutil
import sys
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import zarr
from sffscan.pipeline.batch_targets import BatchError, find_recordings, mosaic_path
from sffscan.pipeline.cli.main import main
from sffscan.pipeline.formats.recording_writer import RecordingWriter

from tests.scan_helpers import session_frames, small_config


@pytest.fixture(scope="module")
def layers(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A folder of four layer recordings; the last one's metadata is corrupt."""
    d = tmp_path_factory.mktemp("job") / "layers"
    d.mkdir()
    cfg = small_config(motion={"x_start_mm": 2.0, "x_end_mm": 5.0},
                       processing={"registration": False})
    writer = RecordingWriter(d / "layer_000.zarr", cfg)
    for frame in session_frames(cfg):  # rendered once for the session (test_batch*)
        writer.write(frame)
    writer.close()
    for i in (1, 2, 3):
        shutil.copytree(d / "layer_000.zarr", d / f"layer_{i:03d}.zarr")
    (d / "layer_003.zarr" / "zarr.json").write_text("{ this is not JSON")
    return d


def _csv(path: Path) -> dict[str, dict[str, str]]:
    with open(path, newline="", encoding="utf-8") as f:
        return {Path(r["recording"]).name: r for r in csv.DictReader(f)}


def test_batch_reports_the_bad_recording_completes_the_others_and_resumes(
        layers: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    out = tmp_path / "out"
    code = main(["batch", str(layers), "-o", str(out), "--workers", "2", "--threads", "1"])
    printed = capsys.readouterr()
    assert code == 1, printed.err  # some failed
    rows = _csv(out / "batch.csv")
    assert sorted(rows) == [f"layer_{i:03d}.zarr" for i in range(4)]
    assert rows["layer_003.zarr"]["status"] == "failed"
    assert "layer_003.zarr" in rows["layer_003.zarr"]["error"]
    assert "layer_003.zarr: failed" in printed.err
    frames = {int(rows[f"layer_{i:03d}.zarr"]["frames"]) for i in range(3)}
    assert len(frames) == 1 and frames.pop() > 50
    for i in range(3):
        row = rows[f"layer_{i:03d}.zarr"]
        assert row["status"] == "complete" and row["frames_lost"] == "0"
        assert 0 < float(row["rmse_um"]) < 200  # a truth exists: the simulated surface
        g = zarr.open_group(row["mosaic"], mode="r")
        assert g.attrs["status"] == "complete"
        assert g.attrs["valid_pixels"] == int(np.isfinite(np.asarray(g["height"])).sum())  # type: ignore[index]
        ome: Any = g.attrs.asdict()["ome"]
        assert len(ome["multiscales"][0]["datasets"]) >= 4
    # the three identical recordings give identical mosaics, whichever worker ran them
    first = np.asarray(zarr.open_group(rows["layer_000.zarr"]["mosaic"], mode="r")["height"])  # type: ignore[index]
    for i in (1, 2):
        other = zarr.open_group(rows[f"layer_{i:03d}.zarr"]["mosaic"], mode="r")["height"]
        assert np.array_equal(np.asarray(other), first, equal_nan=True)  # type: ignore[arg-type]
    assert "3 complete, 1 failed" in printed.out
    first_rmse = [rows[f"layer_{i:03d}.zarr"]["rmse_um"] for i in range(3)]
    stamp = {i: (Path(rows[f"layer_{i:03d}.zarr"]["mosaic"]) / "zarr.json").stat().st_mtime_ns
             for i in range(3)}

    # the rerun skips the complete mosaics and tries the bad one again (one recording to
    # run: one worker process)
    code = main(["batch", str(layers / "layer_*.zarr"), "-o", str(out), "--workers", "1"])
    printed = capsys.readouterr()
    assert code == 1
    rows = _csv(out / "batch.csv")
    assert [rows[f"layer_{i:03d}.zarr"]["status"] for i in range(4)] == [
        "skipped", "skipped", "skipped", "failed"]
    assert rows["layer_000.zarr"]["frames"] != ""
    for i in range(3):  # the accuracy stored in the mosaic by the first run
        assert rows[f"layer_{i:03d}.zarr"]["rmse_um"] == first_rmse[i] != ""
    for i in range(3):
        assert (Path(rows[f"layer_{i:03d}.zarr"]["mosaic"]) / "zarr.json"
                ).stat().st_mtime_ns == stamp[i]
    assert "3 skipped, 1 failed" in printed.out


def test_batch_of_good_recordings_exits_0(layers: Path, tmp_path: Path,
                                          capsys: pytest.CaptureFixture[str]) -> None:
    out = tmp_path / "out"
    code = main(["batch", str(layers / "layer_000.zarr"), "-o", str(out), "--workers", "1",
                 "--no-evaluate", "--csv", str(tmp_path / "r.csv")])
    assert code == 0, capsys.readouterr().err
    row = _csv(tmp_path / "r.csv")["layer_000.zarr"]
    assert row["status"] == "complete" and row["rmse_um"] == ""
    # the results table is never written into a recording, nor over another file, and
    # nothing is processed then; a previous batch's table is replaced on a rerun
    layer = layers / "layer_000.zarr"
    meta = (layer / "zarr.json").read_bytes()
    image = tmp_path / "im_01.png"
    image.write_bytes(b"the user's image")
    for csv_path, words in ((layer / "zarr.json", "inside the Zarr store"),
                            (image, "is not a batch's results table")):
        assert main(["batch", str(layer), "-o", str(tmp_path / "o2"), "--workers", "1",
                     "--csv", str(csv_path)]) == 2
        assert words in capsys.readouterr().err
    assert (layer / "zarr.json").read_bytes() == meta  # the recording's metadata kept
    assert image.read_bytes() == b"the user's image" and not (tmp_path / "o2").exists()
    assert main(["batch", str(layer), "-o", str(out), "--workers", "1", "--no-evaluate",
                 "--csv", str(tmp_path / "r.csv")]) == 0  # a rerun: its table replaced
    assert _csv(tmp_path / "r.csv")["layer_000.zarr"]["status"] == "skipped"


def test_bad_batch_input_exits_2(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["batch", str(tmp_path / "none*.zarr"), "-o", str(tmp_path / "o")]) == 2
    assert "matches nothing" in capsys.readouterr().err
    (tmp_path / "empty").mkdir()
    assert main(["batch", str(tmp_path / "empty"), "-o", str(tmp_path / "o")]) == 2
    assert "without recordings" in capsys.readouterr().err
    with pytest.raises(BatchError, match="no such"):
        find_recordings([tmp_path / "missing.zarr"])
    assert mosaic_path(Path("a/layer_7.zarr"), Path("o")) == Path("o/layer_7.mosaic.zarr")


def test_cover_is_valid_pixels_over_the_planned_area_and_batch_runs_without_torch(
        layers: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    # issue 26: without torch (the optional extra) every batch row failed (import torch);
    # issue 26 item 5: cover read 1.000 for a layer that lost a fifth of its valid pixels
    from sffscan.pipeline.batch import process_recording
    from sffscan.pipeline.batch_targets import plan_targets
    from sffscan.pipeline.config import ScanConfig
    from sffscan.pipeline.cover import plan_cover, planned_box_px
    from sffscan.pipeline.mosaic.layout import mosaic_array

    monkeypatch.setitem(sys.modules, "torch", None)  # import torch raises ImportError
    rec, mos = layers / "layer_000.zarr", tmp_path / "layer_000.mosaic.zarr"
    row = process_recording(str(rec), str(mos), processing={}, evaluate=True, threads=1)
    assert row["status"] == "complete", row["error"]
    assert row["coverage"] == 1.0  # a clean scan measures its whole strip
    g = zarr.open_group(str(mos), mode="r+")
    attrs: dict[str, Any] = g.attrs.asdict()
    assert attrs["accuracy"]["coverage"] == 1.0
    # a corrupt frame's worth of heights lost: the first fifth of the strip's rows
    x0, y0, x1, y1 = planned_box_px(ScanConfig.model_validate(attrs["scan_config"]))
    ox, oy = attrs["origin_px"]
    height = mosaic_array(g, "height")
    lost = (y1 - y0) // 5
    block = np.asarray(height[y0 - oy:y0 - oy + lost, x0 - ox:x1 - ox])
    height[y0 - oy:y0 - oy + lost, x0 - ox:x1 - ox] = np.full_like(block, np.nan)
    assert plan_cover(mos) == pytest.approx(1 - lost / (y1 - y0))
    rows, todo = plan_targets([(rec, mos)])  # the rerun's row of the kept mosaic says so
    assert todo == [] and rows[0].coverage == pytest.approx(0.8, abs=0.01)


def test_a_task_loads_torch_only_for_a_scan_that_uses_it() -> None:
    """A batch task limits torch's threads when its scan measures focus in torch; a scan
    that does not (GLVM, TENV on OpenCV) leaves torch unloaded (it is not imported just to be
    limited), unless it was loaded already."""
    import subprocess

    from sffscan.pipeline.preflight import needs_torch

    assert not needs_torch(small_config())
    assert needs_torch(small_config(processing={"backend": "torch"}))
    assert needs_torch(small_config(processing={"focus_operator": "lape"}))
    code = ("import sys\n"
            "from sffscan.pipeline.batch import _torch_threads\n"
            "with _torch_threads(1, needed=False):\n"
            "    print('torch' in sys.modules)\n"
            "with _torch_threads(1, needed=True):\n"
            "    import torch\n"
            "    print(torch.get_num_threads())\n")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                         check=True, timeout=120).stdout.split()
    assert out == ["False", "1"]
