"""Tests of sffscan.pipeline.metrology.compare and ``sffscan compare``."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest
import scipy.ndimage
from sffscan.pipeline.cli.main import main
from sffscan.pipeline.metrology.compare import (
    CompareReport,
    HeightMap,
    compare_height_maps,
    fit_plane,
    overlap_by_origin,
    read_height_map,
)
from sffscan.pipeline.mosaic.writer import MosaicWriter


def _surface(shape: tuple[int, int] = (80, 90), seed: int = 0) -> np.ndarray:
    rng = np.random.default_rng(seed)
    return scipy.ndimage.gaussian_filter(rng.normal(size=shape), 3) * 500.0 + 1000.0


def test_metrics_against_direct_formulas() -> None:
    ref = _surface()
    est = ref + np.random.default_rng(1).normal(0, 20.0, ref.shape) + 7.0
    est[5:9, 5:9] = np.nan
    r = compare_height_maps(est, ref, max_depth_um=2000.0, bins=16)
    ok = np.isfinite(est)
    d = (est - ref)[ok]
    rmse = math.sqrt(float(np.mean(d**2)))
    assert r.rmse_um == pytest.approx(rmse, rel=1e-9)
    assert r.corr == pytest.approx(float(np.corrcoef(est[ok], ref[ok])[0, 1]), rel=1e-9)
    assert r.psnr_db == pytest.approx(20 * math.log10(2000.0) - 10 * math.log10(rmse**2))
    assert r.mean_error_um == pytest.approx(float(d.mean()))
    assert r.pixels == ok.sum() and r.coverage == pytest.approx(ok.mean())
    h = r.histogram
    assert sum(h.counts) + h.below + h.above == r.pixels
    assert len(h.edges_um) == 17 and h.edges_um[0] == -h.edges_um[-1]


def test_identical_maps() -> None:
    ref = _surface()
    r = compare_height_maps(ref, ref, max_depth_um=1.0)
    assert r.rmse_um == 0.0 and r.corr == pytest.approx(1.0) and r.psnr_db is None  # infinite


def test_align_offset_and_plane() -> None:
    ref = _surface()
    yy, xx = np.indices(ref.shape)
    tilted = ref + 30.0 + 0.5 * xx - 0.25 * yy
    assert fit_plane(tilted - ref) == pytest.approx((30.0, 0.5, -0.25))
    none = compare_height_maps(tilted, ref, max_depth_um=2000.0)
    off = compare_height_maps(tilted, ref, max_depth_um=2000.0, align="offset")
    plane = compare_height_maps(tilted, ref, max_depth_um=2000.0, align="plane")
    assert none.rmse_um is not None and off.rmse_um is not None and plane.rmse_um is not None
    assert off.rmse_um < none.rmse_um
    assert plane.rmse_um < 1e-9
    assert plane.plane_um == pytest.approx((30.0, 0.5, -0.25))


def test_align_shift_recovers_a_known_shift() -> None:
    big = _surface((120, 130), seed=4)
    ref = big[10:100, 10:110]
    est = big[10 + 2:100 + 2, 10 + 3:110 + 3] + 12.0  # est[p] = ref[p + (3, 2)]
    r = compare_height_maps(est, ref, max_depth_um=2000.0, align="shift")
    assert r.shift_px == (-3, -2)
    assert r.rmse_um is not None and r.rmse_um < 1e-9
    assert r.pixels == (90 - 2) * (100 - 3)


def test_bad_input() -> None:
    with pytest.raises(ValueError, match="same shape"):
        compare_height_maps(np.zeros((3, 3)), np.zeros((3, 4)), max_depth_um=1.0)
    with pytest.raises(ValueError, match="align"):
        compare_height_maps(np.zeros((3, 3)), np.zeros((3, 3)), max_depth_um=1.0, align="x")
    with pytest.raises(ValueError, match="max_depth"):
        compare_height_maps(np.zeros((3, 3)), np.zeros((3, 3)), max_depth_um=0.0)


def test_overlap_by_origin() -> None:
    a = HeightMap(np.arange(20.0).reshape(4, 5), "a", 1.0, (10, 20))
    b = HeightMap(np.arange(30.0).reshape(5, 6), "b", 1.0, (12, 18))
    ea, eb, origin = overlap_by_origin(a, b)
    assert origin == (12, 20) and ea.shape == eb.shape == (3, 3)
    np.testing.assert_array_equal(ea, a.height_um[0:3, 2:5])
    np.testing.assert_array_equal(eb, b.height_um[2:5, 0:3])
    with pytest.raises(ValueError, match="do not overlap"):
        overlap_by_origin(a, HeightMap(np.zeros((2, 2)), "c", 1.0, (100, 100)))


def _mosaic(path: Path, height: np.ndarray, origin: tuple[int, int],
            uncertainty: np.ndarray | None = None) -> None:
    w = MosaicWriter(path, origin_px=origin, shape=height.shape, pixel_um=8.5,
                     attrs={"focus_heights_um": [0.0, 1000.0, 2000.0]})
    one = np.ones(height.shape, np.float32)
    arrays = {"height": height, "texture": one * 0.5, "weight": one, "confidence": one}
    if uncertainty is not None:
        arrays["uncertainty"] = uncertainty
    w.write_region(origin[0], origin[1], arrays)
    w.set_status("complete")


def test_the_estimate_s_uncertainty_is_scored_against_the_reference() -> None:
    """``within_2sigma``: the share of the compared pixels with a finite sigma whose error
    is at most 2 sigma, the sigma moved with the estimate by a shift; None without one."""
    ref = _surface((40, 50), seed=2)
    err = np.zeros(ref.shape)
    err[:, :25] = 3.0  # left half 3 µm off, right half exact
    sigma = np.full(ref.shape, 1.0)
    sigma[:5] = np.nan  # unknown: not rated
    r = compare_height_maps(ref + err, ref, max_depth_um=2000.0, sigma=sigma)
    assert (r.sigma_pixels, r.within_2sigma) == (35 * 50, 0.5)
    assert compare_height_maps(ref, ref, max_depth_um=2000.0).within_2sigma is None
    big = _surface((60, 70), seed=4)
    est = big[2:42, 3:53]  # est[p] = ref[p + (3, 2)]
    bigsig = np.where(np.arange(70)[None, :] < 30, 1.0, np.nan) * np.ones((60, 1))
    shifted = compare_height_maps(est, big[:40, :50], max_depth_um=2000.0, align="shift",
                                  sigma=bigsig[2:42, 3:53])
    assert shifted.shift_px == (-3, -2)
    assert shifted.sigma_pixels == (40 - 2) * (30 - 3) and shifted.within_2sigma == 1.0
    with pytest.raises(ValueError, match="sigma shape"):
        compare_height_maps(ref, ref, max_depth_um=2000.0, sigma=sigma[1:])


def test_compare_command(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    ref = _surface((60, 70))
    _mosaic(tmp_path / "a.zarr", ref[:, :50], (100, 200))  # world x 100..150
    _mosaic(tmp_path / "b.zarr", ref[:, 20:] + 5.0, (120, 200))  # world x 120..170
    np.save(tmp_path / "r.npy", ref)
    assert main(["compare", str(tmp_path / "b.zarr"), str(tmp_path / "a.zarr"),
                 "--json", str(tmp_path / "c.json")]) == 0
    r = CompareReport.model_validate_json((tmp_path / "c.json").read_text())
    assert r.pixels == 60 * 30  # the world overlap x 120..150
    assert r.rmse_um == pytest.approx(5.0) and r.max_depth_um == 2000.0
    out = capsys.readouterr().out
    assert "RMSE" in out and "within 2 sigma" not in out  # no uncertainty in these mosaics
    assert r.within_2sigma is None
    # a mosaic with an uncertainty: scored on the world overlap, the sigma cut with it
    sig = np.full((60, 50), 10.0, np.float32)
    sig[:, 20:30] = 1.0  # world x 140..150: 2 sigma = 2 µm < the 5 µm offset
    _mosaic(tmp_path / "c.zarr", ref[:, 20:70] + 5.0, (120, 200), uncertainty=sig)
    assert main(["compare", str(tmp_path / "c.zarr"), str(tmp_path / "a.zarr"),
                 "--json", str(tmp_path / "d.json"), "--overwrite"]) == 0
    r = CompareReport.model_validate_json((tmp_path / "d.json").read_text())
    assert (r.pixels, r.sigma_pixels) == (60 * 30, 60 * 30)
    assert r.within_2sigma == pytest.approx(20 / 30)
    assert "within 2 sigma 66.7 % of 1800 px" in capsys.readouterr().out
    assert main(["compare", str(tmp_path / "a.zarr"), str(tmp_path / "r.npy")]) == 2  # shapes
    assert main(["compare", str(tmp_path / "r.npy"), str(tmp_path / "missing.npy")]) == 2
    capsys.readouterr()
    for bad in ("0", "nan", "inf"):  # 0 was taken for 'not given' (exit 0)
        assert main(["compare", str(tmp_path / "b.zarr"), str(tmp_path / "a.zarr"),
                     "--max-depth-um", bad]) == 2
        assert "--max-depth-um must be a finite number > 0" in capsys.readouterr().err


def test_region_is_in_world_px_when_only_one_map_is_placed(tmp_path: Path) -> None:
    """A mosaic compared with an unplaced array (.npy of the same shape): ``--region`` is in
    the mosaic's world pixels, as documented, not in array pixels."""
    ref = _surface((60, 70))
    est = ref.copy()
    est[10:20, 30:40] += 100.0  # world x 130..140, y 210..220 with the origin (100, 200)
    _mosaic(tmp_path / "e.zarr", est.astype(np.float32), (100, 200))
    np.save(tmp_path / "r.npy", ref)
    json_path = tmp_path / "c.json"
    for est_path, ref_path in (("e.zarr", "r.npy"), ("r.npy", "e.zarr")):
        assert main(["compare", str(tmp_path / est_path), str(tmp_path / ref_path),
                     "--region", "130,210,140,220", "--json", str(json_path), "--overwrite"]) == 0
        r = CompareReport.model_validate_json(json_path.read_text())
        assert r.pixels == 100
        assert r.rmse_um == pytest.approx(100.0, rel=1e-5)


