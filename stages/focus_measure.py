"""Focus measure: the stage, the dispatch, and fast paths of GLVM and TENV (SFF_NOTES.md 2).

Every operator of Pertuz's toolbox (:data:`FOCUS_OPERATORS`, case-insensitive) is
implemented in torch in :mod:`sffscan.stages.operators.toolbox`; :func:`focus_measure`
dispatches to it. GLVM and TENV, the two the scan uses most, also have an OpenCV CPU fast
path here. Two implementations of the same definitions, which agree numerically:

* a torch path (:func:`glvm`, :func:`tenv`) on ``(..., H, W)`` floating tensors, the same code
  on CPU and CUDA; results are created on the input's device and dtype;
* an OpenCV CPU fast path (:func:`glvm_cv`, :func:`tenv_cv`) on 2-D float32 arrays.

:func:`focus_measure` dispatches between them for numpy images.

Definitions (``box_k`` = mean over a k x k window with replicated borders, i.e. MATLAB
``imfilter(I, fspecial('average', k), 'replicate')``; images scaled to 0..1):

* GLVM, modified grey-level variance: ``mu = box_k(I)``, ``fm = box_k((I - mu)**2)``.
* TENV, Tenengrad variance: ``Gx``, ``Gy`` = unnormalised 3 x 3 Sobel (MATLAB
  ``fspecial('sobel')`` and its transpose, replicated borders), ``G = Gx**2 + Gy**2``,
  ``fm = stdfilt(G, ones(k))**2``: the sample variance of G over k x k (1 / (k^2 - 1)),
  with mirrored borders, as the toolbox computes it.

All functions are pure: no state, no import-time side effects. :class:`FocusMeasureStage`
is the thin pipeline stage around them.
"""

from __future__ import annotations

from collections.abc import Iterator, Sequence
from typing import Any

import cv2
import numpy as np
import torch
import torch.nn.functional as F
from sffscan.pipeline.messages import FocusFrame, PlacedFrame
from sffscan.pipeline.runtime import Stage
from sffscan.stages.depth import check_odd_size
from sffscan.stages.focus_volume import new_columns
from sffscan.stages.operators import OPERATORS, check_operator, operator_alignment
from sffscan.stages.operators.filters import box as _box
from sffscan.stages.operators.filters import sample_variance, sobel_energy
from sffscan.stages.operators.toolbox import TOOLBOX

__all__ = [
    "FOCUS_OPERATORS",
    "DeviceFocus",
    "FocusMeasureStage",
    "focus_measure",
    "focus_measure_raw",
    "glvm",
    "glvm_conv2d_baseline",
    "glvm_cv",
    "tenv",
    "tenv_cv",
    "to_unit_float",
]

FOCUS_OPERATORS = OPERATORS
"""Names accepted by :func:`focus_measure` as ``operator`` (any case)."""

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


def _check_window(window: int) -> int:
    return check_odd_size(window, name="window", minimum=3)


def _check_tensor(image: torch.Tensor) -> torch.Tensor:
    """Validate a ``(..., H, W)`` floating tensor; return it as ``(B, H, W)``."""
    if not isinstance(image, torch.Tensor):
        raise TypeError(f"image must be a torch.Tensor, got {type(image).__name__}")
    if not image.is_floating_point():
        raise ValueError(f"image must be a floating tensor, got dtype {image.dtype}")
    if image.ndim < 2:
        raise ValueError(f"image must have shape (..., H, W), got {tuple(image.shape)}")
    return image.reshape(-1, image.shape[-2], image.shape[-1])


# ----------------------------------------------------------------------------- torch path


def glvm(image: torch.Tensor, *, window: int = 9) -> torch.Tensor:
    """Modified grey-level variance (GLVM), local k x k version.

    ``mu = box_k(I)``; ``fm = box_k((I - mu)**2)``, ``box_k`` the k x k mean with replicated
    borders (MATLAB ``imfilter(..., fspecial('average', k), 'replicate')``), computed as
    separable window sums of the replicate-padded image.

    Parameters
    ----------
    image : (..., H, W) floating torch.Tensor
        Images scaled to 0..1, any device.
    window : int, keyword-only
        Odd window size k >= 3, pixels. Default 9.

    Returns
    -------
    (..., H, W) torch.Tensor
        Focus measure, same dtype and device as ``image``; units of intensity squared.
    """
    window = _check_window(window)
    x = _check_tensor(image)
    mu = _box(x, window)
    d = x - mu
    return _box(d * d, window).reshape(image.shape)


