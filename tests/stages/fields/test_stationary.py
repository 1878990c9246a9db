"""Tests of sffscan.stages.fields.stationary: reconstruction of one field from a focus stack."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import pytest
import scipy.ndimage
import zarr
from sffscan.pipeline.cli.main import main
from sffscan.stages.depth import depth_from_focus, levels_to_height
from sffscan.stages.fields.stack_io import (
    read_focus_positions,
    read_image_stack,
    read_zarr_stack,
)
from sffscan.stages.fields.stationary import StackSettings, reconstruct_field
from sffscan.stages.fields.weighted_median import confidence_weighted_median
from sffscan.stages.focus_measure import focus_measure, to_unit_float
from sffscan.stages.sim.camera import Optics, focus_heights, render_stack
from sffscan.stages.sim.world import sinusoid_world

# ----------------------------------------------------------------------------- filter


def test_weighted_median_with_equal_weights_is_the_median() -> None:
    rng = np.random.default_rng(0)
    z = rng.normal(size=(40, 53)).astype(np.float32)
    out = confidence_weighted_median(z, np.ones_like(z), size=7)
    ref = scipy.ndimage.median_filter(z, size=7, mode="nearest")  # independent implementation
    np.testing.assert_array_equal(out, ref)


def test_weighted_median_follows_the_weights() -> None:
    z = np.zeros((15, 15), np.float32)
    w = np.full((15, 15), 0.1, np.float32)
    z[:, :5] = 100.0  # a third of the window, but nearly all of its weight
    w[:, :5] = 1.0
    out = confidence_weighted_median(z, w, size=15)
    assert out[7, 7] == 100.0
    assert confidence_weighted_median(z, np.ones_like(w), size=15)[7, 7] == 0.0


def test_weighted_median_removes_outlier_and_fills_nothing() -> None:
    z = np.full((21, 21), 5.0, np.float32)
    z[10, 10] = 1e4  # a low-confidence outlier
    z[3, 3] = np.nan  # a missing pixel
    w = np.ones_like(z)
    w[10, 10] = 0.01
    out = confidence_weighted_median(z, w, size=5)
    assert out[10, 10] == 5.0
    assert np.isnan(out[3, 3]) and np.isfinite(out).sum() == np.isfinite(z).sum()
    np.testing.assert_array_equal(out[np.isfinite(out)], 5.0)  # NaN never used as a value


def test_weighted_median_size_one_and_errors() -> None:
    z = np.arange(12.0).reshape(3, 4)
    np.testing.assert_array_equal(confidence_weighted_median(z, np.ones_like(z), size=1), z)
    with pytest.raises(ValueError, match="size"):
        confidence_weighted_median(z, np.ones_like(z), size=4)
    with pytest.raises(ValueError, match="weights"):
        confidence_weighted_median(z, -np.ones_like(z), size=3)
    with pytest.raises(ValueError, match="same shape"):
        confidence_weighted_median(z, np.ones((3, 3)), size=3)


# ----------------------------------------------------------------------------- reconstruction

ZS = focus_heights(n_levels=20, z_step_um=400.0)


@pytest.fixture(scope="module")
def sim_stack() -> tuple[np.ndarray, np.ndarray]:
    world = sinusoid_world(pixel_um=17.0, amplitude_um=2500.0, period_px=200.0,
                           offset_um=3800.0)
    optics = Optics(width=120, height=96, pixel_um=17.0)
    stack = render_stack(world, x0=10.0, y0=5.0, focus_heights_um=ZS, optics=optics,
                         rng=np.random.default_rng(3))
    return stack, world.height_um(10.0, 5.0, 120, 96)


def test_reconstruct_reuses_the_pipeline_functions(sim_stack: tuple[np.ndarray, np.ndarray]
                                                   ) -> None:
    stack, _ = sim_stack
    s = StackSettings(method="spc", filter_size=1)
    r = reconstruct_field(stack, focus_heights_um=ZS, settings=s, max_value=1023)
    img = np.stack([to_unit_float(i, max_value=1023) for i in stack])
    levels, conf = depth_from_focus(focus_measure(img, operator="glvm", window=9), method="spc")
    np.testing.assert_array_equal(r.levels, levels)
    np.testing.assert_array_equal(r.confidence, conf)
    np.testing.assert_array_equal(r.height_um, levels_to_height(levels, focus_heights_um=ZS))
    assert r.texture.dtype == np.float32 and 0 <= r.texture.min() and r.texture.max() <= 1


def test_stack_takes_shape_select_and_the_study_s_candidates(
        sim_stack: tuple[np.ndarray, np.ndarray], tmp_path: Path) -> None:
    """``shape_select`` chooses once for the field: on this clean stack of even curves
    (Gaussian blur even in z, light noise) SPC's levels, averaged with the fallback's by
    SPC's share (:func:`sffscan.stages.depth_spc.spc_weight`, nearly all of it here); the
    command takes it, and the study's candidates, by name."""
    from sffscan.stages.depth import CANDIDATE_METHODS
    from sffscan.stages.depth_choice import stack_choice
    from sffscan.stages.depth_levels import first_argmax

    stack, _ = sim_stack
    r = {m: reconstruct_field(stack, focus_heights_um=ZS, max_value=1023,
                              settings=StackSettings(method=m, filter_size=1))
         for m in ("spc", "adaptive", "adaptive_centroid", "shape_select", *CANDIDATE_METHODS)}
    img = np.stack([to_unit_float(i, max_value=1023) for i in stack])
    vol = focus_measure(img, operator="glvm", window=9)
    choice = stack_choice(vol, first_argmax(vol), margin=4)
    assert choice.spc and choice.weight > 0.95
    apart = float(np.abs(r["spc"].levels - r["adaptive_centroid"].levels).max())
    np.testing.assert_allclose(r["shape_select"].levels, r["spc"].levels,
                               atol=(1.0 - choice.weight) * apart + 1e-5)
    assert not np.array_equal(r["shape_select"].levels, r["spc"].levels)
    assert not np.array_equal(r["spc"].levels, r["adaptive"].levels)
    arr = zarr.create_array(str(tmp_path / "s.zarr"), shape=stack.shape, dtype="uint16")
    arr[...] = stack
    arr.attrs["focus_heights_um"] = ZS.tolist()
    out = tmp_path / "f.zarr"
    assert main(["stack", "--zarr", str(tmp_path / "s.zarr"), "--pixel-um", "17",
                 "--bit-depth", "10", "--method", "shape_select", "-o", str(out)]) == 0
    g: Any = zarr.open_group(str(out), mode="r")
    assert g.attrs["status"] == "complete"
    assert "shape_select" in json.dumps(g.attrs["processing"])


