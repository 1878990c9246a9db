"""What a mosaic group holds: its arrays, their fill values, units and codecs.

The arrays, each (y, x) float32 with its unit in its own attributes (``units``):

- ``height``: µm, NaN where nothing valid was measured;
- ``texture``: all-in-focus grey value 0..1, NaN where invalid;
- ``confidence``: the largest confidence of the contributions, 0..1;
- ``weight``: the sum of contribution weights used to blend overlaps;
- ``uncertainty``: µm, one sigma: the weighted mean of the contributions' height
  uncertainties (the depth stage's), NaN where invalid or where a contribution had none
  (format version 3 and earlier wrote no ``uncertainty``: :data:`OPTIONAL`).
"""

from __future__ import annotations

from typing import Any

import numpy as np
import zarr
from zarr.codecs import BloscCodec, BloscShuffle

ARRAYS = ("height", "texture", "confidence", "weight", "uncertainty")
#: arrays an older mosaic may lack (format version 3 and earlier wrote no ``uncertainty``)
OPTIONAL = ("uncertainty",)
FILL = {"height": np.nan, "texture": np.nan, "confidence": 0.0, "weight": 0.0,
        "uncertainty": np.nan}
UNITS = {"height": "µm", "texture": "1 (0..1 grey)", "confidence": "1 (0..1)", "weight": "1",
         "uncertainty": "µm (one sigma)"}
#: codec of the mosaic arrays (measured in bench/recorder_results.md)
DEFAULT_CODEC = "blosc-lz4"

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