def tenv(image: torch.Tensor, *, window: int = 9) -> torch.Tensor:
    """Tenengrad variance (TENV), the toolbox's local k x k version.

    ``G = Gx**2 + Gy**2`` with the unnormalised 3 x 3 Sobel pair (MATLAB
    ``fspecial('sobel')`` and its transpose, replicated borders); ``fm = stdfilt(G,
    ones(k))**2``: the *sample* variance of G in the window (``(sum G^2 - (sum G)^2 / n) /
    (n - 1)``, n = k^2), mirrored borders (MATLAB 'symmetric'), as Pertuz's
    ``focusmeasure.m`` computes it. The thesis' standard-deviation form is the operator
    ``"tenv_std"``. Tiny negative values from round-off are clamped to 0.

    Parameters
    ----------
    image : (..., H, W) floating torch.Tensor
        Images scaled to 0..1, any device.
    window : int, keyword-only
        Odd window size k >= 3, pixels. Default 9.

    Returns
    -------
    (..., H, W) torch.Tensor
        Focus measure, same dtype and device as ``image``; units of intensity^4 (the Sobel
        gain of 4 per axis is not divided out).
    """
    window = _check_window(window)
    x = _check_tensor(image)
    return sample_variance(sobel_energy(x), window).reshape(image.shape)


def glvm_conv2d_baseline(image: torch.Tensor, *, window: int = 9) -> torch.Tensor:
    """GLVM the way the thesis ran it: dense ``F.conv2d`` with a ``ones(k, k) / k**2`` kernel.

    Same definition and borders as :func:`glvm` (replicate padding, then a valid
    convolution), but k^2 multiply-adds per pixel per box filter. Benchmark baseline only.

    Parameters
    ----------
    image : (..., H, W) floating torch.Tensor
        Images scaled to 0..1, any device.
    window : int, keyword-only
        Odd window size k >= 3, pixels. Default 9.

    Returns
    -------
    (..., H, W) torch.Tensor
        Same as :func:`glvm`, same dtype and device as ``image``.
    """
    window = _check_window(window)
    x = _check_tensor(image).unsqueeze(1)  # (B, 1, H, W)
    r = window // 2
    kernel = torch.full(
        (1, 1, window, window), 1.0 / window**2, dtype=image.dtype, device=image.device
    )

    def box(t: torch.Tensor) -> torch.Tensor:
        return F.conv2d(F.pad(t, (r, r, r, r), mode="replicate"), kernel)

    d = x - box(x)
    return box(d * d).reshape(image.shape)


# ----------------------------------------------------------------------------- OpenCV path


def _check_cv_image(image: np.ndarray) -> np.ndarray:
    image = np.asarray(image)
    if image.ndim != 2:
        raise ValueError(f"image must be 2-D (H, W), got shape {image.shape}")
    if not np.issubdtype(image.dtype, np.floating):
        raise ValueError(
            f"image must be floating (scaled to 0..1, see to_unit_float), got dtype {image.dtype}"
        )
    return np.ascontiguousarray(image, dtype=np.float32)


def glvm_cv(image: np.ndarray, *, window: int = 9) -> np.ndarray:
    """GLVM with OpenCV box filters (CPU fast path); same definition as :func:`glvm`.

    Uses ``cv2.boxFilter`` and ``cv2.sqrBoxFilter`` (normalised, ``BORDER_REPLICATE``).

    Parameters
    ----------
    image : (H, W) ndarray of float
        Image scaled to 0..1 (converted to float32).
    window : int, keyword-only
        Odd window size k >= 3, pixels. Default 9.

    Returns
    -------
    (H, W) ndarray of float32
        Focus measure.
    """
    window = _check_window(window)
    img = _check_cv_image(image)
    ksize = (window, window)
    mu = cv2.boxFilter(img, cv2.CV_32F, ksize, normalize=True, borderType=cv2.BORDER_REPLICATE)
    return cv2.sqrBoxFilter(
        img - mu, cv2.CV_32F, ksize, normalize=True, borderType=cv2.BORDER_REPLICATE
    )


