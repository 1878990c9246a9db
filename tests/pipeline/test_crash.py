"""Surviving a crash: SIGKILL of the recorder and of the mosaic writer, and a full disk.

The processes killed are children started from a multiprocessing fork server that has the
pipeline imported already (a fresh interpreter would spend ~2 s importing torch), each
running the command line's ``main`` exactly as ``sffscan`` does.
"""

from __future__ import annotations

import contextlib
import errno
import multiprocessing as mp
import os
import random
import re
import signal
import subprocess
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import zarr
from sffscan.pipeline.cli.main import main
from sffscan.pipeline.config import ScanConfig, config_to_toml
from sffscan.pipeline.formats.recording import RecordingError
from sffscan.pipeline.formats.recording_reader import open_recording
from sffscan.pipeline.mosaic.layout import ARRAYS
from sffscan.pipeline.mosaic.reader import TILE_COMPLETE, TILE_INCOMPLETE, tile_states
from sffscan.pipeline.sim_source import simulate_frames
from sffscan.stages.messages import Frame

from tests.crash_children import quiet_main, torn_replay
from tests.scan_helpers import rendered_scanner, save_frames, small_config


def _cfg(passes: int = 1) -> ScanConfig:
    return small_config(motion={"x_start_mm": 2.0, "x_end_mm": 8.0, "passes": passes},
                        processing={"registration": False})


def _ctx() -> Any:
    ctx = mp.get_context("forkserver")
    ctx.set_forkserver_preload(["tests.crash_children", "sffscan.pipeline.wiring",
                                "sffscan.pipeline.formats.recorder_sink",
                                "sffscan.pipeline.cli.record"])
    return ctx


def _kill_when(proc: Any, reached: Callable[[], bool], timeout_s: float = 60.0) -> bool:
    """SIGKILL ``proc`` as soon as ``reached()`` (a moment defined by the work done, not by
    the machine's speed); True if the kill landed before the process ended by itself."""
    t_end = time.monotonic() + timeout_s
    while proc.is_alive() and time.monotonic() < t_end and not reached():
        time.sleep(0.001)
    alive = bool(proc.is_alive())
    if alive:
        os.kill(proc.pid, signal.SIGKILL)
    proc.join(timeout_s)
    proc.close()
    return alive


def _kill_at_frame(proc: Any, recording: Path, frames: int) -> bool:
    """Kill once ``frames`` frame chunks of the recording exist (``frames/c.<i>.0.0`` in
    version 3, ``frames/c/<i>/0/0`` in version 2)."""
    folder = recording / "frames"

    def reached() -> bool:
        try:
            names = os.listdir(folder)
            n = sum(1 for name in names if name.startswith("c.") and name.endswith(".0.0"))
            if "c" in names:
                n += len(os.listdir(folder / "c"))
        except OSError:  # not created yet
            return False
        return n >= frames

    return _kill_when(proc, reached)


def _seed(name: str) -> int:
    """A seed that changes with every run, printed (SFFSCAN_CRASH_SEED repeats a run)."""
    seed = int(os.environ.get("SFFSCAN_CRASH_SEED", random.randrange(2**32)))
    print(f"{name}: seed {seed} (SFFSCAN_CRASH_SEED={seed} repeats it)")
    return seed


def _kill_at_close(proc: Any, recording: Path) -> bool:
    """Kill as the recorder closes: its reserve file is the first thing the close frees."""
    reserve = recording / ".sffscan-reserve"
    seen = [False]

    def reached() -> bool:
        if reserve.exists():
            seen[0] = True
            return False
        return seen[0]

    return _kill_when(proc, reached)


@pytest.fixture(scope="module")
def one_pass() -> tuple[ScanConfig, list[Frame]]:
    """The one-pass scan of ``_cfg()`` and all its frames, rendered once for the module: the
    scans below feed them again (``rendered_scanner``) instead of rendering each time, and
    check what they recorded against them."""
    cfg = _cfg()
    return cfg, list(simulate_frames(cfg))


