"""Issue 23, the one run path: each test attacks one defect that the orchestration in three
places let through (the defect's number from the issue in the test's name)."""

from __future__ import annotations

import json
import os
import shutil
import socket
import subprocess
import sys
from pathlib import Path
from typing import Any

import pytest
import zarr
from sffscan.pipeline import locks
from sffscan.pipeline.batch import process_recording
from sffscan.pipeline.batch_targets import plan_targets
from sffscan.pipeline.cli.main import main
from sffscan.pipeline.config import ConfigError, config_to_toml
from sffscan.pipeline.formats.recording_writer import RecordingWriter
from sffscan.pipeline.sim_source import simulate_frames

import sffscan
from tests.scan_helpers import small_config

REPO = Path(__file__).resolve().parents[2]


def _attrs(path: Path) -> dict[str, Any]:
    return dict(zarr.open_group(str(path), mode="r").attrs.asdict())


def _config(**extra: dict[str, Any]) -> Any:
    return small_config(motion={"x_start_mm": 2.0, "x_end_mm": 4.5},
                        processing={"registration": False}, **extra)


def _record(path: Path, cfg: Any, *, seed: int | None = None) -> Path:
    frames_cfg = cfg if seed is None else cfg.model_copy(
        update={"source": cfg.source.model_copy(update={"seed": seed})})
    writer = RecordingWriter(path, cfg)
    for frame in simulate_frames(frames_cfg):
        writer.write(frame)
    writer.close()
    return path


@pytest.fixture(scope="module")
def layers(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Path]:
    """Two recordings of one configuration (recorded with ``[output] overwrite = true``)
    with different frames (layer B: another seed), and a complete mosaic of layer A."""
    d = tmp_path_factory.mktemp("layers")
    cfg = _config(output={"overwrite": True, "chunk_px": 128})
    (d / "layers").mkdir()
    a = _record(d / "layers" / "a.zarr", cfg)
    b = _record(d / "layers" / "b.zarr", cfg, seed=7)
    ref = d / "ref.zarr"
    sffscan.replay(a, output=ref)
    return {"a": a, "b": b, "ref": ref, "dir": d}


def _mosaic(layers: dict[str, Path], where: Path) -> Path:
    shutil.copytree(layers["ref"], where)
    return where


def _stamp(path: Path) -> bytes:
    return (path / "zarr.json").read_bytes()