def test_reconstruct_accuracy_on_sim_stack(sim_stack: tuple[np.ndarray, np.ndarray]) -> None:
    """The default's heights within a quarter of a focus step. The post-filter (a
    confidence-weighted median) takes the scatter of a 3-point peak fit off (``adaptive``:
    63.4 -> 61.6 µm, measured); the default's 5-level centroid scatters less, and the filter
    leaves it about as it was (55.4 -> 55.6 µm: within 1 %), better than either."""
    stack, truth = sim_stack

    def rmse(a: np.ndarray) -> float:
        return float(np.sqrt(np.mean((a - truth) ** 2)))

    r = reconstruct_field(stack, focus_heights_um=ZS, max_value=1023)
    peak = reconstruct_field(stack, focus_heights_um=ZS, max_value=1023,
                             settings=StackSettings(method="adaptive"))
    got, raw = rmse(r.height_um), rmse(r.raw_height_um)
    print(f"\nsim sinusoid stack (N=20, 400 µm): RMSE raw {raw:.1f} µm, filtered {got:.1f} µm;"
          f" adaptive {rmse(peak.raw_height_um):.1f} / {rmse(peak.height_um):.1f} µm")
    assert got < 0.25 * 400.0  # a quarter of a focus step
    assert rmse(peak.height_um) < rmse(peak.raw_height_um)
    assert got <= 1.01 * raw
    assert got < rmse(peak.height_um)


def test_min_confidence_marks_invalid(sim_stack: tuple[np.ndarray, np.ndarray]) -> None:
    stack, _ = sim_stack
    base = reconstruct_field(stack, focus_heights_um=ZS, max_value=1023)
    thr = float(np.quantile(base.confidence, 0.2))
    r = reconstruct_field(stack, focus_heights_um=ZS, max_value=1023,
                          settings=StackSettings(min_confidence=thr))
    low = base.confidence < thr
    assert low.any() and np.isnan(r.height_um[low]).all()
    np.testing.assert_array_equal(r.height_um[~low], base.height_um[~low])


