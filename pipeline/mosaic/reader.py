"""Reading a mosaic: its validated attributes, its levels, the state of its tiles after a
crash, and the lazy xarray Dataset that :func:`sffscan.open_mosaic` returns.

Readers open the group without its consolidated metadata (``use_consolidated=False``): a
copy made at the final status that a resume or a damaged array may have made stale.
"""

from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np
import zarr
from pydantic import ValidationError
from sffscan.pipeline.mosaic.attrs import MosaicAttrs
from sffscan.pipeline.mosaic.layout import ARRAYS, mosaic_array, present_arrays
from sffscan.pipeline.mosaic.ngff import level_path

if TYPE_CHECKING:
    import xarray

#: tile states of :func:`tile_states`
TILE_EMPTY, TILE_COMPLETE, TILE_INCOMPLETE = 0, 1, 2


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


def open_dataset(path: str | Path, *, level: int = 0) -> xarray.Dataset:
    """One level of a mosaic as a lazy xarray Dataset over dask with µm coordinates: what
    :func:`sffscan.open_mosaic` returns (parameters, variables and errors described there).
    """
    import dask.array as da
    import xarray as xr

    p = Path(path)
    try:
        group = zarr.open_group(str(p), mode="r", use_consolidated=False)
    except (FileNotFoundError, ValueError, KeyError) as err:
        raise ValueError(f"{p}: not a Zarr group ({err})") from None
    attrs = read_mosaic_attrs(group, p)
    levels = len(attrs.ome.multiscales[0].datasets) if attrs.ome is not None else 1
    if not 0 <= level < levels:
        raise ValueError(f"{p}: no pyramid level {level} (the mosaic has levels 0..{levels - 1})")
    # the arrays this mosaic has (its NGFF pyramids; version 1: the ones present), so a
    # mosaic written before an array was added still opens
    names = ([m.name for m in attrs.ome.multiscales] if attrs.ome is not None else
             [n for n in ARRAYS if isinstance(group.get(n), zarr.Array)])
    variables = {}
    for name in names:
        arr = mosaic_array(group, level_path(name, level))
        variables[name] = (("y", "x"), da.from_array(arr, chunks=arr.chunks),
                           {"units": attrs.units.get(name, "")})
    ny, nx = mosaic_array(group, level_path("height", level)).shape
    f = 2 ** level
    step = attrs.pixel_um * f
    half = (f - 1) / 2 * attrs.pixel_um  # a level-k pixel is centred on its block
    coords = {"y": ("y", attrs.origin_um[1] + half + step * np.arange(ny), {"units": "µm"}),
              "x": ("x", attrs.origin_um[0] + half + step * np.arange(nx), {"units": "µm"})}
    return xr.Dataset(variables, coords=coords,
                      attrs={**attrs.model_dump(mode="json"), "level": level,
                             "pixel_um_level": step})
