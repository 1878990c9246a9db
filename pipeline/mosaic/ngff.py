"""OME-Zarr (NGFF 0.5) metadata of a mosaic: typed models and the one function that builds it.

A mosaic group is an NGFF 0.5 image (Zarr v3): its ``ome`` attribute holds one
``multiscales`` entry per mosaic array, ``height`` first (the one viewers and the
``ome-zarr`` reader show). Each entry lists the arrays of that variable from full
resolution down: ``<name>`` (level 0, the mosaic itself) then ``pyramid/<k>/<name>`` for
k = 1 .. levels - 1, level k halving level k - 1 (see :func:`sffscan.stages.mosaic.downsample`).

Coordinates (axes ``y``, ``x`` in micrometre): element ``i`` of level ``k`` has its centre
at ``i * scale_k + translation_k`` with ``scale_k = 2**k * pixel_um`` and
``translation_k = origin_um + (2**k - 1) / 2 * pixel_um``: a level-k pixel is the mean of a
2^k x 2^k block of level-0 pixels, and its centre is the centre of that block.

For xarray (format version 3): every level also holds 1-D coordinate arrays ``y`` and
``x`` (float64, µm, the element centres above; :data:`COORDS`, :func:`level_coords`), so
``xarray.open_zarr(path)`` (level 0) and ``xarray.open_zarr(path, group="pyramid/<k>")``
get µm coordinates; and the writer consolidates the metadata when it sets the final status
(:func:`consolidate`), not while the arrays still change.

Specification: https://ngff.openmicroscopy.org/0.5/ (validated in the tests with the
``ome-zarr`` reader and the ``ome-zarr-models`` package).
"""

from __future__ import annotations

import warnings
from pathlib import Path
from typing import Literal

import numpy as np
from pydantic import BaseModel, ConfigDict, Field
from sffscan.stages.mosaic import REDUCTION

__all__ = ["COORDS", "NGFF_VERSION", "NgffAxis", "NgffDataset", "NgffMultiscale", "NgffOme",
           "consolidate", "level_coords", "level_path", "mosaic_ngff"]

NGFF_VERSION: Literal["0.5"] = "0.5"


class NgffAxis(BaseModel):
    model_config = ConfigDict(extra="forbid")

    name: Literal["y", "x"]
    type: Literal["space"] = "space"
    unit: Literal["micrometer"] = "micrometer"


class NgffScale(BaseModel):
    model_config = ConfigDict(extra="forbid")

    type: Literal["scale"] = "scale"
    scale: tuple[float, float] = Field(description="(y, x) µm per element")


class NgffTranslation(BaseModel):
    model_config = ConfigDict(extra="forbid")

    type: Literal["translation"] = "translation"
    translation: tuple[float, float] = Field(description="(y, x) µm of element [0, 0]'s centre")


class NgffDataset(BaseModel):
    model_config = ConfigDict(extra="forbid")

    path: str = Field(description="Array of this level, relative to the mosaic group")
    coordinateTransformations: tuple[NgffScale, NgffTranslation]  # noqa: N815 - NGFF name


class NgffMultiscale(BaseModel):
    model_config = ConfigDict(extra="forbid")

    name: str = Field(description="The mosaic array this pyramid downsamples")
    axes: tuple[NgffAxis, NgffAxis]
    datasets: list[NgffDataset] = Field(min_length=1, description="Levels, finest first")
    type: str = Field(description="Reduction from one level to the next")


class NgffOme(BaseModel):
    """The ``ome`` attribute of an NGFF 0.5 image group."""

    model_config = ConfigDict(extra="forbid")

    version: Literal["0.5"] = "0.5"
    multiscales: list[NgffMultiscale] = Field(min_length=1)


#: the 1-D coordinate arrays of every level (format version 3): (y, x) element centres, µm
COORDS = ("y", "x")


def level_path(name: str, level: int) -> str:
    """Path of array ``name`` at pyramid ``level`` inside the mosaic group."""
    return name if level == 0 else f"pyramid/{level}/{name}"


def mosaic_ngff(*, pixel_um: float, origin_px: tuple[int, int], levels: int,
                names: tuple[str, ...]) -> NgffOme:
    """NGFF 0.5 metadata of a mosaic with ``levels`` levels of the arrays ``names``.

    Parameters
    ----------
    pixel_um : float
        Level-0 pixel size, µm.
    origin_px : (int, int)
        World (x, y) pixel of level-0 element [0, 0].
    levels : int
        Number of levels (>= 1), level 0 included.
    names : tuple of str
        Mosaic arrays; the first one is the image viewers show.
    """
    axes = (NgffAxis(name="y"), NgffAxis(name="x"))
    oy, ox = origin_px[1] * pixel_um, origin_px[0] * pixel_um
    multiscales = []
    for name in names:
        datasets = []
        for k in range(levels):
            f = 2 ** k
            half = (f - 1) / 2 * pixel_um
            datasets.append(NgffDataset(path=level_path(name, k), coordinateTransformations=(
                NgffScale(scale=(f * pixel_um, f * pixel_um)),
                NgffTranslation(translation=(oy + half, ox + half)))))
        multiscales.append(NgffMultiscale(name=name, axes=axes, datasets=datasets,
                                          type=REDUCTION.get(name, "nanmean")))
    return NgffOme(multiscales=multiscales)


def level_coords(n: int, *, level: int, pixel_um: float, origin_um: float) -> np.ndarray:
    """Centres, µm (float64, (n,)), of the first ``n`` elements along one axis of ``level``:
    ``origin_um + (2**level - 1) / 2 * pixel_um + i * 2**level * pixel_um`` (the NGFF
    scale and translation of :func:`mosaic_ngff`; ``origin_um``: level-0 element 0's
    centre on that axis)."""
    f = 2 ** level
    return origin_um + (f - 1) / 2 * pixel_um + f * pixel_um * np.arange(n, dtype=np.float64)


def consolidate(path: str | Path) -> None:
    """Consolidate the metadata of the Zarr v3 group at ``path`` (``zarr.consolidate_metadata``:
    the metadata of every array and group, copied into the root ``zarr.json``, so a reader
    opens the mosaic with one read; xarray no longer warns).

    Only for a group whose arrays no longer change: a reader that uses the copy sees the
    shapes of the moment it was made; a writer that reopens the group opens it with
    ``use_consolidated=False`` and its first attribute write drops the copy. zarr 3.1 warns
    that consolidated metadata is not part of the Zarr v3 specification (readers that do
    not know it read each ``zarr.json`` as before); that warning is expected here, and so is
    the one about files in the folder that are not Zarr nodes (the writer's reserve).
    """
    import zarr

    with warnings.catch_warnings():
        warnings.filterwarnings("ignore", message="Consolidated metadata is currently not part",
                                category=UserWarning)
        # a file of the writer's own in the folder (its disk-full reserve) is not a node
        warnings.filterwarnings("ignore", message="Object at .* is not recognized as a "
                                "component of a Zarr hierarchy", category=UserWarning)
        zarr.consolidate_metadata(str(path))
