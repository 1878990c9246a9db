"""The mosaic is an OME-Zarr (NGFF 0.5) image: the ``ome-zarr`` reader and the
``ome-zarr-models`` package (in their own environment) open and validate a scan's mosaic;
``sffscan.open_mosaic`` opens every level lazily with µm coordinates, and so does plain
``xarray.open_zarr`` (coordinate arrays, consolidated metadata: format version 3); version-1
and version-2 mosaics still read."""

from __future__ import annotations

import json
import subprocess
import warnings
from pathlib import Path

import dask.array as da
import numpy as np
import pytest
import xarray as xr
import zarr
from sffscan.pipeline.mosaic.layout import ARRAYS
from sffscan.pipeline.mosaic.ngff import level_path

from sffscan import open_mosaic
from tests.scan_helpers import scan, small_config
from tests.venvs import make_venv

ROOT = Path(__file__).resolve().parents[3]
NGFF_VENV = ROOT / ".venv-ngff"
REQUIREMENTS = ROOT / "tests" / "ngff-requirements.txt"


@pytest.fixture(scope="session")
def ngff_python() -> Path:
    """Python of the NGFF tools' own environment, created on first use (seconds, uv)."""
    python = NGFF_VENV / "bin" / "python"
    probe = [str(python), "-c", "import ome_zarr, ome_zarr_models"]
    if python.exists() and subprocess.run(probe, capture_output=True).returncode == 0:
        return python
    done = make_venv(NGFF_VENV, "-r", str(REQUIREMENTS), timeout=600)
    if done.returncode != 0:
        pytest.fail(f"cannot build the NGFF tools' environment: {done.stderr[-2000:]}")
    return python


