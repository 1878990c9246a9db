"""Exports of a mosaic region: binary PLY point cloud and ISO 25178-72 x3p.

Coordinates are world coordinates: world pixel (x, y) has its centre at
``(x, y) * pixel_um`` µm (the mosaic's convention), z is the height. Only pixels with a
finite height are exported; missing pixels are not filled:

- PLY (binary little-endian): one vertex per finite pixel, ``float x, y, z`` in **mm** and
  ``uchar red, green, blue`` = round(255 * texture) each (the all-in-focus grey as a colour
  that point-cloud tools such as trimesh, open3d, CloudCompare and MeshLab show; 0 where the
  texture is missing, counted), then, for a mosaic with an ``uncertainty`` array (format 4
  and later), ``float uncertainty_um``: the height's uncertainty, µm, one sigma, NaN where
  it is not known (PLY allows any number of named vertex properties; tools that do not know
  one carry or ignore it: CloudCompare shows it as a scalar field). Units are in the
  header's comments. Written band by band, so memory stays bounded for any region.
- x3p (ISO 25178-72, through the ``x3pio`` library): a surface on the regular grid of the
  region, heights in metres (float64), NaN = not measured; x and y increments = the pixel
  size; the placement's offset is the world position (x, y) of the region's first pixel.
  Metadata names sffscan as the instrument (non-contacting probing: shape from focus) and
  keeps the processing settings in the comment. The format has no field for a per-point
  uncertainty: its data matrix holds heights only (several layers of a surface are several
  height maps, which readers would take for heights), and Record2 describes the instrument,
  not each point. What it does allow is vendor-specific files in the container, registered in
  ``main.xml`` by a ``VendorSpecificID`` (Amd 1:2020: one per file) and ignored by software
  that does not know the ID. The uncertainty goes there: :data:`X3P_UNCERTAINTY_ID`, a NumPy
  ``.npy`` file of float64, metres, one sigma, shaped and ordered as the height matrix
  (rows = y), NaN where unknown. Generic x3p viewers show the heights only.
"""

from __future__ import annotations

import io
import json
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import zarr
from sffscan.pipeline.mosaic.attrs import MosaicAttrs
from sffscan.pipeline.mosaic.layout import mosaic_array

__all__ = ["EXPORT_MAX_BYTES", "MosaicRegion", "PLY_DTYPE", "PLY_UNCERTAINTY_DTYPE",
           "X3P_UNCERTAINTY_ID", "X3P_VENDOR", "check_export_size",
           "check_scan_exports", "export_bytes", "read_ply", "read_region", "region_box",
           "trust_problems", "check_trust", "read_x3p_uncertainty", "write_ply", "write_x3p"]

#: the most memory a whole-region export (areal parameters, x3p) may plan to use, bytes;
#: a larger region is refused with its size named (give --region)
EXPORT_MAX_BYTES = 8 * 2**30
#: bytes per pixel a region's export holds at its peak: height and texture float32, the
#: x3p's float64 heights, the areal parameters' float64 copies (levelled surface, mask)
EXPORT_BYTES_PER_PX = 4 + 4 + 8 + 3 * 8

PLY_DTYPE = np.dtype([("x", "<f4"), ("y", "<f4"), ("z", "<f4"), ("red", "u1"), ("green", "u1"),
                      ("blue", "u1")])
"""Record layout of a PLY vertex as written here (15 bytes, little-endian)."""
_PLY_PROPS = [("float", "x"), ("float", "y"), ("float", "z"), ("uchar", "red"),
              ("uchar", "green"), ("uchar", "blue")]
PLY_UNCERTAINTY_DTYPE = np.dtype([*PLY_DTYPE.descr, ("uncertainty_um", "<f4")])
"""Record layout of a PLY vertex of a mosaic with an uncertainty (19 bytes)."""
_PLY_UNC_PROPS = [*_PLY_PROPS, ("float", "uncertainty_um")]
#: the first exports' layout (a ``grey`` property that point-cloud tools ignore), still read
PLY_GREY_DTYPE = np.dtype([("x", "<f4"), ("y", "<f4"), ("z", "<f4"), ("grey", "u1")])


