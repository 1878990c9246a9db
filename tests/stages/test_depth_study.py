"""The synthetic families (stages/sim/families.py) and the leave-one-family-out protocol
(stages/depth_study.py) behind ``sffscan study --families``."""

from __future__ import annotations

import csv
import math
from pathlib import Path

import numpy as np
import pytest
from sffscan.pipeline.cli.main import main
from sffscan.stages.curve_shape import curve_width, floor_share
from sffscan.stages.depth import DEFAULT_METHOD, DEPTH_METHODS, depth_from_focus
from sffscan.stages.depth_study import _Scores, format_table, leave_one_family_out
from sffscan.stages.depth_study_grid import CANDIDATES, THRESHOLDS, width_switch
from sffscan.stages.depth_uncertainty import depth_uncertainty, height_uncertainty_um
from sffscan.stages.focus_measure import focus_measure
from sffscan.stages.sim.families import CROSSED_FAMILIES, FAMILIES, family_names, family_stack
from sffscan.stages.uncertainty_fit import UncertaintyTerms


def test_every_family_renders_a_valid_stack() -> None:
    for fam in FAMILIES + CROSSED_FAMILIES:
        s = family_stack(fam.name, 7, size_px=32)
        n = s.images.shape[0]
        assert 20 <= n <= 100 and s.images.shape[1:] == (32, 32)
        assert s.images.dtype == np.float32 and 0.0 <= s.images.min() <= s.images.max() <= 1.0
        assert s.focus_um.shape == (n,) and s.truth_um.shape == (32, 32)
        assert np.isfinite(s.truth_um).all()
        assert s.truth_um.min() >= s.focus_um[0] and s.truth_um.max() <= s.focus_um[-1]
        bits = int(s.info["bits"])
        codes = s.images * (2**bits - 1)
        np.testing.assert_allclose(codes, np.round(codes), atol=2e-3)  # quantised
    a, b = family_stack("steps", 3, size_px=32), family_stack("steps", 3, size_px=32)
    np.testing.assert_array_equal(a.images, b.images)  # a seed is a stack
    c = family_stack("steps", 4, size_px=32)
    assert not np.array_equal(a.truth_um, c.truth_um) or a.images.shape != c.images.shape
    with pytest.raises(ValueError, match="unknown family 'nope'"):
        family_stack("nope", 0)


def test_a_mixed_texture_varies_within_the_image_and_leaves_uniform_stacks_alone() -> None:
    """``texture="mixed"`` (bench/bench_mixed_texture.py): the in-focus image's local
    contrast varies more from place to place than with one texture; a uniform family's
    stacks are the same with or without the option in the model (its draws come first)."""
    from dataclasses import replace

    from sffscan.stages.sim.families import STEP_UM, Family

    def local_contrast_spread(fam: Family, seed: int) -> float:
        st = family_stack(fam, seed)
        im = st.images[int(round(float(st.truth_um.mean()) / STEP_UM))]  # a flat in focus
        tiles = im.reshape(8, 8, 8, 8).std(axis=(1, 3))
        return float(tiles.std() / tiles.mean())

    flat = Family("flat-clean", surface="flat", noise="none", bits=(12,))
    mixed = replace(flat, texture="mixed")
    uni = [local_contrast_spread(flat, s) for s in range(4)]
    mix = [local_contrast_spread(mixed, s) for s in range(4)]
    assert np.mean(mix) > 1.2 * np.mean(uni), (uni, mix)  # 0.35 vs 0.25 when written
    a = family_stack(FAMILIES[0], 5, size_px=32)
    b = family_stack(replace(FAMILIES[0], texture="uniform"), 5, size_px=32)
    np.testing.assert_array_equal(a.images, b.images)
    assert not np.array_equal(
        family_stack(replace(FAMILIES[0], texture="mixed"), 5, size_px=32).images, a.images)


