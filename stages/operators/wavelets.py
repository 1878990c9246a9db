"""The wavelet focus measures of Pertuz's ``focusmeasure.m`` (WAVS, WAVV, WAVR), through
PyWavelets.

The toolbox decomposes the image with MATLAB's ``wavedec2(Image, L, 'db6')`` and takes
single-branch reconstructions ``wrcoef2(type, C, S, 'db6', n)`` back at the image's size:

- ``H``, ``V``, ``D``: the level-1 horizontal, vertical and diagonal details, reconstructed;
- ``A1``, ``A2``, ``A3`` (WAVR only, a level-3 decomposition): the approximations of levels
  1, 2 and 3, reconstructed.

MATLAB's conventions, which PyWavelets follows here: the default extension mode ``'sym'``
(half-point symmetric, PyWavelets ``"symmetric"``); the decomposition keeps the odd samples
(1-based: 2, 4, ...) of the ``valid`` convolution of the extended signal, ``floor((n + 11)
/ 2)`` coefficients; each reconstruction step inserts zeros between the coefficients,
convolves in full and keeps the central part of the size of the level above (``wkeep2``
``'c'``: ``floor`` of the surplus dropped at the start, ``ceil`` at the end).
PyWavelets' ``idwt2`` returns that full convolution less ``len(filter) - 2`` samples at
each end; :func:`_keep_central` drops the rest as MATLAB does.
``tests/stages/test_wavelet_operators.py``
checks the decomposition against MATLAB's own output and the whole operators against an
independent numpy reference written from MATLAB's algorithm.

The operators (``MEANF`` and ``stdfilt`` as in :mod:`.toolbox`):

- WAVS, sum of wavelet coefficients (Yang 2003): ``MEANF(|H| + |V| + |D|)``;
- WAVV, variance of wavelet coefficients (Yang 2003):
  ``stdfilt(|H|)^2 + stdfilt(|V|)^2 + stdfilt(|D|)^2``;
- WAVR, ratio of wavelet coefficients (Xie 2006): ``MEANF(H^2 + V^2 + D^2) / MEANF(A^2)``
  with ``A = |A1| + |A2| + |A3|``.

The transforms run in float64 numpy on the CPU (PyWavelets has no GPU path), the window
filters in torch on the input's device; the result has the input's device and dtype.

Decimation makes these operators depend on where the image starts: a crop starting at a
column that is not a multiple of its alignment (2 for WAVS and WAVV, 8 for WAVR) gives
other values everywhere, not only at its border.
"""

from __future__ import annotations

import numpy as np
import torch
from sffscan.stages.operators.filters import box, sample_variance

__all__ = ["LEVELS", "WAVELET", "wavelet_branches", "wavr", "wavs", "wavv"]

WAVELET = "db6"
MODE = "symmetric"  # MATLAB's dwtmode default 'sym'
LEVELS = {"wavs": 1, "wavv": 1, "wavr": 3}
"""Decomposition level of each operator (``wavedec2(Image, L, 'db6')``)."""


def _keep_central(a: np.ndarray, shape: tuple[int, int]) -> np.ndarray:
    """MATLAB's ``wkeep2(a, shape, 'c')`` on the last two axes."""
    d0, d1 = a.shape[-2] - shape[0], a.shape[-1] - shape[1]
    return a[..., d0 // 2:d0 // 2 + shape[0], d1 // 2:d1 // 2 + shape[1]]


def _reconstruct(coeffs: tuple, shape: tuple[int, int]) -> np.ndarray:
    """One ``upsconv2`` step of ``wrcoef2``: the single branch ``coeffs`` (PyWavelets'
    ``(cA, (cH, cV, cD))`` with None for the absent ones), cropped to ``shape``."""
    import pywt

    return _keep_central(pywt.idwt2(coeffs, WAVELET, mode=MODE, axes=(-2, -1)), shape)


def wavelet_branches(images: np.ndarray, *, level: int = 1
                     ) -> tuple[np.ndarray, np.ndarray, np.ndarray, list[np.ndarray]]:
    """The toolbox's reconstructed single branches of ``images``.

    Parameters
    ----------
    images : (..., H, W) ndarray of float
        Images, 0..1.
    level : int, keyword-only
        Decomposition level (1 or more).

    Returns
    -------
    h, v, d : (..., H, W) ndarray of float64
        ``wrcoef2('h' / 'v' / 'd', C, S, 'db6', 1)``.
    approximations : list of (..., H, W) ndarray of float64
        ``wrcoef2('a', C, S, 'db6', n)`` for n = 1 .. ``level``.
    """
    import pywt

    x = np.asarray(images, dtype=np.float64)
    sizes = [tuple(x.shape[-2:])]
    ca, (ch, cv, cd) = pywt.dwt2(x, WAVELET, mode=MODE, axes=(-2, -1))
    approx = [ca]
    for _ in range(1, level):
        sizes.append(tuple(approx[-1].shape[-2:]))
        approx.append(pywt.dwt2(approx[-1], WAVELET, mode=MODE, axes=(-2, -1))[0])
    shape = sizes[0]
    h = _reconstruct((None, (ch, None, None)), shape)
    v = _reconstruct((None, (None, cv, None)), shape)
    d = _reconstruct((None, (None, None, cd)), shape)
    recon = []
    for n, a in enumerate(approx, start=1):
        for size in reversed(sizes[:n]):  # up from level n to the image, each step cropped
            a = _reconstruct((a, (None, None, None)), size)
        recon.append(a)
    return h, v, d, recon


def _branches(x: torch.Tensor, level: int) -> tuple[list[torch.Tensor], list[torch.Tensor]]:
    if x.shape[-2] < 2 or x.shape[-1] < 2:
        raise ValueError(f"the wavelet operators need images of at least 2 x 2 px, got "
                         f"{tuple(x.shape[-2:])}")
    h, v, d, approx = wavelet_branches(x.detach().cpu().numpy(), level=level)
    return ([torch.as_tensor(b).to(device=x.device, dtype=x.dtype) for b in (h, v, d)],
            [torch.as_tensor(a).to(device=x.device, dtype=x.dtype) for a in approx])


def wavs(x: torch.Tensor, k: int) -> torch.Tensor:
    """WAVS, sum of wavelet coefficients (Yang 2003): ``MEANF(|H| + |V| + |D|)``."""
    (h, v, d), _ = _branches(x, LEVELS["wavs"])
    return box(h.abs() + v.abs() + d.abs(), k)


def wavv(x: torch.Tensor, k: int) -> torch.Tensor:
    """WAVV, variance of wavelet coefficients (Yang 2003): the sum of ``stdfilt(.)^2`` of
    ``|H|``, ``|V|`` and ``|D|``."""
    (h, v, d), _ = _branches(x, LEVELS["wavv"])
    return sample_variance(h.abs(), k) + sample_variance(v.abs(), k) + sample_variance(d.abs(), k)


def wavr(x: torch.Tensor, k: int) -> torch.Tensor:
    """WAVR, ratio of wavelet coefficients (Xie 2006): ``MEANF(H^2 + V^2 + D^2) ./
    MEANF(A^2)``, ``A = |A1| + |A2| + |A3|`` of a level-3 decomposition."""
    (h, v, d), approx = _branches(x, LEVELS["wavr"])
    a = sum(ai.abs() for ai in approx)
    assert isinstance(a, torch.Tensor)
    return box(h * h + v * v + d * d, k) / box(a * a, k)
