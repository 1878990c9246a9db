"""G-code of a print: extruding moves, layers and object labels.

A small, strict reader of the G-code that FFF slicers write (PrusaSlicer, SuperSlicer,
OrcaSlicer, Cura) for Marlin, RepRap and Klipper firmware. It keeps what the comparison
with a scan needs: every extruding XY move (its end points, the filament it extrudes, its
layer and its object), and the object outlines Klipper's ``EXCLUDE_OBJECT_DEFINE`` gives.

Why not a library: the maintained parser on PyPI (``gcodeparser`` 0.3) matches each line
with a permissive regular expression and silently skips what does not match (``G1 X1..2``
becomes a string parameter, ``G1 Xabc`` disappears), so a corrupt file would give a wrong
expected part without an error. Here every word of a motion command must be a letter and a
number, and any error names the file and the line.

Understood: ``G0``/``G1`` (X Y Z E F), ``G2``/``G3`` arcs (I J, linearised into <= 0.1 mm
chords), ``G20``/``G21`` (inch/mm), ``G90``/``G91``, ``M82``/``M83`` (E is relative under G91 or
M83, as in Marlin and Klipper), ``G92``; object labels
from ``EXCLUDE_OBJECT_DEFINE`` / ``EXCLUDE_OBJECT_START`` / ``EXCLUDE_OBJECT_END``
(Klipper), ``M486 S<n>`` / ``M486 A<name>`` (Marlin, Prusa), ``; printing object NAME`` /
``; stop printing object NAME`` (PrusaSlicer ``gcode_label_objects``) and ``;MESH:NAME``
(Cura); the filament diameter from ``; filament_diameter = 1.75`` (PrusaSlicer's settings
block) or the ``filament_diameter_mm`` argument. Other commands are accepted and ignored.

Layers: the distinct z values of the extruding moves, rounded to 1 µm, in increasing order
(travel z-hops extrude nothing and make no layer). ``;LAYER_CHANGE``/``;Z:``/``;LAYER:``
comments are not needed; a file whose comments name a layer z that no extrusion has is
still read (the comment may precede a layer of travel only).
"""

from __future__ import annotations

import math
import re
from collections.abc import Iterable
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

__all__ = ["GcodeError", "GcodeProgram", "parse_gcode", "read_gcode"]

ARC_CHORD_MM = 0.1  # arcs are split into chords no longer than this, mm
_WORD = re.compile(r"([A-Z])\s*([-+]?(?:\d+\.?\d*|\.\d+))")
_COMMAND = re.compile(r"^([GMT])(\d+)(?:\.\d+)?(?=[\sA-Z;]|$)")
_EXTENDED = re.compile(r"^([A-Z_][A-Z0-9_]*)(?:\s|$)")
_KEYVAL = re.compile(r"([A-Za-z_][A-Za-z0-9_]*)=(\"[^\"]*\"|'[^']*'|\[\[.*?\]\]|\[[^\]]*\]|\S+)")
_LINE_NO = re.compile(r"^N\d+\s*|\*\d+\s*$")  # line numbers and checksums (host protocol)


class GcodeError(ValueError):
    """A G-code file that cannot be read; the message names the file and the line."""


