"""Mosaic: completed depth blocks, stitched in world coordinates into a Zarr v3 group.

Layout of the group (format ``sffscan-mosaic``, version 3; schema in
``schemas/mosaic_attrs.v1.json``):

- ``height``: float32 (y, x), µm, NaN where nothing valid was measured;
- ``texture``: float32 (y, x), all-in-focus grey value 0..1, NaN where invalid;
- ``confidence``: float32 (y, x), the largest confidence of the contributions, 0..1;
- ``weight``: float32 (y, x), the sum of contribution weights used to blend overlaps;
- ``uncertainty``: float32 (y, x), µm, one sigma: the weighted mean of the contributions'
  height uncertainties (the depth stage's), NaN where invalid or where a contribution had
  none;
- ``pyramid/<k>/<name>``, k = 1 .. L-1 (L >= 4): the resolution pyramid of each array,
  level k the 2^k x 2^k reduction of level 0 (:mod:`sffscan.stages.mosaic_pyramid`),
  kept current while the scan runs through a write-back cache of upper-level chunks (a
  level-k chunk is written when the band writes leave it, or after at most 5 s, and at the
  end); the chunks not yet written are journaled (``pyramid_stale``) and recomputed on
  resume.
- ``y``, ``x`` and ``pyramid/<k>/y``, ``pyramid/<k>/x`` (version 3): float64 µm centres of
  each level's rows and columns, so ``xarray.open_zarr`` gets µm coordinates; the metadata
  is consolidated when the writer sets the final status (a resume drops it first).

Each array carries its unit in its own attributes (``units``); the group is an OME-Zarr
(NGFF 0.5) image (attribute ``ome``, :mod:`sffscan.pipeline.formats.ngff`), so OME-Zarr
readers and viewers open it. Version 1 mosaics (no pyramid, no ``ome``) and version 2
(no coordinate arrays, not consolidated) are still read and resumed as they are.

Pixel (row, col) of the arrays is world pixel (origin_px[1] + row, origin_px[0] + col);
world pixel (x, y) has its centre at (x, y) * pixel_um µm. All passes of a plate land in
the one mosaic; where passes overlap, height and texture are the weighted mean with
weight = max(confidence, 1e-3) over valid pixels; ``valid_pixels`` counts the finite
heights of the mosaic (a pixel seen by two passes counts once). Blocks are gathered in memory per
chunk-wide column band and written when the motion has left the band, so each chunk is
written once per pass and memory stays bounded.

Crash safety (a journal in the attributes): each band write covers several chunks of four
arrays and can be torn by a crash. Before a write the writer records its box in
``writing``; after it, ``writes_done`` (the number of writes completed, in stream order)
and ``writing = null``. Zarr's local store replaces each file atomically, so on reopening
(:func:`tile_states`) every tile (chunk) is either complete, empty, or known to be
incomplete (it meets the box of the torn write). :meth:`MosaicWriter.reopen` continues
such a mosaic from a replay of its recording (``sffscan replay --resume``): it resets the
torn box, skips the writes already done (re-applying, inside the reset box only, those that
touched it) and journals the rest; the result is bit for bit the uninterrupted mosaic.
"""

from __future__ import annotations

import datetime as _dt
import logging
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import zarr
from pydantic import ValidationError
from sffscan.pipeline.formats.durable import free_reserve, make_reserve
from sffscan.pipeline.formats.mosaic_attrs import MosaicAttrs
from sffscan.pipeline.formats.ngff import consolidate, mosaic_ngff
from sffscan.stages.messages import DepthBlock
from sffscan.stages.mosaic_pyramid import (
    LAG_S,
    CoordArrays,
    PyramidCache,
    aligned,
    coord_arrays,
    create_coords,
    create_pyramid,
    default_levels,
    pyramid_arrays,
    read_many,
    resize_pyramid,
    update_pyramid,
    write_coords,
    write_many,
)
from sffscan.stages.protocol import Stage
from zarr.codecs import BloscCodec, BloscShuffle

log = logging.getLogger(__name__)

