"""Reading a focus stack's image files: natural order, orientation tags, colour to luma,
and the README's `stack` example run as written."""

from __future__ import annotations

import os
import re
import shutil
import subprocess
import sys
from pathlib import Path

import cv2
import numpy as np
import pytest
import scipy.io
import tifffile
import zarr
from PIL import Image, ImageOps
from sffscan.pipeline.cli.main import main
from sffscan.stages.fields.image_io import (
    apply_orientation,
    natural_order,
    read_image,
    read_orientation,
)
from sffscan.stages.fields.stack_io import read_image_stack

ROOT = Path(__file__).resolve().parents[3]


def _names(paths: list[Path]) -> list[str]:
    return [p.name for p in paths]


def test_natural_order_and_when_it_is_ambiguous() -> None:
    glob = sorted(f"d/image_{i}.tif" for i in range(1, 13))  # what a shell glob gives
    assert glob[:3] == ["d/image_1.tif", "d/image_10.tif", "d/image_11.tif"]
    ordered, why = natural_order(glob)
    assert _names(ordered) == [f"image_{i}.tif" for i in range(1, 13)] and why is None
    ordered, why = natural_order(["im_02.tif", "im_10.tif", "im_01.tif"])
    assert _names(ordered) == ["im_01.tif", "im_02.tif", "im_10.tif"] and why is None
    _, why = natural_order(["im_1.tif", "im_01.tif", "im_2.tif"])
    assert why is not None and "zero padding" in why
    _, why = natural_order(["im_1.tif", "img_2.tif", "im_3.tif"])
    assert why is not None and "pattern" in why
    _, why = natural_order(["a_1_2.tif", "a_2_1.tif", "a_3_3.tif"])
    assert why is not None and "2 numbers change" in why
    _, why = natural_order(["near.tif", "middle.tif", "far.tif"])
    assert why is not None and "no number" in why
    # a constant number (a camera id) does not make the order ambiguous
    ordered, why = natural_order(["cam2_10.png", "cam2_9.png", "cam2_11.png"])
    assert _names(ordered) == ["cam2_9.png", "cam2_10.png", "cam2_11.png"] and why is None


@pytest.fixture()
def pertuz_unpadded(pertuz_dir: Path, tmp_path: Path) -> tuple[list[str], np.ndarray]:
    """pertuz-simu02 copied as image_1.tif .. image_30.tif, listed as a shell glob lists
    them, and the focus table in µm."""
    d = tmp_path / "unpadded"
    d.mkdir()
    for i in range(1, 31):
        shutil.copy(pertuz_dir / f"im_{i:02d}.tif", d / f"image_{i}.tif")
    im = scipy.io.loadmat(pertuz_dir / "imdata.mat", squeeze_me=True,
                          struct_as_record=False)["imdata"]
    return sorted(str(p) for p in d.glob("image_*.tif")), np.asarray(im.focus) * 1e6


def _height(path: Path) -> np.ndarray:
    return np.asarray(zarr.open_group(str(path), mode="r")["height"])


def test_stack_from_an_unpadded_glob_runs_in_focus_order(
        pertuz_unpadded: tuple[list[str], np.ndarray], pertuz_dir: Path, tmp_path: Path,
        capsys: pytest.CaptureFixture[str]) -> None:
    glob, focus_um = pertuz_unpadded
    focus = tmp_path / "focus_um.txt"
    np.savetxt(focus, focus_um)
    common = ["--focus-file", str(focus), "--pixel-um", "1", "--filter-size", "1"]
    assert main(["stack", *glob, *common, "-o", str(tmp_path / "glob.zarr")]) == 0
    err = capsys.readouterr().err
    assert "natural order" in err and "image_1.tif, image_2.tif, ... image_30.tif" in err
    assert "reordered" in err and "ambiguous" not in err
    padded = [str(pertuz_dir / f"im_{i:02d}.tif") for i in range(1, 31)]
    assert main(["stack", *padded, *common, "-o", str(tmp_path / "ref.zarr")]) == 0
    capsys.readouterr()
    np.testing.assert_array_equal(_height(tmp_path / "glob.zarr"), _height(tmp_path / "ref.zarr"))
    # --keep-order takes the glob's order: another (wrong) result
    assert main(["stack", *glob, *common, "--keep-order", "-o", str(tmp_path / "kept.zarr")]) == 0
    assert not np.array_equal(_height(tmp_path / "kept.zarr"), _height(tmp_path / "ref.zarr"),
                              equal_nan=True)