@dataclass(frozen=True)
class GcodeProgram:
    """The extruding moves of a print, in printer coordinates (mm).

    Attributes
    ----------
    start, end : (M, 2) float64
        XY end points of each extruding move, mm.
    z_mm : (M,) float64
        Nozzle height of each move, mm (the top of its bead).
    e_mm : (M,) float64
        Filament length each move extrudes, mm (> 0).
    layer : (M,) int32
        Index of the move's layer into ``layer_z_mm``.
    object_id : (M,) int32
        Index of the move's object into ``objects``; -1 outside any labelled object.
    line : (M,) int32
        1-based line number of the move in the file.
    layer_z_mm : (L,) float64
        Increasing layer heights (tops), mm.
    objects : tuple of str
        Object names, in order of first appearance.
    outlines : dict of str to (K, 2) float64
        Object outlines from ``EXCLUDE_OBJECT_DEFINE POLYGON=...`` where given, mm.
    filament_diameter_mm : float
        Filament diameter used for the bead cross-sections, mm.
    source : str
        Where the program came from (file name or ``"<string>"``).
    """

    start: np.ndarray
    end: np.ndarray
    z_mm: np.ndarray
    e_mm: np.ndarray
    layer: np.ndarray
    object_id: np.ndarray
    line: np.ndarray
    layer_z_mm: np.ndarray
    objects: tuple[str, ...]
    outlines: dict[str, np.ndarray] = field(default_factory=dict)
    filament_diameter_mm: float = 1.75
    source: str = "<string>"

    @property
    def n_layers(self) -> int:
        """Number of layers L."""
        return int(self.layer_z_mm.size)

    def layer_height_mm(self) -> np.ndarray:
        """(L,) float64 thickness of each layer: z_k - z_(k-1), the first layer z_0, mm."""
        z = self.layer_z_mm
        return np.diff(z, prepend=0.0)

    def extent_mm(self) -> tuple[float, float, float, float]:
        """Bounding box of all extrusion (x0, y0, x1, y1), mm."""
        pts = np.concatenate([self.start, self.end])
        return (float(pts[:, 0].min()), float(pts[:, 1].min()),
                float(pts[:, 0].max()), float(pts[:, 1].max()))


@dataclass
class _State:
    x: float = 0.0
    y: float = 0.0
    z: float = 0.0
    e: float = 0.0
    scale: float = 1.0  # mm per unit (25.4 after G20)
    rel_xyz: bool = False
    rel_e: bool = False
    obj: int = -1


def _number(text: str, where: str) -> float:
    v = float(text)
    if not math.isfinite(v):
        raise GcodeError(f"{where}: the number {text!r} is not finite")
    return v


def _words(args: str, where: str, allowed: str) -> dict[str, float]:
    """Letter-number words of a motion command; anything else is an error."""
    out: dict[str, float] = {}
    pos = 0
    args = args.upper()
    while pos < len(args):
        if args[pos].isspace():
            pos += 1
            continue
        m = _WORD.match(args, pos)
        if m is None:
            raise GcodeError(f"{where}: cannot read {args[pos:].strip()!r}: expected a letter "
                             "and a number (e.g. X12.5)")
        letter = m.group(1)
        if letter not in allowed:
            raise GcodeError(f"{where}: unexpected parameter {letter!r} (allowed: "
                             f"{', '.join(allowed)})")
        if letter in out:
            raise GcodeError(f"{where}: parameter {letter} given twice")
        out[letter] = _number(m.group(2), where)
        pos = m.end()
        if pos < len(args) and not (args[pos].isspace() or args[pos].isalpha()):
            raise GcodeError(f"{where}: cannot read {args[m.start():].strip()!r}: a number "
                             "is followed by " + repr(args[pos]))
    return out


def _arc_points(x0: float, y0: float, x1: float, y1: float, i: float, j: float,
                clockwise: bool) -> list[tuple[float, float, float]]:
    """Chord end points (x, y, fraction of the arc) of an I/J arc from (x0, y0) to (x1, y1)."""
    cx, cy = x0 + i, y0 + j
    r = math.hypot(i, j)
    a0 = math.atan2(y0 - cy, x0 - cx)
    a1 = math.atan2(y1 - cy, x1 - cx)
    sweep = a1 - a0
    if clockwise and sweep >= 0:
        sweep -= 2 * math.pi
    elif not clockwise and sweep <= 0:
        sweep += 2 * math.pi
    n = max(1, math.ceil(abs(sweep) * r / ARC_CHORD_MM))
    pts = [(cx + r * math.cos(a0 + sweep * k / n), cy + r * math.sin(a0 + sweep * k / n),
            k / n) for k in range(1, n)]
    return pts + [(x1, y1, 1.0)]


