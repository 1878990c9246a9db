"""The mosaic writer: creates the group, blends band writes in, keeps the pyramid current,
journals every write, resumes an interrupted mosaic and sets the final status.

Crash safety (a journal in the attributes): each band write covers several chunks of the
arrays and can be torn by a crash. Before a write the writer records its box in
``writing``; after it, ``writes_done`` (the number of writes completed, in stream order)
and ``writing = null``. Zarr's local store replaces each file atomically, so on reopening
(:func:`~sffscan.pipeline.mosaic.reader.tile_states`) every tile (chunk) is either complete,
empty, or known to be incomplete (it meets the box of the torn write).
:meth:`MosaicWriter.reopen` continues such a mosaic from a replay of its recording
(``sffscan replay --resume``): it resets the torn box, skips the writes already done
(re-applying, inside the reset box only, those that touched it) and journals the rest; the
result is bit for bit the uninterrupted mosaic.
"""

from __future__ import annotations

import datetime as _dt
import json
import logging
import os
import uuid
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
import zarr
from sffscan.pipeline.formats.durable import free_reserve, make_reserve
from sffscan.pipeline.formats.zarr_chunks import Plans, read_many, write_many
from sffscan.pipeline.mosaic.attrs import MosaicAttrs
from sffscan.pipeline.mosaic.layout import (
    ARRAYS,
    DEFAULT_CODEC,
    FILL,
    UNITS,
    Box,
    mosaic_array,
    mosaic_codecs,
    present_arrays,
)
from sffscan.pipeline.mosaic.ngff import consolidate, mosaic_ngff
from sffscan.pipeline.mosaic.pyramid import (
    LAG_S,
    CoordArrays,
    PyramidCache,
    coord_arrays,
    create_coords,
    create_pyramid,
    pyramid_arrays,
    resize_pyramid,
    update_pyramid,
    write_coords,
)
from sffscan.pipeline.mosaic.reader import count_valid, read_mosaic_attrs
from sffscan.stages.mosaic import aligned, blend, default_levels

log = logging.getLogger(__name__)


def _intersect(a: Box, b: Box) -> Box | None:
    x0, y0 = max(a[0], b[0]), max(a[1], b[1])
    x1, y1 = min(a[0] + a[2], b[0] + b[2]), min(a[1] + a[3], b[1] + b[3])
    return (x0, y0, x1 - x0, y1 - y0) if x1 > x0 and y1 > y0 else None


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


def is_replaceable(path: Path) -> bool:
    """True for an empty folder or a Zarr group written as an sffscan mosaic."""
    if path.is_dir() and not any(path.iterdir()):
        return True
    try:
        group = zarr.open_group(str(path), mode="r", use_consolidated=False)
    except Exception:  # noqa: BLE001 - anything that is not a readable group
        return False
    return group.attrs.get("format") == "sffscan-mosaic"


def check_replaceable(path: Path, *, overwrite: bool) -> None:
    """Raise :class:`FileExistsError` naming ``path`` unless a new mosaic may be written
    there: nothing there, or (with ``overwrite``) a mosaic or an empty folder."""
    if path.exists():
        if not overwrite:
            raise FileExistsError(f"{path}: exists; --overwrite (output.overwrite in a "
                                  "configuration) replaces it, or remove it")
        if not is_replaceable(path):
            raise FileExistsError(f"{path}: exists and is not an sffscan mosaic nor an "
                                  "empty folder; refusing to overwrite it")


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
        default :func:`~sffscan.stages.mosaic.default_levels` (at least 4).
    pyramid_lag_s : float, optional
        Longest time, s, an upper-level chunk keeps changes unwritten while band writes
        still touch it (:class:`~sffscan.pipeline.mosaic.pyramid.PyramidCache`); by default
        :data:`~sffscan.pipeline.mosaic.pyramid.LAG_S` (5 s).

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
        check_replaceable(self.path, overwrite=overwrite)
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
        self.plans = Plans()  # the chunk plans of the arrays, worked out once
        self.cache = (PyramidCache(self.pyramid, lag_s=lag, empty=True, plans=self.plans)
                      if self.pyramid else None)
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
        self._doc = self._read_doc()
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
        self.plans = Plans()
        self.cache = (PyramidCache(self.pyramid, lag_s=LAG_S, plans=self.plans)
                      if self.pyramid else None)
        group.update_attributes({})  # drops consolidated metadata, if any
        self._doc = self._read_doc()
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

    def _read_doc(self) -> dict[str, Any]:
        doc = json.loads((self.path / "zarr.json").read_bytes())
        if not isinstance(doc, dict) or not isinstance(doc.get("attributes"), dict):
            raise ValueError(f"{self.path / 'zarr.json'}: not a Zarr v3 group's metadata")
        return doc

    @property
    def attributes(self) -> dict[str, Any]:
        """The group's attributes as last written (a copy)."""
        return json.loads(json.dumps(self._doc["attributes"], allow_nan=True))

    def update_attributes(self, changes: dict[str, Any]) -> None:
        """Merge ``changes`` into the group's attributes, in one atomic write of its
        ``zarr.json``.

        The group's metadata document (read once when the writer opened the group) with the
        changes, written to a temporary file renamed over the document, as zarr's local
        store writes it, but not through zarr: ``zarr.Group.update_attributes`` cost about
        2 ms of CPU per call for this ~24 kB document (its event loop, its metadata model
        and an indented dump by the pure-Python JSON encoder), and the journal makes two
        per band write; here ~0.1 ms (the same document, compact: readers parse it alike;
        ``bench/bench_mosaic.py``). NaN is written as zarr writes it (``NaN``).
        Consolidated metadata, if any, is dropped (stale once anything changes;
        :meth:`set_status` consolidates again). Every attribute write of the writer, and
        of its users, goes through here, so the document in memory is the one on disk.
        """
        doc = self._doc
        doc["attributes"].update(json.loads(json.dumps(changes, allow_nan=True)))
        doc.pop("consolidated_metadata", None)
        data = json.dumps(doc, allow_nan=True).encode()
        path = self.path / "zarr.json"
        tmp = path.with_suffix(f".{uuid.uuid4().hex}.partial")
        try:
            tmp.write_bytes(data)
            os.replace(tmp, path)
        except BaseException:
            tmp.unlink(missing_ok=True)
            raise

    def _journal(self, **changes: Any) -> None:
        """Update attributes in one atomic write of the group's metadata, with the box of
        the pyramid's unwritten chunks (``pyramid_stale``)."""
        self.update_attributes({**changes, "pyramid_stale": self._stale()})

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
        buf = dict(zip(self.arrays, read_many([(arrays[n], region) for n in self.arrays],
                                              plans=self.plans), strict=True))
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
        write_many(writes, plans=self.plans)

    def flush_pyramid(self) -> None:
        """Write every chunk the pyramid's cache holds (then the pyramid is current)."""
        if self.cache is not None:
            write_many(self.cache.write_back(everything=True), plans=self.plans)

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
        attrs = MosaicAttrs.model_validate({**self.attributes, "status": status,
                                            "pyramid_stale": stale, **extra})
        free_reserve(self.path)  # the final status is written even when the disk is full
        self.update_attributes(attrs.model_dump(mode="json"))
        if self.coords is not None:  # format version 3: one read opens it (xarray, NGFF)
            try:
                consolidate(self.path)
            except OSError as err:
                log.warning("%s: metadata not consolidated (%s); readers open it without",
                            self.path, err)
