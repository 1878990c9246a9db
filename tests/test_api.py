"""The public Python API (``sffscan.__all__``): the README's example runs as written, and
each function does what its docstring says, errors included."""

from __future__ import annotations

import importlib
import inspect
import os
import re
import types
from pathlib import Path

import numpy as np
import pytest
import zarr
from scipy.ndimage import uniform_filter

import sffscan
from tests.scan_helpers import small_config

ROOT = Path(__file__).resolve().parents[1]


def readme_api_example() -> str:
    """The first ```python block of the README's "Python API" section."""
    text = (ROOT / "README.md").read_text(encoding="utf-8")
    section = text.split("\n## Python API\n", 1)
    assert len(section) == 2, "README.md has no '## Python API' section"
    m = re.search(r"```python\n(.*?)```", section[1].split("\n## ", 1)[0], flags=re.S)
    assert m is not None, "the README's Python API section has no python code block"
    return m.group(1)


def test_readme_api_example_runs(pertuz_dir: Path, tmp_path: Path,
                                 capsys: pytest.CaptureFixture[str]) -> None:
    """Run from a folder beside ``shared/``, as the README says (the checkout)."""
    work = tmp_path / "checkout"
    work.mkdir()
    (tmp_path / "shared").symlink_to(pertuz_dir.parents[1], target_is_directory=True)
    code = readme_api_example()
    here = os.getcwd()
    os.chdir(work)
    try:
        ns: dict[str, object] = {"__name__": "__readme__"}
        exec(compile(code, "README.md (Python API)", "exec"), ns)  # noqa: S102
    finally:
        os.chdir(here)
    out = capsys.readouterr().out
    report = ns["report"]
    assert isinstance(report, sffscan.ScanReport)
    assert report.frames > 0 and report.accuracy is not None
    assert f"{report.frames} frames, RMSE" in out
    mosaic = ns["mosaic"]
    assert mosaic["height"].dims == ("y", "x")  # type: ignore[index]
    field = ns["field"]
    assert isinstance(field, sffscan.FieldResult) and field.height_um.shape == (256, 256)
    assert (work / "plate.zarr").is_dir()
    # the accuracy travels with the mosaic (scan, replay and batch store it alike)
    stored = zarr.open_group(str(work / "plate.zarr"), mode="r").attrs["accuracy"]
    assert stored["rmse_um"] == pytest.approx(report.accuracy.rmse_um)  # type: ignore[index]
    assert stored["pixels"] == report.accuracy.pixels  # type: ignore[index]


def test_all_is_the_documented_surface() -> None:
    public = {n for n in dir(sffscan) if not n.startswith("_")}
    modules = {n for n in public if isinstance(getattr(sffscan, n), types.ModuleType)}
    futures = {"annotations"}  # from __future__ import annotations
    assert public - modules - futures <= set(sffscan.__all__)
    for name in sffscan.__all__:
        obj = getattr(sffscan, name)  # every name resolves (lazy ones on first use)
        if callable(obj):
            assert inspect.getdoc(obj), f"sffscan.{name} has no docstring"
    for fn in (sffscan.scan, sffscan.replay, sffscan.reconstruct_stack,
               sffscan.focus_measure, sffscan.open_mosaic):
        doc = inspect.getdoc(fn) or ""
        assert "Parameters\n----------" in doc and "Returns\n-------" in doc, fn.__name__
    assert sffscan.__version__ == importlib.metadata.version("sffscan")


def test_import_loads_nothing_heavy() -> None:
    import subprocess
    import sys

    code = ("import sys, sffscan; "
            "print(sorted(m for m in ('torch', 'cv2', 'zarr', 'xarray', 'dask') "
            "if m in sys.modules))")
    res = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                         check=True, timeout=120)
    assert res.stdout.strip() == "[]"


# ----------------------------------------------------------------------------- scan, replay