def test_the_scatter_blur_model_spills_defocused_light_where_gather_does_not() -> None:
    """``blur_model="scatter"``: each world point spreads its light over its own blur. On a
    plane the blur is the same everywhere and both models render the same image; at a step
    whose near side is in focus the far side's light spills over the edge onto the focused
    side (scatter), where gather leaves the focused side the sharp texture; light is
    conserved; the draws (truth, noise) are the gather stack's; an unknown model is named."""
    from dataclasses import replace

    from sffscan.stages.sim.families import Family, _bank, _scatter

    plane = Family("plane", surface="flat", noise="none", bits=(12,))
    a = family_stack(plane, 2, size_px=32, blur_model="gather")
    b = family_stack(plane, 2, size_px=32, blur_model="scatter")
    np.testing.assert_array_equal(a.truth_um, b.truth_um)
    assert a.images.shape == b.images.shape and not np.array_equal(a.images, b.images)
    # one radius everywhere (between the bank's 3rd and 4th): the two models agree
    tex = np.random.default_rng(0).random((48, 32)).astype(np.float32)
    bank = _bank(tex, "gauss")
    from sffscan.stages.sim.families import BANK_RADII_PX as radii_all
    i3, t3 = np.full((48, 32), 3, np.intp), np.full((48, 32), 0.25)
    gathered = 0.75 * bank[3] + 0.25 * bank[4]
    np.testing.assert_allclose(_scatter(tex, i3, t3, radii_all, "gauss"), gathered, atol=1e-5)
    # a step: columns 0..31 radius 0 (in focus), 32..63 radius 4 px
    radii = np.array([0.0, 4.0])
    tex = np.random.default_rng(1).random((48, 64)).astype(np.float32)
    i = np.zeros((48, 64), np.intp)
    t = np.where(np.arange(64) < 32, 0.0, 1.0)[None, :].repeat(48, axis=0)
    img = _scatter(tex, i, t, radii, "gauss")
    near_edge = (slice(16, 32), slice(28, 32))  # focused side, within the blur's reach
    far_from = (slice(16, 32), slice(0, 12))  # 5 sigma from the edge
    np.testing.assert_allclose(img[far_from], tex[far_from], atol=1e-5)  # sharp, unchanged
    assert np.mean(img[near_edge] - tex[near_edge]) > 0.05  # the defocused side's spill
    np.testing.assert_allclose(img.sum(), tex.sum(), rtol=1e-3)  # light conserved
    with pytest.raises(ValueError, match="blur_model must be one of"):
        family_stack(replace(plane), 2, size_px=32, blur_model="splat")  # type: ignore[arg-type]


def _mean_curve(name: str) -> tuple[np.ndarray, int]:
    """The mean GLVM curve of a flat plate of ``name``'s optics (60 levels, no noise) and
    the level nearest the plate."""
    from dataclasses import replace

    from sffscan.stages.focus_measure import focus_measure

    fam = next(f for f in FAMILIES if f.name == name)
    fam = replace(fam, surface="flat", noise="none", bits=(12,))
    s = family_stack(fam, 1, size_px=48, n_levels=60)
    vol = focus_measure(s.images, window=9)[:, 8:-8, 8:-8]
    return vol.mean(axis=(1, 2)), int(round(float(np.median(s.truth_um)) / 10.0))


def test_lens_blur_is_lopsided_and_even_blur_is_not() -> None:
    """Even blur grows the same above and below focus; a thin lens' (even in 1/z) faster
    below than above, and faster at the near end of the range than at the far end. The
    rendered plate's curve peaks at the plate's level."""
    from sffscan.stages.sim.families import _blur_radius

    even, lens = FAMILIES[0], next(f for f in FAMILIES if f.blur == "lens")
    z = np.array([20.0])
    for d in (1.0, 4.0):
        assert _blur_radius(even, z, 20 - d, 1.0, 60) == _blur_radius(even, z, 20 + d, 1.0, 60)
        below = _blur_radius(lens, z, 20 - d, 1.0, 60)[0]
        above = _blur_radius(lens, z, 20 + d, 1.0, 60)[0]
        assert below > (1.0 + 0.005 * d) * above
    near = _blur_radius(lens, np.array([2.0]), 3.0, 1.0, 60)[0]
    far = _blur_radius(lens, np.array([56.0]), 57.0, 1.0, 60)[0]
    assert near > 5 * far
    for name in ("even-gauss", "lens-gauss", "pillbox"):
        curve, k = _mean_curve(name)
        assert abs(int(np.argmax(curve)) - k) <= 1, name


def test_width_switch_and_curve_width() -> None:
    n = 40
    k = np.arange(n, dtype=np.float64).reshape(n, 1, 1)
    narrow = np.exp(-((k - 20.0) ** 2) / (2 * 1.5**2)) + 0.1
    wide = np.exp(-((k - 20.0) ** 2) / (2 * 6.0**2)) + 0.1
    w = curve_width(np.concatenate([narrow, wide], axis=2))
    assert w[0, 0] == pytest.approx(1.5, abs=0.1) and w[0, 1] == pytest.approx(6.0, abs=0.3)
    spc, ad = np.zeros((1, 2), np.float32), np.ones((1, 2), np.float32)
    np.testing.assert_array_equal(width_switch(spc, ad, w, threshold=3.0), [[1.0, 0.0]])
    np.testing.assert_array_equal(width_switch(spc, ad, w, threshold=math.inf), ad)


