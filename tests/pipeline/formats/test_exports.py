"""Tests of formats.exports (PLY, x3p) and metrology.areal (Sa, Sq, Sz, Ssk, Sku)."""

from __future__ import annotations

import json
import math
import zipfile
from pathlib import Path

import numpy as np
import pytest
import scipy.stats
import x3pio
from sffscan.pipeline.cli.main import main
from sffscan.pipeline.formats.exports import (
    X3P_UNCERTAINTY_ID,
    read_ply,
    read_region,
    read_x3p_uncertainty,
    write_ply,
    write_x3p,
)
from sffscan.pipeline.metrology.areal import areal_parameters, level_surface
from sffscan.pipeline.mosaic.writer import MosaicWriter

PX = 8.5
ORIGIN = (300, 40)


@pytest.fixture()
def mosaic(tmp_path: Path) -> tuple[Path, np.ndarray, np.ndarray]:
    rng = np.random.default_rng(0)
    h = rng.uniform(100.0, 900.0, (30, 40)).astype(np.float32)
    t = rng.uniform(0.0, 1.0, (30, 40)).astype(np.float32)
    h[3, 4] = h[10:12, 20:25] = np.nan
    u = rng.uniform(0.5, 9.0, (30, 40)).astype(np.float32)
    u[5, 6] = np.nan  # a measured height whose uncertainty is not known
    path = tmp_path / "m.zarr"
    w = MosaicWriter(path, origin_px=ORIGIN, shape=h.shape, pixel_um=PX,
                     attrs={"focus_heights_um": [0.0, 500.0, 1000.0],
                            "processing": {"mode": "test"}})
    ok = np.isfinite(h)
    wt = ok.astype(np.float32)
    w.write_region(*ORIGIN, {"height": np.where(ok, h, 0) * wt, "texture": t * wt,
                             "weight": wt, "confidence": wt, "uncertainty": u * wt})
    w.set_status("complete")
    return path, np.where(ok, h, np.nan), np.where(ok, t, np.nan)


def _uncertainty_of(path: Path) -> np.ndarray:
    import zarr

    return np.asarray(zarr.open_group(str(path), mode="r")["uncertainty"])


def _parse_ply(path: Path) -> tuple[list[str], np.ndarray]:
    """Independent minimal reader: header lines, then (n, 6) float64 rows x y z r g b, and
    a 7th column, the uncertainty (µm), when the header declares it."""
    data = path.read_bytes()
    head, body = data.split(b"end_header\n", 1)
    lines = head.decode("ascii").splitlines()
    n = int(next(line for line in lines if line.startswith("element vertex")).split()[-1])
    fields = [("x", "<f4"), ("y", "<f4"), ("z", "<f4"), ("r", "u1"), ("g", "u1"), ("b", "u1")]
    if lines[-1] == "property float uncertainty_um":
        fields.append(("u", "<f4"))
    rec = np.dtype(fields)
    assert len(body) == n * rec.itemsize
    arr = np.frombuffer(body, rec)
    return lines, np.column_stack([arr[k] for k, _ in fields]).astype(np.float64)


def test_ply_export(mosaic: tuple[Path, np.ndarray, np.ndarray], tmp_path: Path) -> None:
    path, h, t = mosaic
    out = tmp_path / "a.ply"
    info = write_ply(out, path, band_rows=7)  # several bands
    lines, v = _parse_ply(out)
    assert lines[:2] == ["ply", "format binary_little_endian 1.0"]
    assert lines[-4:] == ["property uchar red", "property uchar green", "property uchar blue",
                          "property float uncertainty_um"]
    rows, cols = np.nonzero(np.isfinite(h))
    assert info["points"] == rows.size == v.shape[0] and info["no_texture"] == 0
    np.testing.assert_allclose(v[:, 0], (ORIGIN[0] + cols) * PX / 1000, rtol=1e-6)
    np.testing.assert_allclose(v[:, 1], (ORIGIN[1] + rows) * PX / 1000, rtol=1e-6)
    np.testing.assert_allclose(v[:, 2], h[rows, cols] / 1000, rtol=1e-6)
    for c in (3, 4, 5):
        np.testing.assert_array_equal(v[:, c], np.rint(t[rows, cols] * 255))
    u = _uncertainty_of(path)
    np.testing.assert_allclose(v[:, 6], u[rows, cols], rtol=1e-6)  # µm, NaN kept
    assert np.isnan(v[:, 6]).sum() == 1 and any("uncertainty_um in um" in x for x in lines)
    rec, _ = read_ply(out)
    np.testing.assert_array_equal(rec["uncertainty_um"], v[:, 6].astype(np.float32))