@dataclass
class MosaicRegion:
    """A region of a mosaic: arrays (rows, cols) and the world pixel of element [0, 0]."""

    height_um: np.ndarray
    texture: np.ndarray
    x0_px: int
    y0_px: int
    pixel_um: float
    attrs: dict[str, Any]
    uncertainty_um: np.ndarray | None = None
    """Height uncertainty, µm, one sigma (NaN: not known); None for a mosaic without one."""


def _open(path: str | Path) -> tuple[zarr.Group, MosaicAttrs]:
    p = Path(path)
    if not p.exists():
        raise FileNotFoundError(f"{p}: no such mosaic")
    try:
        group = zarr.open_group(str(p), mode="r", use_consolidated=False)
    except Exception as err:  # noqa: BLE001 - not a Zarr group: bad input
        raise ValueError(f"{p}: not a Zarr mosaic ({err})") from None
    if group.attrs.get("format") != "sffscan-mosaic":
        raise ValueError(f"{p}: not an sffscan mosaic (attribute 'format' is "
                         f"{group.attrs.get('format')!r})")
    return group, MosaicAttrs.model_validate(group.attrs.asdict())


def region_box(path: str | Path, region_px: tuple[int, int, int, int] | None = None
               ) -> tuple[int, int, int, int]:
    """The world px box (x0, y0, x1, y1) of ``region_px`` clipped to the mosaic (whole mosaic
    by default); ValueError if it lies outside."""
    group, attrs = _open(path)
    ox, oy = attrs.origin_px
    rows, cols = mosaic_array(group, "height").shape
    if region_px is None:
        return ox, oy, ox + cols, oy + rows
    x0, y0, x1, y1 = region_px
    if not (x1 > x0 and y1 > y0):
        raise ValueError(f"region {region_px} must have x0 < x1 and y0 < y1")
    box = max(x0, ox), max(y0, oy), min(x1, ox + cols), min(y1, oy + rows)
    if box[2] <= box[0] or box[3] <= box[1]:
        raise ValueError(f"region {region_px} lies outside the mosaic "
                         f"({ox}, {oy}, {ox + cols}, {oy + rows})")
    return box


def read_region(path: str | Path, region_px: tuple[int, int, int, int] | None = None
                ) -> MosaicRegion:
    """Height and texture of a world px box (x0, y0, x1, y1) of a mosaic (clipped to it)."""
    group, attrs = _open(path)
    x0, y0, x1, y1 = region_box(path, region_px)
    ox, oy = attrs.origin_px
    sel = (slice(y0 - oy, y1 - oy), slice(x0 - ox, x1 - ox))
    unc = _uncertainty(group)
    return MosaicRegion(np.asarray(mosaic_array(group, "height")[sel]),
                        np.asarray(mosaic_array(group, "texture")[sel]),
                        x0, y0, attrs.pixel_um, attrs.model_dump(mode="json"),
                        None if unc is None else np.asarray(unc[sel]))


def _uncertainty(group: zarr.Group) -> zarr.Array | None:
    """The mosaic's ``uncertainty`` array; None for a mosaic written before it existed."""
    node = group.get("uncertainty")
    return node if isinstance(node, zarr.Array) else None


def export_bytes(rows: int, cols: int) -> int:
    """Memory an export of a ``rows`` x ``cols`` px region holds at its peak, bytes."""
    return int(rows) * int(cols) * EXPORT_BYTES_PER_PX


def _limit_bytes(limit: int | None) -> int:
    from sffscan.pipeline.preflight import MEMORY_SHARE, available_memory_bytes

    have = available_memory_bytes()
    cap = EXPORT_MAX_BYTES if limit is None else int(limit)
    return min(cap, int(MEMORY_SHARE * have)) if have is not None else cap


def check_export_size(path: str | Path, region_px: tuple[int, int, int, int] | None = None,
                      *, limit_bytes: int | None = None) -> tuple[int, int, int, int]:
    """The region's box (:func:`region_box`), or ValueError naming its size when its export
    would need more than ``limit_bytes`` (default :data:`EXPORT_MAX_BYTES`, at most 80 %
    of the memory available)."""
    x0, y0, x1, y1 = box = region_box(path, region_px)
    need, cap = export_bytes(y1 - y0, x1 - x0), _limit_bytes(limit_bytes)
    if need > cap:
        side = int((cap / EXPORT_BYTES_PER_PX) ** 0.5)
        raise ValueError(
            f"{path}: the region x {x0}..{x1} y {y0}..{y1} px ({y1 - y0} x {x1 - x0} px) "
            f"needs about {need / 2**30:.1f} GiB to export, more than the "
            f"{cap / 2**30:.1f} GiB allowed; export it in parts with --region X0,Y0,X1,Y1 "
            f"(at most about {side} x {side} px each)")
    return box