def test_1_replay_does_not_inherit_the_recorded_overwrite(
        layers: dict[str, Path], tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    assert _attrs(layers["a"])["scan_config"]["output"]["overwrite"] is True
    m = _mosaic(layers, tmp_path / "m.zarr")
    before = _stamp(m)
    assert main(["replay", str(layers["a"]), "-o", str(m), "-q"]) == 2
    assert "exists" in capsys.readouterr().err
    with pytest.raises(FileExistsError, match="exists"):
        sffscan.replay(layers["a"], output=m)
    assert _stamp(m) == before


def test_2_a_taken_port_or_a_loose_pairing_folder_is_refused_before_the_mosaic_is_touched(
        layers: dict[str, Path], tmp_path: Path, capsys: pytest.CaptureFixture[str],
        monkeypatch: pytest.MonkeyPatch) -> None:
    m = _mosaic(layers, tmp_path / "keep.zarr")
    before = _stamp(m)
    toml = tmp_path / "scan.toml"
    toml.write_text(config_to_toml(_config()))
    with socket.socket() as taken:
        taken.bind(("127.0.0.1", 0))
        taken.listen()
        port = taken.getsockname()[1]
        code = main(["scan", "--config", str(toml), "--source", f"tcp://127.0.0.1:{port}",
                     "-o", str(m), "--overwrite", "-q", "--no-evaluate"])
    assert code == 2
    assert f"tcp://127.0.0.1:{port}: cannot listen" in capsys.readouterr().err
    assert _stamp(m) == before and _attrs(m)["status"] == "complete"
    # a pairing folder others can write
    monkeypatch.setenv("XDG_RUNTIME_DIR", str(tmp_path))
    loose = tmp_path / f"sffscan-{os.getuid()}"
    loose.mkdir()
    loose.chmod(0o777)
    with socket.socket() as free:
        free.bind(("127.0.0.1", 0))
        port = free.getsockname()[1]
    code = main(["scan", "--config", str(toml), "--source", f"tcp://127.0.0.1:{port}",
                 "-o", str(m), "--overwrite", "-q", "--no-evaluate"])
    assert code == 2
    assert f"{loose}: the pairing folder" in capsys.readouterr().err
    assert _stamp(m) == before


def test_3_a_second_writer_is_refused_with_the_holder_named(
        layers: dict[str, Path], tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    m = _mosaic(layers, tmp_path / "m.zarr")
    before = _stamp(m)
    with locks.acquire(m) as held:
        assert main(["replay", str(layers["a"]), "-o", str(m), "--overwrite", "-q"]) == 2
        err = capsys.readouterr().err
        assert f"being written by {socket.gethostname()} pid {os.getpid()}" in err
        with pytest.raises(locks.LockHeld):
            sffscan.replay(layers["a"], output=m, overwrite=True)
        assert main(["info", str(m)]) == 0
        assert f"being written now by {socket.gethostname()} pid {os.getpid()}" in \
            capsys.readouterr().out
        assert held.file.exists()
    assert not locks.lock_path(m).exists()  # released and removed
    assert _stamp(m) == before
    # a lock file left by a writer that died is stale: taken over, and the run goes on
    locks.lock_path(m).write_text(json.dumps({"host": socket.gethostname(), "pid": 2**22 + 1}))
    assert main(["replay", str(layers["a"]), "-o", str(m), "--overwrite", "-q"]) == 0
    assert not locks.lock_path(m).exists()


def test_4_resume_refuses_another_recording_and_ignores_the_execution_mode(
        layers: dict[str, Path], tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    m = _mosaic(layers, tmp_path / "m.zarr")
    zarr.open_group(str(m), mode="r+").update_attributes({"status": "failed"})
    before = _stamp(m)
    # layer B: the same configuration, other frames
    assert main(["replay", str(layers["b"]), "-o", str(m), "--resume", "-q"]) == 2
    err = capsys.readouterr().err
    assert "cannot resume from the recording" in err and str(layers["a"].resolve()) in err
    assert _stamp(m) == before
    # batch resumes through the same check
    row = process_recording(str(layers["b"]), str(m), processing={}, evaluate=False,
                            threads=1)
    assert row["status"] == "failed" and "cannot resume from the recording" in row["error"]
    assert row["error"].endswith("--overwrite replaces it")
    assert _stamp(m) == before
    # its own recording resumes, and how it runs (threads, not the recorded auto) is no
    # difference (defect 18)
    assert main(["replay", str(layers["a"]), "-o", str(m), "--resume", "-q",
                 "--execution", "threads"]) == 0
    assert _attrs(m)["status"] == "complete"


def test_5_batch_skips_a_recording_being_written_and_redoes_it_when_complete(
        tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    cfg = _config()
    folder, out = tmp_path / "layers", tmp_path / "out"
    folder.mkdir()
    rec = folder / "live.zarr"
    writer = RecordingWriter(rec, cfg)
    frames = list(simulate_frames(cfg))
    for frame in frames[: len(frames) // 2]:
        writer.write(frame)
    writer.flush()
    mosaic = out / "live.mosaic.zarr"
    with locks.acquire(rec, what="recording"):  # as 'sffscan scan --record' holds it
        assert main(["batch", str(folder), "-o", str(out), "--no-evaluate", "-q"]) == 1
        printed = capsys.readouterr()
        assert "recording" in printed.out and "still being written" in printed.out
        assert not mosaic.exists()
        # a replay of it is refused too, naming the writer
        assert main(["replay", str(rec), "-o", str(tmp_path / "x.zarr"), "-q"]) == 2
        assert f"still being written by {socket.gethostname()}" in capsys.readouterr().err
        assert not (tmp_path / "x.zarr").exists()
    # a mosaic made meanwhile from the half-written recording (as the old batch did)
    sffscan.replay(rec, output=mosaic)
    assert _attrs(mosaic)["status"] == "incomplete"
    for frame in frames[len(frames) // 2:]:
        writer.write(frame)
    writer.close()
    # the recording is complete now: the rerun reprocesses it (the task as a worker runs
    # it, without starting a cluster here), no false 'frames lost'
    rows, todo = plan_targets([(rec, mosaic)])
    assert (rows, todo) == ({}, [0])
    row = process_recording(str(rec), str(mosaic), processing={}, evaluate=False, threads=1)
    assert (row["status"], row["frames_lost"]) == ("complete", 0), row
    attrs = _attrs(mosaic)
    assert attrs["status"] == "complete"
    assert attrs["frames_received"] == len(frames)
    # and a rerun keeps it now: the recording is as it was when the mosaic was made
    rows, todo = plan_targets([(rec, mosaic)])
    assert todo == [] and rows[0].status == "skipped"


def _torn(layers: dict[str, Path], where: Path) -> Path:
    m = _mosaic(layers, where)
    ox, oy = _attrs(m)["origin_px"]
    zarr.open_group(str(m), mode="r+").update_attributes(
        {"status": "writing", "writing": [ox, oy, 100, 100]})
    return m


def test_8_export_and_compare_refuse_a_torn_mosaic(
        layers: dict[str, Path], tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    m = _torn(layers, tmp_path / "torn.zarr")
    assert main(["export", str(m)]) == 2
    err = capsys.readouterr().err
    assert f"{m}: 1 tile(s) torn" in err and "--allow-untrustworthy" in err
    assert main(["compare", str(m), str(layers["ref"])]) == 2
    assert f"{m}: 1 tile(s) torn" in capsys.readouterr().err
    assert main(["export", str(m), "--allow-untrustworthy"]) == 0
    assert main(["export", str(layers["ref"])]) == 0


def test_9_outputs_that_would_destroy_inputs_are_refused(
        layers: dict[str, Path], tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    m = _mosaic(layers, tmp_path / "m.zarr")
    inner = m / "rec.zarr"
    shutil.copytree(layers["a"], inner)
    assert main(["replay", str(inner), "-o", str(m), "--overwrite", "-q"]) == 2
    assert "would destroy it" in capsys.readouterr().err
    assert (inner / "zarr.json").is_file() and _attrs(inner)["format"] == "sffscan-recording"
    meta = layers["a"] / "zarr.json"
    before = meta.read_bytes()
    assert main(["replay", str(layers["a"]), "-o", str(tmp_path / "n.zarr"), "--rrd",
                 str(meta), "-q"]) == 2
    assert "inside the Zarr store" in capsys.readouterr().err
    assert meta.read_bytes() == before and not (tmp_path / "n.zarr").exists()
    mosaic_meta = _stamp(m)
    assert main(["export", str(m), "--x3p", str(m / "zarr.json")]) == 2
    assert "inside the Zarr store" in capsys.readouterr().err
    assert _stamp(m) == mosaic_meta


def test_17_export_of_a_region_too_large_is_refused_with_its_size(
        layers: dict[str, Path], tmp_path: Path, capsys: pytest.CaptureFixture[str],
        monkeypatch: pytest.MonkeyPatch) -> None:
    from sffscan.pipeline.formats import exports

    monkeypatch.setattr(exports, "EXPORT_MAX_BYTES", 10_000)
    out = tmp_path / "a.x3p"
    assert main(["export", str(layers["ref"]), "--x3p", str(out)]) == 2
    err = capsys.readouterr().err
    assert "GiB to export" in err and "--region" in err and not out.exists()
    # scan --check says so beforehand
    toml = tmp_path / "scan.toml"
    toml.write_text(config_to_toml(_config()))
    assert main(["scan", "--config", str(toml), "-o", str(tmp_path / "m.zarr"), "--check"]) == 0
    assert "'sffscan export' will need --region" in capsys.readouterr().err


def test_18_a_symlinked_output_is_named_and_batch_out_equal_to_the_input_is_refused(
        layers: dict[str, Path], tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    m = _mosaic(layers, tmp_path / "m.zarr")
    link = tmp_path / "link.zarr"
    link.symlink_to(m)
    assert main(["replay", str(layers["a"]), "-o", str(link), "--overwrite", "-q"]) == 2
    assert f"{link}: is a symbolic link" in capsys.readouterr().err
    assert m.is_dir() and _attrs(m)["status"] == "complete"
    folder = layers["a"].parent
    assert main(["batch", str(folder), "-o", str(folder), "-q"]) == 2
    assert "the folder of the recording" in capsys.readouterr().err
    assert sorted(p.name for p in folder.iterdir()) == ["a.zarr", "b.zarr"]


SIGTERM_CHILD = """
import os, signal, sys
from sffscan.pipeline.cli.common import report_job
from sffscan.pipeline.run import Job
from sffscan.pipeline.sim_source import simulate_frames
from tests.scan_helpers import small_config

cfg = small_config(motion={"x_start_mm": 2.0, "x_end_mm": 4.5},
                   processing={"registration": False, "execution": "threads"},
                   output={"path": sys.argv[1]})

def frames():
    for i, frame in enumerate(simulate_frames(cfg)):
        if i == 40:
            os.kill(os.getpid(), signal.SIGTERM)
        yield frame

sys.exit(report_job(Job(cfg, frames=frames())))
"""


def test_18_sigterm_marks_the_mosaic_failed_as_ctrl_c_does(tmp_path: Path) -> None:
    out = tmp_path / "m.zarr"
    proc = subprocess.run([sys.executable, "-c", SIGTERM_CHILD, str(out)], cwd=REPO,
                          capture_output=True, text=True, timeout=120, check=False)
    assert proc.returncode == 143, proc.stderr
    assert "terminated (SIGTERM)" in proc.stderr
    assert _attrs(out)["status"] == "failed"
    assert not locks.lock_path(out).exists()


def test_config_error_subclasses_are_bad_input() -> None:
    from sffscan.pipeline.preflight import OutputExists
    from sffscan.pipeline.run import InputBusy, ResumeRefused

    for cls in (locks.LockHeld, ResumeRefused, InputBusy, OutputExists):
        assert issubclass(cls, ConfigError)


def test_overrides_have_one_home_and_name_what_they_refuse() -> None:
    """The command line, the API and batch change a configuration through
    :func:`with_overrides`: fields replaced and the whole re-validated; an unknown table or
    field is refused by name, an invalid value with the caller's origin."""
    from sffscan.pipeline.config import ConfigError, demo_config
    from sffscan.pipeline.run import with_overrides

    cfg = demo_config()
    out = with_overrides(cfg, origin="test", output="/tmp/x.zarr", overwrite=True,
                         processing={"depth_method": "spc"}, motion={"speed_mm_s": 5.0})
    assert (out.output.path, out.output.overwrite) == ("/tmp/x.zarr", True)
    assert (out.processing.depth_method, out.motion.speed_mm_s) == ("spc", 5.0)
    assert with_overrides(cfg, origin="test") == cfg
    with pytest.raises(ValueError, match=r"processing: unknown field\(s\) \['speed'\]"):
        with_overrides(cfg, origin="test", processing={"speed": 1})
    with pytest.raises(ValueError, match="optic: not a table"):
        with_overrides(cfg, origin="test", optic={"n_levels": 3})
    with pytest.raises(ConfigError, match="from the API"):
        with_overrides(cfg, origin="from the API", processing={"window": 4})