ARRAYS = ("height", "texture", "confidence", "weight", "uncertainty")
#: arrays an older mosaic may lack (format version 3 and earlier wrote no ``uncertainty``)
OPTIONAL = ("uncertainty",)
MIN_WEIGHT = 1e-3
FILL = {"height": np.nan, "texture": np.nan, "confidence": 0.0, "weight": 0.0,
        "uncertainty": np.nan}
UNITS = {"height": "µm", "texture": "1 (0..1 grey)", "confidence": "1 (0..1)", "weight": "1",
         "uncertainty": "µm (one sigma)"}
#: codec of the mosaic arrays (measured in bench/recorder_results.md)
DEFAULT_CODEC = "blosc-lz4"
#: tile states of :func:`tile_states`
TILE_EMPTY, TILE_COMPLETE, TILE_INCOMPLETE = 0, 1, 2

Box = tuple[int, int, int, int]  # world px (x0, y0, width, height)


def mosaic_codecs(name: str) -> list[Any]:
    """Zarr v3 compressors of the mosaic arrays: ``blosc-lz4`` (byte shuffle, float32),
    ``zstd`` (zarr's default) or ``none``."""
    if name == "blosc-lz4":
        return [BloscCodec(cname="lz4", clevel=5, shuffle=BloscShuffle.shuffle, typesize=4)]
    if name == "zstd":
        from zarr.codecs import ZstdCodec

        return [ZstdCodec(level=0)]
    if name == "none":
        return []
    raise ValueError(f"unknown mosaic codec {name!r} (blosc-lz4, zstd, none)")


def _intersect(a: Box, b: Box) -> Box | None:
    x0, y0 = max(a[0], b[0]), max(a[1], b[1])
    x1, y1 = min(a[0] + a[2], b[0] + b[2]), min(a[1] + a[3], b[1] + b[3])
    return (x0, y0, x1 - x0, y1 - y0) if x1 > x0 and y1 > y0 else None


def blend(
    old: dict[str, np.ndarray], new: dict[str, np.ndarray]
) -> dict[str, np.ndarray]:
    """Blend a new contribution into existing mosaic values by weight.

    Parameters
    ----------
    old : dict of ndarray
        Current ``height``, ``texture``, ``confidence``, ``weight`` of a region.
    new : dict of ndarray
        ``height``, ``texture`` as weighted sums (value * weight), ``weight`` and
        ``confidence`` of the new contribution, same shape.

    Returns
    -------
    dict of ndarray, float32
        Updated values of the four arrays.
    """
    w_old = old["weight"].astype(np.float64)
    w_new = new["weight"].astype(np.float64)
    w = w_old + w_new
    out: dict[str, np.ndarray] = {}
    with np.errstate(invalid="ignore", divide="ignore"):
        for key in ("height", "texture"):
            prev = np.where(w_old > 0, old[key], 0.0) * w_old
            val = (prev + new[key]) / w
            out[key] = np.where(w > 0, val, np.nan).astype(np.float32)
    out["confidence"] = np.maximum(old["confidence"], new["confidence"]).astype(np.float32)
    out["weight"] = w.astype(np.float32)
    if "uncertainty" in old:  # the weighted mean of the contributions' sigmas (errors of
        # overlapping contributions are not independent: no sqrt(n) gain); a contribution
        # without one makes it unknown (NaN), never 0
        su = new.get("uncertainty")
        if su is None:
            su = np.where(w_new > 0, np.nan, 0.0)
        with np.errstate(invalid="ignore", divide="ignore"):
            prev = np.where(w_old > 0, old["uncertainty"], 0.0) * w_old
            out["uncertainty"] = np.where(w > 0, (prev + su) / w, np.nan).astype(np.float32)
    return out


@dataclass
class _Band:
    """Weighted sums of one chunk-wide column band of the current pass."""

    x0: int
    y0: int
    wh: np.ndarray
    wt: np.ndarray
    w: np.ndarray
    conf: np.ndarray
    wu: np.ndarray


def config_differences(old: dict[str, Any], new: dict[str, Any]) -> list[str]:
    """Fields (``table.field``, or a top-level key such as ``version``) in which two scan
    configurations (as stored in a mosaic's ``scan_config``) differ, the ``output`` table
    aside."""
    out = []
    for key in sorted((set(old) | set(new)) - {"output"}):
        a, b = old.get(key), new.get(key)
        if isinstance(a, dict) and isinstance(b, dict):
            out += [f"{key}.{k}" for k in sorted(set(a) | set(b)) if a.get(k) != b.get(k)]
        elif a != b:
            out.append(key)
    return out