@pytest.fixture(scope="module")
def mosaic(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A small scan's mosaic at the default optics' pixel size, 8.5 µm."""
    out = tmp_path_factory.mktemp("ngff") / "m.zarr"
    cfg = small_config(optics={"pixel_um": 8.5},
                       motion={"x_start_mm": 1.0, "x_end_mm": 5.0})
    scan(cfg, out)
    return out


def test_ome_zarr_reader_and_ngff_models_open_the_mosaic(mosaic: Path,
                                                         ngff_python: Path) -> None:
    done = subprocess.run([str(ngff_python), str(ROOT / "tests" / "ngff_check.py"), str(mosaic)],
                          capture_output=True, text=True, timeout=300)
    assert done.returncode == 0, done.stderr[-3000:]
    seen = json.loads(done.stdout)
    g = zarr.open_group(str(mosaic), mode="r")
    ox, oy = (int(v) for v in g.attrs["origin_px"])  # type: ignore[union-attr, arg-type]
    assert seen["nodes"] == 1 and seen["image_nodes"] == 1
    assert seen["levels"] >= 4
    assert [a["unit"] for a in seen["axes"]] == ["micrometer", "micrometer"]
    assert [a["name"] for a in seen["axes"]] == ["y", "x"]
    scale, translation = seen["transforms"][0]
    assert scale == {"type": "scale", "scale": [8.5, 8.5]}
    assert translation["translation"] == pytest.approx([oy * 8.5, ox * 8.5])
    for k, (s, t) in enumerate(seen["transforms"]):
        assert s["scale"] == [8.5 * 2 ** k] * 2
        half = (2 ** k - 1) / 2 * 8.5  # a level-k pixel is centred on its 2^k block
        assert t["translation"] == pytest.approx([oy * 8.5 + half, ox * 8.5 + half])
    h = np.asarray(g["height"])  # type: ignore[index]
    assert seen["shapes"][0] == list(h.shape)
    assert seen["shapes"][3] == [-(-h.shape[0] // 8), -(-h.shape[1] // 8)]
    # the reader reads the pixel values we wrote
    want = np.nanmean(np.asarray(g[level_path("height", 1)]))  # type: ignore[index]
    assert seen["level1_nanmean"] == pytest.approx(float(want), rel=1e-5)
    assert seen["model_multiscales"] == list(ARRAYS)
    assert set(seen["model_levels"]) == {seen["levels"]}


def test_open_mosaic_is_lazy_with_micrometre_coordinates(mosaic: Path) -> None:
    ds = open_mosaic(mosaic)
    g = zarr.open_group(str(mosaic), mode="r")
    ox, oy = (int(v) for v in g.attrs["origin_px"])  # type: ignore[union-attr, arg-type]
    assert set(ds.data_vars) == set(ARRAYS)
    assert all(isinstance(ds[n].data, da.Array) for n in ARRAYS)
    assert ds["height"].attrs["units"] == "µm" and ds["x"].attrs["units"] == "µm"
    assert ds["x"].values[0] == pytest.approx(ox * 8.5)
    assert ds["y"].values[1] - ds["y"].values[0] == pytest.approx(8.5)
    h = np.asarray(g["height"])  # type: ignore[index]
    assert np.array_equal(ds["height"].values, h, equal_nan=True)
    # level 2: 4 x 4 blocks, centred on them
    l2 = open_mosaic(mosaic, level=2)
    assert l2["height"].shape == (-(-h.shape[0] // 4), -(-h.shape[1] // 4))
    assert l2["x"].values[0] == pytest.approx(ox * 8.5 + 1.5 * 8.5)
    assert l2.attrs["pixel_um_level"] == pytest.approx(34.0)
    x = float(l2["x"].values[3])  # the level-2 value at a µm position: its block's mean
    block = ds["height"].sel(x=slice(x - 17, x + 17)).isel(y=slice(0, 4)).values
    assert block.shape == (4, 4)
    if np.isfinite(block).any():
        assert float(l2["height"].values[0, 3]) == pytest.approx(float(np.nanmean(block)),
                                                                 rel=1e-5)
    with pytest.raises(ValueError, match="no pyramid level 9"):
        open_mosaic(mosaic, level=9)


def test_lazy_open_of_a_large_mosaic_reads_nothing(tmp_path: Path) -> None:
    """10^9 pixels open lazily: only metadata is read (nothing is written either)."""
    from sffscan.pipeline.mosaic.writer import MosaicWriter

    path = tmp_path / "big.zarr"
    w = MosaicWriter(path, origin_px=(0, 0), shape=(31_623, 31_623), pixel_um=8.5)
    w.set_status("complete", valid_pixels=0, blocks=0)
    ds = open_mosaic(path, level=0)
    assert ds["height"].size >= 10 ** 9
    assert ds["height"].data.chunksize == (256, 256)
    # no chunk of the arrays was written (only the small 1-D coordinate arrays y, x)
    written = {c.parent.name for c in path.rglob("c")}
    assert written == {"y", "x"}


def test_version_1_mosaics_still_read(mosaic: Path, tmp_path: Path) -> None:
    """A mosaic in the first format (no pyramid, no 'ome') opens as before."""
    old = tmp_path / "v1.zarr"
    src = zarr.open_group(str(mosaic), mode="r")
    dst = zarr.open_group(str(old), mode="w")
    for name in ARRAYS:
        a = src[name]
        dst.create_array(name=name, data=np.asarray(a), chunks=a.chunks)  # type: ignore[union-attr]
    attrs = src.attrs.asdict()
    attrs.pop("ome")
    attrs["format_version"] = 1
    dst.update_attributes(attrs)
    ds = open_mosaic(old)
    assert ds.attrs["format_version"] == 1
    assert np.array_equal(ds["height"].values, np.asarray(src["height"]), equal_nan=True)
    with pytest.raises(ValueError, match="no pyramid level 1"):
        open_mosaic(old, level=1)


def test_xarray_open_zarr_gives_micrometre_coordinates_at_every_level(mosaic: Path) -> None:
    """Plain xarray (no sffscan): every level has the coordinates ``open_mosaic`` computes,
    the metadata is consolidated (no warning, one read), and ``open_groups`` opens the whole
    hierarchy (``open_datatree`` cannot: NGFF 0.5 names every level's dimensions y, x)."""
    root = json.loads((mosaic / "zarr.json").read_text())
    assert "consolidated_metadata" in root
    levels = len(root["attributes"]["ome"]["multiscales"][0]["datasets"])
    for k in range(levels):
        group = None if k == 0 else f"pyramid/{k}"
        with warnings.catch_warnings():
            warnings.simplefilter("error")  # xarray warns when metadata is not consolidated
            ds = xr.open_zarr(mosaic, group=group)
        ours = open_mosaic(mosaic, level=k)
        assert set(ds.data_vars) == set(ARRAYS)
        assert ds["x"].attrs["units"] == "µm"
        np.testing.assert_array_equal(ds["x"].values, ours["x"].values)
        np.testing.assert_array_equal(ds["y"].values, ours["y"].values)
        assert ds["height"].dims == ("y", "x")
        # selecting by µm in plain xarray gives the same pixels as sffscan's reader
        x = float(ours["x"].values[len(ours["x"]) // 2])
        np.testing.assert_array_equal(ds["height"].sel(x=x).values,
                                      ours["height"].sel(x=x).values)
    groups = xr.open_groups(mosaic, engine="zarr")
    assert {"/", "/pyramid/1", f"/pyramid/{levels - 1}"} <= set(groups)
    assert groups["/pyramid/1"]["x"].values[0] == pytest.approx(
        float(open_mosaic(mosaic, level=1)["x"].values[0]))


def test_a_resume_drops_consolidated_metadata_and_the_close_renews_it(tmp_path: Path) -> None:
    """Readers see the arrays grow during a resume (no stale consolidated shapes); the
    coordinate arrays grow with them; the final status consolidates the new shapes."""
    from sffscan.pipeline.mosaic.writer import MosaicWriter

    path = tmp_path / "r.zarr"
    w = MosaicWriter(path, origin_px=(10, 20), shape=(16, 16), pixel_um=2.0, chunk_px=8,
                     levels=2)
    ones = {k: np.ones((8, 8)) for k in ("height", "texture", "confidence", "weight")}
    w.write_region(10, 20, ones)
    w.set_status("failed")
    assert "consolidated_metadata" in json.loads((path / "zarr.json").read_text())
    w = MosaicWriter.reopen(path, scan_config={})
    assert "consolidated_metadata" not in json.loads((path / "zarr.json").read_text())
    w.write_region(10, 20, ones)  # the replay repeats the write already done (skipped)
    w.write_region(10, 20 + 30, ones)  # beyond the last row: the arrays grow to 38 rows
    live = zarr.open_group(str(path), mode="r")  # as any reader opens it
    assert live["height"].shape == (38, 16)  # type: ignore[union-attr]
    w.set_status("complete")
    ds = xr.open_zarr(path)
    assert ds["height"].shape == (38, 16)
    np.testing.assert_allclose(ds["y"].values, (20 + np.arange(38)) * 2.0)
    np.testing.assert_allclose(ds["x"].values, (10 + np.arange(16)) * 2.0)
    top = xr.open_zarr(path, group="pyramid/1")
    np.testing.assert_allclose(top["y"].values, (20 + 0.5 + 2 * np.arange(19)) * 2.0)
    assert ds.attrs["format_version"] == 3


def test_version_2_mosaics_still_read_and_resume(tmp_path: Path) -> None:
    """A version-2 mosaic (no coordinate arrays, not consolidated) reads and resumes as it
    is: no coordinate arrays are added, nothing is consolidated."""
    from sffscan.pipeline.mosaic.writer import MosaicWriter

    path = tmp_path / "v2.zarr"
    w = MosaicWriter(path, origin_px=(0, 0), shape=(16, 16), pixel_um=2.0, chunk_px=8,
                     levels=2)
    ones = {k: np.ones((8, 8)) for k in ("height", "texture", "confidence", "weight")}
    w.write_region(0, 0, ones)
    w.set_status("failed")
    g = zarr.open_group(str(path), mode="r+", use_consolidated=False)
    for name in ("y", "x", "pyramid/1/y", "pyramid/1/x"):
        del g[name]
    g.update_attributes({"format_version": 2})  # also drops the consolidated metadata
    w = MosaicWriter.reopen(path, scan_config={})
    w.write_region(0, 0, ones)  # done already (skipped)
    w.write_region(0, 20, ones)
    w.set_status("complete")
    assert "consolidated_metadata" not in json.loads((path / "zarr.json").read_text())
    ds = open_mosaic(path, level=1)
    assert ds.attrs["format_version"] == 2 and ds["height"].shape == (14, 8)
    assert ds["y"].values[1] - ds["y"].values[0] == pytest.approx(4.0)
    assert "y" not in zarr.open_group(str(path), mode="r")


def test_open_mosaic_reads_the_arrays_the_mosaic_has(mosaic: Path,
                                                     monkeypatch: pytest.MonkeyPatch) -> None:
    """A mosaic written before an array was added to the format (here: a fifth array such
    as an uncertainty) still opens, with the arrays it has."""
    import sffscan.pipeline.mosaic.reader as mosaic_module

    monkeypatch.setattr(mosaic_module, "ARRAYS", (*ARRAYS, "uncertainty"))
    ds = open_mosaic(mosaic, level=1)
    assert set(ds.data_vars) == set(ARRAYS)


def test_consolidation_is_quiet_beside_the_writers_reserve(tmp_path: Path) -> None:
    """The writer's disk-full reserve (a plain file in the folder) is not a Zarr node:
    consolidating beside it warns nothing (warnings are errors in the tests)."""
    from sffscan.pipeline.formats.durable import RESERVE_NAME
    from sffscan.pipeline.mosaic.ngff import consolidate
    from sffscan.pipeline.mosaic.writer import MosaicWriter

    path = tmp_path / "q.zarr"
    MosaicWriter(path, origin_px=(0, 0), shape=(16, 16), pixel_um=2.0, chunk_px=8, levels=2)
    assert (path / RESERVE_NAME).exists()
    consolidate(path)
    assert "consolidated_metadata" in json.loads((path / "zarr.json").read_text())
