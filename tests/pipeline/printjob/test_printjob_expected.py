"""Expected height maps: a single bead's width and height, layers, a model by ray casting."""

from __future__ import annotations

import math

import numpy as np
import pytest
import trimesh
from sffscan.pipeline.printjob.expected import (
    Grid,
    ModelUnitsError,
    PrinterMapping,
    bead_width_mm,
    model_top_surface,
    rasterise_expected,
)
from sffscan.pipeline.printjob.gcode import parse_gcode

D = 1.75  # filament, mm


def _e_for_width(w: float, h: float, length: float) -> float:
    area = (w - h) * h + math.pi * h * h / 4.0  # Slic3r's stadium
    return area * length / (math.pi * D * D / 4.0)


def test_a_single_straight_bead_has_its_width_and_height() -> None:
    e = _e_for_width(0.5, 0.2, 10.0)
    prog = parse_gcode(f"M83\nG1 Z0.2\nG1 X0 Y0\nG1 X10 Y0 E{e:.6f}\n")
    np.testing.assert_allclose(bead_width_mm(prog.e_mm, [10.0], [0.2],
                                             filament_diameter_mm=D), 0.5, atol=1e-5)
    grid = Grid((-1000.0, -1000.0), 10.0, (201, 1201))  # y -1..1 mm, x -1..11 mm
    exp = rasterise_expected(prog, grid, upto_layer=0)
    col = exp.height_um[:, 600]  # x = 5 mm, across the bead
    ys = -1000.0 + 10.0 * np.arange(201)
    assert col.max() == pytest.approx(200.0)
    covered = ys[col > 0]
    assert covered.min() == pytest.approx(-250.0, abs=10)
    assert covered.max() == pytest.approx(250.0, abs=10)
    assert col[ys == 0][0] == pytest.approx(200.0)
    assert col[np.isclose(ys, 150.0)][0] == pytest.approx(200.0)  # the flat top: w/2 - h/2
    # the rounded side (radius h/2 = 100 µm about y = 150, z = 100 µm)
    assert col[np.isclose(ys, 240.0)][0] == pytest.approx(100.0 + math.sqrt(100**2 - 90**2),
                                                          rel=1e-4)
    # along the bead: round caps reach 0.25 mm past each end
    row = exp.height_um[100]
    xs = -1000.0 + 10.0 * np.arange(1201)
    assert xs[row > 0].min() == pytest.approx(-250.0, abs=10)
    assert xs[row > 0].max() == pytest.approx(10250.0, abs=10)
    assert set(np.unique(exp.label)) == {-1}  # no object labels in this program


def test_layers_stack_and_the_incremental_map_equals_the_full_one() -> None:
    e = _e_for_width(0.45, 0.2, 4.0)
    lines = ["M83", "EXCLUDE_OBJECT_START NAME=a"]
    for k in range(3):
        lines.append(f"G1 Z{0.2 * (k + 1):.1f}")
        for j in range(10):
            y = 0.4 * j
            lines += [f"G1 X0 Y{y:.2f}", f"G1 X4 Y{y:.2f} E{e:.5f}"]
    prog = parse_gcode("\n".join(lines))
    grid = Grid((-500.0, -500.0), 20.0, (250, 250))
    full = rasterise_expected(prog, grid, upto_layer=2)
    step = rasterise_expected(prog, grid, upto_layer=2,
                              base=rasterise_expected(prog, grid, upto_layer=1))
    np.testing.assert_array_equal(full.height_um, step.height_um)
    np.testing.assert_array_equal(full.label, step.label)
    assert full.height_um.max() == pytest.approx(600.0)
    assert (full.label[full.height_um > 0] == 0).all()
    # a mapping moves the part: +3 mm in x
    moved = rasterise_expected(prog, grid, upto_layer=2,
                               mapping=PrinterMapping(offset_um=(1000.0, 0.0)))
    np.testing.assert_array_equal(moved.height_um[:, 50:], full.height_um[:, :-50])


def test_model_top_surface_of_a_box_by_ray_casting() -> None:
    box = trimesh.creation.box(extents=(4.0, 2.0, 3.0))  # centred on 0: z -1.5..1.5
    grid = Grid((-3000.0, -2000.0), 100.0, (41, 61))
    top = model_top_surface(box, grid, z_mm=1.0, placement_mm=(0.0, 0.0, 1.5))
    xs, ys = grid.xy_um()
    inside = (np.abs(xs)[None, :] < 1950) & (np.abs(ys)[:, None] < 950)
    outside = (np.abs(xs)[None, :] > 2050) | (np.abs(ys)[:, None] > 1050)
    np.testing.assert_allclose(top[inside], 1000.0)  # printed up to z = 1 mm
    np.testing.assert_allclose(top[outside], 0.0)
    full = model_top_surface(box, grid, z_mm=10.0, placement_mm=(0.0, 0.0, 1.5))
    np.testing.assert_allclose(full[inside], 3000.0, atol=1e-3)  # the whole box


def test_a_model_in_metres_or_inches_is_refused() -> None:
    e = _e_for_width(0.45, 0.2, 20.0)
    prog = parse_gcode(f"M83\nG1 Z0.2\nG1 X0 Y0\nG1 X20 Y0 E{e}\nG1 X20 Y20 E{e}\n")
    grid = Grid((0.0, 0.0), 500.0, (10, 10))
    metres = trimesh.creation.box(extents=(0.02, 0.02, 0.004))
    with pytest.raises(ModelUnitsError, match="metres"):
        model_top_surface(metres, grid, z_mm=0.2, program=prog, name="part.stl")
    inches = trimesh.creation.box(extents=(20 / 25.4, 20 / 25.4, 0.2))
    with pytest.raises(ModelUnitsError, match="inches"):
        model_top_surface(inches, grid, z_mm=0.2, program=prog)
    ok = trimesh.creation.box(extents=(20.0, 20.0, 4.0))
    top = model_top_surface(ok, grid, z_mm=0.2, program=prog)  # placed on the extrusion
    assert top.max() == pytest.approx(200.0)
