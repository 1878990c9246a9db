"""Direct chunk reads and writes give what zarr itself gives: the same values, the same files."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np
import pytest
import zarr
from sffscan.pipeline.formats.recording_writer import frame_codecs
from sffscan.pipeline.formats.zarr_chunks import (
    ChunkChecksumError,
    Plans,
    direct_plan,
    read_into,
    read_many,
    write_many,
)
from sffscan.pipeline.mosaic.layout import mosaic_codecs
from zarr.codecs import Crc32cCodec, GzipCodec

#: name -> (shape, chunks, dtype, fill): the mosaic's tiles (chunks cut by the array's end),
#: the recorder's frames (one chunk per frame), header rows and per-frame metadata
LAYOUTS: dict[str, tuple[tuple[int, ...], tuple[int, ...], str, Any]] = {
    "tiles": ((300, 530), (64, 64), "float32", np.nan),
    "frames": ((5, 24, 40), (1, 24, 40), "uint16", 0),
    "headers": ((9, 6), (1, 6), "int64", -1),
    "meta": ((700,), (256,), "float64", np.nan),
    "blocks": ((7, 30, 41), (3, 16, 16), "int32", -1),
}
CODECS = {"mosaic-blosc-lz4": mosaic_codecs("blosc-lz4"), "blosc-lz4": frame_codecs("blosc-lz4"),
          "blosc-zstd": frame_codecs("blosc-zstd"), "zstd": frame_codecs("zstd"), "none": []}


def _pair(tmp_path: Path, layout: str, compressors: list, *, write_empty: bool = False,
          fill: Any = None, separator: str = "/") -> tuple[zarr.Array, zarr.Array]:
    shape, chunks, dtype, default_fill = LAYOUTS[layout]
    g = zarr.open_group(str(tmp_path / "m.zarr"), mode="a")
    return tuple(g.create_array(name=name, shape=shape, chunks=chunks, dtype=dtype,
                                fill_value=default_fill if fill is None else fill,
                                compressors=compressors,
                                chunk_key_encoding={"name": "default", "separator": separator},
                                config={"write_empty_chunks": write_empty})
                 for name in ("by_zarr", "direct"))  # type: ignore[return-value]


def _files(arr: zarr.Array, root: Path) -> dict[str, bytes]:
    folder = root / arr.path
    return {str(p.relative_to(folder)): p.read_bytes() for p in folder.rglob("*")
            if p.is_file() and p.name != "zarr.json"}


def _selections(rng: np.random.Generator, shape: tuple[int, ...], chunks: tuple[int, ...],
                n: int) -> list[tuple]:
    last = tuple(slice((s - 1) // c * c, s) for s, c in zip(shape, chunks, strict=True))
    out: list[tuple] = [tuple(slice(0, c) for c in chunks),  # the first chunk, whole
                        last,  # the last chunk, cut by the array's end where it is
                        (shape[0] - 1,)]  # the last index of the first axis, the rest whole
    for _ in range(n):
        sel: list[Any] = []
        for s in shape:
            if s > 1 and rng.random() < 0.25:
                sel.append(int(rng.integers(-s, s)))  # an integer drops its axis
            else:
                a = int(rng.integers(0, s))
                sel.append(slice(a, int(rng.integers(a + 1, s + 1))))
        out.append(tuple(sel))
    return out


def _values(rng: np.random.Generator, shape: tuple[int, ...], dtype: str, fill: Any,
            k: int) -> np.ndarray:
    if np.dtype(dtype).kind == "f":
        value = rng.normal(size=shape).astype(dtype)
        value[rng.random(shape) < 0.1] = np.nan
    else:
        value = rng.integers(0, 1000, shape).astype(dtype)
    if k % 4 == 3:
        value[...] = fill  # fill values: whole chunks of them are kept or deleted by config
    return value


@pytest.mark.parametrize("crc", [False, True], ids=["plain", "crc32c"])
@pytest.mark.parametrize("codec", list(CODECS))
@pytest.mark.parametrize("layout", list(LAYOUTS))
def test_writes_and_reads_equal_zarr_s_values_and_files(tmp_path: Path, layout: str,
                                                        codec: str, crc: bool) -> None:
    _compare_with_zarr(tmp_path, layout, codec, crc, "/")


@pytest.mark.parametrize("codec", ["blosc-lz4", "none"])
@pytest.mark.parametrize("layout", list(LAYOUTS))
def test_dot_separated_chunk_keys_equal_zarr_s_values_and_files(tmp_path: Path, layout: str,
                                                                codec: str) -> None:
    """The chunk key encoding of recording format 3 (``c.i.j``): the same files as zarr's."""
    _compare_with_zarr(tmp_path, layout, codec, True, ".")
    folder = tmp_path / "m.zarr" / "direct"
    assert not [p for p in folder.iterdir() if p.is_dir()]  # every chunk in the one folder
    ndim = len(LAYOUTS[layout][0])
    assert (folder / ".".join(["c"] + ["0"] * ndim)).is_file()