def tenv_cv(image: np.ndarray, *, window: int = 9) -> np.ndarray:
    """TENV with OpenCV (CPU fast path); same definition and normalisation as :func:`tenv`.

    ``cv2.Sobel(ksize=3)`` (unnormalised, ``BORDER_REPLICATE``; its sign is the opposite of
    MATLAB's, which squaring removes), then the sample variance of G from
    ``cv2.sqrBoxFilter`` and ``cv2.boxFilter`` with ``BORDER_REFLECT`` (MATLAB's
    'symmetric'), times n / (n - 1), clamped at 0.

    Parameters
    ----------
    image : (H, W) ndarray of float
        Image scaled to 0..1 (converted to float32).
    window : int, keyword-only
        Odd window size k >= 3, pixels. Default 9.

    Returns
    -------
    (H, W) ndarray of float32
        Focus measure.
    """
    window = _check_window(window)
    img = _check_cv_image(image)
    border = cv2.BORDER_REPLICATE
    gx = cv2.Sobel(img, cv2.CV_32F, 1, 0, ksize=3, borderType=border)
    gy = cv2.Sobel(img, cv2.CV_32F, 0, 1, ksize=3, borderType=border)
    g = gx * gx
    g += gy * gy
    ksize = (window, window)
    mirror = cv2.BORDER_REFLECT
    mean = cv2.boxFilter(g, cv2.CV_32F, ksize, normalize=True, borderType=mirror)
    fm = cv2.sqrBoxFilter(g, cv2.CV_32F, ksize, normalize=True, borderType=mirror)
    np.subtract(fm, mean * mean, out=fm)
    n = window * window
    np.multiply(fm, np.float32(n / (n - 1)), out=fm)
    return np.maximum(fm, 0.0, out=fm)


def glvm_cv_raw(image: np.ndarray, image01: np.ndarray, *, max_value: float,
                window: int = 9) -> np.ndarray:
    """GLVM of a raw integer image (CPU fast path); same definition as :func:`glvm_cv`.

    The local mean is box filtered straight from the integer image (OpenCV reads uint8 /
    uint16 at half the memory traffic of float32), the difference is taken against the
    image scaled to 0..1, and the second box filter is a separable sum of the squares:
    about 1.3x faster than :func:`glvm_cv` on the scaled image, equal to float32 round-off.

    Parameters
    ----------
    image : (H, W) ndarray of uint8 or uint16
        Raw image.
    image01 : (H, W) ndarray of float32
        The same image scaled to 0..1 (``image / max_value``).
    max_value : float, keyword-only
        Full scale of the raw values.
    window : int, keyword-only
        Odd window size k >= 3, pixels. Default 9.

    Returns
    -------
    (H, W) ndarray of float32
        Focus measure of ``image01``.
    """
    ksize = (window, window)
    border = cv2.BORDER_REPLICATE
    mu_raw = cv2.boxFilter(image, cv2.CV_32F, ksize, normalize=True, borderType=border)
    d = cv2.scaleAdd(mu_raw, -1.0 / float(max_value), image01)
    cv2.multiply(d, d, dst=d)
    kernel = np.full(window, 1.0 / window, np.float32)
    return cv2.sepFilter2D(d, cv2.CV_32F, kernel, kernel, borderType=border)


def focus_measure_raw(
    image: np.ndarray, *, max_value: float, operator: str = "glvm", window: int = 9
) -> tuple[np.ndarray, np.ndarray]:
    """Scale a raw camera image to 0..1 and compute its focus measure (OpenCV, CPU).

    What the focus stage does for every frame: :func:`to_unit_float`, then
    :func:`focus_measure` with the OpenCV backend, fused where that saves memory passes
    (GLVM: :func:`glvm_cv_raw`). Equal to the two steps to float32 round-off.

    Parameters
    ----------
    image : (H, W) ndarray of uint8 or uint16 (float is accepted too)
        Raw image; may be a strided view (a column range of a frame).
    max_value : float, keyword-only
        Full-scale value (255, 1023, ...).
    operator : str, keyword-only
        One of :data:`FOCUS_OPERATORS` (any case); GLVM and TENV run in OpenCV, the others
        in torch on the CPU.
    window : int, keyword-only
        Odd window size k >= 3, pixels. Default 9.

    Returns
    -------
    image01, focus : (H, W) ndarray of float32
        The scaled image and its focus measure.
    """
    operator = check_operator(operator)
    window = _check_window(window)
    if operator == "glvm" and image.dtype in (np.uint8, np.uint16):
        # one contiguous copy of the raw columns first: OpenCV's box filter reads a
        # strided view about 1.8x slower, and the scaling reads the copy from cache
        raw = np.ascontiguousarray(image)
        image01 = to_unit_float(raw, max_value=max_value)
        return image01, glvm_cv_raw(raw, image01, max_value=max_value, window=window)
    image01 = to_unit_float(image, max_value=max_value)
    if operator in _CV_OPS:
        return image01, _CV_OPS[operator](image01, window=window)
    return image01, _torch_cpu(image01, operator, window)