def test_exports_of_a_mosaic_without_an_uncertainty(
        mosaic: tuple[Path, np.ndarray, np.ndarray], tmp_path: Path) -> None:
    """A mosaic of format 3 (no uncertainty array): the PLY has no such property and the x3p
    no such file."""
    import shutil

    path, h, _ = mosaic
    shutil.rmtree(path / "uncertainty")
    out = tmp_path / "old.ply"
    write_ply(out, path)
    lines, v = _parse_ply(out)
    assert v.shape == (int(np.isfinite(h).sum()), 6) and lines[-1] == "property uchar blue"
    assert list(read_ply(out)[0].dtype.fields or {})[-1] == "blue"
    assert write_x3p(tmp_path / "old.x3p", path)["uncertainty"] == 0
    assert read_x3p_uncertainty(tmp_path / "old.x3p") is None
    assert read_region(path).uncertainty_um is None


def test_trimesh_loads_the_ply_with_colours(mosaic: tuple[Path, np.ndarray, np.ndarray],
                                            tmp_path: Path) -> None:
    """A third-party reader (trimesh) sees the points, in mm, with the texture as colour."""
    import trimesh

    path, h, t = mosaic
    out = tmp_path / "c.ply"
    write_ply(out, path)
    cloud = trimesh.load(out)
    assert isinstance(cloud, trimesh.PointCloud)
    rows, cols = np.nonzero(np.isfinite(h))
    assert len(cloud.vertices) == rows.size
    np.testing.assert_allclose(cloud.vertices[:, 2], h[rows, cols] / 1000, rtol=1e-6)
    colours = np.asarray(cloud.colors)  # (n, 4) RGBA uint8
    assert colours.shape == (rows.size, 4)
    grey = np.rint(t[rows, cols] * 255)
    for c in range(3):
        np.testing.assert_array_equal(colours[:, c], grey)
    assert len(np.unique(colours[:, 0])) > 100  # really the texture, not a default colour


def test_ply_region(mosaic: tuple[Path, np.ndarray, np.ndarray], tmp_path: Path) -> None:
    path, h, _ = mosaic
    box = (ORIGIN[0] + 5, ORIGIN[1] + 2, ORIGIN[0] + 25, ORIGIN[1] + 12)
    info = write_ply(tmp_path / "r.ply", path, box)
    assert info["points"] == int(np.isfinite(h[2:12, 5:25]).sum())
    _, v = _parse_ply(tmp_path / "r.ply")
    assert v[:, 0].min() == pytest.approx(box[0] * PX / 1000)
    with pytest.raises(ValueError, match="outside the mosaic"):
        write_ply(tmp_path / "x.ply", path, (0, 0, 10, 10))


def test_x3p_export_reads_back(mosaic: tuple[Path, np.ndarray, np.ndarray],
                               tmp_path: Path) -> None:
    path, h, _ = mosaic
    out = tmp_path / "a.x3p"
    info = write_x3p(out, path)
    assert info == {"rows": 30, "cols": 40, "missing": int(np.isnan(h).sum()),
                    "uncertainty": 1}
    with zipfile.ZipFile(out) as archive:  # ISO 25178-72 container: main.xml + binary data
        assert "main.xml" in archive.namelist()
    f = x3pio.read(out)  # checks the MD5 checksums too
    z = f.layers[0].z
    np.testing.assert_array_equal(np.isnan(z), np.isnan(h))
    np.testing.assert_allclose(z[np.isfinite(z)], h[np.isfinite(h)] * 1e-6, rtol=1e-7)
    assert f.header.x.increment == pytest.approx(PX * 1e-6)
    assert f.header.y.increment == pytest.approx(PX * 1e-6)
    np.testing.assert_allclose(f.layers[0].placement.offset,
                               [ORIGIN[0] * PX * 1e-6, ORIGIN[1] * PX * 1e-6, 0.0])
    assert f.metadata is not None
    assert f.metadata.probing_system.type == x3pio.ProbingType.NON_CONTACTING
    assert json.loads(f.metadata.comment or "{}")["processing"] == {"mode": "test"}
    # the uncertainty: a vendor-specific file the standard lets a reader ignore
    assert list(f.extensions) == [X3P_UNCERTAINTY_ID]
    u = read_x3p_uncertainty(out)
    assert u is not None and u.shape == z.shape
    want = _uncertainty_of(path).astype(np.float64) * 1e-6
    np.testing.assert_array_equal(np.isnan(u), np.isnan(want))
    np.testing.assert_allclose(u[np.isfinite(u)], want[np.isfinite(want)], rtol=1e-6)


# ----------------------------------------------------------------------------- areal


