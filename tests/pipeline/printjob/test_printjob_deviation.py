"""Deviation and verdicts: pass, fail at the right place, unknown on low confidence or failure."""

from __future__ import annotations

import numpy as np
import pytest
from sffscan.pipeline.printjob.deviation import (
    Tolerances,
    compare_layer,
    failed_layer_verdict,
    fit_printer_mapping,
    worst,
)
from sffscan.pipeline.printjob.expected import ExpectedMap, Grid, PrinterMapping
from sffscan.pipeline.printjob.gcode import GcodeProgram, parse_gcode

GRID = Grid((0.0, 0.0), 50.0, (120, 200))  # 10 x 6 mm at 50 µm/px


def _two_squares() -> ExpectedMap:
    """Object 0: 3 x 3 mm at (1, 1.5) mm, object 1 at (6, 1.5) mm, both 400 µm high."""
    h = np.zeros(GRID.shape, np.float32)
    lab = np.full(GRID.shape, -1, np.int16)
    for k, x0 in enumerate((20, 120)):
        h[30:90, x0:x0 + 60] = 400.0
        lab[30:90, x0:x0 + 60] = k
    return ExpectedMap(h, lab, 1)


def _noisy(exp: ExpectedMap, seed: int = 0) -> np.ndarray:
    return exp.height_um + np.random.default_rng(seed).normal(0, 10.0, GRID.shape).astype(
        np.float32)


def test_a_good_layer_passes_and_a_blob_fails_its_object_at_its_place() -> None:
    exp = _two_squares()
    meas = _noisy(exp)
    conf = np.ones(GRID.shape, np.float32)
    _, v = compare_layer(meas, exp, grid=GRID, objects=["a", "b"], layer=1, z_mm=0.4,
                         confidence=conf)
    assert v.verdict == "pass" and [o.verdict for o in v.objects] == ["pass", "pass"]
    assert v.objects[0].p95_abs_um < 30
    # a 1 x 1 mm blob +300 µm on object b, centred at (7.5, 3.0) mm
    meas[50:70, 140:160] += 300.0
    dev, v = compare_layer(meas, exp, grid=GRID, objects=["a", "b"], layer=1, z_mm=0.4,
                           confidence=conf, tolerances=Tolerances(action="pause"),
                           mapping=PrinterMapping(offset_um=(-1000.0, 0.0)))
    assert v.verdict == "fail" and v.action == "pause"
    a, b = v.objects
    assert a.verdict == "pass" and b.verdict == "fail"
    assert b.excess_mm2 == pytest.approx(1.0, abs=0.05) and b.missing_mm2 == 0
    assert b.defect_xy_um == pytest.approx((7475.0, 2975.0), abs=30)
    assert b.defect_xy_mm == pytest.approx((8.475, 2.975), abs=0.03)
    assert np.nanmedian(dev[55:65, 145:155]) == pytest.approx(300.0, abs=15)


def test_material_pushed_off_the_part_belongs_to_the_nearest_object() -> None:
    exp = _two_squares()
    meas = _noisy(exp)
    meas[30:90, 80:100] = 400.0  # a 1 mm strip printed beside object a (layer shift)
    _, v = compare_layer(meas, exp, grid=GRID, objects=["a", "b"], layer=1, z_mm=0.4)
    assert [o.verdict for o in v.objects] == ["fail", "pass"]
    assert v.objects[0].excess_mm2 > 2.0


def test_low_confidence_and_uncertainty_are_unknown_never_pass() -> None:
    exp = _two_squares()
    meas = _noisy(exp)
    conf = np.ones(GRID.shape, np.float32)
    conf[:, 100:] = 0.0  # object b is dark: no confidence
    _, v = compare_layer(meas, exp, grid=GRID, objects=["a", "b"], layer=1, z_mm=0.4,
                         confidence=conf)
    assert [o.verdict for o in v.objects] == ["pass", "unknown"]
    assert v.verdict == "unknown"
    assert v.objects[1].unknown_fraction > 0.9
    # a defect hidden under low confidence is not judged either way: unknown, not pass
    meas[50:70, 140:160] -= 300.0
    _, v = compare_layer(meas, exp, grid=GRID, objects=["a", "b"], layer=1, z_mm=0.4,
                         confidence=conf)
    assert v.objects[1].verdict == "unknown"
    unc = np.full(GRID.shape, 5.0, np.float32)
    unc[:, :100] = 500.0  # an uncertainty above the tolerance
    _, v = compare_layer(_noisy(exp), exp, grid=GRID, objects=["a", "b"], layer=1, z_mm=0.4,
                         uncertainty_um=unc)
    assert [o.verdict for o in v.objects] == ["unknown", "pass"]
    nan = _noisy(exp)
    nan[:, :100] = np.nan  # not scanned
    _, v = compare_layer(nan, exp, grid=GRID, objects=["a", "b"], layer=1, z_mm=0.4)
    assert v.objects[0].verdict == "unknown"