def test_stack_warns_when_the_order_is_ambiguous(pertuz_dir: Path, tmp_path: Path,
                                                 capsys: pytest.CaptureFixture[str]) -> None:
    names = ["im_1.tif", "im_01.tif", "im_2.tif"]
    for i, name in enumerate(names, start=1):
        shutil.copy(pertuz_dir / f"im_{i:02d}.tif", tmp_path / name)
    assert main(["stack", *(str(tmp_path / n) for n in names), "--focus-start", "0",
                 "--focus-step", "1", "--pixel-um", "1", "--filter-size", "1",
                 "-o", str(tmp_path / "a.zarr")]) == 0
    err = capsys.readouterr().err
    assert "WARNING" in err and "ambiguous" in err and "zero padding" in err


def _exif_png(path: Path, image: np.ndarray, orientation: int) -> None:
    exif = Image.Exif()
    exif[274] = orientation
    Image.fromarray(image).save(path, exif=exif)


@pytest.mark.parametrize("orientation", range(1, 9))
def test_orientation_as_pillow_turns_it(orientation: int, tmp_path: Path) -> None:
    """Every EXIF orientation, against Pillow's ``exif_transpose`` (third party)."""
    rng = np.random.default_rng(orientation)
    stored = rng.integers(0, 256, (5, 7), dtype=np.uint8)  # not square: 5..8 swap axes
    path = tmp_path / f"o{orientation}.png"
    _exif_png(path, stored, orientation)
    assert read_orientation(path) == orientation
    with Image.open(path) as im:
        want = np.asarray(ImageOps.exif_transpose(im))
    got = read_image(path)
    assert got.shape == want.shape and np.array_equal(got, want)
    assert np.array_equal(apply_orientation(stored, orientation), want)


def test_tiff_orientation_tag_is_honoured(tmp_path: Path) -> None:
    """A 16-bit TIFF stored sideways with Orientation = 6 (rotate 90° clockwise to show)."""
    rng = np.random.default_rng(3)
    upright = rng.integers(0, 1024, (4, 6, 9), dtype=np.uint16)  # 4 images of 6 x 9
    paths = []
    for i, img in enumerate(upright):
        p = tmp_path / f"s_{i}.tif"
        stored = np.rot90(img, k=1)  # what the camera wrote: 9 x 6
        tifffile.imwrite(p, stored, extratags=[(274, "H", 1, 6, True)])
        paths.append(p)
    assert read_orientation(paths[0]) == 6
    stack = read_image_stack(paths)
    assert stack.shape == (4, 6, 9) and stack.dtype == np.uint16
    np.testing.assert_array_equal(stack, upright)


def _colour(tmp_path: Path) -> tuple[list[Path], np.ndarray]:
    rng = np.random.default_rng(4)
    rgb = rng.integers(0, 256, (3, 12, 10, 3), dtype=np.uint8)
    paths = []
    for i, img in enumerate(rgb):
        p = tmp_path / f"c_{i}.png"
        cv2.imwrite(str(p), np.ascontiguousarray(img[..., ::-1]))  # OpenCV writes BGR
        paths.append(p)
    return paths, rgb


def test_grey_is_bt601_luma(tmp_path: Path) -> None:
    paths, rgb = _colour(tmp_path)
    with pytest.raises(ValueError, match=r"c_0\.png: colour image \(3 channels\).*--grey"):
        read_image(paths[0])
    got = read_image_stack(paths, grey=True)
    want = 0.299 * rgb[..., 0] + 0.587 * rgb[..., 1] + 0.114 * rgb[..., 2]  # ITU-R BT.601
    assert got.dtype == np.uint8 and got.shape == (3, 12, 10)
    assert np.abs(got.astype(np.float64) - want).max() <= 0.5 + 1e-6  # rounded
    # a colour TIFF (RGB order) gives the same luma
    tifffile.imwrite(tmp_path / "c.tif", rgb[0], photometric="rgb")
    np.testing.assert_array_equal(read_image(tmp_path / "c.tif", grey=True), got[0])