def test_areal_known_answer_sinusoid() -> None:
    a, period = 50.0, 64
    x = np.arange(8 * period)
    z = np.tile(a * np.sin(2 * np.pi * x / period), (32, 1)) + 1000.0
    p = areal_parameters(z, level="mean")  # whole periods: the mean is the offset
    assert p.sq_um == pytest.approx(a / math.sqrt(2), rel=1e-3)
    assert p.sa_um == pytest.approx(2 * a / math.pi, rel=1e-3)
    assert p.sz_um == pytest.approx(2 * a, rel=1e-3)
    assert p.ssk == pytest.approx(0.0, abs=1e-3)
    assert p.sku == pytest.approx(1.5, rel=1e-3)


def test_areal_matches_independent_implementation() -> None:
    rng = np.random.default_rng(5)
    yy, xx = np.indices((50, 60))
    z = rng.gamma(2.0, 10.0, (50, 60)) + 0.3 * xx - 0.2 * yy + 400.0  # skewed, tilted
    z[7, 7] = np.nan
    p = areal_parameters(z)
    # independent: plane by numpy.polynomial-free normal equations, moments by fsum / scipy
    ok = np.isfinite(z)
    a = np.column_stack([np.ones(ok.sum()), xx[ok], yy[ok]]).astype(np.float64)
    coef = np.linalg.solve(a.T @ a, a.T @ z[ok])
    r = z[ok] - a @ coef
    n = r.size
    sq = math.sqrt(math.fsum(v * v for v in r) / n)
    assert p.sq_um == pytest.approx(sq, rel=1e-10)
    assert p.sa_um == pytest.approx(math.fsum(abs(v) for v in r) / n, rel=1e-10)
    assert p.sz_um == pytest.approx(float(r.max() - r.min()), rel=1e-10)
    assert p.ssk == pytest.approx(float(scipy.stats.skew(r, bias=True)), rel=1e-8)
    assert p.sku == pytest.approx(float(scipy.stats.kurtosis(r, fisher=False, bias=True)),
                                  rel=1e-8)
    assert p.pixels == n and p.missing == 1
    assert p.ssk > 0.5  # the gamma surface is skewed: the test can tell


def test_areal_levels_and_errors() -> None:
    z = np.arange(12.0).reshape(3, 4)
    np.testing.assert_allclose(level_surface(z, level="none"), z)
    assert abs(float(level_surface(z, level="mean").mean())) < 1e-12
    assert areal_parameters(z).sq_um == pytest.approx(0.0, abs=1e-9)  # exactly a plane
    with pytest.raises(ValueError, match="no finite"):
        areal_parameters(np.full((3, 3), np.nan), level="mean")
    with pytest.raises(ValueError, match="level"):
        areal_parameters(z, level="cubic")


def test_export_command(mosaic: tuple[Path, np.ndarray, np.ndarray], tmp_path: Path,
                        capsys: pytest.CaptureFixture[str]) -> None:
    path, h, _ = mosaic
    assert main(["export", str(path), "--ply", str(tmp_path / "a.ply"), "--x3p",
                 str(tmp_path / "a.x3p"), "--json", str(tmp_path / "p.json")]) == 0
    out = capsys.readouterr().out
    assert "Sa" in out and "Sku" in out
    params = json.loads((tmp_path / "p.json").read_text())
    assert params["sq_um"] == pytest.approx(areal_parameters(h).sq_um)
    assert (tmp_path / "a.ply").is_file() and (tmp_path / "a.x3p").is_file()
    region = read_region(path, (ORIGIN[0], ORIGIN[1], ORIGIN[0] + 10, ORIGIN[1] + 10))
    assert region.height_um.shape == (10, 10)
    assert main(["export", str(path), "--region", "0,0,5,5"]) == 2
    assert main(["export", str(path), "--region", "1,2,3"]) == 2
    assert main(["export", str(tmp_path / "a.ply")]) == 2  # not a mosaic