def _compare_with_zarr(tmp_path: Path, layout: str, codec: str, crc: bool,
                       separator: str) -> None:
    shape, chunks, dtype, fill = LAYOUTS[layout]
    rng = np.random.default_rng(len(layout) * 31 + len(codec) + crc)
    write_empty = layout in ("frames", "headers") or (crc and layout != "tiles")
    compressors = [*CODECS[codec], *([Crc32cCodec()] if crc else [])]
    by_zarr, direct = _pair(tmp_path, layout, compressors, write_empty=write_empty,
                            separator=separator)
    plan = direct_plan(direct)
    assert plan is not None and plan.crc is crc and plan.write_empty is write_empty
    for k, sel in enumerate(_selections(rng, shape, chunks, 10)):
        value = _values(rng, np.empty(shape)[sel].shape, dtype, fill, k)
        by_zarr[sel] = value
        write_many([(direct, sel, value)])
    np.testing.assert_array_equal(direct[:], by_zarr[:])
    for sel in _selections(rng, shape, chunks, 4):
        np.testing.assert_array_equal(read_many([(direct, sel)])[0], by_zarr[sel])
    root = tmp_path / "m.zarr"
    assert _files(direct, root) == _files(by_zarr, root)  # the same chunks, byte for byte
    assert not list(root.rglob("*.partial"))


@pytest.mark.parametrize("write_empty", [False, True])
def test_a_chunk_of_fill_values_is_kept_or_deleted_as_the_array_s_config_says(
        tmp_path: Path, write_empty: bool) -> None:
    _, direct = _pair(tmp_path, "frames", [*frame_codecs("blosc-lz4"), Crc32cCodec()],
                      write_empty=write_empty)
    write_many([(direct, 1, np.ones((24, 40), np.uint16))])
    write_many([(direct, 1, np.zeros((24, 40), np.uint16))])  # a black frame over it
    chunk = tmp_path / "m.zarr" / "direct" / "c" / "1" / "0" / "0"
    assert chunk.exists() is write_empty
    np.testing.assert_array_equal(read_many([(direct, 1)])[0], 0)


