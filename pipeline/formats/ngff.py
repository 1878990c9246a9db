"""OME-Zarr (NGFF 0.5) metadata of a mosaic: typed models and the one function that builds it.

A mosaic group is an NGFF 0.5 image (Zarr v3): its ``ome`` attribute holds one
``multiscales`` entry per mosaic array, ``height`` first (the one viewers and the
``ome-zarr`` reader show). Each entry lists the arrays of that variable from full
resolution down: ``<name>`` (level 0, the mosaic itself) then ``pyramid/<k>/<name>`` for
k = 1 .. levels - 1, level k halving level k - 1 (see :mod:`sffscan.stages.mosaic_pyramid`).

Coordinates (axes ``y``, ``x`` in micrometre): element ``i`` of level ``k`` has its centre
at ``i * scale_k + translation_k`` with ``scale_k = 2**k * pixel_um`` and
``translation_k = origin_um + (2**k - 1) / 2 * pixel_um``: a level-k pixel is the mean of a
2^k x 2^k block of level-0 pixels, and its centre is the centre of that block.

Specification: https://ngff.openmicroscopy.org/0.5/ (validated in the tests with the
``ome-zarr`` reader and the ``ome-zarr-models`` package).
"""

from __future__ import annotations

from typing import Literal

from pydantic import BaseModel, ConfigDict, Field

__all__ = ["NGFF_VERSION", "NgffAxis", "NgffDataset", "NgffMultiscale", "NgffOme",
           "level_path", "mosaic_ngff"]

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


#: reduction of each array from one level to the next
REDUCTION = {"height": "nanmean", "texture": "nanmean", "confidence": "mean", "weight": "sum"}


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