def parse_gcode(text: str | Iterable[str], *, source: str = "<string>",
                filament_diameter_mm: float | None = None) -> GcodeProgram:
    """Read the extruding moves, layers and objects of a G-code program.

    Parameters
    ----------
    text : str or iterable of str
        The program (or its lines).
    source : str, keyword-only
        Name used in error messages (the file name).
    filament_diameter_mm : float, keyword-only
        Filament diameter, mm; default the file's ``; filament_diameter = D`` comment, else
        1.75.

    Returns
    -------
    GcodeProgram

    Raises
    ------
    GcodeError
        A line that does not parse, an arc without I/J, or a program that extrudes nothing;
        the message names ``source`` and the 1-based line number.
    """
    lines = text.splitlines() if isinstance(text, str) else list(text)
    st = _State()
    names: list[str] = []
    m486: dict[int, str] = {}
    outlines: dict[str, np.ndarray] = {}
    seg: list[tuple[float, float, float, float, float, float, int, int]] = []
    dia_comment: float | None = None

    def obj_index(name: str) -> int:
        if name not in names:
            names.append(name)
        return names.index(name)

    for n, raw in enumerate(lines, start=1):
        where = f"{source}, line {n}"
        code, _, comment = raw.partition(";")
        code = code.strip()
        comment = comment.strip()
        if comment:
            low = comment.lower()
            if low.startswith("printing object "):
                st.obj = obj_index(comment[16:].split(" id:")[0].strip())
            elif low.startswith("stop printing object"):
                st.obj = -1
            elif comment.startswith("MESH:"):
                name = comment[5:].strip()
                st.obj = -1 if name == "NONMESH" else obj_index(name)
            elif low.startswith("filament_diameter ="):
                try:
                    dia_comment = float(comment.split("=")[1].split(",")[0])
                except ValueError:
                    raise GcodeError(f"{where}: cannot read the filament diameter in "
                                     f"{comment!r}") from None
        code = _LINE_NO.sub("", code)
        if not code or code.startswith("@"):  # OctoPrint @-commands never reach the printer
            continue
        up = code.upper()
        m = _COMMAND.match(up)
        if m is None:
            ext = _EXTENDED.match(up)
            if ext is None:
                raise GcodeError(f"{where}: not a G-code command: {code!r}")
            rest = _KEYVAL.sub("", code[ext.end():]).strip()
            if rest:
                raise GcodeError(f"{where}: not a G-code command (G/M/T and a number) nor an "
                                 f"extended command with KEY=VALUE arguments: {code!r}")
            keys = {k.upper(): v.strip("\"'") for k, v in _KEYVAL.findall(code)}
            cmd = ext.group(1)
            if cmd in ("EXCLUDE_OBJECT_DEFINE", "EXCLUDE_OBJECT_START"):
                if "NAME" not in keys:
                    raise GcodeError(f"{where}: {cmd} without NAME=")
                k = obj_index(keys["NAME"])
                if cmd == "EXCLUDE_OBJECT_START":
                    st.obj = k
                elif "POLYGON" in keys:
                    try:
                        poly = np.asarray(eval_polygon(keys["POLYGON"]), dtype=np.float64)
                    except ValueError as err:
                        raise GcodeError(f"{where}: POLYGON: {err}") from None
                    outlines[keys["NAME"]] = poly
            elif cmd == "EXCLUDE_OBJECT_END":
                st.obj = -1
            continue
        letter, num = m.group(1), int(m.group(2))
        cmd = f"{letter}{num}"
        args = up[m.end():]
        if cmd in ("G0", "G1", "G2", "G3"):
            allowed = "XYZEF" + ("IJR" if cmd in ("G2", "G3") else "")
            w = _words(args, where, allowed)
            s = st.scale

            def target(axis: str, cur: float, w: dict[str, float] = w, s: float = s) -> float:
                if axis not in w:
                    return cur
                return cur + w[axis] * s if st.rel_xyz else w[axis] * s

            x1, y1, z1 = target("X", st.x), target("Y", st.y), target("Z", st.z)
            if "E" in w:
                rel_e = st.rel_e or st.rel_xyz  # G91 makes E relative too (Marlin, Klipper)
                e1 = st.e + w["E"] * s if rel_e else w["E"] * s
            else:
                e1 = st.e
            de = e1 - st.e
            moves_xy = (x1, y1) != (st.x, st.y)
            if de > 0 and moves_xy:
                if cmd in ("G2", "G3"):
                    if "I" not in w and "J" not in w:
                        raise GcodeError(f"{where}: arc {cmd} without I/J (R arcs are not "
                                         "supported)")
                    pts = _arc_points(st.x, st.y, x1, y1, w.get("I", 0.0) * s,
                                      w.get("J", 0.0) * s, cmd == "G2")
                    px, py, pf = st.x, st.y, 0.0
                    for qx, qy, qf in pts:
                        seg.append((px, py, qx, qy, z1, de * (qf - pf), st.obj, n))
                        px, py, pf = qx, qy, qf
                else:
                    seg.append((st.x, st.y, x1, y1, z1, de, st.obj, n))
            st.x, st.y, st.z, st.e = x1, y1, z1, e1
        elif cmd == "G92":
            w = _words(args, where, "XYZE")
            st.x = w.get("X", st.x / st.scale) * st.scale
            st.y = w.get("Y", st.y / st.scale) * st.scale
            st.z = w.get("Z", st.z / st.scale) * st.scale
            st.e = w.get("E", st.e / st.scale) * st.scale
        elif cmd == "G20":
            st.scale = 25.4
        elif cmd == "G21":
            st.scale = 1.0
        elif cmd == "G90":
            st.rel_xyz = False  # E keeps its M82/M83 mode
        elif cmd == "G91":
            st.rel_xyz = True
        elif cmd == "M82":
            st.rel_e = False
        elif cmd == "M83":
            st.rel_e = True
        elif cmd == "M486":
            if args.strip().startswith("A"):
                # M486 A<name>: names the object last selected by M486 S
                name = code[m.end():].strip()[1:].strip().strip("\"'")
                if st.obj >= 0 and st.obj < len(names):
                    old = names[st.obj]
                    names[st.obj] = name
                    m486 = {k: (name if v == old else v) for k, v in m486.items()}
                continue
            w = _words(args, where, "SPTCU")
            if "S" in w:
                sid = int(w["S"])
                if sid < 0:
                    st.obj = -1
                else:
                    st.obj = obj_index(m486.setdefault(sid, f"object {sid}"))
    if not seg:
        raise GcodeError(f"{source}: no extruding move (G1 with X/Y and a positive E) in "
                         f"{len(lines)} lines")
    a = np.asarray(seg, dtype=np.float64)
    z = np.round(a[:, 4], 3)
    layer_z = np.unique(z)
    dia = filament_diameter_mm or dia_comment or 1.75
    if not dia > 0:
        raise GcodeError(f"{source}: filament diameter must be > 0, got {dia}")
    return GcodeProgram(
        start=a[:, 0:2].copy(), end=a[:, 2:4].copy(), z_mm=z, e_mm=a[:, 5].copy(),
        layer=np.searchsorted(layer_z, z).astype(np.int32),
        object_id=a[:, 6].astype(np.int32), line=a[:, 7].astype(np.int32),
        layer_z_mm=layer_z, objects=tuple(names), outlines=outlines,
        filament_diameter_mm=float(dia), source=source)