def _attrs(path: Path) -> dict[str, Any]:
    return zarr.open_group(str(path), mode="r").attrs.asdict()


def _arrays(path: Path) -> dict[str, np.ndarray]:
    g = zarr.open_group(str(path), mode="r")
    return {n: np.asarray(g[n]) for n in ARRAYS}


def test_recorder_killed_at_random_moments_keeps_every_complete_frame(
        tmp_path: Path, one_pass: tuple[ScanConfig, list[Frame]]) -> None:
    cfg, reference = one_pass
    toml = tmp_path / "scan.toml"
    toml.write_text(config_to_toml(cfg))
    saved = save_frames(reference, tmp_path / "frames")  # the children's feed
    rng = random.Random(_seed("recorder kills"))
    ctx = _ctx()
    kills, recovered, interrupted = 0, [], None
    for trial in range(12):
        rec = tmp_path / f"rec{trial}.zarr"
        proc = ctx.Process(target=quiet_main, args=([
            "scan", "--config", str(toml), "-o", str(tmp_path / f"m{trial}.zarr"),
            "--record", str(rec), "-q", "--no-evaluate"], (cfg, saved)))
        proc.start()
        if trial < 8:  # killed at a random point: once a random number of frames is stored
            kills += _kill_at_frame(proc, rec, rng.randint(1, len(reference) - 2))
        elif trial < 10:  # near the end
            kills += _kill_at_frame(proc, rec, rng.randint(len(reference) - 3,
                                                           len(reference)))
        else:  # during the close (the status, the final flush, the trim)
            kills += _kill_at_close(proc, rec)
        try:
            r = open_recording(rec)
        except RecordingError as err:  # killed before a whole frame was stored
            assert "no usable frame" in str(err) or "no such recording" in str(err), err
            recovered.append(0)
            continue
        n = r.report.frames
        recovered.append(n)
        # nothing lost or altered before the last complete frame: frames 0..n-1, in order
        assert r.report.defects == 0, r.report.lines()
        assert r.report.first_id == 0 and r.report.last_id == n - 1
        for got, want in zip(r.frames(), reference[:n], strict=True):
            assert got.header == want.header
            assert np.array_equal(got.image, want.image)
        if r.attrs.status == "recording" and (interrupted is None or n > interrupted[1]):
            interrupted = (rec, n)
    assert kills >= 10, f"only {kills} of 12 kills landed while the scan ran"
    assert sum(1 for n in recovered if 0 < n < len(reference)) >= 7, recovered
    # one interrupted recording replays up to its last complete frame: 'incomplete', exit 3
    assert interrupted is not None, recovered
    rec, n = interrupted
    out = tmp_path / "replayed.zarr"
    assert main(["replay", str(rec), "-o", str(out), "-q"]) == (3 if n < len(reference) else 0)
    assert _attrs(out)["recording"]["frames"] == n
    assert _attrs(out)["frames_received"] == n


@pytest.fixture(scope="module")
def two_pass(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, Path]:
    """A two-pass recording and its uninterrupted replay (the reference mosaic)."""
    d = tmp_path_factory.mktemp("twopass")
    toml = d / "scan.toml"
    toml.write_text(config_to_toml(_cfg(passes=2)))
    rec, ref = d / "rec.zarr", d / "ref.zarr"
    assert main(["scan", "--config", str(toml), "-o", str(d / "live.zarr"), "--record",
                 str(rec), "-q", "--no-evaluate"]) == 0
    assert main(["replay", str(rec), "-o", str(ref), "-q"]) == 0
    return rec, ref