def check_scan_exports(cfg: Any) -> list[str]:
    """Warnings about a scan configuration whose whole mosaic could not be exported at once
    (``sffscan scan --check``)."""
    from sffscan.pipeline.plan import scan_extent_px

    x0, y0, x1, y1 = scan_extent_px(cfg)
    need, cap = export_bytes(y1 - y0, x1 - x0), _limit_bytes(None)
    if need <= cap:
        return []
    return [f"the mosaic will be {y1 - y0} x {x1 - x0} px: exporting it whole would need "
            f"about {need / 2**30:.1f} GiB (more than {cap / 2**30:.1f} GiB); 'sffscan export' "
            "will need --region boxes"]


def trust_problems(path: str | Path) -> list[str]:
    """Why a mosaic's values cannot all be trusted: torn tiles (a writer killed during a
    band write, a resume not finished), a writer still at work or gone without a final
    status. Empty for a mosaic that is not ours (a TIFF, an array), checked elsewhere."""
    from sffscan.pipeline import locks
    from sffscan.pipeline.mosaic.reader import tile_states

    try:
        fmt = zarr.open_group(str(path), mode="r", use_consolidated=False).attrs.get("format")
    except Exception:  # noqa: BLE001 - not a Zarr group: not a mosaic
        return []
    if fmt != "sffscan-mosaic":
        return []
    out = []
    holder = locks.holder(path)
    if holder is not None:
        out.append(f"{path}: being written by {locks.describe_holder(holder)}")
    _, info = tile_states(path)
    if info["incomplete"]:
        out.append(f"{path}: {info['incomplete']} tile(s) torn by an interrupted write hold "
                   "untrustworthy values ('sffscan info' shows them; complete them with "
                   "'sffscan replay RECORDING -o MOSAIC --resume')")
    elif info["status"] == "writing" and holder is None:
        out.append(f"{path}: status 'writing': its writer stopped without a final status "
                   "(complete it with 'sffscan replay RECORDING -o MOSAIC --resume')")
    return out


def check_trust(paths: list[str | Path], *, allow: bool = False) -> None:
    """ValueError naming each mosaic among ``paths`` whose values cannot all be trusted
    (:func:`trust_problems`); with ``allow`` each problem is logged as a warning instead."""
    import logging

    problems: list[str] = []
    for path in paths:
        try:
            problems += trust_problems(path)
        except KeyError as err:
            raise ValueError(f"{path}: unreadable mosaic: {err}") from None
    if allow:
        for text in problems:
            logging.getLogger(__name__).warning("%s; --allow-untrustworthy: used all the same",
                                                text)
    elif problems:
        raise ValueError("; ".join(problems) + "\nsffscan: refusing an untrustworthy mosaic "
                         "(--allow-untrustworthy uses it all the same)")


# ----------------------------------------------------------------------------- PLY


def _ply_header(count: int, comment: str, *, uncertainty: bool = False) -> bytes:
    units = "comment units: x y z in mm, red green blue 0..255 (the texture's grey)"
    if uncertainty:
        units += ", uncertainty_um in um (the height's, one sigma; nan: not known)"
    lines = ["ply", "format binary_little_endian 1.0", "comment sffscan height mosaic export",
             units]
    lines += [f"comment {c}" for c in comment.splitlines() if c]
    lines += [f"element vertex {count}"]
    lines += [f"property {t} {n}" for t, n in (_PLY_UNC_PROPS if uncertainty else _PLY_PROPS)]
    lines += ["end_header"]
    # PLY headers are ASCII: other characters (a mosaic named "Prüfkörper") are escaped
    return ("\n".join(lines) + "\n").encode("ascii", errors="backslashreplace")


