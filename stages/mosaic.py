"""Mosaic: completed depth blocks, stitched in world coordinates into a Zarr v3 group.

Layout of the group (format ``sffscan-mosaic``, version 1; schema in
``schemas/mosaic_attrs.v1.json``):

- ``height``: float32 (y, x), µm, NaN where nothing valid was measured;
- ``texture``: float32 (y, x), all-in-focus grey value 0..1, NaN where invalid;
- ``confidence``: float32 (y, x), the largest confidence of the contributions, 0..1;
- ``weight``: float32 (y, x), the sum of contribution weights used to blend overlaps.

Pixel (row, col) of the arrays is world pixel (origin_px[1] + row, origin_px[0] + col);
world pixel (x, y) has its centre at (x, y) * pixel_um µm. All passes of a plate land in
the one mosaic; where passes overlap, height and texture are the weighted mean with
weight = max(confidence, 1e-3) over valid pixels. Blocks are gathered in memory per
chunk-wide column band and written when the motion has left the band, so each chunk is
written once per pass and memory stays bounded.
"""

from __future__ import annotations

import datetime as _dt
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import zarr

from pipeline.messages import DepthBlock, MosaicAttrs
from pipeline.runtime import Stage

ARRAYS = ("height", "texture", "confidence", "weight")
MIN_WEIGHT = 1e-3


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
        group = zarr.open_group(str(path), mode="r")
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
        Extra attributes (the scan configuration, processing settings).
    overwrite : bool
        Replace an existing group; otherwise an existing path is an error.
    """

    def __init__(self, path: str | Path, *, origin_px: tuple[int, int], shape: tuple[int, int],
                 pixel_um: float, chunk_px: int = 256, attrs: dict[str, Any] | None = None,
                 overwrite: bool = False) -> None:
        self.path = Path(path)
        if self.path.exists():
            if not overwrite:
                raise FileExistsError(f"{self.path}: exists (set output.overwrite or remove it)")
            if not is_replaceable(self.path):
                raise FileExistsError(f"{self.path}: exists and is not an sffscan mosaic nor an "
                                      "empty folder; refusing to overwrite it")
        self.origin = origin_px
        self.chunk = chunk_px
        self.group = zarr.open_group(str(self.path), mode="w")
        for name in ARRAYS:
            fill = np.nan if name in ("height", "texture") else 0.0
            self.group.create_array(name=name, shape=shape, chunks=(chunk_px, chunk_px),
                                    dtype="float32", fill_value=fill, dimension_names=("y", "x"))
        attrs = dict(attrs or {})
        header = MosaicAttrs(
            status="writing",
            units={"height": "µm", "texture": "1 (0..1 grey)", "confidence": "1 (0..1)",
                   "weight": "1"},
            pixel_um=pixel_um,
            origin_px=origin_px,
            origin_um=(origin_px[0] * pixel_um, origin_px[1] * pixel_um),
            created=_dt.datetime.now(_dt.UTC).isoformat(timespec="seconds"),
            processing=attrs.pop("processing", {}),
            focus_heights_um=attrs.pop("focus_heights_um", []),
            scan_config=attrs.pop("scan_config", {}),
        )
        if attrs:
            raise ValueError(f"unknown mosaic attributes: {sorted(attrs)}")
        self.group.attrs.update(header.model_dump(mode="json"))
        self.blocks_written = 0

    def _ensure(self, r1: int, c1: int) -> None:
        rows, cols = mosaic_array(self.group, "height").shape
        if r1 > rows or c1 > cols:
            for name in ARRAYS:
                mosaic_array(self.group, name).resize((max(rows, r1), max(cols, c1)))

    def write_region(self, x0: int, y0: int, new: dict[str, np.ndarray]) -> None:
        """Blend weighted sums ``new`` (see :func:`blend`) at world pixel (x0, y0)."""
        r0, c0 = y0 - self.origin[1], x0 - self.origin[0]
        rows, cols = new["weight"].shape
        if r0 < 0 or c0 < 0:
            raise ValueError(f"block at world px (x={x0}, y={y0}) lies before the mosaic origin "
                             f"{self.origin}; widen the scan area in the configuration")
        self._ensure(r0 + rows, c0 + cols)
        sel = (slice(r0, r0 + rows), slice(c0, c0 + cols))
        arrays = {name: mosaic_array(self.group, name) for name in ARRAYS}
        old = {name: np.asarray(arr[sel]) for name, arr in arrays.items()}
        for name, value in blend(old, new).items():
            arrays[name][sel] = value
        self.blocks_written += 1

    def set_status(self, status: str, **extra: Any) -> None:
        attrs = MosaicAttrs.model_validate({**self.group.attrs.asdict(), "status": status, **extra})
        self.group.attrs.update(attrs.model_dump(mode="json"))


class MosaicStage(Stage):
    """Gathers depth blocks into chunk-wide bands and writes them into the mosaic."""

    name = "mosaic"
    unit = "blocks"

    def __init__(self, writer: MosaicWriter) -> None:
        self.writer = writer
        self.bands: dict[int, _Band] = {}
        self.pass_index: int | None = None
        self.valid_px = 0
        self.blocks = 0

    def _band_for(self, cx: int, y0: int, rows: int) -> _Band:
        band = self.bands.get(cx)
        if band is None:
            c = self.writer.chunk
            x0 = self.writer.origin[0] + cx * c
            z = np.zeros((rows, c), np.float64)
            band = _Band(x0, y0, z.copy(), z.copy(), z.copy(), z.astype(np.float32))
            self.bands[cx] = band
        return band

    def _flush_band(self, cx: int) -> None:
        b = self.bands.pop(cx)
        if not (b.w > 0).any():
            return
        self.writer.write_region(b.x0, b.y0, {"height": b.wh, "texture": b.wt, "weight": b.w,
                                              "confidence": b.conf})

    def process(self, item: DepthBlock) -> Iterator[None]:
        h = item.header
        if self.pass_index is not None and h.pass_index != self.pass_index:
            self.flush()
        self.pass_index = h.pass_index
        self.blocks += 1
        valid = np.isfinite(item.height_um)
        self.valid_px += int(valid.sum())
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
                               valid_pixels=self.valid_px, blocks=self.blocks)
        if error is not None:
            raise error

    def extra_stats(self) -> dict[str, int]:
        return {"valid_pixels": self.valid_px, "chunks_written": self.writer.blocks_written}
