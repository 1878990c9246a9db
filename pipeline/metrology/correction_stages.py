"""Optics corrections in the streaming scan: the calibration's vignetting and magnification
per focus level (in the frames, before they are placed in world coordinates) and its field
curvature (in the heights).

    source -> [frame_optics] -> speed_shift -> ... -> depth -> [field_curvature] -> mosaic

Both stages are thin wrappers of the pure functions in
:mod:`sffscan.pipeline.metrology.optics_correction`; :func:`optics_correction_stages` builds
them from a configuration whose ``processing.calibration`` names a calibration file (none
when the file has neither ``lateral`` nor ``field_curvature``).
"""

from __future__ import annotations

import dataclasses
from collections.abc import Iterator, Sequence

import numpy as np
from sffscan.pipeline.config import ScanConfig
from sffscan.pipeline.metrology.calibration_model import (
    Calibration,
    illumination_map,
    load_calibration,
)
from sffscan.pipeline.metrology.optics_correction import (
    ScanCurvature,
    applied,
    check_configured_scale,
    flat_field,
    flat_field_into,
    level_magnification,
    unbreathe_frame,
    unbreathe_resampler,
)
from sffscan.stages.fields.resample import ScaleResampler
from sffscan.stages.messages import DepthBlock, Frame, FrameError
from sffscan.stages.protocol import Stage

__all__ = ["CurvatureStage", "FrameOpticsStage", "corrections_applied",
           "optics_correction_stages"]


class FrameOpticsStage(Stage):
    """Flat-fields each frame (vignetting), then resamples it to the reference level's scale
    about the optical centre (magnification per level).

    Each level's resampling is prepared at its first frame and kept (float32 weights,
    ~0.4 MiB a level for 1280 x 1024 frames; 5-12 ms of CPU to prepare), with one pair of
    work arrays for every level.

    Parameters
    ----------
    magnifications : (N,) array_like of float, or None
        Relative magnification of each focus level (1 = reference); None: not resampled.
    centre_px : (x, y)
        Optical centre, frame px.
    illumination : (H, W) float32 or None
        Relative illumination of the frame; None: not flat-fielded.
    max_value : float
        Full scale the flat-fielded frames are clipped to.
    """

    name = "frame_optics"

    def __init__(self, magnifications: Sequence[float] | np.ndarray | None, *,
                 centre_px: tuple[float, float], illumination: np.ndarray | None = None,
                 max_value: float = 65535.0) -> None:
        self.mags = None if magnifications is None else np.asarray(magnifications, np.float64)
        self.centre = (float(centre_px[0]), float(centre_px[1]))
        self.illumination = illumination
        self.max_value = max_value
        self._resamplers: dict[tuple[int, tuple[int, int]], ScaleResampler] = {}
        self._buffers: tuple[np.ndarray, np.ndarray] | None = None

    def process(self, item: Frame) -> Iterator[Frame]:
        img = item.image
        fid, k = item.header.frame_id, item.header.focus_index
        rs = None
        if self.mags is not None and 0 <= k < self.mags.size:
            rs = self._resampler(k, img.shape)
        dtype = None
        if self.illumination is not None:
            try:
                if rs is not None and self._buffers is not None and \
                        np.issubdtype(img.dtype, np.integer):
                    # flat-fielded into the resampling's work array (which it reads from
                    # there): two full-frame arrays fewer a frame, the same values
                    dtype = img.dtype
                    img = flat_field_into(img, self.illumination, self._buffers[1],
                                          max_value=self.max_value)
                else:
                    img = flat_field(img, self.illumination, max_value=self.max_value)
            except ValueError as err:
                raise FrameError(f"frame_id {fid}: {err}") from None
        if self.mags is not None:
            if not 0 <= k < self.mags.size:
                raise FrameError(f"frame_id {fid}: focus_index {k} outside "
                                 f"the calibrated levels 0..{self.mags.size - 1}")
            try:
                img = unbreathe_frame(img, float(self.mags[k]), centre_px=self.centre,
                                      resampler=rs, buffers=self._buffers if rs else None,
                                      dtype=dtype)
            except ValueError as err:
                raise FrameError(f"frame_id {fid}: {err}") from None
        yield Frame(item.header, img)

    def _resampler(self, k: int, shape: tuple[int, ...]) -> ScaleResampler | None:
        """Level ``k``'s resampling of frames of ``shape`` (None at magnification 1), and
        the work arrays for that shape."""
        m = float(self.mags[k]) if self.mags is not None else 1.0
        if m == 1.0 or len(shape) != 2:
            return None
        key = (k, (int(shape[0]), int(shape[1])))
        rs = self._resamplers.get(key)
        if rs is None:
            rs = self._resamplers[key] = unbreathe_resampler(key[1], m, centre_px=self.centre)
        if self._buffers is None or self._buffers[0].shape != key[1]:
            self._buffers = rs.buffers()
        return rs


class CurvatureStage(Stage):
    """Subtracts the field curvature seen by each world pixel from the depth blocks (their
    texture, confidence and height uncertainty pass unchanged: the correction is a known
    offset per pixel)."""

    name = "field_curvature"
    unit = "blocks"

    def __init__(self, curvature: ScanCurvature) -> None:
        self.curvature = curvature

    def process(self, item: DepthBlock) -> Iterator[DepthBlock]:
        h = item.header
        corr = self.curvature.correction(item.height_um, x0_px=h.x0_px, y0_px=h.y0_px,
                                         pass_index=h.pass_index)
        # every other field as it came: the uncertainty was dropped (unknown in a calibrated
        # scan's whole mosaic) until 2026-12-05
        yield dataclasses.replace(item, height_um=(item.height_um - corr).astype(np.float32))


def optics_correction_stages(cfg: ScanConfig, focus_heights_um: Sequence[float], *,
                             calibration: Calibration | None = None
                             ) -> tuple[list[Stage], list[Stage]]:
    """The correction stages a configuration asks for: (before speed_shift, before mosaic).

    ``calibration`` defaults to the file ``processing.calibration`` names; a calibration
    without ``lateral``, ``vignetting`` or ``field_curvature`` gives no stage for them.
    """
    if calibration is None:
        if not cfg.processing.calibration:
            return [], []
        calibration = load_calibration(cfg.processing.calibration)
    pre: list[Stage] = []
    post: list[Stage] = []
    lat, vig = calibration.lateral, calibration.vignetting
    if lat is not None or vig is not None:
        o = cfg.optics
        centre = lat.optical_centre_px if lat is not None else \
            ((o.width_px - 1) / 2.0, (o.height_px - 1) / 2.0)
        if lat is not None:  # the reference level's scale must be the one frames are placed by
            check_configured_scale(lat, o.pixel_um, frame_px=(o.width_px, o.height_px))
        pre.append(FrameOpticsStage(
            None if lat is None else level_magnification(lat, np.arange(o.n_levels)),
            centre_px=centre, illumination=None if vig is None else illumination_map(vig),
            max_value=o.max_value))
    if calibration.field_curvature is not None:
        post.append(CurvatureStage(ScanCurvature.from_config(
            cfg, calibration.field_curvature, np.asarray(focus_heights_um))))
    return pre, post


def corrections_applied(cfg: ScanConfig) -> list[str]:
    """What a scan with this configuration corrects (the mosaic's attributes): a subset of
    ``z_response``, ``magnification_per_level``, ``field_curvature``; [] without calibration."""
    if not cfg.processing.calibration:
        return []
    return applied(load_calibration(cfg.processing.calibration))
