"""The height uncertainty in the mosaic: blended like the height (the weighted mean of the
contributions' sigmas), NaN where a contribution had none (never 0)."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np
import pytest
import zarr
from sffscan.pipeline.mosaic.layout import UNITS
from sffscan.pipeline.mosaic.stage import MosaicStage
from sffscan.pipeline.mosaic.writer import MosaicWriter
from sffscan.stages.messages import DepthBlock, DepthBlockHeader
from sffscan.stages.mosaic import blend


def _block(x0: int, height: float, conf: float, unc: float | None, *, pass_index: int = 0,
           width: int = 8) -> DepthBlock:
    hdr = DepthBlockHeader(x0_px=x0, y0_px=0, width_px=width, height_px=16,
                           pass_index=pass_index, complete_columns=width,
                           incomplete_columns=0)
    one = np.ones((16, width), np.float32)
    return DepthBlock(hdr, height * one, 0.5 * one, conf * one,
                      None if unc is None else unc * one)


def test_mosaic_blends_the_uncertainty_and_keeps_unknown_unknown(tmp_path: Path) -> None:
    path = tmp_path / "m.zarr"
    stage = MosaicStage(MosaicWriter(path, origin_px=(0, 0), shape=(16, 64), pixel_um=8.5,
                                     chunk_px=16))
    list(stage.process(_block(0, 10.0, 0.5, 2.0)))  # columns 0..7, sigma 2 µm
    list(stage.process(_block(4, 20.0, 1.0, 4.0, pass_index=1)))  # 4..11, overlap 4..7
    list(stage.process(_block(32, 30.0, 1.0, None, pass_index=2)))  # no uncertainty
    stage.close(failed=False)
    g = zarr.open_group(str(path), mode="r")
    u, h = np.asarray(g["uncertainty"]), np.asarray(g["height"])
    assert g["uncertainty"].attrs["units"] == UNITS["uncertainty"]
    assert u[3, 1] == pytest.approx(2.0)
    assert u[3, 5] == pytest.approx((0.5 * 2.0 + 1.0 * 4.0) / 1.5, rel=1e-5)  # like height
    assert h[3, 5] == pytest.approx((0.5 * 10.0 + 1.0 * 20.0) / 1.5, rel=1e-5)
    assert u[3, 9] == pytest.approx(4.0)
    assert np.isfinite(h[:, 32:40]).all() and np.isnan(u[:, 32:40]).all()  # unknown
    assert np.isnan(u[:, 16:32]).all() and np.isnan(h[:, 16:32]).all()  # nothing measured


def test_blend_without_an_uncertainty_in_either_input() -> None:
    """Writers of the four arrays only (stop-and-go, old callers): their contribution's
    sigma is unknown; a region without the array blends as before."""
    one = np.ones((2, 2))
    old = {"height": np.full((2, 2), np.nan), "texture": np.full((2, 2), np.nan),
           "confidence": 0 * one, "weight": 0 * one}
    new = {"height": 5 * one, "texture": 0.5 * one, "confidence": one, "weight": one}
    assert "uncertainty" not in blend(old, new)
    out = blend({**old, "uncertainty": np.full((2, 2), np.nan)}, new)
    assert np.isnan(out["uncertainty"]).all() and (out["height"] == 5).all()
    out = blend({**old, "uncertainty": np.full((2, 2), np.nan)},
                {**new, "uncertainty": 3 * one})
    np.testing.assert_array_equal(out["uncertainty"], 3.0)


def test_the_stack_path_computes_and_stores_the_uncertainty(tmp_path: Path) -> None:
    """reconstruct_field (``sffscan stack``) gives the height an uncertainty, stitched into
    the mosaic; on a family seed the fit never saw, most raw errors lie within 2 sigma."""
    from sffscan.pipeline.stopgo import stitch_field
    from sffscan.stages.fields.stationary import StackSettings, reconstruct_field
    from sffscan.stages.sim.families import family_stack

    s = family_stack("lens-gauss", 12)
    r = reconstruct_field(s.images, focus_heights_um=s.focus_um, settings=StackSettings(),
                          max_value=1.0)
    assert r.uncertainty_um is not None
    finite = np.isfinite(r.height_um)
    np.testing.assert_array_equal(np.isfinite(r.uncertainty_um), finite)
    inner = (slice(4, -4), slice(4, -4))
    err = np.abs(r.raw_height_um - s.truth_um)[inner]
    share = float(np.mean(err <= 2 * r.uncertainty_um[inner]))
    print(f"lens-gauss seed 12: {share:.3f} of |raw error| <= 2 sigma")
    assert 0.85 <= share <= 1.0
    writer = MosaicWriter(tmp_path / "f.zarr", origin_px=(0, 0), shape=s.truth_um.shape,
                          pixel_um=8.5, chunk_px=32)
    stitch_field(writer, r, x0_px=0, y0_px=0, feather=np.ones(s.truth_um.shape))
    u = np.asarray(zarr.open_group(str(tmp_path / "f.zarr"), mode="r")["uncertainty"])
    np.testing.assert_allclose(u[finite], r.uncertainty_um[finite], rtol=1e-5)


def test_a_mosaic_written_before_the_uncertainty_array_still_resumes(tmp_path: Path) -> None:
    """A mosaic of an earlier version has no ``uncertainty`` array: reopening it for a resume
    looked the array up and failed ("mosaic has no array 'uncertainty'"). It resumes with the
    arrays it has, and no uncertainty array appears half-filled."""
    from sffscan.pipeline.mosaic.layout import present_arrays
    from sffscan.pipeline.mosaic.ngff import level_path
    from sffscan.pipeline.mosaic.reader import tile_states

    path = tmp_path / "m.zarr"
    writer = MosaicWriter(path, origin_px=(0, 0), shape=(16, 64), pixel_um=8.5, chunk_px=16)
    list(MosaicStage(writer).process(_block(0, 10.0, 0.5, 2.0)))  # then the writer stops
    g = zarr.open_group(str(path), mode="r+")
    attrs: Any = g.attrs.asdict()
    levels = len(attrs["ome"]["multiscales"][0]["datasets"])
    del g["uncertainty"]
    for k in range(1, levels):
        del g[level_path("uncertainty", k)]
    assert present_arrays(g) == ("height", "texture", "confidence", "weight")
    resumed = MosaicWriter.reopen(path, scan_config={})
    stage = MosaicStage(resumed)
    list(stage.process(_block(0, 10.0, 0.5, 2.0)))  # written already: skipped
    list(stage.process(_block(16, 20.0, 1.0, 4.0, pass_index=1)))
    stage.close(failed=False)
    g = zarr.open_group(str(path), mode="r")
    h = np.asarray(g["height"])
    assert h[3, 2] == pytest.approx(10.0) and h[3, 20] == pytest.approx(20.0)
    assert "uncertainty" not in g and g.attrs["status"] == "complete"
    tile_states(path)  # the tile account reads the arrays the mosaic has