# ----------------------------------------------------------------------------- dispatch

_CV_OPS = {"glvm": glvm_cv, "tenv": tenv_cv}


def _torch_op(operator: str) -> Any:
    """The torch function of a (checked) operator: ``f(image, *, window)``."""
    if operator == "glvm":
        return glvm
    if operator == "tenv":
        return tenv
    fn = TOOLBOX[operator]

    def op(image: torch.Tensor, *, window: int = 9) -> torch.Tensor:
        x = _check_tensor(image)
        return fn(x, _check_window(window)).reshape(image.shape)

    return op


def _torch_cpu(image01: np.ndarray, operator: str, window: int) -> np.ndarray:
    """A toolbox operator of one float32 image on the CPU, through torch."""
    img = np.ascontiguousarray(image01, dtype=np.float32)
    if not img.flags.writeable:
        img = img.copy()
    with torch.inference_mode():
        return _torch_op(operator)(torch.from_numpy(img), window=window).numpy()



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
        see :data:`FOCUS_OPERATORS` and :mod:`sffscan.stages.operators.toolbox`.
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
    operator = check_operator(operator)
    if backend not in _BACKENDS:
        raise ValueError(f"backend must be one of {_BACKENDS}, got {backend!r}")
    window = _check_window(window)
    image = np.asarray(image)
    if image.ndim not in (2, 3):
        raise ValueError(f"image must be (H, W) or (B, H, W), got shape {image.shape}")
    if not np.issubdtype(image.dtype, np.floating):
        raise ValueError(
            f"image must be floating (scaled to 0..1, see to_unit_float), got dtype {image.dtype}"
        )
    img = np.ascontiguousarray(image, dtype=np.float32)

    if backend == "opencv" and operator in _CV_OPS:
        op_cv = _CV_OPS[operator]
        if img.ndim == 2:
            return op_cv(img, window=window)
        out = np.empty_like(img)
        for i in range(img.shape[0]):
            out[i] = op_cv(img[i], window=window)
        return out
    if backend == "opencv":
        device = "cpu"
    if not img.flags.writeable:  # torch.from_numpy warns on read-only arrays
        img = img.copy()
    with torch.inference_mode():
        result = _torch_op(operator)(torch.from_numpy(img).to(device), window=window)
        return result.cpu().numpy()


# ----------------------------------------------------------------------------- device path


class DeviceFocus:
    """Raw frames to focus measure on a torch device (CUDA, or CPU for tests).

    The raw uint8 / uint16 pixels go up as they are (half or a quarter of float32's bytes)
    and are converted and scaled on the device. On CUDA the host side copies each frame or
    batch into one of two page-locked (pinned) staging buffers and uploads it with a
    non-blocking copy on a side stream; the compute stream waits for that copy only, so
    the upload of the next batch overlaps the kernels of this one, and a staging buffer is
    reused only once its earlier copy has finished. Batches of frames (``(B, H, W)``) are
    measured with one set of kernels. float32 throughout: the depth accuracy tests have not
    been run in reduced precision, so none is used.

    Parameters
    ----------
    device : str or torch.device
        Torch device.
    operator : str
        One of :data:`FOCUS_OPERATORS`, any case.
    window : int
        Odd window size k >= 3, px.
    max_value : float
        Full scale of the raw values (255, 1023, ...).
    """

    def __init__(self, *, device: str | torch.device, operator: str = "glvm", window: int = 9,
                 max_value: float = 255.0) -> None:
        self.device = torch.device(device)
        self.op = _torch_op(check_operator(operator))
        self.window = _check_window(window)
        self.scale = 1.0 / float(max_value)
        self.cuda = self.device.type == "cuda"
        self._staging: list[torch.Tensor | None] = [None, None]
        self._events: list[Any] = [None, None]
        self._turn = 0
        self._copy_stream = torch.cuda.Stream(self.device) if self.cuda else None

    def _upload(self, raw: np.ndarray) -> torch.Tensor:
        if raw.dtype == np.uint16 and (raw.size == 0 or int(raw.max()) < 1 << 15):
            raw = raw.view(np.int16)  # same bytes; int16 converts on every device
        elif raw.dtype not in (np.uint8, np.int16):
            raise ValueError(f"raw frames must be uint8 or uint16, got dtype {raw.dtype}")
        if not self.cuda:
            host = np.ascontiguousarray(raw)
            if not host.flags.writeable:  # torch.from_numpy warns on read-only arrays
                host = host.copy()
            return torch.from_numpy(host).to(self.device)
        i = self._turn
        self._turn ^= 1
        buf = self._staging[i]
        if self._events[i] is not None:
            self._events[i].synchronize()  # the buffer's previous upload has finished
        if buf is None or buf.shape != raw.shape or buf.numpy().dtype != raw.dtype:
            buf = torch.from_numpy(np.empty(raw.shape, raw.dtype)).pin_memory()
            self._staging[i] = buf
        np.copyto(buf.numpy(), raw)
        assert self._copy_stream is not None
        with torch.cuda.stream(self._copy_stream):
            dev = buf.to(self.device, non_blocking=True)
            event = torch.cuda.Event()
            event.record(self._copy_stream)
        self._events[i] = event
        torch.cuda.current_stream(self.device).wait_event(event)
        dev.record_stream(torch.cuda.current_stream(self.device))
        return dev

    def measure(self, raw: np.ndarray) -> tuple[torch.Tensor, torch.Tensor]:
        """Scaled image and focus measure of raw frame(s), on the device.

        Parameters
        ----------
        raw : (H, W) or (B, H, W) ndarray of uint8 or uint16

        Returns
        -------
        image01, focus : torch.Tensor, float32, same shape, on ``device``
            Asynchronous on CUDA: ``.cpu()`` (or a synchronize) waits for them.
        """
        raw = np.asarray(raw)
        if raw.ndim not in (2, 3):
            raise ValueError(f"raw must be (H, W) or (B, H, W), got shape {raw.shape}")
        with torch.inference_mode():
            image01 = self._upload(raw).to(torch.float32).mul_(self.scale)
            return image01, self.op(image01, window=self.window)


