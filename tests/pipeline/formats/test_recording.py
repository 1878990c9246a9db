"""Recording format: the writer's layout, the reader's validation, defects reported by id."""

from __future__ import annotations

import shutil
from pathlib import Path

import numpy as np
import pytest
import zarr
from sffscan.pipeline.config import ScanConfig
from sffscan.pipeline.formats.recording import RecordingAttrs, RecordingError
from sffscan.pipeline.formats.recording_reader import open_recording
from sffscan.pipeline.formats.recording_writer import RecordingWriter
from sffscan.pipeline.formats.schema_gen import SCHEMAS
from sffscan.stages.messages import Frame, FrameHeader

from tests.scan_helpers import small_config

H, W = 256, 640


def _frames(n: int, *, positions: bool = True) -> list[Frame]:
    rng = np.random.default_rng(1)
    out = []
    for i in range(n):
        header = FrameHeader(frame_id=i, timestamp_ns=i * 6_666_667, focus_index=i % 50,
                             stage_x_um=100.0 + i * 100.0 if positions else None,
                             stage_y_um=0.0 if positions else None)
        out.append(Frame(header, rng.integers(0, 1024, (H, W), dtype=np.uint16)))
    return out


def plain_recording(path: Path, cfg: ScanConfig, frames: list[Frame], *,
                    ids: list[int] | None = None, skip: tuple[str, ...] = ()) -> zarr.Group:
    """A recording written with plain zarr calls, following the README's layout (not our
    writer): default codecs and chunking of the metadata, exact array lengths."""
    g = zarr.open_group(str(path), mode="w")
    g.attrs.update({"format": "sffscan-recording", "format_version": 1,
                    "frame_shape": [H, W], "dtype": "uint16",
                    "scan_config": cfg.model_dump(mode="json")})
    n = len(frames)
    a = g.create_array("frames", shape=(n, H, W), chunks=(1, H, W), dtype="uint16")
    for i, f in enumerate(frames):
        a[i] = f.image
    cols = {"frame_id": [f.header.frame_id for f in frames] if ids is None else ids,
            "timestamp_ns": [f.header.timestamp_ns for f in frames],
            "focus_index": [f.header.focus_index for f in frames],
            "stage_x_um": [np.nan if f.header.stage_x_um is None else f.header.stage_x_um
                           for f in frames],
            "stage_y_um": [np.nan if f.header.stage_y_um is None else f.header.stage_y_um
                           for f in frames],
            "pass_index": [f.header.pass_index for f in frames]}
    for name, values in cols.items():
        if name not in skip:
            dtype = "float64" if name.startswith("stage") else "int64"
            g.create_array(name, data=np.asarray(values, dtype=dtype))
    return g


def test_writer_layout_round_trips_frames_and_headers(tmp_path: Path) -> None:
    cfg = small_config()
    frames = _frames(40) + [Frame(h.header.model_copy(update={
        "frame_id": 40 + i, "timestamp_ns": (40 + i) * 6_666_667, "stage_x_um": None}), h.image)
                            for i, h in enumerate(_frames(3, positions=False))]
    w = RecordingWriter(tmp_path / "r.zarr", cfg, flush_every=7)
    for f in frames:
        w.write(f)
    w.close()
    g = zarr.open_group(str(tmp_path / "r.zarr"), mode="r")
    assert g["frames"].shape == (43, H, W) and g["frames"].chunks == (1, H, W)  # type: ignore[union-attr]
    assert g["frame_id"].shape == (43,)  # type: ignore[union-attr]
    attrs = RecordingAttrs.model_validate(g.attrs.asdict())
    assert attrs.status == "complete" and attrs.frames == 43 and attrs.codec == "blosc-lz4"
    r = open_recording(tmp_path / "r.zarr")
    assert r.config == cfg
    assert r.report.frames == 43 and r.report.defects == 0 and r.report.gaps == []
    got = list(r.frames())
    assert [f.header for f in got] == [f.header for f in frames]
    assert got[41].header.stage_x_um is None
    assert all(np.array_equal(a.image, b.image) for a, b in zip(got, frames, strict=True))
    with pytest.raises(FileExistsError, match="never overwritten"):
        RecordingWriter(tmp_path / "r.zarr", cfg)


