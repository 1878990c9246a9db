"""``sffscan study``: a table and a plot of operators x windows x methods on a known truth."""

from __future__ import annotations

import csv
import dataclasses
import json
from pathlib import Path

import numpy as np
import pytest
from sffscan.pipeline.cli.common import DEPTH_METHOD_CHOICES
from sffscan.pipeline.cli.main import main


def test_study_on_pertuz(pertuz_dir: Path, tmp_path: Path, capsys: pytest.CaptureFixture
                         ) -> None:
    out = tmp_path / "study"
    rc = main(["study", "--imdata", str(pertuz_dir / "imdata.mat"), "--operators", "GLVM,lapm",
               "--windows", "5,9", "--methods", "gauss3,wcentroid", "-o", str(out)])
    assert rc == 0
    with (out / "study.csv").open() as f:
        rows = list(csv.DictReader(f))
    assert len(rows) == 2 * 2 * 2
    assert {r["operator"] for r in rows} == {"glvm", "lapm"}
    table = {(r["operator"], int(r["window"]), r["method"]): float(r["rmse_um"]) for r in rows}
    # the figures of test_default_depth: GLVM 9, all ROI pixels, raw heights
    assert table["glvm", 9, "wcentroid"] == pytest.approx(15.22e3, rel=0.01)
    assert table["glvm", 9, "gauss3"] == pytest.approx(36.74e3, rel=0.01)
    assert json.loads((out / "study.json").read_text())["rows"][0]["operator"] == "glvm"
    assert (out / "study.png").read_bytes()[:4] == b"\x89PNG"
    assert "best: " in capsys.readouterr().out


def test_study_scores_a_candidate_by_name(pertuz_dir: Path, tmp_path: Path,
                                         capsys: pytest.CaptureFixture) -> None:
    # the study's candidates are accepted by name beside the default (docs/depth-method.md)
    out = tmp_path / "study"
    assert main(["study", "-q", "--imdata", str(pertuz_dir / "imdata.mat"), "--operators",
                 "glvm", "--windows", "9", "--methods", "shape_select,warped_select",
                 "-o", str(out)]) == 0
    with (out / "study.csv").open() as f:
        rmse = {r["method"]: float(r["rmse_um"]) for r in csv.DictReader(f)}
    # pertuz-simu02's curves are lopsided (c = 4.5): the warped axis 9.28 mm, 13.52
    # unwarped (9.72 mm until SPC's range guard took its widths from a floor the noise does
    # not lower, 2026-12-05: the warped stack keeps SPC at more pixels; stages/depth_floor.py;
    # 10.04 mm until SPC was averaged with its fallback by its share, 2026-12-06 morning, and
    # 9.94 mm until that share read the departures' robust spread, the same day:
    # stages/depth_spc.spc_weight)
    assert rmse["shape_select"] == pytest.approx(13.52e3, rel=0.01)
    assert rmse["warped_select"] == pytest.approx(9.28e3, rel=0.01)
    # the uncertainty checked on the same pixels: the default's (0.994 measured; the height
    # uncertainty's band is 0.90 .. 0.98), none for a candidate (never fitted)
    with (out / "study.csv").open() as f:
        within = {r["method"]: float(r["within_2sigma"]) for r in csv.DictReader(f)}
    assert 0.9 <= within["shape_select"] <= 1.0 and np.isnan(within["warped_select"])
    ranking = capsys.readouterr().out
    assert "| within 2 sigma |" in ranking
    assert [ln for ln in ranking.splitlines() if "| warped_select |" in ln][0].endswith("| n/a |")
    assert main(["study", "--chapter3", "--methods", "warped", "-o", str(tmp_path)]) == 2
    assert "candidates: gauss_window_fit, window_pc, warped_select" in capsys.readouterr().err


def test_study_rejects_bad_input(tmp_path: Path, capsys: pytest.CaptureFixture) -> None:
    assert main(["study", "--chapter3", "--operators", "wavc", "-o", str(tmp_path)]) == 2
    assert "wavc" in capsys.readouterr().err
    assert main(["study", "--chapter3", "--windows", "4", "-o", str(tmp_path)]) == 2
    assert main(["study", "--imdata", str(tmp_path / "missing.mat"), "-o", str(tmp_path)]) == 2
    assert "missing.mat" in capsys.readouterr().err
    # -o inside a Zarr store (a mosaic, a recording): refused before any work
    store = tmp_path / "m.zarr"
    store.mkdir()
    (store / "zarr.json").write_text('{"zarr_format": 3, "node_type": "group"}')
    for out in (store, store / "study"):
        for fam in ([], ["--families"]):
            assert main(["study", "--chapter3", *fam, "-o", str(out)]) == 2
            assert "inside the Zarr store" in capsys.readouterr().err
    assert sorted(p.name for p in store.iterdir()) == ["zarr.json"]