def test_stack_command_refuses_colour_without_grey(tmp_path: Path,
                                                   capsys: pytest.CaptureFixture[str]) -> None:
    paths, _ = _colour(tmp_path)
    base = ["stack", *map(str, paths), "--focus-start", "0", "--focus-step", "1",
            "--pixel-um", "1", "--filter-size", "1"]
    assert main([*base, "-o", str(tmp_path / "a.zarr")]) == 2
    err = capsys.readouterr().err
    assert "c_0.png: colour image" in err and "--grey" in err and "Traceback" not in err
    assert main([*base, "--grey", "-o", str(tmp_path / "b.zarr")]) == 0


def _readme_stack_example() -> str:
    """The README's `sffscan stack` example on pertuz-simu02, as written (continuations
    joined)."""
    text = (ROOT / "README.md").read_text(encoding="utf-8")
    m = re.search(r"^(sffscan stack \.\./shared/datasets/pertuz-simu02/.*?[^\\])$", text,
                  flags=re.M | re.S)
    assert m is not None, "README: no 'sffscan stack ../shared/datasets/pertuz-simu02' example"
    return m.group(1).replace("\\\n", " ")


def test_readme_stack_example_runs_as_written(pertuz_dir: Path, tmp_path: Path) -> None:
    """Run from a folder beside ``shared/`` as the README's commands are (the checkout)."""
    cmd = _readme_stack_example()
    assert "[" not in cmd  # no optional parts to leave out: runnable as written
    work = tmp_path / "checkout"
    work.mkdir()
    (tmp_path / "shared").symlink_to(pertuz_dir.parents[1], target_is_directory=True)
    env = dict(os.environ, PATH=f"{Path(sys.executable).parent}{os.pathsep}"
                                f"{os.environ.get('PATH', '')}")
    for _ in range(2):  # and again, over its own output
        res = subprocess.run(["bash", "-c", cmd], cwd=work, env=env, capture_output=True,
                             text=True, timeout=300, check=False)
        assert res.returncode == 0, res.stderr
    out = re.search(r"-o (\S+)", cmd).group(1)  # type: ignore[union-attr]
    g = zarr.open_group(str(work / out), mode="r")
    assert g.attrs["status"] == "complete"
    im = scipy.io.loadmat(pertuz_dir / "imdata.mat", squeeze_me=True,
                          struct_as_record=False)["imdata"]
    np.testing.assert_allclose(np.asarray(g.attrs.asdict()["focus_heights_um"], dtype=float),
                               np.asarray(im.focus) * 1e6,
                               rtol=1e-12)