# ----------------------------------------------------------------------------- stage


class FocusMeasureStage(Stage):
    """Scales each placed frame to 0..1 and computes its focus measure.

    Only the columns that can still add to the focus volume are measured (see
    :func:`sffscan.stages.focus_volume.new_columns`), with enough neighbouring columns that the
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
    """

    name = "focus_measure"

    def __init__(self, *, operator: str = "glvm", window: int = 9, backend: str = "opencv",
                 device: str = "cpu", max_value: float = 255.0, margin: int,
                 directions: Sequence[int] = (1,)) -> None:
        self.operator = check_operator(operator)
        self.window = _check_window(window)
        self.backend = backend
        self.device = device
        self.max_value = max_value
        self.margin = margin
        self.directions = list(directions)
        self.alignment = operator_alignment(self.operator)
        self._pass: int | None = None
        self._prev_x: dict[int, int] = {}
        self._device_focus: DeviceFocus | None = None
        self.columns_measured = 0
        self.columns_total = 0

    def process(self, item: PlacedFrame) -> Iterator[FocusFrame]:
        hdr = item.header
        if hdr.pass_index != self._pass:
            self._pass, self._prev_x = hdr.pass_index, {}
        h, w = item.image.shape
        x = item.offset_px[0]
        c0, c1 = new_columns(x, self._prev_x.get(hdr.focus_index), width=w,
                             margin=self.margin,
                             direction=self.directions[hdr.pass_index % len(self.directions)])
        self._prev_x[hdr.focus_index] = x
        a0, a1 = max(c0 - self.margin, 0), min(c1 + self.margin, w)
        a0 -= a0 % self.alignment  # the wavelet operators decimate: start on their grid
        if self.backend == "opencv":
            image01, fm = focus_measure_raw(item.image[:, a0:a1], max_value=self.max_value,
                                            operator=self.operator, window=self.window)
        else:
            if self._device_focus is None:
                self._device_focus = DeviceFocus(device=self.device, operator=self.operator,
                                                 window=self.window, max_value=self.max_value)
            t01, tfm = self._device_focus.measure(item.image[:, a0:a1])
            image01, fm = t01.cpu().numpy(), tfm.cpu().numpy()
        self.columns_measured += c1 - c0
        self.columns_total += w
        yield FocusFrame(item, image01[:, c0 - a0:c1 - a0], fm[:, c0 - a0:c1 - a0], c0)

    def extra_stats(self) -> dict[str, float]:
        share = self.columns_measured / self.columns_total if self.columns_total else 0.0
        return {"measured_column_share": round(share, 3)}
