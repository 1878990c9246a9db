"""The attributes of a mosaic Zarr group (format ``sffscan-mosaic``): the typed model that
``schemas/mosaic_attrs.json`` is generated from, and the accuracy record it may carry."""

from __future__ import annotations

from typing import Any, Literal

from pydantic import BaseModel, ConfigDict, Field
from sffscan.pipeline.mosaic.ngff import NgffOme


class MosaicAccuracy(BaseModel):
    """A mosaic's accuracy against a true surface (``sffscan batch``'s evaluation of a
    simulated recording): RMSE, Pearson correlation and PSNR of ``height`` over the finite
    pixels compared; a statistic that is undefined (no pixels, no variance) or infinite
    (PSNR of an exact match) is null."""

    model_config = ConfigDict(extra="forbid", allow_inf_nan=False)

    truth: str = Field(description="What the heights were compared with")
    rmse_um: float | None = Field(ge=0, description="Root-mean-square error, µm")
    corr: float | None = Field(ge=-1, le=1, description="Pearson correlation coefficient")
    psnr_db: float | None = Field(
        description="Peak signal-to-noise ratio, dB, with the focus range as the peak")
    pixels: int = Field(ge=0, description="Pixels compared (finite in the mosaic)")
    coverage: float = Field(ge=0, le=1, description="Finite fraction of the pixels asked")
    within_2sigma: float | None = Field(
        default=None, ge=0, le=1,
        description="Share of the compared pixels with a finite uncertainty whose |error| "
        "is at most twice it (calibrated: 0.90 .. 0.98); null without an uncertainty")
    sigma_pixels: int | None = Field(
        default=None, ge=0, description="Compared pixels with a finite uncertainty")


class MosaicAttrs(BaseModel):
    """Attributes of a mosaic Zarr group (format ``sffscan-mosaic``)."""

    model_config = ConfigDict(extra="forbid")

    format: Literal["sffscan-mosaic"] = "sffscan-mosaic"
    format_version: Literal[1, 2, 3] = Field(
        default=3, description="3: as 2, with 1-D coordinate arrays y, x (µm) at every level "
        "and metadata consolidated at the final status; 2: an OME-Zarr (NGFF 0.5) image with "
        "a resolution pyramid (attribute 'ome'); 1: the four arrays only (still read)")
    status: Literal["writing", "complete", "incomplete", "failed"] = Field(
        description="'complete' after a clean end of stream in which every expected frame "
        "(frames_expected) was received and processed; 'incomplete' after a clean end with "
        "fewer (frames_received < frames_expected, or no count from the sender); 'failed' if a "
        "stage failed (the arrays hold every block completed before the failure)")
    frames_expected: int | None = Field(
        default=None, ge=0, description="Frames the scan should have: the plan's (or "
        "camera.frames, or the recording's), or the count the sender's end message gave; null "
        "when unknown")
    frames_received: int | None = Field(
        default=None, ge=0, description="Frames received and processed")
    units: dict[str, str] = Field(description="Unit of each array")
    pixel_um: float = Field(gt=0, description="Pixel scale, µm/px")
    origin_px: tuple[int, int] = Field(description="World (x, y) px of array element [0, 0]")
    origin_um: tuple[float, float] = Field(description="World (x, y) µm of array element [0, 0]")
    axes: tuple[Literal["y"], Literal["x"]] = ("y", "x")
    created: str = Field(description="UTC creation time, ISO 8601")
    processing: dict[str, Any] = Field(description="Focus operator, window, depth method, ...")
    focus_heights_um: list[float] = Field(description="Height in focus at each level, µm")
    scan_config: dict[str, Any] = Field(description="The scan configuration (scan_config schema)")
    valid_pixels: int | None = Field(default=None, ge=0)
    blocks: int | None = Field(default=None, ge=0)
    codec: str | None = Field(default=None, description="Codec of the arrays, informative")
    writes_done: int = Field(
        default=0, ge=0, description="Journal: region writes completed, in stream order (each "
        "blends one chunk-wide band of a pass into all four arrays)")
    writing: tuple[int, int, int, int] | None = Field(
        default=None, description="Journal: world px box (x0, y0, width, height) of the write "
        "in progress; not null after a crash: the tiles (chunks) it covers may be torn")
    rebuild: list[tuple[int, int, int, int]] = Field(
        default_factory=list, description="World px boxes reset by 'replay --resume' that are "
        "being rebuilt from the writes before 'writes_done'; their tiles are incomplete")
    recording: dict[str, Any] | None = Field(
        default=None, description="The recording this mosaic was replayed from (path, frames, "
        "defects found), null for a live scan")
    resumed: int = Field(default=0, ge=0, description="Times 'replay --resume' continued it")
    pyramid_stale: tuple[int, int, int, int] | None = Field(
        default=None, description="Journal: world px box (x0, y0, width, height) of level 0 "
        "whose pyramid levels the writer holds unwritten (a bounded write-back cache); after "
        "a crash, 'replay --resume' recomputes them; null once written")
    ome: NgffOme | None = Field(
        default=None, description="OME-Zarr (NGFF 0.5) multiscales metadata: one pyramid per "
        "array, 'height' first (format version 2); null in version 1")
    accuracy: MosaicAccuracy | None = Field(
        default=None, description="Accuracy against the true surface, stored by the run that "
        "evaluated it (a simulated recording's replay in 'sffscan batch'); null if not "
        "evaluated")