def test_reconstruct_rejects_bad_input(sim_stack: tuple[np.ndarray, np.ndarray]) -> None:
    stack, _ = sim_stack
    with pytest.raises(ValueError, match="19 values for 20 images"):
        reconstruct_field(stack, focus_heights_um=ZS[:-1])
    with pytest.raises(ValueError, match="image 0: values up to"):
        reconstruct_field(stack, focus_heights_um=ZS, max_value=255)
    bad = stack.astype(np.float32) / 1023
    bad[4, 2, 2] = np.nan
    with pytest.raises(ValueError, match="image 4: image contains NaN"):
        reconstruct_field(bad, focus_heights_um=ZS)
    with pytest.raises(ValueError, match="filter_size"):
        StackSettings(filter_size=4)
    with pytest.raises(ValueError, match="method"):
        StackSettings(method="best")


def test_valid_pixels_reconstruct_their_box_alone(sim_stack: tuple[np.ndarray, np.ndarray]
                                                 ) -> None:
    """With ``valid`` (an aligned stack's covered pixels), the field is the reconstruction of
    their bounding box alone, whatever lies beyond it (an aligned frame's replicated border,
    here garbage); NaN and confidence 0 outside; every pixel valid is the plain call."""
    stack, _ = sim_stack
    s = StackSettings()  # the default method: its choice is judged on the box's curves
    valid = np.zeros(stack.shape[1:], bool)
    valid[10:80, 15:100] = True
    valid[10, 15] = False  # a corner left out: the box is still 10..80 x 15..100
    garbage = stack.copy()
    rng = np.random.default_rng(11)
    outside = ~np.pad(np.ones((70, 85), bool), ((10, 16), (15, 20)))
    garbage[:, outside] = rng.integers(0, 1024, (stack.shape[0], int(outside.sum())))
    got = reconstruct_field(garbage, focus_heights_um=ZS, settings=s, max_value=1023,
                            valid=valid)
    ref = reconstruct_field(stack[:, 10:80, 15:100], focus_heights_um=ZS, settings=s,
                            max_value=1023)
    for name in ("height_um", "raw_height_um", "levels", "texture", "confidence",
                 "uncertainty_um"):
        a, b = getattr(got, name), getattr(ref, name)
        assert a.shape == stack.shape[1:], name
        np.testing.assert_array_equal(a[10:80, 15:100], b, err_msg=name)
        rest = np.ones(stack.shape[1:], bool)
        rest[10:80, 15:100] = False
        assert (a[rest] == 0).all() if name == "confidence" else np.isnan(a[rest]).all(), name
    plain = reconstruct_field(stack, focus_heights_um=ZS, settings=s, max_value=1023)
    whole = reconstruct_field(stack, focus_heights_um=ZS, settings=s, max_value=1023,
                              valid=np.ones(stack.shape[1:], bool))
    np.testing.assert_array_equal(whole.height_um, plain.height_um)
    with pytest.raises(ValueError, match="valid must have the images' shape"):
        reconstruct_field(stack, focus_heights_um=ZS, valid=valid[:, :-1])
    with pytest.raises(ValueError, match="no pixel is covered"):
        reconstruct_field(stack, focus_heights_um=ZS, valid=np.zeros_like(valid))
    with pytest.raises(ValueError, match="fewer than 3 x 3"):
        reconstruct_field(stack, focus_heights_um=ZS, valid=valid & (np.arange(96) < 12)[:, None])


# ----------------------------------------------------------------------------- files


def test_read_stacks_and_focus_files(tmp_path: Path) -> None:
    imgs = (np.arange(3 * 8 * 9) % 251).astype(np.uint8).reshape(3, 8, 9)
    paths = []
    for i, im in enumerate(imgs):
        paths.append(tmp_path / f"im{i}.png")
        cv2.imwrite(str(paths[-1]), im)
    np.testing.assert_array_equal(read_image_stack(paths), imgs)
    cv2.imwrite(str(tmp_path / "odd.png"), np.zeros((5, 5), np.uint8))
    with pytest.raises(ValueError, match="odd.png: shape"):
        read_image_stack([*paths, tmp_path / "odd.png"])
    (tmp_path / "f.txt").write_text("# mm\n0.1, 0.2\n0.3\n")
    np.testing.assert_allclose(read_focus_positions(tmp_path / "f.txt", scale_to_um=1000),
                               [100, 200, 300])
    (tmp_path / "g.txt").write_text("1\nx2\n")
    with pytest.raises(ValueError, match="g.txt:2"):
        read_focus_positions(tmp_path / "g.txt")
    arr = zarr.create_array(str(tmp_path / "s.zarr"), shape=imgs.shape, dtype="uint8")
    arr[...] = imgs
    arr.attrs["focus_heights_um"] = [1.0, 2.0, 3.0]
    stack, table = read_zarr_stack(tmp_path / "s.zarr")
    np.testing.assert_array_equal(stack, imgs)
    np.testing.assert_array_equal(table, [1.0, 2.0, 3.0])


