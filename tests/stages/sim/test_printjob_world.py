"""The simulated print world: the G-code's beads, and each injected defect where it belongs."""

from __future__ import annotations

import numpy as np
import pytest
from sffscan.pipeline.printjob.expected import PrinterMapping, rasterise_expected
from sffscan.pipeline.printjob.gcode import parse_gcode
from sffscan.stages.sim.print_world import PrintDefect, PrintWorld

from tests.pipeline.printjob.test_printjob_jobstore import tiny_gcode

PROG = parse_gcode(tiny_gcode(3))
MAP = PrinterMapping()


def world(*defects: PrintDefect, layer: int = 2) -> PrintWorld:
    return PrintWorld(PROG, MAP, 50.0, (0.0, 0.0, 9000.0, 5000.0), defects=defects,
                      bead_jitter_um=0.0).at_layer(layer)


def test_without_defects_the_world_is_the_expected_surface() -> None:
    w = world()
    exp = rasterise_expected(PROG, w.grid, upto_layer=2, mapping=MAP)
    np.testing.assert_array_equal(w.true_heights(), exp.height_um)
    # the camera's window (world px) samples the raster, bilinearly between pixels
    r = w.true_heights()
    np.testing.assert_allclose(w.height_um(30.0, 40.0, 4, 3), r[40:43, 30:34])
    np.testing.assert_allclose(w.height_um(30.0, 40.5, 4, 1),
                               (r[40:41, 30:34] + r[41:42, 30:34]) / 2, rtol=1e-5)
    assert w.height_um(30.0, 44.0, 1, 1)[0, 0] == 600.0  # a bead's centre line, y = 2.2 mm
    assert w.height_um(1000.0, 1000.0, 2, 2).max() == 0.0  # beyond the raster: the bed
    assert w.texture(0.0, 0.0, 8, 8).shape == (8, 8)


def test_each_defect_changes_the_surface_as_described() -> None:
    clean = world().true_heights()
    xs, ys = world().grid.xy_um()
    at = (np.abs(ys[:, None] - 2200) < 60) & (np.abs(xs[None, :] - 6200) < 60)
    gap = world(PrintDefect("gap", 2, "right", (6.2, 2.2), size_mm=1.0)).true_heights()
    assert np.allclose((clean - gap)[at], 200.0)  # the layer is missing: one layer lower
    assert np.array_equal(world(PrintDefect("gap", 1, "right", (6.2, 2.2))).true_heights(),
                          clean)  # transient: bridged by the next layer
    blob = world(PrintDefect("blob", 2, "right", (6.2, 2.2), size_mm=0.8,
                             height_um=400.0)).true_heights()
    assert (blob - clean)[at].max() == pytest.approx(400.0, rel=0.02)
    missing = world(PrintDefect("missing_object", 1, "left")).true_heights()
    assert missing[:, :80].max() == pytest.approx(200.0)  # only layer 0 of 'left'
    assert np.array_equal(missing[:, 90:], clean[:, 90:])
    shifted = world(PrintDefect("layer_shift", 2, "right", shift_mm=(1.0, 0.0))).true_heights()
    assert shifted[44, 154] == pytest.approx(600.0) and clean[44, 154] == 0.0  # x 7.7 mm
    lifted = world(PrintDefect("lifted_corner", 1, "left", (1.0, 1.0), size_mm=2.0,
                               height_um=500.0)).true_heights()
    lift = lifted - clean
    assert lift.max() > 400 and lift[:, 90:].max() == 0.0  # the corner of 'left' only
    with pytest.raises(ValueError, match="unknown object"):
        world(PrintDefect("blob", 1, "nope"))