STEP_UM = 100.0


@pytest.fixture(scope="module")
def own_stack(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, np.ndarray]:
    """A user's stack as files: 10 simulated 10-bit TIFFs (im_1 .. im_10, 64 x 48 px) of a
    sinusoidal surface, focus positions 0, 100, ... 900 µm in a text file, the truth .npy."""
    import tifffile
    from sffscan.stages.sim.camera import Optics, render_stack
    from sffscan.stages.sim.world import sinusoid_world

    d = tmp_path_factory.mktemp("own")
    zs = np.arange(10) * STEP_UM
    world = dataclasses.replace(
        sinusoid_world(seed=3, amplitude_um=0.35 * zs[-1], period_px=40.0,
                       offset_um=0.5 * zs[-1]), texture_scales_px=(1.0, 2.0))
    optics = Optics(width=64, height=48, pixel_um=8.5, noise_sigma=0.0, bit_depth=10)
    images = render_stack(world, x0=0.0, y0=0.0, focus_heights_um=zs, optics=optics,
                          rng=np.random.default_rng(1))
    for i, im in enumerate(images):
        tifffile.imwrite(d / f"im_{i + 1}.tif", im)
    truth = world.height_um(0.0, 0.0, 64, 48)
    np.save(d / "truth.npy", truth)
    (d / "focus.txt").write_text("\n".join(f"{z:g}" for z in zs) + "\n")
    return d, truth


def _images(d: Path) -> list[str]:
    # the shell's alphabetical glob (im_10 before im_2): the study takes the natural order
    return sorted(str(p) for p in d.glob("im_*.tif"))


def test_study_on_own_image_files(own_stack: tuple[Path, np.ndarray], tmp_path: Path,
                                  capsys: pytest.CaptureFixture) -> None:
    d, truth = own_stack
    out = tmp_path / "study"
    rc = main(["study", *_images(d), "--focus-file", str(d / "focus.txt"), "--truth",
               str(d / "truth.npy"), "--bit-depth", "10", "--operators", "glvm,lapm",
               "--windows", "3,5", "-o", str(out)])
    assert rc == 0
    with (out / "study.csv").open() as f:
        rows = list(csv.DictReader(f))
    combos = {(r["operator"], int(r["window"]), r["method"]) for r in rows}
    assert len(rows) == len(combos) == 2 * 2 * len(DEPTH_METHOD_CHOICES)
    rmse = {(r["operator"], int(r["window"]), r["method"]): float(r["rmse_um"]) for r in rows}
    best = min(rmse, key=lambda c: rmse[c])
    # a sub-level method wins, well below a focus step and below the plain argmax
    assert best[2] != "argmax" and rmse[best] < 0.3 * STEP_UM
    assert rmse[best] < 0.6 * rmse[best[0], best[1], "argmax"]
    text = capsys.readouterr().out
    ranking = [ln for ln in text.splitlines() if ln.startswith("| 1 |")]
    assert ranking and f"| {best[0].upper()} | {best[1]} | {best[2]} |" in ranking[0]
    assert json.loads((out / "study.json").read_text())["scored_pixels"] == truth.size
    # order matters: the files in the order given (alphabetical) score far worse
    assert main(["study", *_images(d), "--keep-order", "--focus-file", str(d / "focus.txt"),
                 "--truth", str(d / "truth.npy"), "--operators", "lapm", "--windows",
                 str(best[1]), "--methods", best[2], "-o", str(tmp_path / "k")]) == 0
    with (tmp_path / "k" / "study.csv").open() as f:
        assert float(next(csv.DictReader(f))["rmse_um"]) > 2 * rmse[best]