def test_protocol_holds_out_each_family() -> None:
    fams = ["even-gauss", "slopes", "flat-fine-8bit"]
    t = leave_one_family_out(families=fams, seeds=1, size_px=32)
    assert list(t.rmse) == fams and set(t.tuned) == set(fams)
    assert all(v["width-switch"] in THRESHOLDS for v in t.tuned.values())
    assert all(v["scatter-select"] in CANDIDATES["scatter-select"] for v in t.tuned.values())
    assert t.methods == (*DEPTH_METHODS, *CANDIDATES) and t.chosen in t.methods
    for row in t.rmse.values():
        assert set(row) == set(t.methods)
        assert all(np.isfinite(v) and v >= 0 for v in row.values())
    # the worst ratio is the largest held-out ratio of each method to the row's best
    for m in t.methods:
        ratios = [r[m] / min(r[k] for k in DEPTH_METHODS) for r in t.rmse.values()]
        assert t.worst_ratio[m] == pytest.approx(max(ratios))
    md = format_table(t)
    assert md.count("\n") == len(fams) + 2 and "worst ratio" in md
    with pytest.raises(ValueError, match="at least 2 families"):
        leave_one_family_out(families=["steps"], seeds=1)


def test_the_held_out_family_is_not_used_for_tuning(monkeypatch: pytest.MonkeyPatch) -> None:
    """The threshold tuned for a family does not change when only that family's data
    change (its held-out scores do)."""
    import sffscan.stages.depth_study as ds

    fams = ["even-gauss", "slopes", "pillbox"]
    base = ds.leave_one_family_out(families=fams, seeds=1, size_px=32)
    real = ds.family_stack

    def shifted(name: str, seed: int, **kw: object) -> object:
        return real("ends" if name == "pillbox" else name, seed, **kw)  # type: ignore[arg-type]

    monkeypatch.setattr(ds, "family_stack", shifted)
    other = ds.leave_one_family_out(families=fams, seeds=1, size_px=32)
    assert other.tuned["pillbox"] == base.tuned["pillbox"]
    assert other.rmse["pillbox"] != base.rmse["pillbox"]