def test_an_8_bit_photograph_is_not_taken_for_heights_in_um(tmp_path: Path) -> None:
    """An 8-bit grey image compared as if it held µm gave an RMSE of 154,599 µm and exit 0
    (issue 26, item 6): refused, naming the file and its type."""
    import tifffile

    rng = np.random.default_rng(0)
    photo = rng.integers(0, 256, size=(32, 32), dtype=np.uint8)
    tifffile.imwrite(tmp_path / "photo.tif", photo)
    np.save(tmp_path / "ref.npy", rng.normal(size=(32, 32)))
    with pytest.raises(ValueError, match=r"photo\.tif: an 8-bit array \(uint8\)"):
        read_height_map(tmp_path / "photo.tif")
    assert main(["compare", str(tmp_path / "photo.tif"), str(tmp_path / "ref.npy")]) == 2


def test_region_in_mm_scores_the_same_box_as_in_world_px(
        tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """``--region`` of compare and export in mm (issue 26, item 10): the mosaics' 8.5 µm
    pixels give the world px box that covers it; an array without a pixel size refuses mm."""
    ref = _surface((60, 70))
    _mosaic(tmp_path / "a.zarr", ref, (0, 0))
    _mosaic(tmp_path / "b.zarr", ref + 1.0, (0, 0))
    a, b = str(tmp_path / "a.zarr"), str(tmp_path / "b.zarr")
    capsys.readouterr()
    assert main(["compare", a, b, "--region", "10,5,40,30"]) == 0
    in_px = capsys.readouterr().out
    # 0.085 mm = 10 px, 42.5 µm = 5 px, 0.34 mm = 40 px, 255 µm = 30 px
    assert main(["compare", a, b, "--region", "0.085mm,42.5um,0.34mm,255µm"]) == 0
    assert capsys.readouterr().out == in_px
    assert main(["export", a, "--region", "0.085mm,42.5um,0.34mm,255um",
                 "--x3p", str(tmp_path / "r.x3p")]) == 0
    assert "25x30 surface" in capsys.readouterr().out  # rows 5..30, columns 10..40
    np.save(tmp_path / "r.npy", ref)
    assert main(["compare", str(tmp_path / "r.npy"), str(tmp_path / "r.npy"),
                 "--region", "0,0,1mm,1mm"]) == 2
    assert "needs the pixel size" in capsys.readouterr().err