def test_scan_and_replay(tmp_path: Path) -> None:
    cfg = small_config(motion={"x_start_mm": 2.0, "x_end_mm": 6.0})
    rec = tmp_path / "rec.zarr"
    live = sffscan.scan(cfg, output=tmp_path / "live.zarr", record=rec, evaluate=True)
    assert isinstance(live, sffscan.ScanReport)
    assert live.output == tmp_path / "live.zarr" and live.frames > 0
    assert live.accuracy is not None and live.accuracy.pixels > 0
    # the uncertainty scored on the same truth: every scored pixel has one
    assert live.accuracy.sigma_pixels == live.accuracy.pixels
    assert 0.5 < live.accuracy.within_2sigma <= 1.0
    from sffscan.pipeline.wiring import format_summary

    line = f"uncertainty {100 * live.accuracy.within_2sigma:.1f} % of {live.accuracy.pixels} px"
    assert line in format_summary(live)
    again = sffscan.replay(rec, output=tmp_path / "replay.zarr")
    assert again.frames == live.frames and again.extras["recording"]["frames"] == live.frames
    a, b = sffscan.open_mosaic(live.output), sffscan.open_mosaic(again.output)
    np.testing.assert_array_equal(a["height"].values, b["height"].values)  # bit for bit
    # an existing mosaic is kept unless overwrite=True
    with pytest.raises(OSError, match="exists"):
        sffscan.scan(cfg, output=tmp_path / "live.zarr")
    with pytest.raises(sffscan.RecordingError):
        sffscan.replay(tmp_path / "live.zarr", output=tmp_path / "x.zarr")


def test_scan_errors_name_the_field(tmp_path: Path) -> None:
    cfg = small_config(motion={"x_start_mm": 2.0, "x_end_mm": 6.0})
    with pytest.raises(sffscan.ConfigError, match="processing.window"):
        sffscan.scan(cfg, output=tmp_path / "m.zarr", processing={"window": 4})
    with pytest.raises(ValueError, match="unknown field"):
        sffscan.scan(cfg, output=tmp_path / "m.zarr", processing={"windw": 9})
    with pytest.raises(ValueError, match="evaluate=True"):  # refused before anything runs
        sffscan.scan(cfg, output=tmp_path / "m.zarr", frames=[], evaluate=True)
    assert not (tmp_path / "m.zarr").exists()


def test_load_config_names_file_and_field(tmp_path: Path) -> None:
    from sffscan.pipeline.config import config_to_toml

    good = tmp_path / "scan.toml"
    good.write_text(config_to_toml(sffscan.demo_config()), encoding="utf-8")
    assert sffscan.load_config(good) == sffscan.demo_config()
    bad = tmp_path / "bad.toml"
    bad.write_text(config_to_toml(sffscan.demo_config()).replace("window = 9", "window = 4"),
                   encoding="utf-8")
    with pytest.raises(sffscan.ConfigError, match=r"bad\.toml.*processing\.window"):
        sffscan.load_config(bad)


# ----------------------------------------------------------------------------- open_mosaic


def test_open_mosaic_coordinates_in_um_and_lazy(tmp_path: Path) -> None:
    from sffscan.pipeline.mosaic.writer import MosaicWriter

    shape, origin, px = (6, 9), (-20, 7), 8.5
    h = np.arange(54, dtype=np.float32).reshape(shape)
    w = MosaicWriter(tmp_path / "m.zarr", origin_px=origin, shape=shape, pixel_um=px,
                     attrs={"focus_heights_um": [0.0, 1.0, 2.0], "processing": {"mode": "t"}})
    one = np.ones(shape, np.float32)
    w.write_region(*origin, {"height": h, "texture": one, "weight": one, "confidence": one})
    w.set_status("complete")
    ds = sffscan.open_mosaic(tmp_path / "m.zarr")
    assert ds["height"].dims == ("y", "x") and ds["height"].shape == shape
    assert type(ds["height"].data).__module__.startswith("dask")  # nothing read yet
    np.testing.assert_allclose(ds["x"].values, (origin[0] + np.arange(9)) * px)
    np.testing.assert_allclose(ds["y"].values, (origin[1] + np.arange(6)) * px)
    np.testing.assert_array_equal(ds["height"].values, h)
    # element [r, c] is world px (origin + c, origin + r): select by µm
    assert float(ds["height"].sel(x=(origin[0] + 2) * px, y=(origin[1] + 1) * px)) == h[1, 2]
    assert ds.attrs["status"] == "complete" and ds["height"].attrs["units"] == "µm"
    with pytest.raises(ValueError, match="nothing.zarr"):
        sffscan.open_mosaic(tmp_path / "nothing.zarr")
    g = zarr.open_group(str(tmp_path / "other.zarr"), mode="w")
    g.attrs["format"] = "something-else"
    with pytest.raises(ValueError, match="other.zarr"):
        sffscan.open_mosaic(tmp_path / "other.zarr")