def ply_vertices(height_um: np.ndarray, texture: np.ndarray, *, x0_px: int, y0_px: int,
                 pixel_um: float, uncertainty_um: np.ndarray | None = None) -> np.ndarray:
    """PLY records of the finite pixels of a (rows, cols) block: :data:`PLY_DTYPE`, or
    :data:`PLY_UNCERTAINTY_DTYPE` with ``uncertainty_um`` (rows, cols) given."""
    rows, cols = np.nonzero(np.isfinite(height_um))
    out = np.empty(rows.size, dtype=PLY_DTYPE if uncertainty_um is None
                   else PLY_UNCERTAINTY_DTYPE)
    if uncertainty_um is not None:
        out["uncertainty_um"] = uncertainty_um[rows, cols]
    mm = pixel_um / 1000.0
    out["x"] = (x0_px + cols) * mm
    out["y"] = (y0_px + rows) * mm
    out["z"] = height_um[rows, cols] / 1000.0
    t = texture[rows, cols]
    grey = np.where(np.isfinite(t), np.clip(np.rint(np.nan_to_num(t) * 255), 0, 255), 0)
    out["red"] = out["green"] = out["blue"] = grey
    return out


def write_ply(path: str | Path, mosaic: str | Path,
              region_px: tuple[int, int, int, int] | None = None, *,
              band_rows: int = 256) -> dict[str, int]:
    """Write the finite pixels of a mosaic region as a binary PLY point cloud.

    Parameters
    ----------
    path : str or Path
        Output ``.ply`` file.
    mosaic : str or Path
        The mosaic (Zarr group).
    region_px : (x0, y0, x1, y1), optional
        World px box; the whole mosaic by default.
    band_rows : int, keyword-only
        Rows read at once (memory bound).

    Returns
    -------
    dict
        ``points`` written and ``no_texture`` (points whose colour is 0 for lack of a
        texture).
    """
    group, attrs = _open(mosaic)
    x0, y0, x1, y1 = region_box(mosaic, region_px)
    ox, oy = attrs.origin_px
    height, texture = mosaic_array(group, "height"), mosaic_array(group, "texture")
    unc = _uncertainty(group)
    bands = [(r, min(r + band_rows, y1)) for r in range(y0, y1, band_rows)]
    cs = slice(x0 - ox, x1 - ox)
    count = sum(int(np.isfinite(np.asarray(height[a - oy:b - oy, cs])).sum()) for a, b in bands)
    comment = (f"source {Path(mosaic).name} region x {x0}..{x1} y {y0}..{y1} px, "
               f"pixel {attrs.pixel_um} um")
    no_tex = written = 0
    out = Path(path)
    part = out.with_name(out.name + ".part")  # renamed when whole: no half-written PLY
    try:
        with open(part, "wb") as f:
            f.write(_ply_header(count, comment, uncertainty=unc is not None))
            for a, b in bands:
                h = np.asarray(height[a - oy:b - oy, cs])
                t = np.asarray(texture[a - oy:b - oy, cs])
                u = None if unc is None else np.asarray(unc[a - oy:b - oy, cs])
                rec = ply_vertices(h, t, x0_px=x0, y0_px=a, pixel_um=attrs.pixel_um,
                                   uncertainty_um=u)
                no_tex += int((~np.isfinite(t[np.isfinite(h)])).sum())
                written += rec.size
                f.write(rec.tobytes())
        if written != count:  # the mosaic changed between the passes
            raise ValueError(f"{mosaic}: changed while exporting ({count} then {written} "
                             "points)")
        part.replace(out)
    finally:
        part.unlink(missing_ok=True)
    return {"points": written, "no_texture": no_tex}


def read_ply(path: str | Path) -> tuple[np.ndarray, list[str]]:
    """Read a binary little-endian PLY of :data:`PLY_DTYPE` or
    :data:`PLY_UNCERTAINTY_DTYPE` vertices (as written here; the first exports'
    :data:`PLY_GREY_DTYPE` too).

    Returns the records and the header lines.
    """
    data = Path(path).read_bytes()
    end = data.find(b"end_header\n")
    if not data.startswith(b"ply\n") or end < 0:
        raise ValueError(f"{path}: not a PLY file")
    header = data[:end].decode("ascii").splitlines()
    if "format binary_little_endian 1.0" not in header:
        raise ValueError(f"{path}: not binary little-endian PLY")
    count = next(int(line.split()[2]) for line in header if line.startswith("element vertex"))
    props = [tuple(line.split()[1:]) for line in header if line.startswith("property")]
    if props == _PLY_PROPS:
        dtype = PLY_DTYPE
    elif props == _PLY_UNC_PROPS:
        dtype = PLY_UNCERTAINTY_DTYPE
    elif props == [("float", "x"), ("float", "y"), ("float", "z"), ("uchar", "grey")]:
        dtype = PLY_GREY_DTYPE
    else:
        raise ValueError(f"{path}: unexpected vertex properties {props}")
    body = data[end + len(b"end_header\n"):]
    if len(body) != count * dtype.itemsize:
        raise ValueError(f"{path}: {len(body)} bytes of data for {count} vertices")
    return np.frombuffer(body, dtype=dtype), header


