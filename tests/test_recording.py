"""Recording format: the writer's layout, the reader's validation, defects reported by id."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import zarr

from pipeline.config import ScanConfig
from pipeline.messages import Frame, FrameHeader
from pipeline.recording import RecordingAttrs, RecordingError, open_recording
from pipeline.schema_gen import SCHEMAS
from stages.recorder import RecordingWriter
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
    frames = _frames(40) + [Frame(h.header.model_copy(update={"frame_id": 40 + i,
                                                              "stage_x_um": None}), h.image)
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
