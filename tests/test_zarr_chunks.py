"""Direct chunk reads and writes give what zarr itself gives: the same values, the same files."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import zarr
from sffscan.pipeline.formats.zarr_chunks import direct_plan, read_many, write_many
from sffscan.stages.mosaic import mosaic_codecs
from zarr.codecs import Crc32cCodec, GzipCodec


def _pair(tmp_path: Path, compressors: list, fill: float) -> tuple[zarr.Array, zarr.Array]:
    g = zarr.open_group(str(tmp_path / "m.zarr"), mode="w")
    return tuple(g.create_array(name=name, shape=(300, 530), chunks=(64, 64), dtype="float32",
                                fill_value=fill, compressors=compressors)
                 for name in ("by_zarr", "direct"))  # type: ignore[return-value]


def _files(arr: zarr.Array, root: Path) -> dict[str, bytes]:
    folder = root / arr.path
    return {str(p.relative_to(folder)): p.read_bytes() for p in folder.rglob("*")
            if p.is_file() and p.name != "zarr.json"}


def _regions(rng: np.random.Generator, shape: tuple[int, int], n: int):  # noqa: ANN202
    out = [(slice(0, 64), slice(64, 128)),  # one whole chunk
           (slice(256, 300), slice(512, 530)),  # the corner chunk, cut by the array's end
           (slice(10, 200), slice(100, 101))]  # one column over several chunks
    for _ in range(n):
        r0, c0 = rng.integers(0, shape[0] - 1), rng.integers(0, shape[1] - 1)
        r1, c1 = rng.integers(r0 + 1, shape[0] + 1), rng.integers(c0 + 1, shape[1] + 1)
        out.append((slice(int(r0), int(r1)), slice(int(c0), int(c1))))
    return out


@pytest.mark.parametrize("codec", ["blosc-lz4", "zstd", "none"])
@pytest.mark.parametrize("fill", [np.nan, 0.0])
def test_writes_and_reads_equal_zarr_s_values_and_files(tmp_path: Path, codec: str,
                                                        fill: float) -> None:
    by_zarr, direct = _pair(tmp_path, mosaic_codecs(codec), fill)
    assert direct_plan(direct) is not None
    rng = np.random.default_rng(7)
    for k, sel in enumerate(_regions(rng, (300, 530), 12)):
        shape = (sel[0].stop - sel[0].start, sel[1].stop - sel[1].start)
        value = rng.normal(size=shape).astype(np.float32)
        if k % 5 == 4:
            value[:] = fill  # fill values: a chunk they cover whole is deleted, not written
        value[rng.random(shape) < 0.1] = np.nan
        by_zarr[sel] = value
        write_many([(direct, sel, value)])
    np.testing.assert_array_equal(direct[:], by_zarr[:])
    for other in _regions(rng, (300, 530), 3):
        np.testing.assert_array_equal(read_many([(direct, other)])[0], by_zarr[other])
    root = tmp_path / "m.zarr"
    assert _files(direct, root) == _files(by_zarr, root)  # the same chunks, byte for byte
    assert not list(root.rglob("*.partial"))


def test_other_codecs_go_through_zarr(tmp_path: Path) -> None:
    for compressors in ([GzipCodec()], [*mosaic_codecs("blosc-lz4"), Crc32cCodec()]):
        by_zarr, direct = _pair(tmp_path, compressors, np.nan)
        assert direct_plan(direct) is None
        value = np.arange(70 * 90, dtype=np.float32).reshape(70, 90)
        write_many([(direct, (slice(5, 75), slice(60, 150)), value)])
        by_zarr[5:75, 60:150] = value
        np.testing.assert_array_equal(read_many([(direct, (slice(0, 300), slice(0, 530)))])[0],
                                      by_zarr[:])


def test_a_region_of_the_wrong_shape_is_refused_naming_the_array(tmp_path: Path) -> None:
    _, direct = _pair(tmp_path, mosaic_codecs("blosc-lz4"), np.nan)
    with pytest.raises(ValueError, match="direct.*cannot take values of shape"):
        write_many([(direct, (slice(0, 10), slice(0, 10)), np.zeros((10, 11), np.float32))])