def test_defects_are_detected_and_reported_with_frame_ids(tmp_path: Path) -> None:
    cfg = small_config()
    frames = _frames(30)
    # stored ids: gap 5..6 lost, 10 duplicated, 15 stored after 16, metadata lost at index 20
    ids = [0, 1, 2, 3, 4, 7, 8, 9, 10, 10, 11, 12, 13, 14, 16, 15, 17, 18, 19, 20,
           -1, 22, 23, 24, 25, 26, 27, 28, 29, 30]
    path = tmp_path / "r.zarr"
    plain_recording(path, cfg, frames, ids=ids)
    root = path / "frames" / "c"
    (root / "22" / "0" / "0").unlink()  # frame_id 23: chunk lost
    (root / "24" / "0" / "0").write_bytes(b"\x00garbage")  # frame_id 25: corrupt
    data = (root / "25" / "0" / "0").read_bytes()
    (root / "25" / "0" / "0").write_bytes(data[: len(data) // 2])  # frame_id 26: truncated
    r = open_recording(path)
    rep = r.report
    assert rep.duplicates == [10]
    assert rep.out_of_order == [15]
    assert rep.missing_metadata == [20]
    assert rep.missing_chunks == [23]
    assert (5, 2) in rep.gaps and (21, 1) in rep.gaps and (23, 1) in rep.gaps
    replayed = [f.header.frame_id for f in r.frames()]
    assert rep.corrupt == [25, 26]
    assert replayed == sorted(set(range(31)) - {5, 6, 21, 23, 25, 26})
    # the duplicate kept is the first copy (array index 8), not the second (index 9)
    by_id = {f.header.frame_id: f for f in r.frames()}
    assert np.array_equal(by_id[10].image, frames[8].image)
    text = "\n".join(rep.lines())
    assert "duplicates  1: frame_id 10" in text and "corrupt     2: frame_id 25, 26" in text
    assert "gaps        3 (4 frames lost)" in text


@pytest.mark.parametrize(("damage", "message"), [
    ("no_frame_id", "per-frame array 'frame_id' is missing"),
    ("no_frames", "array 'frames' is missing"),
    ("shape", r"array 'frames' has shape \[4, 256, 320\], expected \[n, 256, 640\]"),
    ("dtype", "array 'frames' has dtype uint8, the attribute dtype says uint16"),
    ("attrs", "attribute 'frame_shape"),
    ("config", "optics.pixel_um"),
    ("format", "not an sffscan recording"),
])
def test_unrecoverable_input_is_a_clear_error(tmp_path: Path, damage: str, message: str) -> None:
    cfg = small_config()
    path = tmp_path / "r.zarr"
    g = plain_recording(path, cfg, _frames(4), skip=("frame_id",) if damage == "no_frame_id"
                        else ())
    if damage == "no_frames":
        del g["frames"]
    elif damage in ("shape", "dtype"):
        del g["frames"]
        g.create_array("frames", shape=(4, H, W // 2 if damage == "shape" else W),
                       chunks=(1, H, W // 2 if damage == "shape" else W),
                       dtype="uint8" if damage == "dtype" else "uint16")
    elif damage == "attrs":
        g.attrs["frame_shape"] = "256x640"
    elif damage == "config":
        sc = cfg.model_dump(mode="json")
        sc["optics"]["pixel_um"] = -1
        g.attrs["scan_config"] = sc
    elif damage == "format":
        g.attrs["format"] = "something-else"
    with pytest.raises(RecordingError, match=message):
        open_recording(path)


def test_missing_optional_metadata_is_reported_not_filled(tmp_path: Path) -> None:
    cfg = small_config()
    path = tmp_path / "r.zarr"
    plain_recording(path, cfg, _frames(5), skip=("stage_x_um", "stage_y_um", "pass_index"))
    r = open_recording(path)
    assert [f.header.stage_x_um for f in r.frames()] == [None] * 5
    assert any("speed model" in n for n in r.report.notes)
    two = small_config(motion={"passes": 2})
    plain_recording(path, two, _frames(5), skip=("pass_index",))
    with pytest.raises(RecordingError, match="'pass_index' is missing"):
        open_recording(path)


def test_recording_attrs_schema_is_generated_and_names_the_field() -> None:
    assert SCHEMAS["recording_attrs.v1.json"] is RecordingAttrs
    schema = RecordingAttrs.model_json_schema()
    assert {"format", "format_version", "frame_shape", "dtype", "scan_config"} <= set(
        schema["properties"])
    with pytest.raises(ValueError, match="dtype"):
        RecordingAttrs.model_validate({"frame_shape": [2, 2], "dtype": "float32",
                                       "scan_config": {}})


def test_an_all_black_frame_is_recorded_not_lost(tmp_path: Path) -> None:
    # zarr skips chunks equal to the fill value unless told otherwise: a dark frame (all 0)
    # must still be in the recording, not reported as a lost frame
    frames = _frames(4)
    frames[2] = Frame(frames[2].header, np.zeros((H, W), np.uint16))
    w = RecordingWriter(tmp_path / "r.zarr", small_config())
    for f in frames:
        w.write(f)
    w.close()
    r = open_recording(tmp_path / "r.zarr")
    assert r.report.defects == 0 and r.report.frames == 4, r.report.lines()
    assert np.array_equal(list(r.frames())[2].image, frames[2].image)


@pytest.mark.parametrize(("image", "message"), [
    (np.full((H, W), 70_000, np.int32), "frame_id 0: image dtype int32"),
    (np.full((H, W), 3.7), "frame_id 0: image dtype float64"),
    (np.zeros((H, W // 2), np.uint16), r"frame_id 0: image dtype uint16 shape \(256, 320\)"),
])
def test_the_writer_refuses_frames_that_disagree_with_the_configuration(
        tmp_path: Path, image: np.ndarray, message: str) -> None:
    # never cast (70000 would wrap to 4464 in uint16) nor store a frame of another shape
    w = RecordingWriter(tmp_path / "r.zarr", small_config())
    with pytest.raises(ValueError, match=message):
        w.write(Frame(_frames(1)[0].header, image))


def test_a_missing_part_of_a_frame_split_over_chunks_is_reported_not_filled(
        tmp_path: Path) -> None:
    g = zarr.open_group(str(tmp_path / "r.zarr"), mode="w")
    g.attrs.update({"format": "sffscan-recording", "format_version": 1, "frame_shape": [H, W],
                    "dtype": "uint16", "scan_config": small_config().model_dump(mode="json")})
    a = g.create_array("frames", shape=(3, H, W), chunks=(1, H // 2, W), dtype="uint16")
    for i in range(3):
        a[i] = 5
    for name in ("frame_id", "timestamp_ns", "focus_index"):
        g.create_array(name, data=np.arange(3, dtype="int64"))
    (tmp_path / "r.zarr" / "frames" / "c" / "1" / "1" / "0").unlink()  # lower half of frame 1
    r = open_recording(tmp_path / "r.zarr")
    assert r.report.missing_chunks == [1]
    assert [f.header.frame_id for f in r.frames()] == [0, 2]
    assert all((f.image == 5).all() for f in r.frames())


def _chunked_metadata(path: Path, n: int, *, status: str = "complete") -> None:
    """A plain-zarr recording of ``n`` frames, metadata in chunks of 4 with zarr's default
    fill value (0)."""
    g = zarr.open_group(str(path), mode="w")
    g.attrs.update({"format": "sffscan-recording", "format_version": 1, "frame_shape": [H, W],
                    "dtype": "uint16", "scan_config": small_config().model_dump(mode="json"),
                    "status": status, "frames": n})
    a = g.create_array("frames", shape=(n, H, W), chunks=(1, H, W), dtype="uint16")
    for i in range(n):
        a[i] = i + 1
    for name in ("frame_id", "timestamp_ns", "focus_index"):
        g.create_array(name, data=np.arange(n, dtype="int64") + 1, chunks=(4,))


def test_lost_or_corrupt_metadata_chunks_are_defects_never_zeros_nor_an_unwritten_tail(
        tmp_path: Path) -> None:
    path = tmp_path / "r.zarr"
    # the last frame_id chunk corrupt: not a crash tail ("not written"), a defect
    _chunked_metadata(path, 10)
    (path / "frame_id" / "c" / "2").write_bytes(b"xx")
    rep = open_recording(path).report
    assert rep.missing_metadata == [8, 9] and rep.defects == 2 and rep.unwritten == 0
    # the last frame_id chunk deleted from a complete recording: a defect too
    _chunked_metadata(path, 10)
    (path / "frame_id" / "c" / "2").unlink()
    rep = open_recording(path).report
    assert rep.missing_metadata == [8, 9] and rep.duplicates == [], rep.lines()
    # a focus_index chunk deleted: its entries are missing, not focus level 0 (the fill value)
    _chunked_metadata(path, 10)
    (path / "focus_index" / "c" / "1").unlink()
    r = open_recording(path)
    assert r.report.missing_metadata == [4, 5, 6, 7]
    assert [f.header.focus_index for f in r.frames()] == [1, 2, 3, 4, 9, 10]


def test_frames_found_corrupt_while_replaying_are_counted_as_lost(tmp_path: Path) -> None:
    path = tmp_path / "r.zarr"
    _chunked_metadata(path, 6)
    (path / "frames" / "c" / "3" / "0" / "0").write_bytes(b"\x00garbage")
    r = open_recording(path)
    assert len(list(r.frames())) == 5
    summary = r.report.as_dict()
    assert r.report.corrupt == [4] and summary["frames"] == 5 and summary["frames_lost"] == 1
    assert "frames      5 usable" in "\n".join(r.report.lines())
    list(r.frames())  # reading again counts nothing twice
    assert r.report.frames == 5 and r.report.as_dict()["frames_lost"] == 1


def test_a_failing_final_flush_still_marks_the_recording_failed(tmp_path: Path) -> None:
    from sffscan.pipeline.sim_source import simulate_frames

    cfg = small_config()
    writer = RecordingWriter(tmp_path / "rec.zarr", cfg)
    frames = simulate_frames(cfg)
    for _ in range(3):
        writer.write(next(frames))

    def broken_flush() -> None:
        raise OSError(28, "No space left on device")

    writer.flush = broken_flush  # type: ignore[method-assign]
    with pytest.raises(OSError, match="No space"):
        writer.close()
    attrs = zarr.open_group(str(tmp_path / "rec.zarr"), mode="r").attrs.asdict()
    assert attrs["status"] == "failed"
    assert "No space left" in str(attrs["error"])


@pytest.mark.parametrize(("codec", "status"), [("blosc-lz4", "complete"), ("blosc-zstd", "failed"),
                                               ("zstd", "complete"), ("none", "complete")])
def test_direct_chunk_writes_make_the_recording_zarr_makes_byte_for_byte(
        tmp_path: Path, monkeypatch: pytest.MonkeyPatch, codec: str, status: str) -> None:
    """The writer's own chunk writes (zarr_chunks), through the page cache and past it,
    and zarr's setitem: the same files, the same files made durable; arrays grown and
    metadata chunks crossed several times."""
    import json

    from sffscan.pipeline.formats import durable
    from sffscan.pipeline.formats import recording_writer as recorder

    monkeypatch.setattr(recorder, "GROW", 8)
    monkeypatch.setattr(recorder, "META_CHUNK", 8)
    synced: dict[str, set[str]] = {}
    frames = _frames(27, positions=True)
    frames[3] = Frame(frames[3].header, np.zeros((H, W), np.uint16))  # a black frame: kept
    frames[9] = Frame(frames[9].header.model_copy(update={"stage_x_um": None}), frames[9].image)
    n = 23 if status == "failed" else 27
    unbuffered = 0
    for way in ("zarr", "page_cache", "unbuffered"):
        root = tmp_path / f"{way}.zarr"
        done: set[str] = set()
        monkeypatch.setattr(durable, "fsync_path", lambda path, directory=False, done=done,
                            root=root: done.add(str(Path(path).relative_to(root.parent))
                                                .replace(root.name, "<rec>")))
        w = RecordingWriter(root, small_config(), codec=codec, flush_every=5, flush_s=1e9,
                            fsync_s=3600.0, via_zarr=way == "zarr", recording_id="0" * 32,
                            page_cache=way != "unbuffered")
        if w.unbuffered is not None:
            w.unbuffered.min_bytes = 0  # every chunk file (the frames here are small)
        for f in frames[:n]:
            w.write(f)
        if w.unbuffered is not None:
            unbuffered = w.unbuffered.written
        w.close(status=status, error="stopped" if status == "failed" else None)
        synced[way] = done
    by_zarr = tmp_path / "zarr.zarr"
    files = _files_of(by_zarr)
    assert "frames/c.3.0.0" in files and "frame_id/c/2" in files and "headers/c.22.0" in files
    for way in ("page_cache", "unbuffered"):
        direct = tmp_path / f"{way}.zarr"
        assert files == _files_of(direct)
        for name in files:
            a, b = (by_zarr / name).read_bytes(), (direct / name).read_bytes()
            if name == "zarr.json":  # the group's attributes: all equal but the creation time
                a, b = (json.dumps({k: v for k, v in json.loads(x)["attributes"].items()
                                    if k != "created"}).encode() for x in (a, b))
            assert a == b, (way, name)
        assert synced["zarr"] == synced[way]
        assert {f"<rec>/frames/c.{n - 1}.0.0", "<rec>/frame_id/c/2", "<rec>"} <= synced[way]
        r = open_recording(direct)
        assert r.report.frames == n and r.report.defects == 0
    # past the page cache where this file system allows it (ext4, xfs; tmpfs since Linux 6.6)
    assert unbuffered >= (2 * n if _takes_o_direct(tmp_path) else 0)


def _takes_o_direct(folder: Path) -> bool:
    from sffscan.pipeline.formats.unbuffered import UnbufferedFiles

    return UnbufferedFiles(min_bytes=0).write(folder / "o_direct.probe", (b"x",))


def _files_of(folder: Path) -> list[str]:
    return sorted(str(p.relative_to(folder)) for p in folder.rglob("*") if p.is_file())


def test_trimming_at_close_deletes_what_zarr_s_resize_deletes(tmp_path: Path) -> None:
    from sffscan.pipeline.formats.recording_writer import _trim

    g = zarr.open_group(str(tmp_path / "g.zarr"), mode="w")
    arrays = [g.create_array(name="frames", shape=(12, 4, 5), chunks=(1, 4, 5), dtype="uint16",
                             fill_value=0, config={"write_empty_chunks": True}),
              g.create_array(name="meta", shape=(40,), chunks=(8,), dtype="int64", fill_value=-1),
              g.create_array(name="dotted", shape=(12, 4, 5), chunks=(1, 4, 5), dtype="uint16",
                             fill_value=0, config={"write_empty_chunks": True},
                             chunk_key_encoding={"name": "default", "separator": "."})]
    arrays[0][:7] = np.arange(7 * 20, dtype=np.uint16).reshape(7, 4, 5)  # 0..6 stored
    arrays[1][:33] = np.arange(33)  # chunks 0..4 stored
    arrays[2][:7] = arrays[0][:7]
    shutil.copytree(tmp_path / "g.zarr", tmp_path / "copy.zarr")
    copy = zarr.open_group(str(tmp_path / "copy.zarr"), mode="r+")
    for arr, n in zip(arrays, (5, 17, 5), strict=True):
        arr.resize((n, *arr.shape[1:]))  # zarr's own: deletes the chunks outside
        _trim(copy[arr.basename], n)  # type: ignore[arg-type]
    for name in ("frames", "meta", "dotted"):
        ours, theirs = tmp_path / "copy.zarr" / name, tmp_path / "g.zarr" / name
        assert _files_of(ours) == _files_of(theirs)
        assert all((ours / f).read_bytes() == (theirs / f).read_bytes() for f in _files_of(ours))
    assert _files_of(tmp_path / "copy.zarr" / "frames") == [
        *(f"c/{i}/0/0" for i in range(5)), "zarr.json"]
    assert _files_of(tmp_path / "copy.zarr" / "meta") == ["c/0", "c/1", "c/2", "zarr.json"]
    assert _files_of(tmp_path / "copy.zarr" / "dotted") == [
        *(f"c.{i}.0.0" for i in range(5)), "zarr.json"]
