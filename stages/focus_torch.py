"""The torch path of the focus measure and of the focus volume's accumulation.

The same code on CPU and CUDA, results on the input's device and dtype (as kornia's
operators): the toolbox's GLVM and TENV on ``(..., H, W)`` tensors (:func:`glvm`,
:func:`tenv`), the thesis-style dense-convolution GLVM (:func:`glvm_conv2d_baseline`, the
benchmark baseline), any toolbox operator on a device (:func:`measure_on_device`), raw
frames to focus measure on a device (:class:`DeviceFocus`), and the device-side
accumulation of focus frames into per-pixel sums (:func:`accumulate_levels_torch`).

Kept apart from :mod:`sffscan.stages.focus_measure` and :mod:`sffscan.stages.focus_volume`,
whose CPU scan path is OpenCV and numpy, so that the scan's worker processes do not import
torch (about 1 s and 300 MB of memory each, measured on the 2-core dev VM); those modules
load this one at the first use of a torch path. The operators' definitions are
:mod:`sffscan.stages.operators.toolbox` (registered in
:data:`sffscan.stages.operators.FOCUS_OPERATORS`); this module is their front end.
"""

from __future__ import annotations

from collections.abc import Callable
from functools import partial
from typing import Any

import numpy as np

try:
    import torch
    import torch.nn.functional as F
except ModuleNotFoundError as err:  # torch is the optional extra [torch]
    if err.name != "torch":
        raise
    raise ModuleNotFoundError(
        "this needs torch, which is not installed: the torch backend and devices "
        "(processing.backend = 'torch', CUDA) and the focus operators other than GLVM and "
        "TENV run in torch; install it with: pip install 'sffscan[torch]'",
        name="torch") from err
from sffscan.stages.depth import harmonic_table
from sffscan.stages.operators import FOCUS_OPERATORS, check_operator, check_window, toolbox

__all__ = [
    "DeviceFocus",
    "accumulate_levels_torch",
    "glvm",
    "glvm_conv2d_baseline",
    "measure_on_device",
    "new_accumulator_torch",
    "tenv",
    "torch_operator",
]


def _check_tensor(image: torch.Tensor) -> torch.Tensor:
    """Validate a ``(..., H, W)`` floating tensor; return it as ``(B, H, W)``."""
    if not isinstance(image, torch.Tensor):
        raise TypeError(f"image must be a torch.Tensor, got {type(image).__name__}")
    if not image.is_floating_point():
        raise ValueError(f"image must be a floating tensor, got dtype {image.dtype}")
    if image.ndim < 2:
        raise ValueError(f"image must have shape (..., H, W), got {tuple(image.shape)}")
    return image.reshape(-1, image.shape[-2], image.shape[-1])


def _apply(definition: Callable[[torch.Tensor, int], torch.Tensor], image: torch.Tensor,
           window: int) -> torch.Tensor:
    """An operator's definition ``f(x, k)`` on a checked ``(..., H, W)`` tensor."""
    window = check_window(window)
    return definition(_check_tensor(image), window).reshape(image.shape)


# ----------------------------------------------------------------------------- front ends


def torch_operator(operator: str) -> Callable[..., torch.Tensor]:
    """The torch front end of an operator: ``f(image, *, window=9)`` on ``(..., H, W)``
    floating tensors, the result on the input's device and dtype (as kornia's operators).

    Parameters
    ----------
    operator : str
        One of :data:`sffscan.stages.operators.FOCUS_OPERATORS`, any case.
    """
    definition = FOCUS_OPERATORS[check_operator(operator)].torch_function()

    def front_end(image: torch.Tensor, *, window: int = 9) -> torch.Tensor:
        return _apply(definition, image, window)

    return front_end


def glvm(image: torch.Tensor, *, window: int = 9) -> torch.Tensor:
    """Modified grey-level variance (GLVM), local k x k version: the front end of
    :func:`sffscan.stages.operators.toolbox.glvm`.

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
    return _apply(toolbox.glvm, image, window)


def tenv(image: torch.Tensor, *, window: int = 9) -> torch.Tensor:
    """Tenengrad variance (TENV), the toolbox's local k x k version: the front end of
    :func:`sffscan.stages.operators.toolbox.tenv`.

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
    return _apply(toolbox.tenv, image, window)


def _dense_mean(x: torch.Tensor, window: int) -> torch.Tensor:
    """The k x k mean as the thesis computed it: replicate padding, then a dense
    ``F.conv2d`` with a ``ones(k, k) / k**2`` kernel (k^2 multiply-adds per pixel)."""
    r = window // 2
    kernel = torch.full((1, 1, window, window), 1.0 / window**2, dtype=x.dtype,
                        device=x.device)
    return F.conv2d(F.pad(x.unsqueeze(1), (r, r, r, r), mode="replicate"), kernel)[:, 0]