def present_arrays(group: zarr.Group) -> tuple[str, ...]:
    """The mosaic arrays a group holds, in :data:`ARRAYS` order: all of them for a mosaic of
    this version, the first four for one written before ``uncertainty`` existed (it still
    resumes, without that array)."""
    return tuple(n for n in ARRAYS if n not in OPTIONAL or isinstance(group.get(n), zarr.Array))


def mosaic_array(group: zarr.Group, name: str) -> zarr.Array:
    """One array of a mosaic group; a clear error if it is missing or not an array."""
    node = group.get(name)
    if not isinstance(node, zarr.Array):
        raise ValueError(f"{group.store}: mosaic has no array '{name}'")
    return node


def is_replaceable(path: Path) -> bool:
    """True for an empty folder or a Zarr group written as an sffscan mosaic."""
    if path.is_dir() and not any(path.iterdir()):
        return True
    try:
        group = zarr.open_group(str(path), mode="r", use_consolidated=False)
    except Exception:  # noqa: BLE001 - anything that is not a readable group
        return False
    return group.attrs.get("format") == "sffscan-mosaic"


class MosaicWriter:
    """Owns a mosaic Zarr group: creates it, blends blocks in, marks its status.

    Parameters
    ----------
    path : str or Path
        Location of the Zarr v3 group.
    origin_px : (int, int)
        World (x, y) pixel of array element [0, 0].
    shape : (int, int)
        Initial (rows, cols); the arrays grow if a block lands beyond them.
    pixel_um : float
        Pixel scale, µm/px.
    chunk_px : int
        Chunk edge, px.
    attrs : dict
        Extra attributes (the scan configuration, processing settings, the recording).
    overwrite : bool
        Replace an existing group; otherwise an existing path is an error.
    codec : str
        Compressor of the arrays (:func:`mosaic_codecs`).
    levels : int, optional
        Levels of the resolution pyramid, level 0 included (>= 1; 1 = no pyramid); by
        default :func:`~sffscan.stages.mosaic_pyramid.default_levels` (at least 4).
    pyramid_lag_s : float, optional
        Longest time, s, an upper-level chunk keeps changes unwritten while band writes
        still touch it (:class:`~sffscan.stages.mosaic_pyramid.PyramidCache`); by default
        :data:`~sffscan.stages.mosaic_pyramid.LAG_S` (5 s).

    Notes
    -----
    The pyramid is written back through a cache of upper-level chunks: a level-k chunk is
    written when the band writes leave its columns (2^k chunk-wide bands), or at the first
    band write after it has held unwritten changes for ``pyramid_lag_s`` s, and every chunk
    at :meth:`set_status`; so a viewer sees level k lag level 0 by at most that. Each
    journal entry (``writing`` before a band write, ``writes_done`` after it) also records
    ``pyramid_stale``, the world px box under the chunks not yet written; :meth:`reopen`
    recomputes it from level 0. The cache holds only the chunks under the last write (for
    the demo's 256 x 1040 px bands: at most 6 chunks of the four arrays, 6.4 MiB).
    """

    #: what a ``complete`` status is checked against: returns the status to set
    #: (``complete`` or ``incomplete``) and the frame counts (``frames_expected``,
    #: ``frames_received``); see :mod:`sffscan.pipeline.completeness`
    account: Callable[[], tuple[str, dict[str, Any]]] | None = None

    def __init__(self, path: str | Path, *, origin_px: tuple[int, int], shape: tuple[int, int],
                 pixel_um: float, chunk_px: int = 256, attrs: dict[str, Any] | None = None,
                 overwrite: bool = False, codec: str = DEFAULT_CODEC,
                 levels: int | None = None, pyramid_lag_s: float | None = None) -> None:
        self.path = Path(path)
        if self.path.exists():
            if not overwrite:
                raise FileExistsError(f"{self.path}: exists; --overwrite (output.overwrite in a "
                                      "configuration) replaces it, or remove it")
            if not is_replaceable(self.path):
                raise FileExistsError(f"{self.path}: exists and is not an sffscan mosaic nor an "
                                      "empty folder; refusing to overwrite it")
        self.origin = origin_px
        self.chunk = chunk_px
        levels = default_levels(shape) if levels is None else levels
        if levels < 1:
            raise ValueError(f"mosaic pyramid levels must be >= 1, got {levels}")
        compressors = mosaic_codecs(codec)
        self.group = zarr.open_group(str(self.path), mode="w")
        for name in ARRAYS:
            self.group.create_array(name=name, shape=shape, chunks=(chunk_px, chunk_px),
                                    dtype="float32", fill_value=FILL[name],
                                    compressors=compressors, dimension_names=("y", "x"),
                                    attributes={"units": UNITS[name]})
        # the level-0 arrays, looked up once (a lookup reads the array's metadata: 0.5 ms)
        self.arrays: tuple[str, ...] = ARRAYS
        self.level0 = {name: mosaic_array(self.group, name) for name in ARRAYS}
        create_pyramid(self.group, shape=shape, levels=levels, chunk_px=chunk_px, fill=FILL,
                       units=UNITS, compressors=compressors)
        self.pyramid = pyramid_arrays(self.group, ARRAYS, levels)
        # 1-D µm coordinates of every level, for xarray (format version 3)
        self.pixel_um = pixel_um
        self.origin_um = (origin_px[0] * pixel_um, origin_px[1] * pixel_um)
        self.coords: CoordArrays | None = create_coords(
            self.group, shape=shape, levels=levels, pixel_um=pixel_um, origin_um=self.origin_um)
        lag = LAG_S if pyramid_lag_s is None else pyramid_lag_s
        self.cache = PyramidCache(self.pyramid, lag_s=lag, empty=True) if self.pyramid else None
        attrs = dict(attrs or {})
        header = MosaicAttrs(
            status="writing",
            units=dict(UNITS),
            pixel_um=pixel_um,
            origin_px=origin_px,
            origin_um=(origin_px[0] * pixel_um, origin_px[1] * pixel_um),
            created=_dt.datetime.now(_dt.UTC).isoformat(timespec="seconds"),
            processing=attrs.pop("processing", {}),
            focus_heights_um=attrs.pop("focus_heights_um", []),
            scan_config=attrs.pop("scan_config", {}),
            recording=attrs.pop("recording", None),
            codec=codec,
            ome=mosaic_ngff(pixel_um=pixel_um, origin_px=origin_px, levels=levels, names=ARRAYS),
        )
        if attrs:
            raise ValueError(f"unknown mosaic attributes: {sorted(attrs)}")
        self.group.update_attributes(header.model_dump(mode="json"))
        # room for the final status even on a full disk (freed by set_status; issue 13)
        make_reserve(self.path)
        self.blocks_written = 0
        self.writes = 0  # write_region calls so far, in stream order
        self.done = 0  # writes already in the mosaic when it was reopened
        self.rebuild: list[Box] = []
        self.valid_px = 0  # finite heights in the mosaic (overlaps counted once)

    @classmethod
    def reopen(cls, path: str | Path, *, scan_config: dict[str, Any]) -> MosaicWriter:
        """Continue an interrupted mosaic (status ``writing`` or ``failed``).

        The mosaic must have been made with ``scan_config`` (its ``output`` table aside).
        The box of a torn write (and any box a previous resume was still rebuilding) is
        reset to the fill values and recorded in ``rebuild`` before anything else, so a
        crash during the resume is itself resumable.
        """
        p = Path(path)
        try:
            # not through consolidated metadata (stale once arrays change); the first
            # attribute write below drops it, and set_status consolidates again
            group = zarr.open_group(str(p), mode="r+", use_consolidated=False)
        except Exception as exc:  # noqa: BLE001 - anything that is not a group
            raise ValueError(f"{p}: cannot resume, not a readable Zarr group ({exc})") from exc
        if group.attrs.get("format") != "sffscan-mosaic":
            raise ValueError(f"{p}: cannot resume, not an sffscan mosaic")
        attrs = read_mosaic_attrs(group, path)
        if attrs.status == "complete":
            raise ValueError(f"{p}: the mosaic is complete already; nothing to resume")
        diff = config_differences(attrs.scan_config, scan_config)
        if diff:
            raise ValueError(f"{p}: cannot resume with a different configuration "
                             f"(differs in {', '.join(diff)})")
        self = cls.__new__(cls)
        self.path, self.group = p, group
        self.arrays = present_arrays(group)
        self.level0 = {name: mosaic_array(group, name) for name in self.arrays}
        self.origin = attrs.origin_px
        self.chunk = int(self.level0["height"].chunks[0])
        self.blocks_written = 0
        self.writes = 0
        self.done = attrs.writes_done
        levels = len(attrs.ome.multiscales[0].datasets) if attrs.ome is not None else 1
        self.pyramid = pyramid_arrays(group, self.arrays, levels)
        self.cache = PyramidCache(self.pyramid, lag_s=LAG_S) if self.pyramid else None
        group.update_attributes({})  # drops consolidated metadata, if any
        self.pixel_um, self.origin_um = attrs.pixel_um, attrs.origin_um
        self.coords = coord_arrays(group, levels)  # None before format version 3
        rebuild = [tuple(b) for b in attrs.rebuild]
        if attrs.writing is not None and tuple(attrs.writing) not in rebuild:
            rebuild.append(tuple(attrs.writing))
        self.rebuild = [(int(b[0]), int(b[1]), int(b[2]), int(b[3])) for b in rebuild]
        # arrays may have been resized unequally when the writer stopped
        rows = max(a.shape[0] for a in self.level0.values())
        cols = max(a.shape[1] for a in self.level0.values())
        self._ensure(rows, cols)
        if attrs.pyramid_stale is not None:  # levels the writer had not written back
            sel = self._region(attrs.pyramid_stale)
            if sel is not None:
                self._update_pyramid(sel)
        self._journal(rebuild=[list(b) for b in self.rebuild], writing=None, status="writing",
                      resumed=attrs.resumed + 1)
        self.valid_px = count_valid(self.level0["height"])
        for box in self.rebuild:
            self._reset(box)
        make_reserve(self.path)  # room for the final status even on a full disk
        return self

    def _journal(self, **changes: Any) -> None:
        """Update attributes in one atomic write of the group's metadata, with the box of
        the pyramid's unwritten chunks (``pyramid_stale``)."""
        self.group.update_attributes({**changes, "pyramid_stale": self._stale()})

    def _stale(self) -> list[int] | None:
        """World px box (x0, y0, width, height) under the pyramid's unwritten chunks."""
        sel = self.cache.stale() if self.cache is not None else None
        if sel is None:
            return None
        return [self.origin[0] + sel[1].start, self.origin[1] + sel[0].start,
                sel[1].stop - sel[1].start, sel[0].stop - sel[0].start]

    def _region(self, box: Box) -> tuple[slice, slice] | None:
        """Array slices of a world box, clipped to the arrays."""
        rows, cols = self.level0["height"].shape
        r0, c0 = box[1] - self.origin[1], box[0] - self.origin[0]
        r1, c1 = min(rows, r0 + box[3]), min(cols, c0 + box[2])
        r0, c0 = max(0, r0), max(0, c0)
        return (slice(r0, r1), slice(c0, c1)) if r1 > r0 and c1 > c0 else None

    def _reset(self, box: Box) -> None:
        sel = self._region(box)
        if sel is None:
            return
        height = self.level0["height"]
        self.valid_px -= int(np.isfinite(np.asarray(height[sel])).sum())
        for name in self.arrays:
            self.level0[name][sel] = FILL[name]
        self._update_pyramid(sel)

    def _update_pyramid(self, sel: tuple[slice, slice]) -> None:
        update_pyramid(self.level0, self.pyramid, sel)

    def _ensure(self, r1: int, c1: int) -> None:
        shapes = [self.level0[n].shape for n in self.arrays]
        if any(r1 > r or c1 > c for r, c in shapes) or len(set(shapes)) > 1:
            rows = max([r1] + [r for r, _ in shapes])
            cols = max([c1] + [c for _, c in shapes])
            for name in self.arrays:
                arr = self.level0[name]
                if arr.shape != (rows, cols):
                    arr.resize((rows, cols))
            resize_pyramid(self.pyramid, (rows, cols))
            if self.coords is not None:
                write_coords(self.coords, (rows, cols), pixel_um=self.pixel_um,
                             origin_um=self.origin_um)

    def _blend(self, x0: int, y0: int, new: dict[str, np.ndarray]) -> None:
        r0, c0 = y0 - self.origin[1], x0 - self.origin[0]
        rows, cols = new["weight"].shape
        self._ensure(r0 + rows, c0 + cols)
        sel = (slice(r0, r0 + rows), slice(c0, c0 + cols))
        arrays = self.level0
        # one read of the region widened to whole pyramid blocks: the blend's input, and,
        # blended, the pyramid's
        shape = (int(arrays["height"].shape[0]), int(arrays["height"].shape[1]))
        region = aligned(sel, shape, len(self.pyramid) + 1) if self.pyramid else sel
        buf = dict(zip(self.arrays, read_many([(arrays[n], region) for n in self.arrays]),
                       strict=True))
        a, b = r0 - region[0].start, c0 - region[1].start
        sub = (slice(a, a + rows), slice(b, b + cols))
        old = {name: v[sub] for name, v in buf.items()}
        out = blend(old, new)
        self.valid_px += int(np.isfinite(out["height"]).sum() - np.isfinite(old["height"]).sum())
        writes = [(arrays[name], sel, value) for name, value in out.items()]
        if self.cache is not None:
            for name, value in out.items():
                buf[name][sub] = value
            self.cache.update(region, buf)
            # the chunks due go with level 0, in one round trip; a crash in it is covered by
            # the journal (the torn box, and the unwritten chunks' box of the last entry)
            writes += self.cache.write_back()
        write_many(writes)

    def flush_pyramid(self) -> None:
        """Write every chunk the pyramid's cache holds (then the pyramid is current)."""
        if self.cache is not None:
            write_many(self.cache.write_back(everything=True))

    def write_region(self, x0: int, y0: int, new: dict[str, np.ndarray]) -> None:
        """Blend weighted sums ``new`` (see :func:`blend`) at world pixel (x0, y0).

        Journaled (see the module): ``writing`` before, ``writes_done`` after. When the
        mosaic was reopened, writes already done are skipped, except inside the boxes being
        rebuilt.
        """
        seq = self.writes
        self.writes += 1
        rows, cols = new["weight"].shape
        if y0 - self.origin[1] < 0 or x0 - self.origin[0] < 0:
            raise ValueError(f"block at world px (x={x0}, y={y0}) lies before the mosaic origin "
                             f"{self.origin}; widen the scan area in the configuration")
        box = (x0, y0, cols, rows)
        if seq < self.done:  # in the mosaic already, except in the boxes being rebuilt
            for reset in self.rebuild:
                part = _intersect(box, reset)
                if part is not None:
                    a, b = part[1] - y0, part[0] - x0
                    self._blend(part[0], part[1], {k: v[a:a + part[3], b:b + part[2]]
                                                   for k, v in new.items()})
            return
        if self.rebuild:  # every earlier write has been re-applied: the boxes are whole again
            self.rebuild = []
            self._journal(rebuild=[])
        self._journal(writing=list(box))
        self._blend(x0, y0, new)
        self._journal(writing=None, writes_done=seq + 1)
        self.blocks_written += 1

    def set_status(self, status: str, **extra: Any) -> None:
        """Set the status; a ``complete`` one is checked against :attr:`account` (if set),
        which may make it ``incomplete`` and adds the frame counts."""
        if status == "complete" and self.account is not None:
            status, counts = self.account()
            extra.update(counts)
        if self.rebuild or self.writes < self.done:
            status = "failed" if status == "complete" else status
            extra["rebuild"] = [list(b) for b in self.rebuild]
        # the levels are current before the final status; if they cannot be written (a
        # full disk), their box stays journaled and a resume recomputes it
        stale = self._stale()
        try:
            self.flush_pyramid()
            stale = None
        except OSError as err:
            log.warning("%s: pyramid levels over world px box %s not written (%s); "
                        "'replay --resume' recomputes them", self.path, stale, err)
            status = "failed" if status == "complete" else status
        attrs = MosaicAttrs.model_validate({**self.group.attrs.asdict(), "status": status,
                                            "pyramid_stale": stale, **extra})
        free_reserve(self.path)  # the final status is written even when the disk is full
        self.group.update_attributes(attrs.model_dump(mode="json"))
        if self.coords is not None:  # format version 3: one read opens it (xarray, NGFF)
            try:
                consolidate(self.path)
            except OSError as err:
                log.warning("%s: metadata not consolidated (%s); readers open it without",
                            self.path, err)