def test_a_defect_cut_by_uncertain_pixels_is_one_blob_of_its_out_pixels() -> None:
    """A defect's slopes are steps whose uncertainty exceeds the tolerance: those pixels are
    unknown, never out, but they do not cut the defect into blobs under the fail area (the
    print-job bench's layer-4 blob, 2026-12-05, was `warn` in pieces of 0.43 mm² and less)."""
    exp = _two_squares()
    meas = _noisy(exp)
    meas[50:70, 140:160] += 300.0  # 1 x 1 mm, +300 µm on object b
    unc = np.full(GRID.shape, 5.0, np.float32)
    unc[50:70, 149:151] = 500.0  # a ridge across it too uncertain to judge
    unc[59:61, 140:160] = 500.0
    tol = Tolerances(fail_area_mm2=0.5)
    _, v = compare_layer(meas, exp, grid=GRID, objects=["a", "b"], layer=1, z_mm=0.4,
                         uncertainty_um=unc, tolerances=tol)
    b = v.objects[1]
    assert b.verdict == "fail"
    # the out pixels only: 400 less the 76 under the ridge, 0.81 mm² in one blob
    assert b.excess_mm2 == pytest.approx(324 * 0.0025)
    assert b.defect_area_mm2 == pytest.approx(324 * 0.0025)
    assert b.unknown_fraction == pytest.approx(76 / 54**2)  # the square off its edge band
    assert b.defect_xy_um == pytest.approx((7475.0, 2975.0), abs=30)
    # not measured at all (NaN) does not join: two halves of 0.4 mm² each warn
    half = meas.copy()
    half[50:70, 149:151] = np.nan
    _, v = compare_layer(half, exp, grid=GRID, objects=["a", "b"], layer=1, z_mm=0.4,
                         tolerances=tol)
    assert v.objects[1].verdict == "warn"
    assert v.objects[1].defect_area_mm2 == pytest.approx(180 * 0.0025)


def test_a_failed_scan_is_unknown_and_worst_orders_verdicts() -> None:
    v = failed_layer_verdict(3, 0.8, ["a", "b"], reason="the scan timed out")
    assert v.verdict == "unknown" and {o.verdict for o in v.objects} == {"unknown"}
    assert "timed out" in v.reason
    assert worst(["pass", "unknown"]) == "unknown"
    assert worst(["unknown", "warn"]) == "warn"
    assert worst(["warn", "fail", "pass"]) == "fail"
    assert worst([]) == "unknown"


def test_small_noise_blobs_and_the_edge_band_are_not_alarms() -> None:
    exp = _two_squares()
    meas = _noisy(exp)
    meas[40, 40] += 500.0  # one hot pixel
    meas[:, 19:21] = 0.0  # the focus window smears the step: the edge band is not judged
    _, v = compare_layer(meas, exp, grid=GRID, objects=["a", "b"], layer=1, z_mm=0.4)
    assert v.verdict == "pass"
    _, v = compare_layer(meas, exp, grid=GRID, objects=["a", "b"], layer=1, z_mm=0.4,
                         tolerances=Tolerances(edge_band_um=0.0, min_blob_mm2=0.0,
                                               warn_area_mm2=0.001, fail_area_mm2=0.5))
    assert v.objects[0].verdict == "warn"


def _l_layer() -> tuple[GcodeProgram, Grid]:
    """An L-shaped first layer of 0.4 mm lines, and a 50 µm grid over it."""
    lines = ["M83", "G1 Z0.2"]
    for j in range(12):
        y = 1.0 + 0.4 * j
        lines += [f"G1 X1 Y{y:.2f}", f"G1 X{4 if j > 3 else 8} Y{y:.2f} E0.3"]
    return parse_gcode("\n".join(lines)), Grid((0.0, 0.0), 50.0, (160, 240))


def test_fit_printer_mapping_finds_the_translation() -> None:
    prog, grid = _l_layer()
    truth = PrinterMapping(offset_um=(730.0, -420.0))
    from sffscan.pipeline.printjob.expected import rasterise_expected

    meas = rasterise_expected(prog, grid, upto_layer=0, mapping=truth).height_um
    meas = meas + np.random.default_rng(1).normal(0, 10, meas.shape).astype(np.float32)
    fit = fit_printer_mapping(meas, prog, grid)
    assert fit.offset_um == pytest.approx(truth.offset_um, abs=25.0)  # half a pixel


def test_fit_printer_mapping_refuses_a_map_that_does_not_correlate() -> None:
    """A measured map of noise alone (no printed layer in it) gives no significant peak:
    ValueError naming the peak, not a translation."""
    prog, grid = _l_layer()
    meas = np.random.default_rng(2).normal(0, 10, grid.shape).astype(np.float32)
    with pytest.raises(ValueError, match="no significant correlation peak .*peak 0"):
        fit_printer_mapping(meas, prog, grid)
