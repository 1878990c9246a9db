"""Focus measure: the numpy front end of the focus operators, and the stage.

Every operator of Pertuz's toolbox is registered in
:data:`sffscan.stages.operators.FOCUS_OPERATORS` (case-insensitive names) with one
definition in torch (:mod:`sffscan.stages.operators.toolbox`); GLVM and TENV, the two the
scan uses most, also have an OpenCV CPU front end with the same definition
(:mod:`sffscan.stages.operators.opencv`). :func:`focus_measure` runs an operator on numpy
images: OpenCV where the operator has it, else the torch definition on the CPU or a torch
device (:mod:`sffscan.stages.focus_torch`, the torch front end, loaded at its first use:
the scan's CPU path does not import torch). :func:`focus_measure_raw` is what the focus
stage does for every frame; :class:`FocusMeasureStage` is the thin pipeline stage around
it. All functions are pure: no state, no import-time side effects.
"""

from __future__ import annotations

from collections.abc import Iterator, Sequence
from typing import TYPE_CHECKING

import numpy as np
from sffscan.stages.bands import BandWorkers, row_bands
from sffscan.stages.messages import FocusFrame, PlacedFrame, RawColumns
from sffscan.stages.operators import (
    FOCUS_OPERATORS,
    check_operator,
    check_window,
    operator_alignment,
)
from sffscan.stages.operators.opencv import glvm_cv
from sffscan.stages.protocol import Stage
from sffscan.stages.volume_columns import new_columns

if TYPE_CHECKING:  # torch loads with the first use of the torch path
    from sffscan.stages.focus_torch import DeviceFocus

__all__ = [
    "FocusMeasureStage",
    "focus_measure",
    "focus_measure_raw",
    "to_unit_float",
]

_BACKENDS = ("opencv", "torch")


# ----------------------------------------------------------------------------- helpers


def to_unit_float(image: np.ndarray, *, max_value: float) -> np.ndarray:
    """Scale a camera image to float32 in 0..1.

    Parameters
    ----------
    image : (H, W) ndarray of uint8, uint16 or float
        Raw grey image.
    max_value : float
        Full-scale value (255 for 8-bit, 1023 for 10-bit data in uint16, 1.0 for images
        already in 0..1). Must be finite and > 0.

    Returns
    -------
    (H, W) ndarray of float32
        ``image / max_value``.

    Raises
    ------
    ValueError
        If ``image`` is not 2-D, not numeric, or contains NaN / inf, or ``max_value`` is not a
        positive finite number.
    """
    image = np.asarray(image)
    if image.ndim != 2:
        raise ValueError(f"image must be 2-D (H, W), got shape {image.shape}")
    if not (np.issubdtype(image.dtype, np.integer) or np.issubdtype(image.dtype, np.floating)):
        raise ValueError(f"image must be an integer or floating array, got dtype {image.dtype}")
    if not np.isfinite(max_value) or max_value <= 0:
        raise ValueError(f"max_value must be a positive finite number, got {max_value!r}")
    if np.issubdtype(image.dtype, np.floating):
        bad = ~np.isfinite(image)
        if bad.any():
            row, col = np.argwhere(bad)[0]
            kind = "NaN" if np.isnan(image[row, col]) else "inf"
            raise ValueError(f"image contains {kind} (first at row {row}, column {col})")
    return np.multiply(image, np.float32(1.0 / max_value), dtype=np.float32)


