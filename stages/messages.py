"""Typed messages passed between stages.

The header models (pydantic) are the single source of truth for the wire and file
formats: ``schemas/*.json`` are generated from them (``sffscan schemas``) and a test fails
when they drift. Array payloads travel beside the headers as numpy arrays (in process) or
raw bytes (on the wire), never pickled.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np
from pydantic import BaseModel, ConfigDict, Field


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
class RawColumns:
    """A placed frame whose focus measure the depth stage's band processes compute
    (:meth:`sffscan.stages.depth_stage.DepthStage.process`): the frame columns [c0, c1)
    measured and [a0, a1) read, and the measure's ``operator``, ``window`` and
    ``max_value`` (:func:`sffscan.stages.focus_measure.focus_measure_raw`). Passed from
    the focus measure stage to the depth stage in one process, never sent between
    processes."""

    placed: PlacedFrame
    columns: tuple[int, int, int, int]
    measure: dict[str, Any]


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