def read_mosaic_attrs(group: zarr.Group, path: str | Path) -> MosaicAttrs:
    """A mosaic group's attributes, validated; ``ValueError`` names the file and the field."""
    try:
        return MosaicAttrs.model_validate(group.attrs.asdict())
    except ValidationError as err:
        first = err.errors()[0]
        where = ".".join(str(v) for v in first["loc"]) or "(attributes)"
        raise ValueError(f"{path}: not a valid sffscan mosaic: attribute '{where}': "
                         f"{first['msg']} ({len(err.errors())} problem(s))") from None


def pyramid_levels(path: str | Path) -> list[dict[str, Any]]:
    """The resolution levels of a mosaic, finest first: ``level``, ``path`` (of the height
    array), ``shape`` (rows, cols) and ``pixel_um`` (µm per element, from the NGFF
    metadata; version 1 mosaics have level 0 only)."""
    group = zarr.open_group(str(path), mode="r", use_consolidated=False)
    attrs = read_mosaic_attrs(group, path)
    if attrs.ome is None:
        paths = [("height", attrs.pixel_um)]
    else:
        paths = [(d.path, d.coordinateTransformations[0].scale[1])
                 for d in attrs.ome.multiscales[0].datasets]
    return [{"level": k, "path": p, "shape": tuple(int(n) for n in mosaic_array(group, p).shape),
             "pixel_um": um} for k, (p, um) in enumerate(paths)]


