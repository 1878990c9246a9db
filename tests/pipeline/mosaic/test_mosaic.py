"""Mosaic writer: Zarr v3 layout, attributes, blending of overlaps by confidence."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import zarr
from sffscan.pipeline.mosaic.attrs import MosaicAttrs
from sffscan.pipeline.mosaic.stage import MosaicStage
from sffscan.pipeline.mosaic.writer import MosaicWriter
from sffscan.stages.messages import DepthBlock, DepthBlockHeader
from sffscan.stages.mosaic import MIN_WEIGHT, BandGatherer, blend


def _block(x0: int, y0: int, height: np.ndarray, conf: float, pass_index: int) -> DepthBlock:
    rows, cols = height.shape
    hdr = DepthBlockHeader(x0_px=x0, y0_px=y0, width_px=cols, height_px=rows,
                           pass_index=pass_index, complete_columns=cols, incomplete_columns=0)
    return DepthBlock(hdr, height.astype(np.float32), np.full_like(height, 0.5, np.float32),
                      np.full(height.shape, conf, np.float32))


def test_blend_is_the_confidence_weighted_mean() -> None:
    old = {"height": np.array([[np.nan, 10.0]]), "texture": np.array([[np.nan, 0.2]]),
           "confidence": np.array([[0.0, 0.5]]), "weight": np.array([[0.0, 0.5]])}
    new = {"height": np.array([[1.5 * 20.0, 1.5 * 20.0]]), "texture": np.array([[0.3, 0.3]]),
           "confidence": np.array([[1.5, 1.5]]), "weight": np.array([[1.5, 1.5]])}
    out = blend(old, new)
    assert out["height"][0, 0] == pytest.approx(20.0)
    assert out["height"][0, 1] == pytest.approx((10 * 0.5 + 20 * 1.5) / 2.0)
    assert out["weight"][0, 1] == pytest.approx(2.0)
    assert out["confidence"][0, 1] == pytest.approx(1.5)


def _blend_float64(old: dict[str, np.ndarray], new: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
    """The blend as it was written before issue 28's float32 change: float64 arithmetic,
    rounded to float32 once at the end."""
    w_old, w_new = old["weight"].astype(np.float64), new["weight"].astype(np.float64)
    w = w_old + w_new
    out = {}
    with np.errstate(invalid="ignore", divide="ignore"):
        for key in ("height", "texture", "uncertainty"):
            acc = (np.where(w_old > 0, old[key], 0.0) * w_old + new[key]) / w
            out[key] = np.where(w > 0, acc, np.nan).astype(np.float32)
    out["weight"] = w.astype(np.float32)
    return out


def test_float32_blend_is_the_float64_one_for_a_first_contribution_and_near_it_after() -> None:
    # a pixel's first contribution and a pixel the new one does not weigh are bit-identical
    # to the float64 blend; an overlap within float32 round-off
    rng = np.random.default_rng(7)
    shape = (64, 96)
    seen = rng.random(shape) < 0.5
    w_old = np.where(seen, rng.uniform(1e-3, 1.0, shape), 0.0).astype(np.float32)
    old = {k: np.where(seen, rng.uniform(0.0, s, shape), np.nan).astype(np.float32)
           for k, s in (("height", 800.0), ("texture", 1.0), ("uncertainty", 5.0))}
    old |= {"weight": w_old, "confidence": w_old.copy()}
    w_new = np.where(rng.random(shape) < 0.8, rng.uniform(1e-3, 1.0, shape), 0.0).astype(
        np.float32)
    new = {k: (rng.uniform(0.0, s, shape).astype(np.float32) * w_new)
           for k, s in (("height", 800.0), ("texture", 1.0), ("uncertainty", 5.0))}
    new |= {"weight": w_new, "confidence": w_new.copy()}
    got, ref = blend(old, new), _blend_float64(old, new)
    for key in ("height", "texture", "uncertainty", "weight"):
        assert got[key].dtype == np.float32
        first = ~seen
        assert np.array_equal(got[key][first], ref[key][first], equal_nan=True), key
        both = seen & (w_new > 0)  # a weighted mean of two values: float32 round-off of
        # the larger of them
        scale = np.maximum(np.abs(old[key]), np.abs(new[key] / np.where(w_new > 0, w_new, 1)))
        assert np.all(np.abs(got[key] - ref[key])[both]
                      <= 4 * np.finfo(np.float32).eps * scale[both]), key
        assert np.array_equal(got[key][seen & (w_new == 0)], ref[key][seen & (w_new == 0)],
                              equal_nan=True), key


def test_two_passes_blend_and_attributes(tmp_path: Path) -> None:
    path = tmp_path / "m.zarr"
    writer = MosaicWriter(path, origin_px=(-10, -5), shape=(40, 64), pixel_um=8.5,
                          chunk_px=16, attrs={"processing": {"depth_method": "spc"}})
    stage = MosaicStage(writer)
    rows = 20
    a = np.full((rows, 8), 100.0)
    b = np.full((rows, 8), 200.0)
    for x0 in range(0, 48, 8):  # pass 0 at rows 0..19, confidence 0.2
        list(stage.process(_block(x0, 0, a, 0.2, 0)))
    for x0 in range(40, -8, -8):  # pass 1 at rows 10..29, moving -x, confidence 0.6
        list(stage.process(_block(x0, 10, b, 0.6, 1)))
    list(stage.finish())
    stage.close(failed=False)
    g = zarr.open_group(str(path), mode="r")
    attrs = MosaicAttrs.model_validate(g.attrs.asdict())
    assert attrs.status == "complete" and attrs.origin_px == (-10, -5)
    assert attrs.units["height"] == "µm"
    h = np.asarray(g["height"])
    assert h.shape == (40, 64) and g["height"].chunks == (16, 16)
    r = lambda y: y + 5  # noqa: E731 - world row -> array row
    c = lambda x: x + 10  # noqa: E731
    assert h[r(5), c(3)] == pytest.approx(100.0)  # pass 0 alone
    assert h[r(25), c(3)] == pytest.approx(200.0)  # pass 1 alone
    assert h[r(15), c(3)] == pytest.approx((100 * 0.2 + 200 * 0.6) / 0.8)  # overlap
    assert np.isnan(h[r(33), c(3)]) and np.isnan(h[r(5), c(50)])  # never measured
    assert np.asarray(g["weight"])[r(15), c(3)] == pytest.approx(0.8)


def test_failed_run_keeps_what_was_complete(tmp_path: Path) -> None:
    path = tmp_path / "m.zarr"
    stage = MosaicStage(MosaicWriter(path, origin_px=(0, 0), shape=(16, 64), pixel_um=8.5,
                                     chunk_px=16))
    list(stage.process(_block(0, 0, np.full((16, 8), 7.0), 0.5, 0)))
    stage.close(failed=True)
    g = zarr.open_group(str(path), mode="r")
    assert g.attrs["status"] == "failed"
    assert np.asarray(g["height"])[3, 3] == pytest.approx(7.0)


def test_existing_mosaic_is_not_overwritten_and_origin_is_enforced(tmp_path: Path) -> None:
    path = tmp_path / "m.zarr"
    writer = MosaicWriter(path, origin_px=(0, 0), shape=(16, 16), pixel_um=8.5, chunk_px=16)
    with pytest.raises(FileExistsError, match="m.zarr"):
        MosaicWriter(path, origin_px=(0, 0), shape=(16, 16), pixel_um=8.5)
    with pytest.raises(ValueError, match="before the mosaic origin"):
        writer.write_region(-4, 0, {k: np.zeros((2, 2)) for k in
                                    ("height", "texture", "weight", "confidence")})
    writer.write_region(10, 12, {"height": np.ones((8, 8)), "texture": np.ones((8, 8)),
                                 "weight": np.ones((8, 8)), "confidence": np.ones((8, 8))})
    assert zarr.open_group(str(path), mode="r")["height"].shape == (20, 18)  # grew


def test_failing_write_still_sets_the_status(tmp_path: Path) -> None:
    path = tmp_path / "m.zarr"
    writer = MosaicWriter(path, origin_px=(0, 0), shape=(16, 64), pixel_um=8.5, chunk_px=16)
    stage = MosaicStage(writer)
    list(stage.process(_block(0, 0, np.full((16, 8), 7.0), 0.5, 0)))
    list(stage.process(_block(40, 0, np.full((16, 8), 9.0), 0.5, 0)))  # flushes the first band
    real = writer.write_region

    def broken(x0: int, y0: int, new: dict) -> None:
        raise OSError("disk full")

    writer.write_region = broken  # type: ignore[method-assign]
    with pytest.raises(OSError, match="disk full"):
        stage.close(failed=False)
    writer.write_region = real  # type: ignore[method-assign]
    g = zarr.open_group(str(path), mode="r")
    assert g.attrs["status"] == "failed"
    assert np.asarray(g["height"])[3, 3] == pytest.approx(7.0)  # written before: kept


def test_band_gatherer_sums_blocks_into_bands_the_motion_leaves() -> None:
    """The mosaic's band gathering is pure computation (no writer): weighted sums per
    chunk-wide band, a band handed over once a block lands beyond it."""
    gather = BandGatherer(chunk_px=16, origin_x_px=-4)
    h = np.full((4, 8), 10.0)
    h[0, 0] = np.nan  # invalid: weight 0
    assert gather.add(_block(-4, 2, h, 0.5, 0)) == []  # band 0: world x -4 .. 11
    assert gather.add(_block(8, 2, np.full((4, 8), 20.0), 0.0, 0)) == []  # bands 0 and 1
    assert gather.add(_block(20, 2, np.full((4, 8), 30.0), 0.25, 0)) == [0]  # left band 0
    band = gather.take(0)
    assert band is not None and (band.x0, band.y0) == (-4, 2)
    sums = band.sums()
    assert sums["weight"][0, 0] == 0.0 and sums["weight"][1, 0] == pytest.approx(0.5)
    assert sums["height"][1, 0] == pytest.approx(10.0 * 0.5)
    assert sums["weight"][1, 12] == pytest.approx(MIN_WEIGHT)  # confidence 0: the floor
    assert sums["height"][1, 12] == pytest.approx(20.0 * MIN_WEIGHT)
    assert np.isnan(sums["uncertainty"][1, 0])  # the blocks carried no uncertainty
    assert gather.open_bands() == [1]
    empty = BandGatherer(chunk_px=16, origin_x_px=0)
    empty.add(_block(0, 0, np.full((4, 8), np.nan), 0.5, 0))
    assert empty.take(0) is None  # nothing valid landed: nothing to write


def test_journal_is_written_directly_and_zarr_reads_it(tmp_path: Path) -> None:
    """The writer's attribute writes bypass zarr (MosaicWriter.update_attributes): zarr, and
    a reader opening the group afresh, see each one at once; the document keeps every key
    zarr wrote, and a consolidated copy is dropped, not left stale."""
    path = tmp_path / "m.zarr"
    writer = MosaicWriter(path, origin_px=(0, 0), shape=(16, 64), pixel_um=8.5, chunk_px=16)
    before = json.loads((path / "zarr.json").read_text())
    writer.write_region(0, 0, {"height": np.full((16, 16), 5.0), "texture": np.full((16, 16), 0.5),
                               "weight": np.ones((16, 16)), "confidence": np.ones((16, 16))})
    after = zarr.open_group(str(path), mode="r", use_consolidated=False).attrs.asdict()
    assert after["writes_done"] == 1 and after["writing"] is None
    assert after["status"] == "writing" and writer.attributes == after
    doc = json.loads((path / "zarr.json").read_text())
    assert {k: v for k, v in doc.items() if k != "attributes"} == \
        {k: v for k, v in before.items() if k != "attributes"}
    writer.update_attributes({"recording": {"path": "r.zarr", "frames": [1, 2]}})
    rec: Any = zarr.open_group(str(path), mode="r").attrs["recording"]
    assert rec["frames"] == [1, 2]
    writer.set_status("complete")
    g = zarr.open_group(str(path), mode="r")  # consolidated by set_status
    rec = g.attrs["recording"]
    assert g.attrs["status"] == "complete" and rec["path"] == "r.zarr"
    assert "consolidated_metadata" in json.loads((path / "zarr.json").read_text())
    writer.update_attributes({"resumed": 1})  # a later write drops the stale copy
    doc = json.loads((path / "zarr.json").read_text())
    assert "consolidated_metadata" not in doc and doc["attributes"]["resumed"] == 1
    assert not list(path.glob("*.partial"))