# ----------------------------------------------------------------------------- focus measure


def test_focus_measure_is_glvm_with_replicated_borders() -> None:
    """GLVM = box_k((I - box_k(I))^2), borders replicate: against scipy (float64)."""
    rng = np.random.default_rng(0)
    img = rng.random((2, 40, 50))
    got = sffscan.focus_measure(img, operator="glvm", window=9)
    assert got.shape == img.shape and got.dtype == np.float32
    for i in range(2):
        mu = uniform_filter(img[i], 9, mode="nearest")
        want = uniform_filter((img[i] - mu) ** 2, 9, mode="nearest")
        np.testing.assert_allclose(got[i], want, rtol=1e-5, atol=1e-7)
    assert np.abs(sffscan.focus_measure(np.full((20, 20), 0.3), window=5)).max() < 1e-6
    with pytest.raises(ValueError, match="window"):
        sffscan.focus_measure(img[0], window=8)
    with pytest.raises(ValueError, match="operator"):
        sffscan.focus_measure(img[0], operator="nope")


# ----------------------------------------------------------------------------- stacks


def _synthetic_stack(levels: tuple[int, int], n: int = 15) -> np.ndarray:
    """Left half sharpest at level levels[0], right half at levels[1] (contrast of a
    random texture falls off as a Gaussian of the level distance)."""
    rng = np.random.default_rng(2)
    tex = rng.random((40, 60))
    k = np.arange(n, dtype=np.float64)[:, None, None]
    peak = np.where(np.arange(60) < 30, levels[0], levels[1])[None, None, :]
    amp = np.exp(-0.5 * ((k - peak) / 2.0) ** 2)
    return (0.5 + 0.45 * amp * (tex - 0.5)).astype(np.float32)


def test_reconstruct_stack_finds_the_sharpest_level() -> None:
    focus_um = 100.0 + 50.0 * np.arange(15)
    stack = _synthetic_stack((4, 10))
    field = sffscan.reconstruct_stack(stack, focus_um, method="gauss3", filter_size=1)
    assert isinstance(field, sffscan.FieldResult)
    for arr in (field.height_um, field.raw_height_um, field.levels, field.texture,
                field.confidence):
        assert arr.shape == (40, 60) and arr.dtype == np.float32
    inner = (slice(8, -8), slice(8, 22)), (slice(8, -8), slice(38, 52))  # away from the edge
    assert np.median(field.height_um[inner[0]]) == pytest.approx(focus_um[4], abs=5.0)
    assert np.median(field.height_um[inner[1]]) == pytest.approx(focus_um[10], abs=5.0)
    same = sffscan.reconstruct_stack(
        stack, focus_um, settings=sffscan.StackSettings(method="gauss3", filter_size=1))
    np.testing.assert_array_equal(same.height_um, field.height_um)


def test_reconstruct_stack_errors() -> None:
    stack = _synthetic_stack((4, 10))
    focus_um = np.arange(15.0)
    with pytest.raises(TypeError, match="not both"):
        sffscan.reconstruct_stack(stack, focus_um, settings=sffscan.StackSettings(),
                                  method="argmax")
    with pytest.raises(ValueError, match="15 images"):
        sffscan.reconstruct_stack(stack, focus_um[:14])
    with pytest.raises(ValueError, match="N >= 3"):
        sffscan.reconstruct_stack(stack[:2], focus_um[:2])
    with pytest.raises(ValueError, match="method"):
        sffscan.reconstruct_stack(stack, focus_um, method="nope")
    with pytest.raises(ValueError, match="image 0"):
        sffscan.reconstruct_stack(stack * 2.0, focus_um)  # above the full scale 1.0


def test_a_scan_with_another_focus_measure_warns_its_uncertainty_is_not_calibrated(
        tmp_path: Path, caplog: pytest.LogCaptureFixture) -> None:
    cfg = small_config(motion={"x_start_mm": 2.0, "x_end_mm": 3.0})
    with caplog.at_level("WARNING"):
        sffscan.scan(cfg, output=tmp_path / "k9.zarr")
        assert "not calibrated" not in caplog.text  # GLVM 9: what the constants were fitted with
        sffscan.scan(cfg, output=tmp_path / "k5.zarr", processing={"window": 5})
    assert "with GLVM k=5 it is not calibrated" in caplog.text