def test_stack_command(sim_stack: tuple[np.ndarray, np.ndarray], tmp_path: Path) -> None:
    stack, truth = sim_stack
    arr = zarr.create_array(str(tmp_path / "s.zarr"), shape=stack.shape, dtype="uint16")
    arr[...] = stack
    arr.attrs["focus_heights_um"] = ZS.tolist()
    out = tmp_path / "f.zarr"
    args = ["stack", "--zarr", str(tmp_path / "s.zarr"), "--pixel-um", "17", "--bit-depth", "10",
            "-o", str(out)]
    assert main(args) == 0
    g: Any = zarr.open_group(str(out), mode="r")
    assert g.attrs["status"] == "complete" and g.attrs["processing"]["mode"] == "stationary"
    h = np.asarray(g["height"][...])
    assert float(np.sqrt(np.mean((h - truth) ** 2))) < 100.0
    tex = np.asarray(g["texture"][...])
    assert 0.0 <= tex.min() and tex.max() <= 1.0
    assert main(args) == 2  # exists, no --overwrite
    assert main([*args, "--overwrite", "--focus-start", "0", "--focus-step", "1"]) == 0
    assert main(["stack", "--zarr", str(tmp_path / "s.zarr"), "--pixel-um", "17",
                 "--focus-file", str(tmp_path / "missing.txt"), "-o", str(tmp_path / "x")]) == 2
    assert main(["stack", str(tmp_path / "nope.tif"), "a", "b", "--pixel-um", "1",
                 "--focus-start", "0", "--focus-step", "1", "-o", str(tmp_path / "y")]) == 2


def test_stack_command_names_a_bad_focus_table(sim_stack: tuple[np.ndarray, np.ndarray],
                                               tmp_path: Path,
                                               capsys: pytest.CaptureFixture[str]) -> None:
    """A focus table that is not strictly monotonic is refused before any processing, the
    message naming the file (or the option) and the first bad position."""
    stack, _ = sim_stack
    arr = zarr.create_array(str(tmp_path / "s.zarr"), shape=stack.shape, dtype="uint16")
    arr[...] = stack
    table = ZS.copy()
    table[7] = table[6]
    focus = tmp_path / "focus.txt"
    focus.write_text("\n".join(str(v) for v in table))
    base = ["stack", "--zarr", str(tmp_path / "s.zarr"), "--pixel-um", "17", "-o",
            str(tmp_path / "f.zarr")]
    capsys.readouterr()
    assert main([*base, "--focus-file", str(focus)]) == 2
    err = capsys.readouterr().err
    assert "focus.txt" in err and "position 7" in err
    assert main([*base, "--focus-start", "0", "--focus-step", "0"]) == 2
    assert "--focus-step" in capsys.readouterr().err
    assert not (tmp_path / "f.zarr").exists()


def test_the_uncertainty_from_shared_curves_is_the_one_computed_alone() -> None:
    """``stack_curves`` of a volume, given to ``stack_uncertainty_um`` for several methods
    (``sffscan study``), gives what each computes alone; curves of another volume are
    refused by name."""
    from sffscan.stages.fields.stationary import stack_curves, stack_uncertainty_um
    from sffscan.stages.sim.families import family_stack

    st = family_stack("lens-gauss", 0, size_px=48)
    vol = focus_measure(st.images, window=5)
    curves = stack_curves(vol)
    for method in ("spc", "centroid", "gauss3"):
        d = depth_from_focus(vol, method=method, spread_size=5)[0]
        alone = stack_uncertainty_um(vol, d, st.focus_um, method=method, window=5)
        shared = stack_uncertainty_um(vol, d, st.focus_um, method=method, window=5,
                                      curves=curves)
        assert alone is not None and shared is not None
        np.testing.assert_array_equal(shared, alone)
    with pytest.raises(ValueError, match="curves are of a volume of shape"):
        stack_uncertainty_um(vol[:, :10], d[:10], st.focus_um, method="spc", curves=curves)
