"""``sffscan batch`` reruns: a mosaic left by a killed writer is resumed and ends equal to an
uninterrupted run; an incomplete one is kept; one made with another configuration is kept
and reported until ``--overwrite``; the accuracy is stored in the mosaic and shown again
for skipped rows."""

from __future__ import annotations

import csv
import math
import multiprocessing as mp
import shutil
import signal
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import zarr
from sffscan.pipeline.batch import process_recording, store_accuracy, stored_accuracy
from sffscan.pipeline.cli.main import main
from sffscan.pipeline.formats.recording_writer import RecordingWriter
from sffscan.pipeline.metrology.evaluate import Accuracy
from sffscan.pipeline.mosaic.attrs import MosaicAttrs
from sffscan.pipeline.mosaic.layout import ARRAYS
from sffscan.pipeline.mosaic.ngff import level_path

from sffscan.api import replay
from tests.pyramid_children import torn_replay
from tests.scan_helpers import session_frames, small_config


def _attrs(path: Path) -> dict[str, Any]:
    return dict(zarr.open_group(str(path), mode="r").attrs.asdict())


def _arrays(path: Path) -> dict[str, np.ndarray]:
    g = zarr.open_group(str(path), mode="r")
    levels = len(_attrs(path)["ome"]["multiscales"][0]["datasets"])
    return {level_path(n, k): np.asarray(g[level_path(n, k)])  # type: ignore[index]
            for n in ARRAYS for k in range(levels)}


def _csv(path: Path) -> dict[str, dict[str, str]]:
    with open(path, newline="", encoding="utf-8") as f:
        return {Path(r["recording"]).name: r for r in csv.DictReader(f)}