def glvm_conv2d_baseline(image: torch.Tensor, *, window: int = 9) -> torch.Tensor:
    """GLVM the way the thesis ran it: the definition of :func:`glvm` with each mean a dense
    ``F.conv2d`` with a ``ones(k, k) / k**2`` kernel. Benchmark baseline only.

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
    return _apply(partial(toolbox.glvm, mean=_dense_mean), image, window)


def measure_on_device(image01: np.ndarray, *, operator: str, window: int,
                      device: str | torch.device = "cpu") -> np.ndarray:
    """A (checked) operator of float32 image(s) ``(H, W)`` or ``(B, H, W)`` on a torch
    device, the result copied back to host memory (float32, same shape)."""
    img = np.ascontiguousarray(image01, dtype=np.float32)
    if not img.flags.writeable:  # torch.from_numpy warns on read-only arrays
        img = img.copy()
    with torch.inference_mode():
        result = torch_operator(operator)(torch.from_numpy(img).to(device), window=window)
        return result.cpu().numpy()


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
        One of :data:`sffscan.stages.operators.FOCUS_OPERATORS`, any case.
    window : int
        Odd window size k >= 3, px.
    max_value : float
        Full scale of the raw values (255, 1023, ...).
    """

    def __init__(self, *, device: str | torch.device, operator: str = "glvm", window: int = 9,
                 max_value: float = 255.0) -> None:
        self.device = torch.device(device)
        self.op = torch_operator(check_operator(operator))
        self.window = check_window(window)
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


# ----------------------------------------------------------------------------- accumulation


def new_accumulator_torch(*, n_levels: int, shape: tuple[int, int],
                          device: str | torch.device = "cpu") -> dict[str, torch.Tensor]:
    """Empty per-pixel state of :func:`accumulate_levels_torch` on a torch device.

    Returns
    -------
    dict of torch.Tensor
        ``sums`` (4, H, W) float32: H_0, sum k y, Re H_1, Im H_1 (the rows of
        :func:`sffscan.stages.depth.harmonic_table`); ``best`` (H, W) float32 running maximum (-1);
        ``argmax`` (H, W) int64 its level; ``table`` (4, N) float32.
    """
    h, w = shape
    dev = torch.device(device)
    return {
        "sums": torch.zeros((4, h, w), dtype=torch.float32, device=dev),
        "best": torch.full((h, w), -1.0, dtype=torch.float32, device=dev),
        "argmax": torch.zeros((h, w), dtype=torch.int64, device=dev),
        "table": torch.as_tensor(harmonic_table(n_levels), dtype=torch.float32, device=dev),
    }


def accumulate_levels_torch(acc: dict[str, torch.Tensor], focus: torch.Tensor,
                            levels: torch.Tensor) -> None:
    """Add a batch of focus frames, each at its level, to the per-pixel sums and argmax.

    The device-side counterpart of the accumulation of
    :class:`sffscan.stages.focus_volume.FocusVolume`, for frames already on one pixel grid
    (the caller cuts each frame's columns to its place): one matrix
    product adds the batch to the four sums, one max over the batch updates the running
    maximum, and ties keep the lowest level, as :func:`sffscan.stages.depth.depth_from_focus`'s
    argmax does. :func:`sffscan.stages.depth.depth_from_harmonics` turns the state into depth.

    Parameters
    ----------
    acc : dict of torch.Tensor
        State from :func:`new_accumulator_torch`, updated in place.
    focus : (B, H, W) torch.Tensor, float32
        Focus measure of B frames, on the state's device; each (pixel, level) pair must be
        added once.
    levels : (B,) torch.Tensor of int
        Focus level of each frame, 0..N-1.
    """
    b = focus.shape[0]
    levels = levels.to(device=focus.device, dtype=torch.int64)
    sums = acc["sums"]
    sums.view(4, -1).addmm_(acc["table"][:, levels], focus.reshape(b, -1))
    bmax = focus.amax(dim=0)
    n = acc["table"].shape[1]
    lev = torch.where(focus == bmax, levels.view(b, 1, 1), n).amin(dim=0)
    best, amax = acc["best"], acc["argmax"]
    sharper = (bmax > best) | ((bmax == best) & (lev < amax))
    torch.where(sharper, bmax, best, out=best)
    torch.where(sharper, lev, amax, out=amax)