def test_stack_names_an_unmatched_glob_and_a_missing_file_first(
        pertuz_dir: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    # issue 26 item 7: a shell glob that matches nothing arrives as its pattern
    common = ["--focus-start", "0", "--focus-step", "1", "--pixel-um", "1",
              "-o", str(tmp_path / "a.zarr")]
    assert main(["stack", str(tmp_path / "*.tif"), *common]) == 2
    err = capsys.readouterr().err
    assert "no file matches the pattern" in err and "*.tif" in err
    assert "at least 3" not in err
    # a missing file is named before any word on the order of the names
    names = ["im_1.tif", "im_01.tif", "im_2.tif"]
    for i, name in enumerate(names[:2], start=1):
        shutil.copy(pertuz_dir / f"im_{i:02d}.tif", tmp_path / name)
    assert main(["stack", *(str(tmp_path / n) for n in names), *common]) == 2
    err = capsys.readouterr().err
    assert "im_2.tif: file not found" in err and "ambiguous" not in err
    assert not (tmp_path / "a.zarr").exists()
    # a file given twice (overlapping globs, another spelling of one path) is refused
    shutil.copy(pertuz_dir / "im_03.tif", tmp_path / "im_3.tif")
    twice = [str(tmp_path / "im_1.tif"), str(tmp_path / "im_3.tif"),
             str(tmp_path / "." / "im_1.tif")]
    assert main(["stack", *twice, *common]) == 2
    err = capsys.readouterr().err
    assert "im_1.tif: given twice (images 0 and 2" in err
    # a pixel size that is not a finite positive number, before anything is read
    ok = [str(tmp_path / n) for n in ("im_1.tif", "im_01.tif", "im_3.tif")]
    for bad in ("inf", "nan", "0"):
        args = ["stack", *ok, "--focus-start", "0", "--focus-step", "1", "--pixel-um", bad,
                "-o", str(tmp_path / "a.zarr")]
        assert main(args) == 2
        assert f"--pixel-um must be a finite number > 0, got {float(bad)}" in \
            capsys.readouterr().err
    assert not (tmp_path / "a.zarr").exists()


def _weighted_median_by_argsort(z: np.ndarray, w: np.ndarray, size: int) -> np.ndarray:
    """The filter as it was written before (argsort and gathers), the reference."""
    valid = np.isfinite(z)
    wz = np.where(valid, np.maximum(w, 1e-3), 0.0).astype(np.float32)
    zz = np.where(valid, z, np.inf).astype(np.float32)
    r = size // 2
    zs = np.lib.stride_tricks.sliding_window_view(np.pad(zz, r, mode="edge"), (size, size))
    ws = np.lib.stride_tricks.sliding_window_view(np.pad(wz, r, mode="edge"), (size, size))
    zs = zs.reshape(*z.shape, size * size)
    ws = ws.reshape(*z.shape, size * size)
    order = np.argsort(zs, axis=-1, kind="stable")
    zs = np.take_along_axis(zs, order, axis=-1)
    cum = np.cumsum(np.take_along_axis(ws, order, axis=-1), axis=-1, dtype=np.float64)
    k = np.count_nonzero(cum < 0.5 * cum[..., -1:], axis=-1)
    return np.where(valid, np.take_along_axis(zs, k[..., None], axis=-1)[..., 0], np.nan)


@pytest.mark.parametrize("size", [3, 15])
def test_weighted_median_equals_the_argsort_form(size: int) -> None:
    from sffscan.stages.fields.weighted_median import confidence_weighted_median

    rng = np.random.default_rng(size)
    z = (rng.normal(size=(37, 53)) * 100).astype(np.float32)
    z[rng.random(z.shape) < 0.1] = np.nan
    z[:6, :6] = -0.0  # ties, and a negative zero
    z[30:, 40:] = 12.5
    z[0, 40:] = -np.inf
    w = rng.random(z.shape).astype(np.float32)
    w[rng.random(z.shape) < 0.2] = 0.0
    ref = _weighted_median_by_argsort(z, w, size)
    for threads in (1, 3):  # blocks of rows in threads: the same result, progress in order
        calls: list[tuple[int, int]] = []
        got = confidence_weighted_median(z, w, size=size, block_rows=8, threads=threads,
                                         progress=lambda d, n, c=calls: c.append((d, n)))
        np.testing.assert_array_equal(got, ref)
        assert calls == [(8, 37), (16, 37), (24, 37), (32, 37), (37, 37)]


def test_stack_shows_its_progress(pertuz_dir: Path, tmp_path: Path,
                                  capsys: pytest.CaptureFixture[str]) -> None:
    # issue 26 item 4: a long stack said nothing until it ended
    padded = [str(pertuz_dir / f"im_{i:02d}.tif") for i in range(1, 31)]
    assert main(["stack", *padded, "--focus-start", "0", "--focus-step", "1", "--pixel-um",
                 "1", "--filter-size", "5", "-o", str(tmp_path / "a.zarr")]) == 0
    err = capsys.readouterr().err
    assert re.search(r"images 1/30 \(3\.3 %\)", err) and "read 30 images in" in err, err
    assert "reconstruction done in" in err
    assert re.search(r"median rows \d+/256", err), err
    assert "weighted median 5x5 done in" in err
    # -q: warnings and errors only, no progress display (both displays showed before)
    assert main(["stack", *padded, "--focus-start", "0", "--focus-step", "1", "--pixel-um",
                 "1", "--filter-size", "5", "-o", str(tmp_path / "b.zarr"), "-q"]) == 0
    err = capsys.readouterr().err
    assert "images" not in err and "median rows" not in err and "done in" not in err, err
    # the mosaic is never written inside the --zarr stack it is made from
    stack = tmp_path / "s.zarr"
    arr = zarr.create_array(str(stack), shape=(5, 24, 32), dtype="uint8")
    arr[...] = np.random.default_rng(0).integers(0, 256, (5, 24, 32), dtype=np.uint8)
    arr.attrs["focus_heights_um"] = [0.0, 1.0, 2.0, 3.0, 4.0]
    assert main(["stack", "--zarr", str(stack), "--pixel-um", "1", "-q",
                 "-o", str(stack / "m.zarr")]) == 2
    assert "inside the input" in capsys.readouterr().err
    assert sorted(p.name for p in stack.iterdir()) == ["c", "zarr.json"]


def test_the_stack_command_reconstructs_as_reconstruct_field(pertuz_dir: Path) -> None:
    """The command's steps shown one by one (reconstruction, then the filter with its
    progress) give what reconstruct_field gives."""
    from dataclasses import fields as dc_fields

    from sffscan.pipeline.cli.stack_steps import reconstruct_with_progress
    from sffscan.stages.fields.stationary import StackSettings, reconstruct_field

    stack = read_image_stack([pertuz_dir / f"im_{i:02d}.tif" for i in range(1, 31)])
    table = np.arange(30, dtype=np.float64)
    settings = StackSettings(filter_size=5, min_confidence=0.3)
    a = reconstruct_with_progress(stack, table, settings, None)
    b = reconstruct_field(stack, focus_heights_um=table, settings=settings)
    assert a.settings == b.settings
    assert np.isnan(b.height_um).any()  # min_confidence took some pixels
    for f in dc_fields(b):
        if f.name != "settings":
            x, y = getattr(a, f.name), getattr(b, f.name)
            assert (x is None and y is None) or np.array_equal(x, y, equal_nan=True), f.name


def test_png_orientation_read_from_its_chunks_wherever_the_exif_lies(tmp_path: Path) -> None:
    """The PNG's eXIf chunk is found by walking the chunks (the pixels are not decoded for
    it), after the image data too; a PNG without one is as stored; ImageMagick's EXIF in a
    text chunk, and a file that is not a PNG, are left to Pillow, as before."""
    import zlib

    from sffscan.stages.fields.image_io import _png_exif

    stored = np.arange(35, dtype=np.uint8).reshape(5, 7)
    plain = tmp_path / "plain.png"
    Image.fromarray(stored).save(plain)
    assert _png_exif(plain) == b"" and read_orientation(plain) == 1
    exif = Image.Exif()
    exif[274] = 6
    data = exif.tobytes()[6:] if exif.tobytes().startswith(b"Exif") else exif.tobytes()
    chunk = (len(data).to_bytes(4, "big") + b"eXIf" + data
             + zlib.crc32(b"eXIf" + data).to_bytes(4, "big"))
    raw = plain.read_bytes()
    late = tmp_path / "late.png"  # the eXIf chunk after IDAT, just before IEND
    late.write_bytes(raw[:-12] + chunk + raw[-12:])
    assert _png_exif(late) == data
    with Image.open(late) as im:
        assert im.getexif().get(274) == 6  # Pillow agrees (it decodes the image for it)
    assert read_orientation(late) == 6
    assert read_image(late).shape == (7, 5)
    text = b"Raw profile type exif\x00\nexif\n  4\n00000000\n"
    magick = tmp_path / "magick.png"
    magick.write_bytes(raw[:33] + len(text).to_bytes(4, "big") + b"tEXt" + text
                       + zlib.crc32(b"tEXt" + text).to_bytes(4, "big") + raw[33:])
    assert _png_exif(magick) is None
    notpng = tmp_path / "x.png"
    notpng.write_bytes(b"not an image")
    assert _png_exif(notpng) is None and read_orientation(notpng) == 1
    assert _png_exif(tmp_path / "gone.png") is None  # Pillow's path, as before: as stored
    assert read_orientation(tmp_path / "gone.png") == 1


def test_a_candidate_method_writes_no_uncertainty_and_says_so(
        pertuz_dir: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """A study's candidate (``--method window_pc``) has no fitted uncertainty constants: the
    stack's mosaic holds its heights and an uncertainty that is unknown (NaN) everywhere,
    not another method's constants in its place, and stderr says why; the default's is
    known."""
    images = [str(pertuz_dir / f"im_{i:02d}.tif") for i in range(1, 31)]
    common = ["--focus-start", "0", "--focus-step", "10", "--pixel-um", "1",
              "--filter-size", "1"]
    assert main(["stack", *images, *common, "--method", "window_pc",
                 "-o", str(tmp_path / "cand.zarr")]) == 0
    err = capsys.readouterr().err
    assert "WARNING" in err and "no height uncertainty" in err and "window_pc" in err
    g = zarr.open_group(str(tmp_path / "cand.zarr"), mode="r")
    assert np.isfinite(np.asarray(g["height"])).any()
    assert np.isnan(np.asarray(g["uncertainty"])).all()
    assert main(["stack", *images, *common, "-o", str(tmp_path / "default.zarr")]) == 0
    assert "no height uncertainty" not in capsys.readouterr().err
    u = np.asarray(zarr.open_group(str(tmp_path / "default.zarr"), mode="r")["uncertainty"])
    assert np.isfinite(u).any()
