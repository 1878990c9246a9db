"""Typed messages passed between stages.

The header models (pydantic) are the single source of truth for the wire and file
formats: ``schemas/*.json`` are generated from them (``sffscan schemas``) and a test fails
when they drift. Array payloads travel beside the headers as numpy arrays (in process) or
raw bytes (on the wire), never pickled.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Literal

import numpy as np
from pydantic import BaseModel, ConfigDict, Field
from sffscan.pipeline.formats.ngff import NgffOme


class FrameHeader(BaseModel):
    """Metadata of one raw camera frame."""

    model_config = ConfigDict(extra="forbid", frozen=True, allow_inf_nan=False)

    frame_id: int = Field(ge=0, le=2**63 - 1, description="Frame counter of the camera, from "
                          "0 (stored as int64)")
    timestamp_ns: int = Field(ge=0, le=2**63 - 1, description="Exposure time stamp, ns "
                              "(device clock; stored as int64)")
    focus_index: int = Field(ge=0, le=2**31 - 1, description="Focus level of the lens "
                             "staircase, 0..N-1 (stored as int32)")
    stage_x_um: float | None = Field(
        default=None,
        description="Commanded stage position along x: world x of the frame's first column, "
        "µm; null when the source has no position (the speed model is used)",
    )
    stage_y_um: float | None = Field(
        default=None,
        description="Commanded stage position along y: world y of the frame's first row, µm",
    )
    pass_index: int = Field(default=0, ge=0, le=2**31 - 1,
                            description="Index of the parallel scan pass (stored as int32)")


class DepthBlockHeader(BaseModel):
    """Metadata of a block of completed world columns (the depth stage's output)."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    x0_px: int = Field(description="World column of the block's first column, px")
    y0_px: int = Field(description="World row of the block's first row, px")
    width_px: int = Field(ge=1)
    height_px: int = Field(ge=1)
    pass_index: int = Field(ge=0)
    complete_columns: int = Field(ge=0, description="Columns seen at all N focus levels")
    incomplete_columns: int = Field(ge=0, description="Columns that missed levels: invalid")


@dataclass(slots=True)
class Frame:
    """A raw frame: header plus image, shape (H, W), uint8 or uint16."""

    header: FrameHeader
    image: np.ndarray


@dataclass(slots=True)
class PlacedFrame:
    """A frame with its position in world pixels.

    ``predicted_px`` is the (x, y) position from the stage/speed, fractional px;
    ``offset_px`` the integer (x, y) world position of the frame's first pixel after
    registration; ``correction_px`` the registration correction that was applied.
    """

    header: FrameHeader
    image: np.ndarray
    predicted_px: tuple[float, float]
    offset_px: tuple[int, int]
    correction_px: tuple[float, float] = (0.0, 0.0)


@dataclass(slots=True)
class FocusFrame:
    """A placed frame with the focus measure and unit-scaled image of columns
    [col0, col0 + w) (float32, (H, w)): the columns that can still add to the volume."""

    placed: PlacedFrame
    image01: np.ndarray
    focus: np.ndarray
    col0: int = 0


@dataclass(slots=True)
class DepthBlock:
    """Completed world columns: height (µm, NaN invalid), texture (0..1), confidence, and
    the height's uncertainty (µm, one sigma, NaN invalid; None where not computed)."""

    header: DepthBlockHeader
    height_um: np.ndarray
    texture: np.ndarray
    confidence: np.ndarray
    uncertainty_um: np.ndarray | None = None


class FrameError(ValueError):
    """A frame that cannot be processed; the message names the frame_id."""


def check_frame(frame: Frame, *, shape: tuple[int, int], dtype: np.dtype, n_levels: int) -> None:
    """Raise :class:`FrameError` naming the frame if its image or header is unusable."""
    fid = frame.header.frame_id
    img = frame.image
    if not isinstance(img, np.ndarray):
        raise FrameError(f"frame_id {fid}: image is {type(img).__name__}, not a numpy array")
    if img.shape != shape:
        raise FrameError(f"frame_id {fid}: image shape {img.shape} differs from the configured "
                         f"(height, width) {shape}")
    if img.dtype.kind == "f" and not np.isfinite(img).all():
        bad = int(np.count_nonzero(~np.isfinite(img)))
        raise FrameError(f"frame_id {fid}: image has {bad} NaN/inf pixels")
    if img.dtype != dtype:
        raise FrameError(f"frame_id {fid}: image dtype {img.dtype} differs from the configured "
                         f"{np.dtype(dtype)}")
    if frame.header.focus_index >= n_levels:
        raise FrameError(f"frame_id {fid}: focus_index {frame.header.focus_index} is not below "
                         f"the number of focus levels {n_levels}")


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