def count_valid(height: zarr.Array) -> int:
    """Finite values of a mosaic array, read one row of chunks at a time."""
    rows = int(height.shape[0])
    step = int(height.chunks[0])
    return sum(int(np.isfinite(np.asarray(height[r:r + step])).sum())
               for r in range(0, rows, step))


def tile_states(path: str | Path) -> tuple[np.ndarray, dict[str, Any]]:
    """The state of every tile (chunk) of a mosaic, as found on reopening it.

    Returns
    -------
    states : ndarray, uint8, (tile rows, tile cols)
        :data:`TILE_EMPTY` (no chunk written), :data:`TILE_COMPLETE` (every write that
        touched it finished) or :data:`TILE_INCOMPLETE` (a write was in progress or a resume
        was rebuilding it: its values are not to be trusted; ``replay --resume`` completes it).
    info : dict
        ``status``, ``writes_done``, ``writing``, ``rebuild``, and tile counts.
    """
    from zarr.core.sync import sync

    group = zarr.open_group(str(path), mode="r", use_consolidated=False)
    attrs = read_mosaic_attrs(group, path)
    h = mosaic_array(group, "height")
    chunk = int(h.chunks[0])
    names = present_arrays(group)
    rows = max(mosaic_array(group, n).shape[0] for n in names)
    cols = max(mosaic_array(group, n).shape[1] for n in names)
    states = np.zeros((-(-rows // chunk), -(-cols // chunk)), np.uint8)
    for name in names:
        arr = mosaic_array(group, name)
        sp = arr.store_path
        prefix = f"{sp.path}/c/"

        async def _list(prefix: str = prefix, sp: Any = sp) -> list[str]:
            return [k async for k in sp.store.list_prefix(prefix)]

        for key in sync(_list()):
            parts = key[len(prefix):].split("/")
            if len(parts) == 2 and all(q.isdigit() for q in parts):
                r, c = int(parts[0]), int(parts[1])
                if r < states.shape[0] and c < states.shape[1]:
                    states[r, c] = TILE_COMPLETE
    bad = [tuple(b) for b in attrs.rebuild] + ([tuple(attrs.writing)] if attrs.writing else [])
    ox, oy = attrs.origin_px
    for x0, y0, w, hgt in bad:
        r0, c0 = max(0, (y0 - oy) // chunk), max(0, (x0 - ox) // chunk)
        r1, c1 = (y0 - oy + hgt - 1) // chunk + 1, (x0 - ox + w - 1) // chunk + 1
        states[r0:r1, c0:c1] = TILE_INCOMPLETE
    info = {"status": attrs.status, "writes_done": attrs.writes_done,
            "writing": attrs.writing, "rebuild": attrs.rebuild,
            "tiles": int(states.size), "complete": int((states == TILE_COMPLETE).sum()),
            "incomplete": int((states == TILE_INCOMPLETE).sum()),
            "empty": int((states == TILE_EMPTY).sum())}
    return states, info


class MosaicStage(Stage):
    """Gathers depth blocks into chunk-wide bands and writes them into the mosaic."""

    name = "mosaic"
    unit = "blocks"

    def __init__(self, writer: MosaicWriter) -> None:
        self.writer = writer
        self.bands: dict[int, _Band] = {}
        self.pass_index: int | None = None
        self.blocks = 0

    def _band_for(self, cx: int, y0: int, rows: int) -> _Band:
        band = self.bands.get(cx)
        if band is None:
            c = self.writer.chunk
            x0 = self.writer.origin[0] + cx * c
            z = np.zeros((rows, c), np.float64)
            band = _Band(x0, y0, z.copy(), z.copy(), z.copy(), z.astype(np.float32), z.copy())
            self.bands[cx] = band
        return band

    def _flush_band(self, cx: int) -> None:
        b = self.bands.pop(cx)
        if not (b.w > 0).any():
            return
        self.writer.write_region(b.x0, b.y0, {"height": b.wh, "texture": b.wt, "weight": b.w,
                                              "confidence": b.conf, "uncertainty": b.wu})

    def process(self, item: DepthBlock) -> Iterator[None]:
        h = item.header
        if self.pass_index is not None and h.pass_index != self.pass_index:
            self.flush()
        self.pass_index = h.pass_index
        self.blocks += 1
        valid = np.isfinite(item.height_um)
        weight = np.where(valid, np.maximum(item.confidence, MIN_WEIGHT), 0.0)
        c, ox = self.writer.chunk, self.writer.origin[0]
        first = (h.x0_px - ox) // c
        last = (h.x0_px + h.width_px - 1 - ox) // c
        rows = item.height_um.shape[0]
        for cx in range(first, last + 1):
            band = self._band_for(cx, h.y0_px, rows)
            a = max(h.x0_px, band.x0)
            e = min(h.x0_px + h.width_px, band.x0 + c)
            src = slice(a - h.x0_px, e - h.x0_px)
            dst = slice(a - band.x0, e - band.x0)
            w = weight[:, src]
            band.w[:, dst] += w
            band.wh[:, dst] += np.where(valid[:, src], item.height_um[:, src], 0.0) * w
            band.wt[:, dst] += np.where(valid[:, src], item.texture[:, src], 0.0) * w
            band.conf[:, dst] = np.maximum(band.conf[:, dst], item.confidence[:, src])
            if item.uncertainty_um is None:  # unknown: NaN where this block contributes
                band.wu[:, dst] += np.where(w > 0, np.nan, 0.0)
            else:
                band.wu[:, dst] += np.where(valid[:, src], item.uncertainty_um[:, src], 0.0) * w
        # bands the motion has left behind are final for this pass
        for cx in [k for k in self.bands if k < first or k > last]:
            self._flush_band(cx)
        return iter(())

    def flush(self) -> None:
        for cx in sorted(self.bands):
            self._flush_band(cx)

    def finish(self) -> Iterator[None]:
        self.flush()
        return iter(())

    def close(self, *, failed: bool) -> None:
        # On failure, what is already complete is still written: the mosaic stays readable.
        # Each band is tried on its own, and the status is set whatever happens.
        error: Exception | None = None
        for cx in sorted(self.bands):
            try:
                self._flush_band(cx)
            except Exception as exc:  # noqa: BLE001 - re-raised below, after the status
                error = error or exc
        failed = failed or error is not None
        self.writer.set_status("failed" if failed else "complete",
                               valid_pixels=self.writer.valid_px, blocks=self.blocks)
        if error is not None:
            raise error

    def extra_stats(self) -> dict[str, int]:
        return {"valid_pixels": self.writer.valid_px,
                "chunks_written": self.writer.blocks_written}