def test_study_families_command(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    out = tmp_path / "st"
    assert main(["study", "--families", "--family", "even-gauss,slopes", "--seeds", "1",
                 "-o", str(out)]) == 0
    text = capsys.readouterr().out
    assert "| held out |" in text and "chosen by the held-out results" in text
    assert "90 % over stacks" in text  # each row's spread over its stacks
    with (out / "held_out.csv").open() as f:
        rows = list(csv.DictReader(f))
    assert len(rows) == 2 * (len(DEPTH_METHODS) + len(CANDIDATES))
    assert {r["set"] for r in rows} == {"even-gauss", "slopes"}
    assert min(float(r["ratio_to_best"]) for r in rows if r["method"] in DEPTH_METHODS) == 1.0
    assert (out / "held_out.md").read_text().startswith("| held out |")
    assert "90 % over stacks" in (out / "held_out.md").read_text()
    assert main(["study", "--families", "--family", "even-gauss,nope", "-o", str(out)]) == 2
    assert "nope" in capsys.readouterr().err
    assert main(["study", "--families", "--seeds", "0", "-o", str(out)]) == 2
    # the second generator: the same seeds with the blur scattered, said in the summary
    capsys.readouterr()
    sc = tmp_path / "sc"
    assert main(["study", "--families", "--family", "even-gauss,slopes", "--seeds", "1",
                 "--blur-model", "scatter", "-o", str(sc)]) == 0
    assert "rendered with the scatter blur model" in capsys.readouterr().out
    with (sc / "held_out.csv").open() as f:
        scattered = {(r["set"], r["method"]): r["rmse_levels"] for r in csv.DictReader(f)}
    assert scattered != {(r["set"], r["method"]): r["rmse_levels"] for r in rows}
    with pytest.raises(SystemExit):
        main(["study", "--families", "--blur-model", "splat", "-o", str(sc)])


def test_family_names() -> None:
    assert family_names() == [f.name for f in FAMILIES] and len(set(family_names())) >= 8
    both = family_names(crossed=True)
    assert both[:len(FAMILIES)] == family_names() and len(set(both)) == len(both)
    assert both[len(FAMILIES):] == [f.name for f in CROSSED_FAMILIES]


def test_study_crossed_families(tmp_path: Path, capsys: pytest.CaptureFixture[str],
                                monkeypatch: pytest.MonkeyPatch) -> None:
    """--crossed runs the protocol on the study's families and the crossed ones (the
    protocol itself stubbed to record the names: the full run takes 15 s); a crossed name
    is accepted by --family."""
    import sffscan.stages.depth_study as ds

    calls: list[list[str]] = []
    real = ds.leave_one_family_out

    def record(**kw: object) -> object:
        calls.append(list(kw["families"] or []))  # type: ignore[call-overload]
        return real(**{**kw, "families": ["slopes", "slopes-lens-noisy"], "seeds": 1,
                       "size_px": 32})  # type: ignore[arg-type]

    monkeypatch.setattr(ds, "leave_one_family_out", record)
    assert main(["study", "--families", "--crossed", "-o", str(tmp_path / "a")]) == 0
    assert calls[-1] == family_names(crossed=True)
    assert main(["study", "--families", "--family", "slopes,slopes-lens-noisy", "--seeds",
                 "1", "-o", str(tmp_path / "b")]) == 0
    assert calls[-1] == ["slopes", "slopes-lens-noisy"]
    assert "slopes-lens-noisy" in capsys.readouterr().out


def test_adaptive_on_a_family_stack_is_finite() -> None:
    s = family_stack("ends", 2, size_px=32)
    from sffscan.stages.focus_measure import focus_measure

    d, c = depth_from_focus(focus_measure(s.images, window=9), method="adaptive")
    assert np.isfinite(d).all() and (c >= 0).all()


def test_protocol_reports_the_uncertainty_coverage() -> None:
    fams = ["even-gauss", "steps"]
    t = leave_one_family_out(families=fams, seeds=1, size_px=32)
    assert set(t.coverage) == set(fams) and set(t.uncertainty_fit) == {*fams, "all"}
    assert all(0.0 <= c <= 1.0 for c in t.coverage.values())
    from sffscan.stages.depth_study import format_coverage

    for a, r, c in t.uncertainty_fit.values():
        assert 0.1 - 1e-9 <= a <= 100.0 + 1e-9 and 1e-4 - 1e-9 <= c <= 10.0 + 1e-9
        assert 1e-3 - 1e-9 <= r <= 100.0 + 1e-9
    assert format_coverage(t).count("\n") == len(fams) + 2


def test_depth_uncertainty_known_answers() -> None:
    from sffscan.stages.curve_shape import width_excess
    from sffscan.stages.depth_uncertainty import (
        MIX_SCALE,
        depth_range,
        depth_relief,
        depth_scatter,
        depth_uncertainty,
        uncertainty_um,
    )

    smooth = np.add.outer(np.arange(40.0), np.arange(40.0)) * 0.1  # a plane: no scatter
    assert float(depth_scatter(smooth)[6:-6, 6:-6].max()) < 1e-5  # borders: replicated
    assert float(depth_relief(smooth)[8:-8, 8:-8].max()) < 1e-5  # nor relief
    rng = np.random.default_rng(1)
    noisy = smooth + rng.normal(0.0, 0.5, smooth.shape)
    s = depth_scatter(noisy)
    assert 0.3 < float(np.median(s)) < 0.7  # about the noise (the median takes a little)
    q = depth_relief(noisy)
    # white noise about its 9 x 9 mean: sigma sqrt(1 - 1/81), RMS over 81 px
    assert float(np.median(q)) == pytest.approx(0.5 * math.sqrt(80 / 81), rel=0.1)
    width = np.full(smooth.shape, 4.0)
    sig = depth_uncertainty(noisy, width, scatter_scale=2.0, relief_scale=0.5,
                            floor_levels=0.1)
    np.testing.assert_allclose(sig, np.sqrt((2.0 * s) ** 2 + (0.5 * q) ** 2 + 0.1**2),
                               rtol=1e-5)
    # a bump of the window's size: the 5 x 5 median follows it (little scatter), the 9 x 9
    # mean does not (its relief); a sinusoid of 9 px period, amplitude 1: RMS about the
    # box mean 1 / sqrt 2 (the box of 9 px averages a whole period to 0 along x)
    bump = np.sin(2 * np.pi * np.arange(40) / 9.0)[None, :] * np.ones((40, 1))
    np.testing.assert_allclose(depth_relief(bump)[10:-10, 10:-10], math.sqrt(0.5), rtol=1e-4)
    assert float(depth_scatter(bump)[10:-10, 10:-10].max()) < 0.6 * math.sqrt(0.5)
    # the depth's range over 19 x 19 px: a step of 6 levels within 9 px, 0 beyond; an
    # isolated stray maximum does not count (the 5 x 5 median)
    step = np.where(np.arange(40) < 20, 0.0, 6.0)[None, :] * np.ones((40, 1))
    step[5, 5] = 30.0
    r = depth_range(step, window=9)
    assert r[20, 11] == pytest.approx(6.0) and r[20, 28] == pytest.approx(6.0)
    assert r[20, 10] == 0.0 and r[20, 29] == 0.0 and r[5, 5] == 0.0
    # a curve twice as wide as those about it (a window that sees two heights)
    wide = width.copy()
    wide[20, 20] = 8.0
    far = np.full(smooth.shape, 100.0)  # heights far apart about it: no cap
    x = width_excess(wide, far, window=9)
    mean = (8.0 + 360 * 4.0) / 361  # the mean width over 19 x 19 px
    assert x[20, 20] == pytest.approx(math.sqrt(64.0 - mean**2), rel=1e-4)
    assert x[0, 0] == 0.0 and x[20, 21] == 0.0  # narrower than the mean: no excess
    # capped at half the depth's range (a mix of heights D apart widens by <= D / 2)
    cap = width_excess(wide, np.full(smooth.shape, 2.0), window=9)
    assert cap[20, 20] == pytest.approx(1.0) and cap.max() == pytest.approx(1.0)
    # the depth map beside it: a plane rising 0.1 level per px (range 3.6 levels)
    sig = depth_uncertainty(smooth, wide, scatter_scale=2.0, relief_scale=1.0,
                            floor_levels=0.0)
    assert sig[20, 20] == pytest.approx(MIX_SCALE * min(x[20, 20], 1.8), rel=1e-4)
    np.testing.assert_allclose(floor_share(np.array([10.0, 0.0, 4.0]),
                                           np.array([0.5, 0.0, 0.0]), 10), [0.5, 1.0, 0.0])
    um = uncertainty_um(np.ones((1, 3)), np.array([[0.2, 1.5, 9.0]]),
                        focus_heights_um=np.array([0.0, 10.0, 30.0]))
    np.testing.assert_allclose(um, [[10.0, 20.0, 20.0]])


def test_height_uncertainty_from_sums_matches_the_volume_path() -> None:
    """The streaming form (sums and minima) gives the whole-volume form's sigma, in µm."""
    from sffscan.stages.depth import focus_sums

    s = family_stack("steps", 0, size_px=48, n_levels=30)
    vol = focus_measure(s.images, window=9)
    d = depth_from_focus(vol, method="adaptive")[0]
    sums = focus_sums(vol)
    want = depth_uncertainty(d, curve_width(vol))
    # depth_uncertainty's constants are the default method's
    got = height_uncertainty_um(d, sums, vol.min(axis=0), method=DEFAULT_METHOD, n_levels=30,
                                focus_heights_um=s.focus_um)
    np.testing.assert_allclose(got, want * 10.0, rtol=2e-3, atol=1e-3)


def test_uncertainty_fitted_without_a_family_covers_its_errors() -> None:
    """Leave one family out at a small scale: the constants fitted on the training seeds of
    four families, held-out seeds of a fifth. Steps, whose large errors are at the terraces'
    edges, where the depth map shows no scatter (the scatter and width model of 681dca9
    fitted without steps covered 0.79 .. 0.90), are never under the band (the side that
    misleads); since the excess width is one sigma, not a half (2026-12-05), they are over
    it on these seeds (0.990; 0.965 before), as in the protocol's table. Noisy steps under a
    thin lens, whose peak takes the other side of a step, were under it with half the
    excess (0.876) and are in it now (0.916): docs/depth-study.md,
    docs/depth-method-log.md."""
    from sffscan.stages.depth_study import uncertainty_sample
    from sffscan.stages.focus_measure import focus_measure
    from sffscan.stages.uncertainty_fit import fit_uncertainty, uncertainty_coverage

    def sample(name: str, seed: int) -> UncertaintyTerms:
        s = family_stack(name, seed, size_px=64)
        vol = focus_measure(s.images, window=9)
        mask = np.zeros(s.truth_um.shape, bool)
        mask[4:-4, 4:-4] = True
        return uncertainty_sample(vol, s.truth_um / 10.0, mask)

    train = [[sample(f, seed) for seed in (0, 1)]
             for f in ("even-gauss", "lens-gauss", "pillbox", "ends")]
    fit = fit_uncertainty(train)
    steps = uncertainty_coverage([sample("steps", seed) for seed in (3, 4, 5)], fit)
    noisy = uncertainty_coverage([sample("steps-lens-noisy", seed) for seed in (3, 4, 5)], fit)
    print(f"fit without them: {fit}; seeds 3-5: steps {steps:.3f}, steps-lens-noisy {noisy:.3f}")
    assert steps >= 0.90
    assert 0.90 <= noisy <= 0.98


def test_uncertainty_covers_held_out_errors_of_a_noisy_family() -> None:
    """The shipped constants on seeds the fit never saw (seeds 10, 11): between 90 % and
    98 % of the pixels within 2 sigma."""
    from sffscan.stages.depth import focus_sums
    from sffscan.stages.depth_uncertainty import height_uncertainty_um
    from sffscan.stages.focus_measure import focus_measure

    inside = []
    for seed in (10, 11):
        s = family_stack("even-noisy", seed)
        vol = focus_measure(s.images, window=9)
        d = depth_from_focus(vol, method="adaptive")[0]
        sig = height_uncertainty_um(d, focus_sums(vol), vol.min(axis=0), method="adaptive",
                                    n_levels=vol.shape[0], focus_heights_um=s.focus_um)
        err = np.abs(d * 10.0 - s.truth_um)[4:-4, 4:-4]
        inside.append(err <= 2 * sig[4:-4, 4:-4])
    share = float(np.mean(inside))
    print(f"even-noisy seeds 10, 11: {share:.3f} within 2 sigma")
    assert 0.90 <= share <= 0.98


def test_a_depth_block_crosses_processes_with_its_uncertainty() -> None:
    """The wire format carries the block's uncertainty (and a block without one)."""
    from sffscan.pipeline.wire import _build, _fields
    from sffscan.stages.messages import DepthBlock, DepthBlockHeader

    hdr = DepthBlockHeader(x0_px=3, y0_px=4, width_px=2, height_px=2, pass_index=0,
                           complete_columns=2, incomplete_columns=0)
    arrays = [np.full((2, 2), v, np.float32) for v in (1.0, 2.0, 3.0, 4.0)]
    for unc in (arrays[3], None):
        block = DepthBlock(hdr, arrays[0], arrays[1], arrays[2], unc)
        sent: list[np.ndarray] = []
        got = _build(_fields(block, sent), sent)
        assert got.header == hdr and len(sent) == (4 if unc is not None else 3)
        np.testing.assert_array_equal(got.confidence, arrays[2])
        if unc is None:
            assert got.uncertainty_um is None
        else:
            np.testing.assert_array_equal(got.uncertainty_um, unc)


def test_candidate_estimators_known_answers() -> None:
    """The weighted log-Gaussian fit finds a sampled Gaussian on a floor; the windowed PC a
    symmetric peak; both at sub-level positions either side of the window's centre."""
    from sffscan.stages.depth_candidates import gauss_window_fit, half_height_run, window_pc

    n = 40
    k = np.arange(n, dtype=np.float64).reshape(n, 1, 1)
    peaks = np.array([[17.3, 18.8, 20.0]])
    vol = np.exp(-((k - peaks) ** 2) / (2 * 1.6**2)) + 0.2
    centre = np.round(peaks).astype(int)
    fit = gauss_window_fit(vol, centre, np.zeros((1, 3)), half_window=5)
    np.testing.assert_allclose(fit, peaks, atol=0.02)  # the floor is the curve's minimum
    run = half_height_run(vol, centre)
    assert (run >= 3).all() and (run <= 5).all()  # FWHM 3.8 levels
    pc = window_pc(vol, centre, factor=4.0)
    np.testing.assert_allclose(pc, peaks, atol=0.05)
    flat = np.ones((n, 1, 1))  # no maximum: the fallback
    assert gauss_window_fit(flat, np.array([[7]]), np.array([[3.5]]), half_window=3)[0, 0] == 3.5


def test_half_height_count_is_not_cut_by_a_dip_where_the_run_is() -> None:
    """A curve whose levels 18..22 lie above half height (peak 1 at level 20 over a floor
    of 0), level 21 dipping to 0.4: the run through the maximum stops at the dip (18..20,
    3 levels), the count does not (4); without the dip both are 5. Levels beyond ``reach``
    are not counted."""
    from sffscan.stages.depth_candidates import half_height_count, half_height_run

    vol = np.zeros((40, 1, 2))
    vol[18:23, 0, :] = [[0.7, 0.7], [0.9, 0.9], [1.0, 1.0], [0.4, 0.95], [0.6, 0.6]]
    vol[35, 0, :] = 0.8  # above half height, 15 levels from the centre: beyond reach 14
    centre = np.full((1, 2), 20)
    assert half_height_run(vol, centre, reach=14).tolist() == [[3, 5]]
    assert half_height_count(vol, centre, reach=14).tolist() == [[4, 5]]
    assert half_height_count(vol, centre, reach=15).tolist() == [[5, 6]]
    flat = np.ones((40, 1, 1))  # no level above half height: the maximum alone, as the run
    assert half_height_count(flat, np.full((1, 1), 20)).tolist() == [[1]]
    assert half_height_run(flat, np.full((1, 1), 20)).tolist() == [[1]]


def test_spc_bias_adds_in_quadrature_where_the_default_took_spc() -> None:
    """depth_uncertainty's ``b``: sigma^2 grows by exactly b^2 (levels; in µm times the
    focus step), nothing else changes; a stack that takes SPC carries its departure |d| as
    b (stack_choice), a scan block of it the same (block_choice), and a stack or block that
    takes a peak (the fallback, or a peak method by name) the size of its curves' centroid
    pull (fallback_bias)."""
    from sffscan.stages.block_depth import SPC_BLOCKS, block_choice
    from sffscan.stages.depth import first_argmax, focus_sums
    from sffscan.stages.depth_choice import stack_choice
    from sffscan.stages.depth_levels import median_filter_levels
    from sffscan.stages.depth_spc import spc_departure
    from sffscan.stages.depth_statistics import pull_statistics, takes_centroid

    s = family_stack("even-gauss", 0, size_px=48, n_levels=30)
    vol = focus_measure(s.images, window=9)
    a = first_argmax(vol)
    d = depth_from_focus(vol, method="shape_select", argmax=a)[0]
    w = curve_width(vol)
    plain = depth_uncertainty(d, w).astype(np.float64)
    biased = depth_uncertainty(d, w, bias_levels=0.4).astype(np.float64)
    np.testing.assert_allclose(biased ** 2, plain ** 2 + 0.16, rtol=1e-5)
    step = float(s.focus_um[1] - s.focus_um[0])
    um = height_uncertainty_um(d, focus_sums(vol), vol.min(axis=0), method="shape_select",
                               n_levels=30, focus_heights_um=s.focus_um, bias_levels=0.4)
    um0 = height_uncertainty_um(d, focus_sums(vol), vol.min(axis=0), method="shape_select",
                                n_levels=30, focus_heights_um=s.focus_um)
    np.testing.assert_allclose(um.astype(np.float64) ** 2,
                               um0.astype(np.float64) ** 2 + (0.4 * step) ** 2, rtol=1e-4)
    choice = stack_choice(vol, a)  # even, clean curves: SPC
    pull, noise = pull_statistics(vol, a)
    # the departure about the argmax filtered as the depth takes it (11 px by default)
    dep = spc_departure(vol, median_filter_levels(a, 11, 30),
                        centroid=takes_centroid(pull, noise=noise))
    assert dep != spc_departure(vol, a, centroid=takes_centroid(pull, noise=noise))
    # the bias of SPC averaged with the fallback: SPC's share of its departure
    assert choice.spc and 0.5 <= choice.weight <= 1.0
    assert choice.bias == pytest.approx(choice.weight * abs(dep[0])) and choice.bias > 0
    big = focus_measure(family_stack("even-gauss", 0, size_px=160, n_levels=30).images,
                        window=9)  # a block judges every 16th row and 8th column
    method, bias, floor, locking, weight = block_choice(big, first_argmax(big))
    # SPC's share no peak locking; the fallback's share its own
    fallback = block_choice(big, first_argmax(big), method="adaptive_centroid")
    assert locking == pytest.approx((1.0 - weight) * fallback.locking, abs=1e-12)
    assert method in SPC_BLOCKS and bias > 0 and floor is not None and floor.width > 0
    assert 0.5 <= weight <= 1.0 and fallback.weight == 0.0
    # a scan's block gives its filtered argmax at the judged grid (10 x 20 curves here)
    with pytest.raises(ValueError, match=r"judged curves' \(10, 20\) pixels"):
        block_choice(big, first_argmax(big), centre=lambda: np.zeros((1, 1), np.intp))
    lopsided = family_stack("lens-pillbox-noisy", 0, size_px=48, n_levels=30)
    lv = focus_measure(lopsided.images, window=9)
    la = first_argmax(lv)
    pull, noise = pull_statistics(lv, la)
    from sffscan.stages.block_depth import block_peak_bias
    from sffscan.stages.depth_choice import (
        centroid_locking,
        fallback_bias,
        method_bias,
        method_locking,
    )
    from sffscan.stages.depth_statistics import sampled_curves

    # the fallback's bias: the size of its curves' centroid pull (fallback_bias); where it
    # takes the 5-level centroid (as here), beside it that centroid's locking at the judged
    # curves' median width (added where the scatter cannot show it)
    assert takes_centroid(pull, noise=noise)
    locking = centroid_locking(float(np.median(curve_width(lv)[(la >= 2) & (la <= 27)])))
    assert 0.01 < locking < 0.07
    refused = stack_choice(lv, la)
    assert refused[:4] == (False, abs(pull), pull, noise) and abs(pull) > 0
    assert refused.locking == pytest.approx(locking, rel=1e-6)
    assert refused.floor is None
    sample = sampled_curves(lv, la)
    assert sample is not None
    block_pull, block_noise = pull_statistics(*sample)
    assert takes_centroid(block_pull, noise=block_noise)
    judged = (sample[1] >= 2) & (sample[1] <= 27) & np.broadcast_to(sample[2], sample[1].shape)
    block_locking = centroid_locking(float(np.median(curve_width(sample[0])[judged])))
    method, bias, floor, got_locking, weight = block_choice(lv, la)
    assert weight == 0.0  # the fallback alone
    assert method not in SPC_BLOCKS and bias == pytest.approx(abs(block_pull)) and bias > 0
    assert got_locking == pytest.approx(block_locking, rel=1e-6) and got_locking > 0
    assert floor is None  # the guard's floor only where the block takes SPC
    assert block_choice(lv, la, method="adaptive_centroid")[1::2] == pytest.approx(
        (abs(block_pull), block_locking))
    # "adaptive" takes the 3-point Gaussian: no locking (exact on a Gaussian curve)
    assert block_peak_bias(lv, la) == pytest.approx(abs(block_pull))
    assert method_bias(lv, la, "adaptive") == pytest.approx(abs(pull))
    assert method_locking(lv, la, "adaptive") == 0.0
    assert method_bias(lv, la, "adaptive_centroid") == pytest.approx(abs(pull))
    assert method_locking(lv, la, "adaptive_centroid") == pytest.approx(locking, rel=1e-6)
    assert method_bias(lv, la, "shape_select") == pytest.approx(refused.bias)
    assert method_locking(lv, la, "shape_select") == pytest.approx(locking, rel=1e-6)
    # the whole-curve and wide-window methods: the size of their depth's departure from the
    # curves' peaks (given their depth), pulled into the lopsided curves' longer flank
    from sffscan.stages.depth_statistics import peak_departure

    centre = median_filter_levels(la, 11, 30)
    for m in ("spc", "pc", "wcentroid"):
        dm = depth_from_focus(lv, method=m)[0]
        got = method_bias(lv, la, m, depth=dm)
        assert got == pytest.approx(abs(peak_departure(dm, lv, centre))) and got > 0.05
        with pytest.raises(ValueError, match=f"method '{m}': .* give the depth"):
            method_bias(lv, la, m)
    assert method_bias(lv, la, "gauss3") == 0.0  # no bias term for the other methods
    assert method_locking(lv, la, "spc") == 0.0
    assert fallback_bias(-0.3) == 0.3 and fallback_bias(float("nan")) == 0.0


def _stack(sse: dict[str, float], count: int, errors: np.ndarray) -> _Scores:
    z = np.zeros(count, np.float32)
    return _Scores(sse, count, errors.astype(np.float32), z, z, z, z)


def test_stack_spread_known_answers() -> None:
    from sffscan.stages.depth import DEFAULT_METHOD
    from sffscan.stages.depth_study import stack_spread
    from sffscan.stages.uncertainty_fit import UncertaintyConstants

    methods = ("gauss3", DEFAULT_METHOD)
    c = UncertaintyConstants(1.0, 1.0, 0.5)  # sigma 0.5 everywhere: |error| <= 1 covered
    # identical stacks: every resample is the same pool, the interval a point
    same = [_stack({"gauss3": 4.0, DEFAULT_METHOD: 9.0}, 4, np.array([0.5, 2, 0.1, 3]))] * 3
    sp = stack_spread(same, methods=methods, constants=c)
    assert sp.stacks == 3
    assert sp.ratio == pytest.approx((1.5, 1.5)) and sp.coverage == pytest.approx((0.5, 0.5))
    # two stacks: the default best on one, twice the best's RMSE on the other; the pools
    # are {A, A}, {A, B}, {B, B} (1/4, 1/2, 1/4): the 90 % interval spans the extremes
    a = _stack({"gauss3": 4.0, DEFAULT_METHOD: 4.0}, 4, np.array([0.0, 0, 0, 0]))
    b = _stack({"gauss3": 1.0, DEFAULT_METHOD: 4.0}, 4, np.array([5.0, 5, 5, 5]))
    sp = stack_spread([a, b], methods=methods, constants=c, resamples=4000)
    assert sp.ratio == pytest.approx((1.0, 2.0)) and sp.coverage == pytest.approx((0.0, 1.0))
    # the same seed, the same interval
    assert stack_spread([a, b], methods=methods, constants=c) == stack_spread(
        [a, b], methods=methods, constants=c)
    with pytest.raises(ValueError, match="no held-out stack"):
        stack_spread([], methods=methods, constants=c)


def test_protocol_reports_each_familys_spread_over_stacks() -> None:
    from sffscan.stages.depth_study import format_spread

    fams = ["even-gauss", "steps"]
    t = leave_one_family_out(families=fams, seeds=2, size_px=32)
    assert set(t.spread) == set(fams)
    for f, sp in t.spread.items():
        best = min(t.rmse[f][m] for m in DEPTH_METHODS)
        from sffscan.stages.depth import DEFAULT_METHOD

        point = t.rmse[f][DEFAULT_METHOD] / best
        assert sp.stacks == 2 and sp.ratio[0] - 1e-9 <= point <= sp.ratio[1] + 1e-9
        assert sp.coverage[0] - 1e-9 <= t.coverage[f] <= sp.coverage[1] + 1e-9
    md = format_spread(t)
    assert md.count("\n") == len(fams) + 1 and "90 % over stacks" in md


def test_held_out_seeds_can_start_anywhere_after_the_training_seeds(
        tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    import sffscan.stages.depth_study as ds

    fams = ["even-gauss", "steps"]
    seen: list[int] = []
    real = ds.family_stack

    def spy(name: str, seed: int, **kw: object) -> object:
        seen.append(seed)
        return real(name, seed, **kw)  # type: ignore[arg-type]

    with pytest.MonkeyPatch.context() as mp:
        mp.setattr(ds, "family_stack", spy)
        t = ds.leave_one_family_out(families=fams, seeds=1, size_px=32, held_out_from=5)
    assert sorted(set(seen)) == [0, 5]  # training seed 0, held-out seed 5 (not 1)
    plain = ds.leave_one_family_out(families=fams, seeds=1, size_px=32)
    assert t.rmse != plain.rmse
    with pytest.raises(ValueError, match="overlap the training seeds"):
        ds.leave_one_family_out(families=fams, seeds=2, held_out_from=1)
    out = tmp_path / "st"
    assert main(["study", "--families", "--family", "even-gauss,steps", "--seeds", "1",
                 "--held-out-from", "5", "-o", str(out)]) == 0
    assert "held out 5 .. 5" in capsys.readouterr().out
    assert main(["study", "--families", "--family", "even-gauss,steps", "--seeds", "2",
                 "--held-out-from", "1", "-o", str(out)]) == 2
    assert "--held-out-from 1" in capsys.readouterr().err
