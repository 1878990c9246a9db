"""Recording integrity (issue 13): CRC-32C on every chunk, header copies beside the frames,
no single chunk file a single point of failure, malformed files exit 2 naming the file."""

from __future__ import annotations

import os
import random
import shutil
from pathlib import Path

import numpy as np
import pytest
import zarr
from sffscan.pipeline.cli.main import main
from sffscan.pipeline.config import config_to_toml
from sffscan.pipeline.formats.recording import PER_FRAME, RecordingError
from sffscan.pipeline.formats.recording_reader import open_recording

from tests.scan_helpers import small_config


@pytest.fixture(scope="module")
def recorded(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, int]:
    """A recording of a short simulated scan (version 3) and its frame count."""
    d = tmp_path_factory.mktemp("integrity")
    cfg = small_config(motion={"x_start_mm": 2.0, "x_end_mm": 6.0},
                       processing={"registration": False})
    toml = d / "scan.toml"
    toml.write_text(config_to_toml(cfg))
    rec = d / "rec.zarr"
    assert main(["scan", "--config", str(toml), "-o", str(d / "live.zarr"), "--record",
                 str(rec), "-q", "--no-evaluate"]) == 0
    r = open_recording(rec)
    assert r.attrs.format_version == 4 and r.report.defects == 0
    assert not (rec / ".sffscan-reserve").exists()  # freed at close
    return rec, r.report.frames


def _chunk(rec: Path, array: str, *key: int) -> Path:
    """The file of a chunk, named by the array's own chunk key encoding (``c.i.0.0`` in
    version 3, ``c/i/0/0`` in version 2)."""
    arr = zarr.open_array(str(rec / array), mode="r")
    return rec / array / arr.metadata.encode_chunk_key(key)  # type: ignore[union-attr]


def _copy(src: Path, dst: Path) -> Path:
    shutil.copytree(src, dst)
    return dst