# ----------------------------------------------------------------------------- x3p

X3P_VENDOR = "https://sffscan.invalid"
"""The vendor part of sffscan's ``VendorSpecificID``: the project owns no domain, and
``.invalid`` (RFC 2606) is one that no other vendor can own."""
X3P_UNCERTAINTY_FILE = "height_uncertainty.npy"
X3P_UNCERTAINTY_ID = f"{X3P_VENDOR}/{X3P_UNCERTAINTY_FILE}"
"""``VendorSpecificID`` of the height uncertainty in an x3p file (an ``.npy`` file, float64
metres, one sigma, the height matrix's shape)."""


def _version() -> str:
    from importlib.metadata import PackageNotFoundError, version

    try:
        return version("sffscan")
    except PackageNotFoundError:
        return "unknown"


def write_x3p(path: str | Path, mosaic: str | Path,
              region_px: tuple[int, int, int, int] | None = None) -> dict[str, int]:
    """Write a mosaic region as an ISO 25178-72 x3p surface (via ``x3pio``).

    The height's uncertainty, where the mosaic has one, as the vendor-specific file
    :data:`X3P_UNCERTAINTY_ID` (see the module: the format has no per-point uncertainty
    field; :func:`read_x3p_uncertainty` reads it back).

    Returns ``rows``, ``cols``, ``missing`` (NaN, "not measured", points) and
    ``uncertainty`` (1 when the file carries it, else 0).
    """
    import x3pio
    from x3pio import CoordinateSystem, Metadata, Placement, ProbingType

    region = read_region(mosaic, region_px)
    z_m = region.height_um.astype(np.float64) * 1e-6
    px_m = region.pixel_um * 1e-6
    meta = Metadata.for_software("sffscan", _version())
    meta.instrument.manufacturer = "sffscan"
    meta.instrument.model = "shape from focus (sffscan)"
    meta.probing_system.type = ProbingType.NON_CONTACTING
    meta.probing_system.identification = (
        f"shape from focus, {region.pixel_um} um/px, "
        f"{len(region.attrs.get('focus_heights_um') or [])} focus levels")
    meta.comment = json.dumps({"source": str(mosaic),
                               "region_px": [region.x0_px, region.y0_px,
                                             region.x0_px + z_m.shape[1],
                                             region.y0_px + z_m.shape[0]],
                               "processing": region.attrs.get("processing", {})},
                              ensure_ascii=True, sort_keys=True)
    placement = Placement.translation(region.x0_px * px_m, region.y0_px * px_m, 0.0)
    surface = x3pio.Surface.from_array(z_m, x_scale=px_m, y_scale=px_m, metadata=meta,
                                       placement=placement,
                                       coordinate_system=CoordinateSystem.VIEW)
    if region.uncertainty_um is not None:
        buf = io.BytesIO()
        np.save(buf, region.uncertainty_um.astype("<f8") * 1e-6, allow_pickle=False)
        surface.extensions.add(X3P_VENDOR, X3P_UNCERTAINTY_FILE, buf.getvalue())
    surface.save(path)
    return {"rows": int(z_m.shape[0]), "cols": int(z_m.shape[1]),
            "missing": int((~np.isfinite(z_m)).sum()),
            "uncertainty": int(region.uncertainty_um is not None)}


def read_x3p_uncertainty(path: str | Path) -> np.ndarray | None:
    """The height uncertainty (metres, one sigma, (rows, cols) float64, NaN: not known) of an
    x3p file written by :func:`write_x3p`; None when the file carries none."""
    import x3pio

    ext = x3pio.read(path).extensions
    if X3P_UNCERTAINTY_ID not in ext:
        return None
    data = ext[X3P_UNCERTAINTY_ID]
    if data is None:
        raise ValueError(f"{path}: {X3P_UNCERTAINTY_ID} names no file")
    return np.asarray(np.load(io.BytesIO(data), allow_pickle=False), dtype=np.float64)