def eval_polygon(text: str) -> list[tuple[float, float]]:
    """Points of a Klipper ``POLYGON=[[x,y],...]`` value (no ``eval``: numbers only)."""
    nums = re.findall(r"[-+]?(?:\d+\.?\d*|\.\d+)(?:[eE][-+]?\d+)?", text)
    if not text.strip().startswith("[") or len(nums) < 6 or len(nums) % 2:
        raise ValueError(f"expected [[x,y],[x,y],[x,y],...], got {text!r}")
    v = [float(t) for t in nums]
    return list(zip(v[0::2], v[1::2], strict=True))


def read_gcode(path: str | Path, *, filament_diameter_mm: float | None = None) -> GcodeProgram:
    """Read a G-code file (see :func:`parse_gcode`); errors name the file and the line.

    Raises
    ------
    GcodeError
        The file cannot be read or does not parse.
    """
    p = Path(path)
    try:
        text = p.read_text(encoding="utf-8", errors="strict")
    except FileNotFoundError:
        raise GcodeError(f"{p}: G-code file not found") from None
    except UnicodeDecodeError as err:
        raise GcodeError(f"{p}: not UTF-8 text (byte {err.start})") from None
    except OSError as err:
        raise GcodeError(f"{p}: cannot read: {err.strerror}") from None
    return parse_gcode(text, source=str(p), filament_diameter_mm=filament_diameter_mm)
