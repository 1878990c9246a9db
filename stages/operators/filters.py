"""MATLAB's neighbourhood filters in torch, with MATLAB's borders (for :mod:`.toolbox`).

Every function takes ``(B, H, W)`` floating tensors and returns a tensor of the same shape
(except where said), on the input's device and dtype; nothing here keeps state.

Borders, as MATLAB pads them:

* ``imfilter(..., 'replicate')``: the edge pixel repeated (:func:`correlate`, :func:`box`);
* ``stdfilt`` and ``entropyfilt``: mirrored *including* the edge pixel (MATLAB and numpy
  ``'symmetric'``, OpenCV ``BORDER_REFLECT``; torch has no such mode, :func:`pad` builds it
  with an index gather);
* ``nlfilter``: zeros.

A kernel of size s has its origin at ``(s + 1) // 2 - 1`` (0-based), MATLAB's
``floor((s + 1) / 2)``: the centre for odd sizes, the upper-left of the centre for even ones.
"""

from __future__ import annotations

import numpy as np
import torch
import torch.nn.functional as F

__all__ = ["box", "correlate", "local_sums", "pad", "sample_variance", "sobel_energy",
           "window_sum", "windows"]


def _index(n: int, before: int, after: int, mode: str, device: torch.device) -> torch.Tensor:
    """Source index of each padded position along one axis (``symmetric`` / ``replicate``)."""
    i = torch.arange(-before, n + after, device=device)
    if mode == "replicate":
        return i.clamp(0, n - 1)
    period = 2 * n  # symmetric: ... 1 0 | 0 1 ... n-1 | n-1 n-2 ...
    i = torch.remainder(i, period)
    return torch.where(i >= n, period - 1 - i, i)


def pad(x: torch.Tensor, top: int, bottom: int, left: int, right: int, *,
        mode: str) -> torch.Tensor:
    """Pad the last two axes of ``x``: ``mode`` is ``"replicate"``, ``"symmetric"`` or
    ``"zeros"``."""
    if mode == "zeros":
        return F.pad(x, (left, right, top, bottom))
    if mode == "replicate" and max(top, bottom) < x.shape[-2] and max(left, right) < x.shape[-1]:
        return F.pad(x, (left, right, top, bottom), mode="replicate")
    if mode not in ("replicate", "symmetric"):
        raise ValueError(f"unknown padding mode {mode!r}")
    rows = _index(x.shape[-2], top, bottom, mode, x.device)
    cols = _index(x.shape[-1], left, right, mode, x.device)
    return x.index_select(-2, rows).index_select(-1, cols)


def window_sum(x: torch.Tensor, window: int, dim: int) -> torch.Tensor:
    """Sums of ``window`` consecutive elements along ``dim`` (output ``window - 1`` shorter).

    Doubling scheme: partial sums of width 1, 2, 4, ... are built by adding shifted views,
    and the widths in the binary expansion of ``window`` are combined, so a window of k
    costs about 2 log2(k) elementwise adds instead of k (4 instead of 8 for k = 9). Pairwise
    summation, so float32 round-off is no worse than a direct sum.
    """
    n_out = x.size(dim) - window + 1
    result: torch.Tensor | None = None
    power, width, offset = x, 1, 0
    while True:
        if window & 1:
            term = power.narrow(dim, offset, n_out)
            result = term if result is None else result + term
            offset += width
        window >>= 1
        if not window:
            break
        m = power.size(dim) - width
        power = power.narrow(dim, 0, m) + power.narrow(dim, width, m)
        width *= 2
    assert result is not None
    return result


def local_sums(x: torch.Tensor, size: int, *, mode: str) -> torch.Tensor:
    """Sum over the ``size`` x ``size`` neighbourhood of every pixel (MATLAB origin)."""
    before = (size + 1) // 2 - 1
    p = pad(x, before, size - 1 - before, before, size - 1 - before, mode=mode)
    return window_sum(window_sum(p, size, -2), size, -1)


def box(x: torch.Tensor, window: int) -> torch.Tensor:
    """``imfilter(x, fspecial('average', k), 'replicate')``: the k x k mean.

    Replicate padding clamps each axis independently, so the 2-D mean separates into a
    vertical and a horizontal 1-D window sum (see :func:`window_sum`), then one division.
    Elementwise ops only: the same code runs on any device and about 15x faster on CPU than
    ``F.avg_pool2d`` with a (k, 1) kernel.
    """
    return local_sums(x, window, mode="replicate") / (window * window)