@pytest.fixture(scope="module")
def job(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Path | int]:
    """A small layer recording, its uninterrupted replay, a mosaic of it whose writer was
    killed in the middle of a band write, and a copy of the recording with a corrupt frame
    chunk (a lost frame: its replay ends incomplete)."""
    d = tmp_path_factory.mktemp("resume")
    cfg = small_config(motion={"x_start_mm": 2.0, "x_end_mm": 5.0},
                       processing={"registration": False})
    rec, ref, torn = d / "layer.zarr", d / "ref.zarr", d / "torn.zarr"
    writer = RecordingWriter(rec, cfg)
    for frame in session_frames(cfg):  # rendered once for the session (test_batch*)
        writer.write(frame)
    writer.close()
    replay(rec, output=ref)
    writes = int(_attrs(ref)["writes_done"])
    kill_at = writes // 2
    ctx = mp.get_context("forkserver")
    ctx.set_forkserver_preload(["tests.pyramid_children", "sffscan.pipeline.wiring"])
    proc = ctx.Process(target=torn_replay, args=(str(rec), str(torn), kill_at, "level0"))
    proc.start()
    proc.join(120)
    assert proc.exitcode == -signal.SIGKILL
    proc.close()
    assert (_attrs(torn)["status"], _attrs(torn)["writes_done"]) == ("writing", kill_at)
    assert _attrs(torn)["writing"] is not None  # a torn band write
    gappy = d / "gappy.zarr"
    shutil.copytree(rec, gappy)
    frames = zarr.open_array(str(gappy / "frames"), mode="r")
    chunk = gappy / "frames" / frames.metadata.encode_chunk_key((40, 0, 0))  # any format
    data = bytearray(chunk.read_bytes())
    data[len(data) // 2] ^= 0x10
    chunk.write_bytes(bytes(data))
    return {"rec": rec, "ref": ref, "torn": torn, "gappy": gappy, "kill_at": kill_at}


def test_rerun_resumes_an_interrupted_mosaic_keeps_an_incomplete_one_and_shows_stored_rmse(
        job: dict[str, Path], tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    rec, gappy = job["rec"], job["gappy"]
    out = tmp_path / "out"
    mosaic = out / "layer.mosaic.zarr"
    shutil.copytree(job["torn"], mosaic)
    code = main(["batch", str(rec), str(gappy), "-o", str(out), "--workers", "2"])
    printed = capsys.readouterr()
    assert code == 1, printed.err  # the gappy recording's mosaic is incomplete
    rows = _csv(out / "batch.csv")
    row = rows["layer.zarr"]
    assert row["status"] == "resumed", row
    assert row["note"] == f"resumed: {job['kill_at']} band write(s) kept, 1 torn region(s) " \
                          "rebuilt"
    # complete, and equal to the uninterrupted replay at every pyramid level
    attrs = _attrs(mosaic)
    assert (attrs["status"], attrs["resumed"]) == ("complete", 1)
    for key, want in _arrays(job["ref"]).items():
        assert np.array_equal(_arrays(mosaic)[key], want, equal_nan=True), key
    # the accuracy is stored in the mosaic, as the row shows it
    acc = stored_accuracy(attrs)
    assert acc is not None and acc.truth == "the simulation's true surface"
    assert 0 < float(row["rmse_um"]) < 200 and float(row["rmse_um"]) == acc.rmse_um
    assert float(row["coverage"]) == acc.coverage and acc.pixels == attrs["valid_pixels"]
    assert acc.corr is not None and 0.5 < acc.corr <= 1
    # and the uncertainty's calibration on that truth, counted again here from the arrays
    from sffscan.pipeline.config import ScanConfig
    from sffscan.pipeline.sim_source import make_world

    g = zarr.open_group(str(mosaic), mode="r")
    h, u = np.asarray(g["height"]), np.asarray(g["uncertainty"])
    ox, oy = attrs["origin_px"]
    cfg = ScanConfig.model_validate(attrs["scan_config"])
    err = h - make_world(cfg).height_um(ox, oy, h.shape[1], h.shape[0])
    rated = np.isfinite(err) & np.isfinite(u)
    assert acc.sigma_pixels == int(rated.sum()) > 0
    assert acc.within_2sigma == pytest.approx(float(np.mean(np.abs(err[rated]) <= 2 * u[rated])))
    assert float(row["within_2sigma"]) == acc.within_2sigma
    # the recording with a corrupt frame chunk ends incomplete
    g = rows["gappy.zarr"]
    assert (g["status"], g["frames_lost"]) == ("incomplete", "1")
    assert _attrs(out / "gappy.mosaic.zarr")["status"] == "incomplete"
    stamp = {p: (out / p / "zarr.json").stat().st_mtime_ns
             for p in ("layer.mosaic.zarr", "gappy.mosaic.zarr")}

    # the rerun leaves both as they are: the complete one skipped with its stored accuracy,
    # the incomplete one kept (final: the recording lost a frame), exit 1 still
    code = main(["batch", str(rec), str(gappy), "-o", str(out), "--workers", "2"])
    printed = capsys.readouterr()
    assert code == 1
    again = _csv(out / "batch.csv")
    assert again["layer.zarr"]["status"] == "skipped"
    for col in ("rmse_um", "coverage", "frames", "valid_pixels"):
        assert again["layer.zarr"][col] == row[col] != "", col
    assert again["gappy.zarr"]["status"] == "incomplete"
    assert again["gappy.zarr"]["note"].startswith("kept: frames lost in the recording")
    # one frame of 84 lost: every column missed a focus level, nothing valid to score (the
    # stored accuracy says so: no RMSE, coverage 0)
    kept = stored_accuracy(_attrs(out / "gappy.mosaic.zarr"))
    assert kept is not None and (kept.pixels, kept.rmse_um, kept.coverage) == (0, None, 0.0)
    assert (again["gappy.zarr"]["rmse_um"], again["gappy.zarr"]["coverage"]) == ("", "0.0")
    assert again["gappy.zarr"]["frames_lost"] == "1"
    for p, t in stamp.items():
        assert (out / p / "zarr.json").stat().st_mtime_ns == t, p
    assert "1 skipped, 1 incomplete" in printed.out
    assert "gappy.zarr: incomplete" in printed.err


def test_another_configuration_is_not_resumed_until_overwrite(
        job: dict[str, Path], tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    out = tmp_path / "out"
    mosaic = out / "layer.mosaic.zarr"
    shutil.copytree(job["torn"], mosaic)
    before = _attrs(mosaic)
    # the task itself (as a worker runs it): the mosaic was made with the default depth method
    row = process_recording(str(job["rec"]), str(mosaic), processing={"depth_method": "spc"},
                            evaluate=False, threads=1)
    assert row["status"] == "failed"
    assert "cannot resume with a different configuration (differs in processing." \
           "depth_method)" in row["error"]
    assert "--overwrite replaces it" in row["error"]
    assert _attrs(mosaic) == before  # kept as it was
    # an unreadable array: not resumed either, kept, and the row says so
    broken = tmp_path / "broken.mosaic.zarr"
    shutil.copytree(job["torn"], broken)
    (broken / "height" / "zarr.json").write_text("{ not JSON")
    row = process_recording(str(job["rec"]), str(broken), processing={}, evaluate=False,
                            threads=1)
    assert row["status"] == "failed" and row["error"].startswith(f"{broken}: cannot resume (")
    assert row["error"].endswith("the mosaic (status writing) is kept: --overwrite replaces it")
    assert "JSONDecodeError" in row["error"]
    assert (broken / "height" / "zarr.json").read_text() == "{ not JSON"
    # --overwrite replaces it with a fresh run of the new configuration
    code = main(["batch", str(job["rec"]), "-o", str(out), "--workers", "1", "--method", "spc",
                 "--overwrite", "--no-evaluate"])
    assert code == 0, capsys.readouterr().err
    row2 = _csv(out / "batch.csv")["layer.zarr"]
    assert (row2["status"], row2["note"], row2["rmse_um"]) == ("complete", "", "")
    attrs = _attrs(mosaic)
    assert (attrs["status"], attrs["resumed"], attrs["accuracy"]) == ("complete", 0, None)
    assert attrs["processing"]["depth_method"] == "spc"


def test_stored_accuracy_keeps_json_finite_and_old_mosaics_read(job: dict[str, Path],
                                                                tmp_path: Path) -> None:
    mosaic = tmp_path / "m.zarr"
    shutil.copytree(job["ref"], mosaic)
    assert stored_accuracy(_attrs(mosaic)) is None  # made without one: still reads
    MosaicAttrs.model_validate(_attrs(mosaic))
    # nothing compared: RMSE and CORR undefined; an exact match: PSNR infinite
    stored = store_accuracy(mosaic, Accuracy(math.nan, math.nan, math.inf, 0, 0.0),
                            truth="a test surface")
    assert (stored.rmse_um, stored.corr, stored.psnr_db) == (None, None, None)
    attrs = MosaicAttrs.model_validate(_attrs(mosaic))
    assert attrs.accuracy == stored
    # a correlation rounded past 1 is clamped, the rest kept as computed
    store_accuracy(mosaic, Accuracy(3.25, 1.0000000002, 41.5, 1234, 0.75), truth="t")
    got = stored_accuracy(_attrs(mosaic))
    assert got is not None
    assert (got.rmse_um, got.corr, got.psnr_db, got.pixels, got.coverage) == (
        3.25, 1.0, 41.5, 1234, 0.75)