def test_torn_mosaic_tiles_are_known_and_resume_completes_bit_for_bit(
        tmp_path: Path, two_pass: tuple[Path, Path]) -> None:
    rec, ref = two_pass
    reference = _arrays(ref)
    writes = int(_attrs(ref)["writes_done"])
    # a write of the second pass: its band overlaps bands of the first pass already written
    kill_at = writes - 3
    out = tmp_path / "torn.zarr"
    ctx = _ctx()
    proc = ctx.Process(target=torn_replay, args=(["replay", str(rec), "-o", str(out), "-q"],
                                                  kill_at))
    proc.start()
    proc.join(60)
    assert proc.exitcode == -signal.SIGKILL
    proc.close()
    states, info = tile_states(out)
    assert info["status"] == "writing" and info["writes_done"] == kill_at
    assert info["writing"] is not None and info["incomplete"] > 0
    box = info["writing"]
    chunk = int(zarr.open_group(str(out), mode="r")["height"].chunks[0])  # type: ignore[union-attr]
    ox, oy = _attrs(out)["origin_px"]
    rows = range((box[1] - oy) // chunk, (box[1] - oy + box[3] - 1) // chunk + 1)
    cols = range((box[0] - ox) // chunk, (box[0] - ox + box[2] - 1) // chunk + 1)
    assert {(r, c) for r in rows for c in cols} == set(zip(*np.nonzero(
        states == TILE_INCOMPLETE), strict=True))
    assert main(["info", str(out)]) == 0
    assert main(["replay", str(rec), "-o", str(out), "-q", "--resume"]) == 0
    resumed = _arrays(out)
    for name in ARRAYS:
        assert np.array_equal(resumed[name], reference[name], equal_nan=True), name
    states, info = tile_states(out)
    assert info["status"] == "complete" and info["incomplete"] == 0
    assert info["writes_done"] == writes
    # a complete mosaic is not resumed again: nothing to do, nothing wrong (exit 0)
    assert main(["replay", str(rec), "-o", str(out), "-q", "--resume"]) == 0


def test_mosaic_writer_killed_at_random_moments_resumes(
        tmp_path: Path, two_pass: tuple[Path, Path]) -> None:
    rec, ref = two_pass
    reference = _arrays(ref)
    writes = int(_attrs(ref)["writes_done"])
    rng = random.Random(_seed("mosaic writer kills"))
    ctx = _ctx()
    resumed_trials = 0
    for trial in range(2):
        out = tmp_path / f"m{trial}.zarr"
        # killed inside a random band write, between two of its four arrays: a real torn write
        kill_at = rng.randint(1, writes - 2)
        proc = ctx.Process(target=torn_replay,
                           args=(["replay", str(rec), "-o", str(out), "-q"], kill_at))
        proc.start()
        proc.join(120)
        assert proc.exitcode == -signal.SIGKILL
        proc.close()
        states, info = tile_states(out)
        assert info["writing"] is not None and info["writes_done"] == kill_at
        assert set(np.unique(states)) <= {0, TILE_COMPLETE, TILE_INCOMPLETE}
        if info["status"] == "complete":
            continue
        resumed_trials += 1
        assert main(["replay", str(rec), "-o", str(out), "-q", "--resume"]) == 0
        resumed = _arrays(out)
        for name in ARRAYS:
            assert np.array_equal(resumed[name], reference[name], equal_nan=True), name
    assert resumed_trials > 0, "no kill landed while the mosaic was written: nothing tested"


def test_injected_disk_full_stops_the_scan_and_keeps_what_was_written(
        tmp_path: Path, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture,
        one_pass: tuple[ScanConfig, list[Frame]]) -> None:
    from sffscan.pipeline import sim_source as scanner
    from sffscan.pipeline.formats import recording_writer as recorder

    cfg, reference = one_pass
    monkeypatch.setattr(scanner, "simulate_frames", rendered_scanner(cfg, reference))
    toml = tmp_path / "scan.toml"
    toml.write_text(config_to_toml(cfg))
    orig = recorder.RecordingWriter.write

    def full(self: recorder.RecordingWriter, frame: Any) -> None:
        if frame.header.frame_id == 37:
            raise OSError(errno.ENOSPC, "No space left on device")
        orig(self, frame)

    monkeypatch.setattr(recorder.RecordingWriter, "write", full)
    rec = tmp_path / "rec.zarr"
    code = main(["scan", "--config", str(toml), "-o", str(tmp_path / "m.zarr"), "--record",
                 str(rec), "-q", "--no-evaluate"])
    err = capsys.readouterr().err
    assert code == 1
    assert "recorder" in err and "disk full at frame_id 37" in err
    assert "keeps the 37 frame(s) written before it (frame_id 0..36)" in err
    r = open_recording(rec)
    assert r.attrs.status == "failed" and "disk full at frame_id 37" in str(r.attrs.error)
    assert r.report.frames == 37 and r.report.defects == 0
    for got, want in zip(r.frames(), reference, strict=False):
        assert got.header == want.header and np.array_equal(got.image, want.image)
    assert zarr.open_group(str(tmp_path / "m.zarr"), mode="r").attrs["status"] == "failed"


def test_real_disk_full_on_a_small_tmpfs(tmp_path: Path, capsys: pytest.CaptureFixture,
                                        monkeypatch: pytest.MonkeyPatch,
                                        one_pass: tuple[ScanConfig, list[Frame]]) -> None:
    from sffscan.pipeline import sim_source as scanner

    monkeypatch.setattr(scanner, "simulate_frames", rendered_scanner(*one_pass))
    mnt = tmp_path / "small"
    mnt.mkdir()
    done = subprocess.run(["mount", "-t", "tmpfs", "-o", "size=3m", "tmpfs", str(mnt)],
                          capture_output=True, check=False)
    if done.returncode != 0:
        pytest.skip(f"cannot mount a tmpfs here (needs root): {done.stderr.decode().strip()}")
    try:
        toml = tmp_path / "scan.toml"
        toml.write_text(config_to_toml(one_pass[0]))
        rec = mnt / "rec.zarr"
        code = main(["scan", "--config", str(toml), "-o", str(tmp_path / "m.zarr"), "--record",
                     str(rec), "-q", "--no-evaluate"])
        err = capsys.readouterr().err
        assert code == 1 and "disk full at frame_id" in err
        promised = re.search(r"keeps the (\d+) frame\(s\) written before it \(frame_id "
                             r"(\d+)\.\.(\d+)\)", err)
        assert promised is not None, err
        n, first, last = (int(v) for v in promised.groups())
        r = open_recording(rec)
        # the message is true: exactly the frames it names are readable, and whole
        assert (r.report.frames, r.report.first_id, r.report.last_id) == (n, first, last)
        assert r.report.defects == 0 and r.attrs.status == "failed"
        assert sum(1 for _ in r.frames()) == n
    finally:
        with contextlib.suppress(Exception):
            subprocess.run(["umount", str(mnt)], check=False)


def test_real_disk_full_under_a_replays_mosaic(tmp_path: Path, two_pass: tuple[Path, Path],
                                               capsys: pytest.CaptureFixture) -> None:
    """The mosaic's disk fills up during a replay: exit 1 (a stage failed, as documented),
    status 'failed' (written from the mosaic's reserve), the mosaic still readable."""
    rec, _ = two_pass
    mnt = tmp_path / "small"
    mnt.mkdir()
    done = subprocess.run(["mount", "-t", "tmpfs", "-o", "size=600k", "tmpfs", str(mnt)],
                          capture_output=True, check=False)
    if done.returncode != 0:
        pytest.skip(f"cannot mount a tmpfs here (needs root): {done.stderr.decode().strip()}")
    try:
        out = mnt / "m.zarr"
        assert main(["replay", str(rec), "-o", str(out), "-q"]) == 1
        assert "No space left on device" in capsys.readouterr().err
        assert _attrs(out)["status"] == "failed"
        assert main(["info", str(out)]) == 0
    finally:
        with contextlib.suppress(Exception):
            subprocess.run(["umount", str(mnt)], check=False)