def test_file_outputs_replace_a_file_only_with_overwrite(
        mosaic: tuple[Path, np.ndarray, np.ndarray], tmp_path: Path,
        capsys: pytest.CaptureFixture[str]) -> None:
    """An export, a comparison's report or a stack's height map written over an existing
    file (a mistyped name: an input image, a calibration) is refused naming the option and
    leaves the file as it was; ``--overwrite`` replaces it."""
    path, _, _ = mosaic
    image = tmp_path / "im_01.png"
    image.write_bytes(b"\x89PNG the user's own image")
    for flag in ("--x3p", "--ply", "--json"):
        assert main(["export", str(path), flag, str(image)]) == 2
        assert f"{flag} {image}: exists; --overwrite replaces it" in capsys.readouterr().err
        assert image.read_bytes() == b"\x89PNG the user's own image"
    assert main(["compare", str(path), str(path), "--json", str(image)]) == 2
    assert "--json" in capsys.readouterr().err
    assert image.read_bytes() == b"\x89PNG the user's own image"
    assert main(["export", str(path), "--x3p", str(image), "--overwrite"]) == 0
    assert zipfile.is_zipfile(image)  # replaced, as asked
    npy = tmp_path / "h.npy"
    npy.write_bytes(b"kept")
    stack = ["stack", str(tmp_path / "missing.png"), "--focus-start", "0", "--focus-step", "1",
             "--pixel-um", "5", "-o", str(tmp_path / "s.zarr")]
    for name in ("h.npy", "h"):  # np.save appends .npy
        assert main([*stack, "--save-npy", str(tmp_path / name)]) == 2
        assert f"--save-npy {npy}: exists" in capsys.readouterr().err  # before the images
    assert npy.read_bytes() == b"kept"


def test_x3p_and_areal_parameters_against_surfalize(tmp_path: Path) -> None:
    """A third-party implementation (surfalize, MIT: its own x3p reader, its own levelling
    and ISO 25178-2 height parameters) reads the exported x3p and gets the same surface,
    scale and Sa, Sq, Sp, Sv, Sz, Ssk, Sku as pipeline.metrology.areal on the mosaic region."""
    from surfalize import Surface  # imported here: about 3 s, for this test only

    rng = np.random.default_rng(5)
    yy, xx = np.indices((50, 60))
    h = (rng.gamma(2.0, 10.0, (50, 60)) + 0.3 * xx - 0.2 * yy + 400.0).astype(np.float32)
    h[7, 7] = np.nan
    h[20:22, 30:35] = np.nan
    path = tmp_path / "g.zarr"
    w = MosaicWriter(path, origin_px=ORIGIN, shape=h.shape, pixel_um=PX,
                     attrs={"focus_heights_um": [0.0, 1000.0]})
    ok = np.isfinite(h)
    wt = ok.astype(np.float32)
    w.write_region(*ORIGIN, {"height": np.where(ok, h, 0) * wt, "texture": wt * 0.5,
                             "weight": wt, "confidence": wt})
    w.set_status("complete")
    write_x3p(tmp_path / "g.x3p", path)

    s = Surface.load(str(tmp_path / "g.x3p"))  # surfalize's reader, µm
    assert s.step_x == pytest.approx(PX) and s.step_y == pytest.approx(PX)
    assert s.data.shape == h.shape
    np.testing.assert_array_equal(np.isnan(s.data), ~ok)
    np.testing.assert_allclose(s.data[ok], h[ok], rtol=1e-6)
    # surfalize refuses NaN: give them a value and mask them (left out of fit and parameters)
    masked = Surface(np.nan_to_num(s.data, nan=0.0), s.step_x, s.step_y, mask=~ok)
    theirs = masked.level().height_parameters()
    ours = areal_parameters(read_region(path).height_um, level="plane")
    assert ours.pixels == int(ok.sum()) and ours.missing == int((~ok).sum())
    for name, value in (("Sa", ours.sa_um), ("Sq", ours.sq_um), ("Sp", ours.sp_um),
                        ("Sv", ours.sv_um), ("Sz", ours.sz_um), ("Ssk", ours.ssk),
                        ("Sku", ours.sku)):
        assert value == pytest.approx(float(theirs[name]), rel=1e-6), name
    assert ours.ssk > 0.5  # skewed: Ssk's sign and size are tested, not just 0 == 0


def test_ply_of_a_mosaic_with_a_non_ascii_name(mosaic: tuple[Path, np.ndarray, np.ndarray],
                                               tmp_path: Path,
                                               monkeypatch: pytest.MonkeyPatch) -> None:
    """The PLY header is ASCII: a mosaic named 'Prüfkörper' is still exported (its name
    escaped in the comment), and a failed export leaves no half-written file."""
    path, h, _ = mosaic
    named = tmp_path / "Prüfkörper.zarr"
    path.rename(named)
    out = tmp_path / "p.ply"
    assert main(["export", str(named), "--ply", str(out)]) == 0
    lines, v = _parse_ply(out)
    assert v.shape[0] == int(np.isfinite(h).sum())
    assert any("Pr\\xfcfk\\xf6rper.zarr" in line for line in lines)
    out.unlink()

    def broken(*args: object, **kwargs: object) -> np.ndarray:
        raise OSError("disk full")

    monkeypatch.setattr("sffscan.pipeline.formats.exports.ply_vertices", broken)
    with pytest.raises(OSError, match="disk full"):
        write_ply(out, named)
    assert not list(tmp_path.glob("*.ply*"))  # no truncated PLY left behind