def test_twenty_flipped_bytes_in_frame_chunks_are_all_detected(
        recorded: tuple[Path, int], tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    src, n = recorded
    rec = _copy(src, tmp_path / "flipped.zarr")
    seed = int(os.environ.get("SFFSCAN_FLIP_SEED", random.randrange(2**32)))
    print(f"byte flips: seed {seed} (SFFSCAN_FLIP_SEED={seed} repeats it)")
    rng = random.Random(seed)
    fid = np.asarray(zarr.open_group(str(rec), mode="r")["frame_id"])  # type: ignore[index]
    flipped = sorted(rng.sample(range(n), 20))
    for i in flipped:  # one byte anywhere in the chunk file, checksum bytes included
        path = _chunk(rec, "frames", i, 0, 0)
        assert path.name == f"c.{i}.0.0"  # version 3: every chunk in the array's folder
        data = bytearray(path.read_bytes())
        data[rng.randrange(len(data))] ^= 1 << rng.randrange(8)
        path.write_bytes(bytes(data))
    want = sorted(int(fid[i]) for i in flipped)
    assert main(["info", str(rec), "--verify"]) == 3  # frames a replay leaves out
    out = capsys.readouterr().out
    assert "verified    every usable frame decoded; 20 corrupt" in out, out
    assert "corrupt     20: frame_id " + ", ".join(map(str, want)) in out
    mosaic = tmp_path / "m.zarr"
    assert main(["replay", str(rec), "-o", str(mosaic), "-q"]) == 3  # incomplete
    attrs = zarr.open_group(str(mosaic), mode="r").attrs.asdict()
    assert attrs["status"] == "incomplete"
    assert (attrs["frames_expected"], attrs["frames_received"]) == (n, n - 20)
    assert attrs["recording"]["corrupt"] == want and attrs["recording"]["frames_lost"] == 20


@pytest.mark.parametrize("damage", ["delete", "truncate"])
def test_any_one_metadata_chunk_lost_loses_no_frame(recorded: tuple[Path, int], tmp_path: Path,
                                                    damage: str) -> None:
    """Every chunk of every per-frame array, deleted or truncated in turn: every frame is
    still replayed, with its header, rebuilt from the copy beside it."""
    src, n = recorded
    reference = [(f.header, f.image) for f in open_recording(src).frames()]
    for name in PER_FRAME:
        for chunk in sorted((src / name / "c").iterdir()):
            rec = tmp_path / f"{damage}-{name}-{chunk.name}.zarr"
            _copy(src, rec)
            target = rec / name / "c" / chunk.name
            if damage == "delete":
                target.unlink()
            else:
                target.write_bytes(target.read_bytes()[:7])
            r = open_recording(rec)
            assert r.report.frames == n and r.report.defects == 0, (name, r.report.lines())
            got = [(f.header, f.image) for f in r.frames()]
            assert len(got) == n
            for (h, img), (wh, wimg) in zip(got, reference, strict=True):
                assert h == wh and np.array_equal(img, wimg)
            shutil.rmtree(rec)


def test_a_lost_frame_or_header_chunk_loses_that_frame_only(
        recorded: tuple[Path, int], tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    src, n = recorded
    rec = _copy(src, tmp_path / "holes.zarr")
    _chunk(rec, "frames", 5, 0, 0).unlink()
    _chunk(rec, "headers", 9, 0).unlink()  # the metadata still describes frame 9
    r = open_recording(rec)
    assert r.report.frames == n - 1 and r.report.missing_chunks == [5]
    # frame 12 loses both its header copy and (with the frame_id chunk) its metadata
    _chunk(rec, "headers", 12, 0).unlink()
    (rec / "frame_id" / "c" / "0").unlink()
    r = open_recording(rec)
    assert r.report.frames == n - 3  # 5 (no frame), 9 and 12 (no header, no metadata)
    assert r.report.missing_chunks == [5] and r.report.missing_metadata == [9, 12]
    assert main(["replay", str(rec), "-o", str(tmp_path / "m.zarr"), "-q"]) == 3
    assert "3 missing" in capsys.readouterr().out


def test_verify_checks_the_header_copies_too(recorded: tuple[Path, int], tmp_path: Path,
                                             capsys: pytest.CaptureFixture[str]) -> None:
    src, n = recorded
    rec = _copy(src, tmp_path / "hdr.zarr")
    path = _chunk(rec, "headers", 7, 0)
    data = bytearray(path.read_bytes())
    data[len(data) // 2] ^= 0x10
    path.write_bytes(bytes(data))
    assert main(["info", str(rec), "--verify"]) == 0
    out = capsys.readouterr().out
    assert "header copies: 1 corrupt, lost or not matching the metadata" in out
    assert "0 corrupt" in out  # the frame itself is usable: its metadata is intact
    assert open_recording(rec).report.frames == n


def test_version_1_recordings_still_replay(recorded: tuple[Path, int], tmp_path: Path) -> None:
    """A version-1 recording (no checksums, no header copies) opens and replays."""
    src, n = recorded
    rec = _copy(src, tmp_path / "v1.zarr")
    shutil.rmtree(rec / "headers")
    g = zarr.open_group(str(rec), mode="r+")
    g.update_attributes({"format_version": 1})
    r = open_recording(rec)
    assert r.attrs.format_version == 1 and r.report.frames == n
    assert sum(1 for _ in r.frames()) == n


@pytest.mark.parametrize(("target", "content"), [
    ("zarr.json", b"{\"zarr_format\": 3, \"node_type\": \"gro"),
    ("zarr.json", b"\xff\xfe garbage"),
    ("frames/zarr.json", b"{\"zarr_format\": 3, \"node_t"),
    ("frame_id/zarr.json", b"[]"),
])
def test_malformed_files_exit_2_naming_the_file(recorded: tuple[Path, int], tmp_path: Path,
                                                capsys: pytest.CaptureFixture[str],
                                                target: str, content: bytes) -> None:
    src, _ = recorded
    rec = _copy(src, tmp_path / "bad.zarr")
    (rec / target).write_bytes(content)
    for argv in (["info", str(rec)], ["info", str(rec), "--verify"],
                 ["replay", str(rec), "-o", str(tmp_path / "m.zarr"), "-q"]):
        assert main(argv) == 2, argv
        err = capsys.readouterr().err
        assert f"{rec}/{target}" in err, err
        assert "Traceback" not in err
    with pytest.raises(RecordingError, match=target.replace(".", r"\.")):
        open_recording(rec)


def test_a_malformed_mosaic_exits_2_naming_it(recorded: tuple[Path, int], tmp_path: Path,
                                             capsys: pytest.CaptureFixture[str]) -> None:
    src, _ = recorded
    mosaic = tmp_path / "m.zarr"
    shutil.copytree(src.parent / "live.zarr", mosaic)
    (mosaic / "height" / "zarr.json").write_bytes(b"{\"zarr_format\": 3, \"shape\": [1")
    assert main(["info", str(mosaic)]) == 2
    assert str(mosaic) in capsys.readouterr().err
    assert main(["replay", str(src), "-o", str(mosaic), "-q", "--resume"]) == 2
    assert str(mosaic) in capsys.readouterr().err


def test_the_recorder_makes_what_it_wrote_durable(tmp_path: Path,
                                                 monkeypatch: pytest.MonkeyPatch) -> None:
    """fsync of every frame chunk, header copy, metadata chunk and zarr.json, and of their
    folders: at the interval (here: every write) and at close."""
    from sffscan.pipeline.formats import durable
    from sffscan.pipeline.formats.recording_writer import RecordingWriter
    from sffscan.pipeline.sim_source import simulate_frames

    from tests.pipeline.formats.test_transport import tiny_config

    synced: list[tuple[Path, bool]] = []
    monkeypatch.setattr(durable, "fsync_path",
                        lambda path, directory=False: synced.append((Path(path), directory)))
    cfg = tiny_config()
    frames = [f for _, f in zip(range(5), simulate_frames(cfg), strict=False)]
    root = tmp_path / "late.zarr"
    writer = RecordingWriter(root, cfg, fsync_s=3600.0)
    for frame in frames:
        writer.write(frame)
    assert synced == []  # within the interval: nothing forced yet
    writer.close()
    files = {str(p.relative_to(root)) for p, d in synced if not d}
    dirs = {p for p, d in synced if d}
    for i in range(5):
        assert f"frames/c.{i}.0.0" in files and f"headers/c.{i}.0" in files
    assert {"zarr.json", "frames/zarr.json", "frame_id/c/0", "timestamp_ns/c/0"} <= files
    # version 3: the frame and header chunks lie in their array's folder, no folder per frame
    assert dirs == {root, root.parent, root / "frames", root / "headers",
                    *(root / name for name in PER_FRAME),
                    *(root / name / "c" for name in PER_FRAME)}
    synced.clear()
    writer = RecordingWriter(tmp_path / "eager.zarr", cfg, fsync_s=0.0)
    writer.write(frames[0])
    assert any(str(p).endswith("frames/c.0.0.0") for p, _ in synced)  # at the first write
    writer.close()


@pytest.mark.parametrize("version", [2, 4])
def test_versions_2_and_4_open_verify_and_replay_the_same_frames(tmp_path: Path,
                                                                 version: int) -> None:
    """Version 4 (as 3) names the frame and header chunks ``c.i.0.0`` (one folder), version 2
    ``c/i/0/0`` (a folder per frame, as recorded before): each opens, verifies and replays
    the frames written; a lost frame chunk is reported lost, a flipped byte corrupt."""
    from sffscan.pipeline.formats.recording_writer import RecordingWriter
    from sffscan.pipeline.sim_source import simulate_frames

    from tests.pipeline.formats.test_transport import tiny_config

    cfg = tiny_config()
    frames = [f for _, f in zip(range(12), simulate_frames(cfg), strict=False)]
    rec = tmp_path / f"v{version}.zarr"
    writer = RecordingWriter(rec, cfg, key_separator={2: "/", 4: "."}[version])
    for f in frames:
        writer.write(f)
    writer.close()  # trims the arrays from 1024 entries to 12
    names = sorted(p.name for p in (rec / "frames").iterdir())
    if version == 4:
        assert names == sorted([*(f"c.{i}.0.0" for i in range(12)), "zarr.json"])
        assert sorted(p.name for p in (rec / "headers").iterdir()) == sorted(
            [*(f"c.{i}.0" for i in range(12)), "zarr.json"])
    else:
        assert names == ["c", "zarr.json"]
        assert sorted(int(p.name) for p in (rec / "frames" / "c").iterdir()) == list(range(12))
    r = open_recording(rec)
    assert r.attrs.format_version == version and r.report.frames == 12
    assert r.report.defects == 0 and r.verify() == [] and not r.report.notes
    got = list(r.frames())
    assert [f.header for f in got] == [f.header for f in frames]
    assert all(np.array_equal(a.image, b.image) for a, b in zip(got, frames, strict=True))
    _chunk(rec, "frames", 4, 0, 0).unlink()
    path = _chunk(rec, "frames", 7, 0, 0)
    data = bytearray(path.read_bytes())
    data[len(data) // 3] ^= 0x04
    path.write_bytes(bytes(data))
    (rec / "frame_id" / "c" / "0").unlink()  # every frame_id: rebuilt from the header copies
    r = open_recording(rec)
    fid = [f.header.frame_id for f in frames]
    assert r.report.missing_chunks == [fid[4]] and r.report.frames == 11
    assert any("12 entries rebuilt from the header copies" in note for note in r.report.notes)
    assert r.verify() == [fid[7]] and r.report.frames == 10