def focus_measure_raw(
    image: np.ndarray, *, max_value: float, operator: str = "glvm", window: int = 9,
    rows: tuple[int, int] | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """Scale a raw camera image to 0..1 and compute its focus measure (OpenCV, CPU).

    What the focus stage does for every frame: :func:`to_unit_float`, then
    :func:`focus_measure` with the OpenCV backend; GLVM takes its local mean from the raw
    image (see :func:`sffscan.stages.operators.opencv.glvm_cv`), equal to the two steps to
    float32 round-off.

    Parameters
    ----------
    image : (H, W) ndarray of uint8 or uint16 (float is accepted too)
        Raw image; may be a strided view (a column range of a frame).
    max_value : float, keyword-only
        Full-scale value (255, 1023, ...).
    operator : str, keyword-only
        One of :data:`sffscan.stages.operators.FOCUS_OPERATORS` (any case); GLVM and TENV
        run in OpenCV, the others in torch on the CPU.
    window : int, keyword-only
        Odd window size k >= 3, pixels. Default 9.
    rows : (int, int), optional, keyword-only
        Only the band of rows ``r0 <= y < r1``: measured on the band widened by the
        operator's reach (:func:`sffscan.stages.operators.operator_reach`, its start on
        the operator's grid), so that it equals the whole image's rows; bit-identical for
        GLVM and TENV (their OpenCV arithmetic does not depend on where the band starts),
        to float32 round-off for the others. What a worker that owns a band of rows, or a
        strip-blocked loop that keeps the band in cache, measures.

    Returns
    -------
    image01, focus : (H, W) ndarray of float32 (``(r1 - r0, W)`` with ``rows``)
        The scaled image and its focus measure.
    """
    op = FOCUS_OPERATORS[check_operator(operator)]
    window = check_window(window)
    if rows is not None:
        r0, r1 = rows
        height = image.shape[0]
        if not 0 <= r0 < r1 <= height:
            raise ValueError(f"rows must satisfy 0 <= r0 < r1 <= {height} (the image's "
                             f"height), got {rows}")
        reach = op.reach(window)
        a0, a1 = max(r0 - reach, 0), min(r1 + reach, height)
        a0 -= a0 % op.alignment
        image01, fm = focus_measure_raw(image[a0:a1], max_value=max_value,
                                        operator=op.name, window=window)
        return image01[r0 - a0:r1 - a0], fm[r0 - a0:r1 - a0]
    if op.name == "glvm" and image.dtype in (np.uint8, np.uint16):
        # one contiguous copy of the raw columns first: OpenCV's box filter reads a
        # strided view about 1.8x slower, and the scaling reads the copy from cache
        raw = np.ascontiguousarray(image)
        image01 = to_unit_float(raw, max_value=max_value)
        return image01, glvm_cv(image01, window=window, raw=raw, max_value=max_value)
    image01 = to_unit_float(image, max_value=max_value)
    cpu = op.opencv_function()
    if cpu is not None:
        return image01, cpu(image01, window=window)
    from sffscan.stages.focus_torch import measure_on_device  # torch loads with first use

    return image01, measure_on_device(image01, operator=op.name, window=window, device="cpu")


# ----------------------------------------------------------------------------- dispatch


def focus_measure(
    image: np.ndarray,
    *,
    operator: str = "glvm",
    window: int = 9,
    backend: str = "opencv",
    device: str = "cpu",
) -> np.ndarray:
    """Focus measure of one image or a batch, with the chosen operator and backend.

    Parameters
    ----------
    image : (H, W) or (B, H, W) ndarray of float
        Image(s) already scaled to 0..1 (see :func:`to_unit_float`); computed in float32.
    operator : str, keyword-only
        Focus measure operator, the toolbox's acronym in any case (``"LAPM"``, ``"glvm"``),
        see :data:`sffscan.stages.operators.FOCUS_OPERATORS`.
    window : int, keyword-only
        Odd window size k >= 3, pixels. Default 9.
    backend : {"opencv", "torch"}, keyword-only
        ``"opencv"``: CPU fast path, image by image (GLVM and TENV; the other operators run
        in torch on the CPU). ``"torch"``: the whole batch at once on ``device``, result
        copied back to host memory.
    device : str, keyword-only
        Torch device for ``backend="torch"`` (``"cpu"``, ``"cuda"``, ``"cuda:1"``...);
        ignored by the OpenCV backend.

    Returns
    -------
    ndarray of float32
        Focus measure, same shape as ``image``.

    Raises
    ------
    ValueError
        Unknown ``operator`` or ``backend``, bad ``window``, or an image that is not a 2-D or
        3-D floating array.
    """
    op = FOCUS_OPERATORS[check_operator(operator)]
    if backend not in _BACKENDS:
        raise ValueError(f"backend must be one of {_BACKENDS}, got {backend!r}")
    window = check_window(window)
    image = np.asarray(image)
    if image.ndim not in (2, 3):
        raise ValueError(f"image must be (H, W) or (B, H, W), got shape {image.shape}")
    if not np.issubdtype(image.dtype, np.floating):
        raise ValueError(
            f"image must be floating (scaled to 0..1, see to_unit_float), got dtype {image.dtype}"
        )
    img = np.ascontiguousarray(image, dtype=np.float32)

    cpu = op.opencv_function() if backend == "opencv" else None
    if cpu is not None:
        if img.ndim == 2:
            return cpu(img, window=window)  # type: ignore[no-any-return]
        out = np.empty_like(img)
        for i in range(img.shape[0]):
            out[i] = cpu(img[i], window=window)
        return out
    from sffscan.stages.focus_torch import measure_on_device  # torch loads with first use

    return measure_on_device(img, operator=op.name, window=window,
                             device="cpu" if backend == "opencv" else device)


# ----------------------------------------------------------------------------- stage


class FocusMeasureStage(Stage):
    """Scales each placed frame to 0..1 and computes its focus measure.

    Only the columns that can still add to the focus volume are measured (see
    :func:`sffscan.stages.volume_columns.new_columns`), with enough neighbouring columns that the
    result equals the whole frame's focus measure there (the range starting on a multiple
    of :func:`sffscan.stages.operators.operator_alignment`: 2 or 8 px for the wavelet
    operators). This relies on every frame it
    passes on reaching the focus volume: the queues after this stage must block, never drop
    (a frame lost before this stage is fine: it is never counted as seen).

    Parameters
    ----------
    operator, window, backend, device
        See :func:`focus_measure`.
    max_value : float
        Full scale of the raw frames (255 for uint8, 1023 for 10-bit in uint16).
    margin : int
        The focus measure's reach into the frame border, px
        (:attr:`sffscan.pipeline.config.ProcessingConfig.focus_reach_px`): the focus volume leaves
        out this border, and each measured column range is widened by it, so the result
        there equals the whole frame's focus measure.
    directions : sequence of {+1, -1}
        Direction of motion of each pass (cycled).
    workers : int
        Band workers (:mod:`sffscan.stages.bands`): with the OpenCV backend, each frame's
        rows are measured in that many bands at once (:func:`focus_measure_raw`'s
        ``rows``), then joined: bit-identical for GLVM and TENV. 1: one call per frame.
    bands_measure : bool
        The depth stage's band workers (:class:`~sffscan.stages.bands.BandTasks`: processes
        or threads) measure the focus (the OpenCV backend): each the rows it accumulates,
        never gathered (:meth:`sffscan.stages.shared_volume.SharedFocusVolume.add_raw`).
        The stage then passes on, instead of each focus frame, the frame and its columns
        (:class:`~sffscan.stages.messages.RawColumns`): a sink that taps it gets no focus
        frames (the live view measures the frames it shows itself).
    torch_threads : int or None
        With the torch backend: torch's intra-op threads in the process that runs the stage,
        set at its first frame and restored when it closes (None: torch's own setting).
        Where the stages already run in parallel the pool's idle threads only spin after
        each call (see :mod:`sffscan.pipeline.measuring`).
    """

    name = "focus_measure"

    def __init__(self, *, operator: str = "glvm", window: int = 9, backend: str = "opencv",
                 device: str = "cpu", max_value: float = 255.0, margin: int,
                 directions: Sequence[int] = (1,), workers: int = 1,
                 bands_measure: bool = False, torch_threads: int | None = None) -> None:
        self.operator = check_operator(operator)
        self.window = check_window(window)
        self.backend = backend
        self.device = device
        self.max_value = max_value
        self.margin = margin
        self.directions = list(directions)
        self.alignment = operator_alignment(self.operator)
        self._pass: int | None = None
        self._prev_x: dict[int, int] = {}
        self._device_focus: DeviceFocus | None = None
        self.workers = workers
        self._bands: BandWorkers | None = None  # made at the first frame
        if bands_measure and backend != "opencv":
            raise ValueError("band workers measure the focus with the OpenCV backend "
                             f"only, not {backend!r}")
        self.bands_measure = bands_measure
        if torch_threads is not None and torch_threads < 1:
            raise ValueError(f"torch_threads must be >= 1 or None, got {torch_threads}")
        self.torch_threads = torch_threads
        self._torch_threads_before: int | None = None  # torch's, to restore at close
        self.columns_measured = 0
        self.columns_total = 0

    def columns(self, item: PlacedFrame) -> tuple[int, int, int, int]:
        """The frame columns [c0, c1) measured and [a0, a1) read (see the class); counted
        in the stage's statistics."""
        hdr = item.header
        if hdr.pass_index != self._pass:
            self._pass, self._prev_x = hdr.pass_index, {}
        w = item.image.shape[1]
        x = item.offset_px[0]
        c0, c1 = new_columns(x, self._prev_x.get(hdr.focus_index), width=w,
                             margin=self.margin,
                             direction=self.directions[hdr.pass_index % len(self.directions)])
        self._prev_x[hdr.focus_index] = x
        a0, a1 = max(c0 - self.margin, 0), min(c1 + self.margin, w)
        a0 -= a0 % self.alignment  # the wavelet operators decimate: start on their grid
        self.columns_measured += c1 - c0
        self.columns_total += w
        return c0, c1, a0, a1

    def process(self, item: PlacedFrame) -> Iterator[FocusFrame | RawColumns]:
        c0, c1, a0, a1 = self.columns(item)
        if self.bands_measure:  # measured by the depth stage's band workers
            yield RawColumns(item, (c0, c1, a0, a1), {
                "operator": self.operator, "window": self.window,
                "max_value": self.max_value})
            return
        if self.backend == "opencv" and self.workers > 1:
            image01, fm = self._measure_bands(item.image[:, a0:a1])
        elif self.backend == "opencv":
            image01, fm = focus_measure_raw(item.image[:, a0:a1], max_value=self.max_value,
                                            operator=self.operator, window=self.window)
        else:
            if self._device_focus is None:
                from sffscan.stages.focus_torch import DeviceFocus  # torch: first use

                self._limit_torch_threads()
                self._device_focus = DeviceFocus(device=self.device, operator=self.operator,
                                                 window=self.window, max_value=self.max_value)
            t01, tfm = self._device_focus.measure(item.image[:, a0:a1])
            image01, fm = t01.cpu().numpy(), tfm.cpu().numpy()
        yield FocusFrame(item, image01[:, c0 - a0:c1 - a0], fm[:, c0 - a0:c1 - a0], c0)

    def _measure_bands(self, image: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """:func:`focus_measure_raw` of ``image`` by bands of rows in the band workers."""
        if self._bands is None:
            self._bands = BandWorkers(self.workers, name="focus-band")
        parts = self._bands.run(
            lambda r0, r1: focus_measure_raw(image, max_value=self.max_value,
                                             operator=self.operator, window=self.window,
                                             rows=(r0, r1)),
            row_bands(0, image.shape[0], self.workers))
        return (np.concatenate([p[0] for p in parts]),
                np.concatenate([p[1] for p in parts]))

    def _limit_torch_threads(self) -> None:
        if self.torch_threads is None:
            return
        import torch

        self._torch_threads_before = torch.get_num_threads()
        torch.set_num_threads(self.torch_threads)

    def close(self, *, failed: bool) -> None:
        if self._bands is not None:
            self._bands.close()
            self._bands = None
        if self._torch_threads_before is not None:
            import torch

            torch.set_num_threads(self._torch_threads_before)
            self._torch_threads_before = None


    def extra_stats(self) -> dict[str, float]:
        share = self.columns_measured / self.columns_total if self.columns_total else 0.0
        return {"measured_column_share": round(share, 3)}