def sample_variance(x: torch.Tensor, window: int) -> torch.Tensor:
    """``stdfilt(x, ones(k)) .^ 2``: the k x k sample variance (1 / (n - 1)), mirrored borders.

    As MATLAB computes it: ``(sum x^2 - (sum x)^2 / n) / (n - 1)``, negative round-off
    clamped to 0.
    """
    n = window * window
    s1 = local_sums(x, window, mode="symmetric")
    s2 = local_sums(x * x, window, mode="symmetric")
    return ((s2 - s1 * s1 / n) / (n - 1)).clamp_min_(0.0)


def correlate(x: torch.Tensor, kernel: np.ndarray, *, conv: bool = False,
              mode: str = "replicate") -> torch.Tensor:
    """``imfilter(x, kernel, mode)`` (``conv=True``: ``imfilter(..., 'conv')``).

    ``kernel`` is a 2-D float64 array; with ``conv`` it is rotated by 180 degrees first,
    as MATLAB does. Computed as one ``F.conv2d`` (a cross-correlation) on the padded image;
    a float32 input on CUDA in float64 (cuDNN's TF32 would round it to 10 bits).
    """
    k = np.asarray(kernel, dtype=np.float64)
    if conv:
        k = k[::-1, ::-1]
    kh, kw = k.shape
    oy, ox = (kh + 1) // 2 - 1, (kw + 1) // 2 - 1
    p = pad(x, oy, kh - 1 - oy, ox, kw - 1 - ox, mode=mode)
    if p.is_cuda and p.dtype == torch.float32:
        # cuDNN may run float32 convolutions in TF32 (torch's default for convolutions: 10
        # bits of mantissa): on an H200 DCTM, DCTR, GDER, LAPD, LAPM and SFIL differed in
        # float32 from the float64 definitions by up to 2e-3 of their largest value
        # (2026-12-04, bench/lent_machine.sh; TF32 the likely cause, GLVM and TENV, without
        # a convolution, agreed). These are measurements: the convolution runs in float64
        # and comes back in float32, without touching torch's global flags (not yet run on
        # a GPU).
        weight = torch.as_tensor(k.copy(), dtype=torch.float64, device=p.device)[None, None]
        return F.conv2d(p.unsqueeze(1).double(), weight)[:, 0].float()
    weight = torch.as_tensor(k.copy(), dtype=x.dtype, device=x.device)[None, None]
    return F.conv2d(p.unsqueeze(1), weight)[:, 0]


def sobel_energy(x: torch.Tensor) -> torch.Tensor:
    """``Gx**2 + Gy**2`` of the unnormalised 3 x 3 Sobel, replicate borders.

    MATLAB's ``fspecial('sobel')`` is ``[[1, 2, 1], [0, 0, 0], [-1, -2, -1]]`` and its
    transpose; the sign (correlation or convolution) does not matter once squared.
    Implemented separably with slices of the padded image.
    """
    p = F.pad(x, (1, 1, 1, 1), mode="replicate")
    smooth_v = p[..., :-2, :] + 2.0 * p[..., 1:-1, :] + p[..., 2:, :]  # (B, H, W+2)
    smooth_h = p[..., :, :-2] + 2.0 * p[..., :, 1:-1] + p[..., :, 2:]  # (B, H+2, W)
    gx = smooth_v[..., :, :-2] - smooth_v[..., :, 2:]
    gy = smooth_h[..., :-2, :] - smooth_h[..., 2:, :]
    return gx * gx + gy * gy


def windows(x: torch.Tensor, size: int, *, mode: str = "zeros") -> torch.Tensor:
    """Every pixel's ``size`` x ``size`` neighbourhood, ``(B, H * W, size, size)``.

    MATLAB ``nlfilter``'s windows (zero padding, origin ``(size + 1) // 2 - 1``). Memory
    is ``size**2`` times the image: callers go image by image.
    """
    before = (size + 1) // 2 - 1
    p = pad(x, before, size - 1 - before, before, size - 1 - before, mode=mode)
    b, h, w = x.shape
    u = F.unfold(p.unsqueeze(1), size)  # (B, size*size, H*W), row-major in the window
    return u.transpose(1, 2).reshape(b, h * w, size, size)