def test_study_on_a_zarr_stack_with_roi(own_stack: tuple[Path, np.ndarray], tmp_path: Path
                                       ) -> None:
    import tifffile
    import zarr

    d, truth = own_stack
    stack = np.stack([tifffile.imread(d / f"im_{i + 1}.tif") for i in range(10)])
    arr = zarr.create_array(str(tmp_path / "s.zarr"), shape=stack.shape, dtype="uint16")
    arr[...] = stack
    arr.attrs["focus_heights_um"] = (np.arange(10) * STEP_UM).tolist()
    t = zarr.create_array(str(tmp_path / "t.zarr"), shape=truth.shape, dtype="float64")
    t[...] = truth
    common = ["study", "--zarr", str(tmp_path / "s.zarr"), "--bit-depth", "10",
              "--operators", "glvm", "--windows", "5", "--methods", "gauss3"]
    assert main([*common, "--truth", str(d / "truth.npy"), "-o", str(tmp_path / "a")]) == 0
    assert main([*common, "--truth", str(tmp_path / "t.zarr"), "--roi", "8,4,30,20",
                 "-o", str(tmp_path / "b")]) == 0
    a = json.loads((tmp_path / "a" / "study.json").read_text())
    b = json.loads((tmp_path / "b" / "study.json").read_text())
    assert a["scored_pixels"] == truth.size and b["scored_pixels"] == 30 * 20
    assert a["rows"][0]["rmse_um"] != b["rows"][0]["rmse_um"]


def test_study_names_a_bad_truth_or_focus_table(own_stack: tuple[Path, np.ndarray],
                                                tmp_path: Path, capsys: pytest.CaptureFixture
                                                ) -> None:
    d, truth = own_stack
    np.save(tmp_path / "small.npy", truth[:-1])
    (tmp_path / "short.txt").write_text("0\n100\n200\n")
    base = ["study", *_images(d), "--operators", "glvm", "--windows", "3", "-o",
            str(tmp_path / "o")]
    focus = ["--focus-file", str(d / "focus.txt")]
    capsys.readouterr()
    assert main([*base, *focus, "--truth", str(tmp_path / "small.npy")]) == 2
    err = capsys.readouterr().err
    assert "small.npy" in err and "64 x 47" in err and "64 x 48" in err
    assert main([*base, "--focus-file", str(tmp_path / "short.txt"), "--truth",
                 str(d / "truth.npy")]) == 2
    assert "short.txt: 3 focus positions for 10 images" in capsys.readouterr().err
    assert main([*base, *focus, "--truth", str(tmp_path / "none.npy")]) == 2
    assert "none.npy" in capsys.readouterr().err
    assert main([*base, *focus]) == 2  # no truth
    assert "--truth" in capsys.readouterr().err
    assert main([*base, *focus, "--truth", str(d / "truth.npy"), "--roi", "60,0,10,10"]) == 2
    assert "--roi 60,0,10,10" in capsys.readouterr().err
    assert main([*base, *focus, "--truth", str(d / "truth.npy"), "--chapter3"]) == 2
    assert "one stack" in capsys.readouterr().err
    assert not (tmp_path / "o").exists()


def test_study_without_matplotlib_writes_the_table(tmp_path: Path, monkeypatch: pytest.MonkeyPatch,
                                                   capsys: pytest.CaptureFixture) -> None:
    """issue 26 item 1: no matplotlib, no crash: the CSV and JSON are written, the message
    says why there is no figure."""
    import sys

    from sffscan.pipeline.cli.study import StudyRow, write_outputs

    monkeypatch.setitem(sys.modules, "matplotlib", None)  # import matplotlib -> ImportError
    monkeypatch.setitem(sys.modules, "matplotlib.pyplot", None)
    rows = [StudyRow("glvm", 9, "spc", 1.0, 0.9, 30.0, 0.01)]
    paths = write_outputs(rows, tmp_path / "o", title="t")
    assert [p.name for p in paths] == ["study.csv", "study.json"]
    assert (tmp_path / "o" / "study.csv").read_text().startswith("operator,")
    assert not (tmp_path / "o" / "study.png").exists()
    assert "matplotlib is not installed" in capsys.readouterr().err


def test_within_2sigma_counts_the_pixels_that_hold_every_value() -> None:
    """The share of scored pixels with |height - truth| <= 2 sigma, over the pixels where
    height, truth and sigma are finite; NaN without an uncertainty or without a pixel."""
    from sffscan.pipeline.cli.study import within_2sigma

    h = np.array([[0.0, 1.0, 2.0, 3.0], [0.0, 5.0, np.nan, 0.0]])
    t = np.zeros((2, 4))
    s = np.array([[1.0, 0.5, 1.0, 1.0], [1.0, 1.0, 1.0, np.nan]])
    mask = np.ones((2, 4), bool)
    # finite everywhere but (1, 2) and (1, 3): |err| 0, 1, 2, 3, 0, 5 against 2, 1, 2, 2, 2, 2
    assert within_2sigma(h, t, s, mask) == pytest.approx(4 / 6)
    mask[0, 3] = False
    assert within_2sigma(h, t, s, mask) == pytest.approx(4 / 5)
    assert np.isnan(within_2sigma(h, t, None, mask))
    assert np.isnan(within_2sigma(h, t, s, np.zeros((2, 4), bool)))
