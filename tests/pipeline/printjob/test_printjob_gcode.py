"""G-code reading: moves, layers, extrusion modes, object labels, and errors naming the line."""

from __future__ import annotations

import math

import numpy as np
import pytest
from sffscan.pipeline.printjob.demo import demo_gcode
from sffscan.pipeline.printjob.gcode import GcodeError, parse_gcode, read_gcode

ABSOLUTE = """\
; a tiny two-object program
G21
G90
M82
G92 E0
EXCLUDE_OBJECT_DEFINE NAME=left CENTER=1,0 POLYGON=[[0,0],[2,0],[2,1],[0,1]]
G1 Z0.2 F600
EXCLUDE_OBJECT_START NAME=left
G1 X0 Y0
G1 X2 Y0 E0.1 ; extrude
EXCLUDE_OBJECT_END NAME=left
G1 X5 Y0 E0.1 ; travel (E unchanged)
EXCLUDE_OBJECT_START NAME=right
G1 X7 Y0 E0.2
EXCLUDE_OBJECT_END NAME=right
G1 E-0.5 ; retract
G92 E0
G1 Z0.6 ; z hop, no extrusion
G1 Z0.4
EXCLUDE_OBJECT_START NAME=left
G1 X0 Y0 E0.5
EXCLUDE_OBJECT_END NAME=left
"""


def test_absolute_moves_layers_and_klipper_objects() -> None:
    p = parse_gcode(ABSOLUTE)
    assert p.objects == ("left", "right")
    assert p.layer_z_mm.tolist() == [0.2, 0.4]  # the z hop extrudes nothing: no layer
    assert p.start.tolist() == [[0, 0], [5, 0], [7, 0]]
    np.testing.assert_allclose(p.e_mm, [0.1, 0.1, 0.5])
    assert p.object_id.tolist() == [0, 1, 0]
    assert p.layer.tolist() == [0, 0, 1]
    assert p.line.tolist() == [10, 14, 21]
    np.testing.assert_allclose(p.outlines["left"], [[0, 0], [2, 0], [2, 1], [0, 1]])
    np.testing.assert_allclose(p.layer_height_mm(), [0.2, 0.2])


def test_relative_extrusion_relative_moves_and_inches() -> None:
    text = "M83\nG1 Z0.3\nG1 X1 Y1\nG1 X3 Y1 E0.2\nG91\nG1 X1 E0.3\nG90\nG20\nG1 X1 Y0 E0.01\n"
    p = parse_gcode(text)
    np.testing.assert_allclose(p.e_mm, [0.2, 0.3, 0.254])
    np.testing.assert_allclose(p.end, [[3, 1], [4, 1], [25.4, 0]])


def test_arcs_are_linearised_with_the_extrusion_shared() -> None:
    p = parse_gcode("M83\nG1 Z0.2\nG1 X10 Y0\nG3 X-10 Y0 I-10 J0 E1.0\n")
    assert len(p.e_mm) == math.ceil(math.pi * 10 / 0.1)
    np.testing.assert_allclose(p.e_mm.sum(), 1.0)
    r = np.hypot(*p.end.T)
    np.testing.assert_allclose(r, 10.0, atol=1e-9)
    assert p.end[:, 1].min() >= -1e-9  # counter-clockwise from +x to -x: through +y


def test_prusaslicer_and_cura_comments_label_objects() -> None:
    text = ("; filament_diameter = 2.85\nG1 Z0.2\n; printing object cube id:0 copy 0\n"
            "G1 X1 E1\n; stop printing object cube id:0 copy 0\n;MESH:cyl.stl\nG1 X2 E2\n"
            ";MESH:NONMESH\nG1 X3 E3\nM486 S4\nM486 Acone\nG1 X4 E4\nM486 S-1\nG1 X5 E5\n")
    p = parse_gcode(text)
    assert p.objects == ("cube", "cyl.stl", "cone")
    assert p.object_id.tolist() == [0, 1, -1, 2, -1]
    assert p.filament_diameter_mm == 2.85


@pytest.mark.parametrize(("bad", "line", "what"), [
    ("G1 X1..2 E1", 3, "cannot read"),
    ("G1 Xabc", 3, "cannot read"),
    ("G1 X1 Q5", 3, "unexpected parameter 'Q'"),
    ("G1 X1 X2", 3, "given twice"),
    ("hello world", 3, "not a G-code command"),
    ("G2 X1 Y1 E1", 3, "without I/J"),
])
def test_bad_lines_name_the_line(bad: str, line: int, what: str) -> None:
    text = f"G90\nG1 Z0.2\n{bad}\nG1 X9 E9\n"
    with pytest.raises(GcodeError, match=rf"job\.gcode, line {line}: .*{what}"):
        parse_gcode(text, source="job.gcode")


def test_a_program_without_extrusion_is_an_error(tmp_path) -> None:
    f = tmp_path / "travel.gcode"
    f.write_text("G28\nG1 X10 Y10 F3000\n")
    with pytest.raises(GcodeError, match="travel.gcode: no extruding move"):
        read_gcode(f)
    with pytest.raises(GcodeError, match="not found"):
        read_gcode(tmp_path / "missing.gcode")


def test_the_shipped_prusaslicer_plate() -> None:
    p = read_gcode(demo_gcode())
    assert p.n_layers == 20
    np.testing.assert_allclose(p.layer_z_mm, 0.2 * np.arange(1, 21), atol=1e-9)
    assert sorted(p.objects) == ["box_a.stl", "box_c.stl", "cylinder_b.stl", "cylinder_d.stl"]
    assert (p.object_id >= 0).all()
    x0, y0, x1, y1 = p.extent_mm()
    assert 90 < x0 < x1 < 110 and 90 < y0 < y1 < 110