@pytest.mark.parametrize("damage", ["flip", "truncate"])
def test_a_corrupt_chunk_is_an_error_naming_its_file(tmp_path: Path, damage: str) -> None:
    by_zarr, direct = _pair(tmp_path, "meta", [*frame_codecs("zstd"), Crc32cCodec()])
    write_many([(direct, slice(0, 700), np.arange(700.0))])
    chunk = tmp_path / "m.zarr" / "direct" / "c" / "1"
    raw = bytearray(chunk.read_bytes())
    if damage == "flip":
        raw[len(raw) // 2] ^= 0x10
    chunk.write_bytes(bytes(raw) if damage == "flip" else bytes(raw[:3]))
    name = f"{chunk}: stored and computed CRC-32C do not match"
    with pytest.raises(ChunkChecksumError, match=name):
        read_many([(direct, slice(200, 300))])
    with pytest.raises(ChunkChecksumError, match=name):  # a partial write reads it first
        write_many([(direct, slice(300, 301), np.zeros(1))])
    np.testing.assert_array_equal(read_many([(direct, slice(0, 256))])[0], np.arange(256.0))
    (tmp_path / "m.zarr" / "by_zarr" / "c").mkdir(parents=True)
    (tmp_path / "m.zarr" / "by_zarr" / "c" / "1").write_bytes(chunk.read_bytes())
    with pytest.raises(ValueError, match="checksum"):  # zarr refuses it as well
        by_zarr[200:300]


@pytest.mark.parametrize("codec", list(CODECS))
@pytest.mark.parametrize("layout", ["frames", "tiles", "blocks"])
def test_read_into_gives_read_many_s_values_whole_chunks_decoded_in_place(
        tmp_path: Path, layout: str, codec: str) -> None:
    """read_into writes a region into the caller's array: the values read_many gives (a
    chunk never written reads as the fill value), for whole chunks decoded straight into
    it, for other regions copied; a C-contiguous array of the wrong shape or dtype is
    refused naming the array."""
    shape, chunks, dtype, fill = LAYOUTS[layout]
    _, direct = _pair(tmp_path, layout, [*CODECS[codec], Crc32cCodec()])
    rng = np.random.default_rng(3)
    write_many([(direct, tuple(slice(0, s) for s in shape),
                 _values(rng, shape, dtype, fill, 0))])
    # a chunk left unwritten: the last one (deleted as all fill if it was)
    last = tuple(slice((s - 1) // c * c, min(((s - 1) // c + 1) * c, s))
                 for s, c in zip(shape, chunks, strict=True))
    write_many([(direct, last, np.full([x.stop - x.start for x in last], fill, dtype))])
    plans = Plans()
    for sel in [*_selections(rng, shape, chunks, 12), last]:
        want = read_many([(direct, sel)])[0]
        out = np.full(want.shape, 7, dtype)
        assert read_into(direct, sel, out, plans=plans) is out
        np.testing.assert_array_equal(out, want)
    with pytest.raises(ValueError, match="direct"):
        read_into(direct, (0,), np.empty((1, 2), dtype))


def test_read_into_refuses_a_corrupt_or_truncated_chunk_naming_its_file(
        tmp_path: Path) -> None:
    _, direct = _pair(tmp_path, "frames", [*frame_codecs("blosc-lz4"), Crc32cCodec()])
    write_many([(direct, slice(0, 5), np.arange(5 * 24 * 40, dtype="uint16").reshape(5, 24, 40))])
    chunk = tmp_path / "m.zarr" / "direct" / "c" / "2" / "0" / "0"
    raw = bytearray(chunk.read_bytes())
    raw[len(raw) // 2] ^= 0x10
    chunk.write_bytes(bytes(raw))
    out = np.empty((24, 40), "uint16")
    with pytest.raises(ChunkChecksumError, match=f"{chunk}: stored and computed"):
        read_into(direct, 2, out)
    # without a checksum a truncated chunk fails in the decoder, named
    _, plain = _pair(tmp_path / "b", "frames", frame_codecs("blosc-lz4"))
    write_many([(plain, slice(0, 5), np.zeros((5, 24, 40), "uint16") + 3)])
    part = tmp_path / "b" / "m.zarr" / "direct" / "c" / "1" / "0" / "0"
    part.write_bytes(part.read_bytes()[:-7])
    with pytest.raises(ValueError, match=str(part)):
        read_into(plain, 1, out)
    np.testing.assert_array_equal(read_into(plain, 0, out), 3)


def test_other_codecs_and_orders_go_through_zarr(tmp_path: Path) -> None:
    for k, compressors in enumerate([[GzipCodec()], [Crc32cCodec(), *mosaic_codecs("zstd")],
                                     [*mosaic_codecs("zstd"), *mosaic_codecs("blosc-lz4")]]):
        g = zarr.open_group(str(tmp_path / f"m{k}.zarr"), mode="w")
        direct = g.create_array(name="a", shape=(300, 530), chunks=(64, 64), dtype="float32",
                                fill_value=np.nan, compressors=compressors)
        assert direct_plan(direct) is None
        value = np.arange(70 * 90, dtype=np.float32).reshape(70, 90)
        write_many([(direct, (slice(5, 75), slice(60, 150)), value)])
        np.testing.assert_array_equal(read_many([(direct, (slice(5, 75), slice(60, 150)))])[0],
                                      value)


def test_bad_selections_and_values_are_refused_naming_the_array(tmp_path: Path) -> None:
    _, direct = _pair(tmp_path, "frames", frame_codecs("none"))
    with pytest.raises(ValueError, match="direct.*cannot take values of shape"):
        write_many([(direct, (0, slice(0, 10)), np.zeros((10, 11), np.uint16))])
    with pytest.raises(IndexError, match="direct.*out of bounds for axis 0"):
        write_many([(direct, 5, np.zeros((24, 40), np.uint16))])
    with pytest.raises(IndexError, match="direct.*only step-1"):
        read_many([(direct, slice(0, 5, 2))])


def test_the_direct_path_uses_zarr_s_public_api_only() -> None:
    """zarr 3.2 to 3.4 moved or removed the private names (``zarr.core.chunk_grids.
    RegularChunkGrid``...) this module once imported, which broke every mosaic and recording
    read and write: no import of a private zarr module or name."""
    import ast

    from sffscan.pipeline.formats import zarr_chunks

    tree = ast.parse(Path(zarr_chunks.__file__).read_text())
    private = []
    for node in ast.walk(tree):
        if isinstance(node, ast.ImportFrom) and (node.module or "").startswith("zarr"):
            names = [node.module or "", *(a.name for a in node.names)]
        elif isinstance(node, ast.Import):
            names = [a.name for a in node.names if a.name.startswith("zarr")]
        else:
            continue
        private += [n for n in names if n.startswith("zarr.core") or any(
            part.startswith("_") for part in n.split("."))]
    assert not private, private


def test_direct_chunks_need_none_of_zarr_s_internal_classes(tmp_path: Path,
                                                            monkeypatch: pytest.MonkeyPatch
                                                            ) -> None:
    """As on zarr 3.2+: the internal chunk grid, key encoding and metadata classes gone,
    the direct path still plans, writes zarr's files and reads them."""
    import zarr.core.chunk_grids
    import zarr.core.chunk_key_encodings
    import zarr.core.metadata

    by_zarr, direct = _pair(tmp_path, "frames", [*frame_codecs("blosc-lz4"), Crc32cCodec()],
                            write_empty=True, separator=".")
    for module, name in ((zarr.core.chunk_grids, "RegularChunkGrid"),
                         (zarr.core.chunk_key_encodings, "DefaultChunkKeyEncoding"),
                         (zarr.core.metadata, "ArrayV3Metadata")):
        monkeypatch.delattr(module, name)
    plan = direct_plan(direct)
    assert plan is not None and plan.crc and plan.chunks == (1, 24, 40)
    value = np.arange(2 * 24 * 40, dtype=np.uint16).reshape(2, 24, 40)
    write_many([(direct, slice(1, 3), value)])
    got = read_many([(direct, slice(0, 5))])[0]
    monkeypatch.undo()  # zarr's own indexing needs them
    by_zarr[1:3] = value
    np.testing.assert_array_equal(got, by_zarr[:])
    root = tmp_path / "m.zarr"
    assert _files(direct, root) == _files(by_zarr, root)


def test_a_plans_cache_works_out_each_array_once_and_keeps_it_through_a_resize(
        tmp_path: Path) -> None:
    """Plans.of: one plan per array object (resized in place, it keeps it and writes past
    its old end as zarr does); another object gets its own; reads and writes through the
    cache give what zarr gives."""
    by_zarr, direct = _pair(tmp_path, "tiles", mosaic_codecs("blosc-lz4"))
    plans = Plans()
    first = plans.of(direct)
    assert first is not None and plans.of(direct) is first
    for arr in (by_zarr, direct):
        arr.resize((340, 530))
    assert plans.of(direct) is first
    value = np.arange(40 * 530, dtype=np.float32).reshape(40, 530)
    by_zarr[300:340] = value
    write_many([(direct, (slice(300, 340), slice(0, 530)), value)], plans=plans)
    np.testing.assert_array_equal(read_many([(direct, (slice(280, 340),))], plans=plans)[0],
                                  np.asarray(by_zarr[280:340]))
    again = zarr.open_array(str(tmp_path / "m.zarr" / "direct"), mode="r+")
    other = plans.of(again)
    assert other is not None and other is not first
    assert (other.folder, other.chunks, other.dtype) == (first.folder, first.chunks, first.dtype)
