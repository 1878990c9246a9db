"""The per-pixel focus measures of Pertuz's ``focusmeasure.m``, in torch.

Each operator follows the toolbox's definition (``FM = focusmeasure(Image, Measure, WSize)``
with ``WSize = k``): its filters, their borders and scaling, on images scaled to 0..1.
``MEANF`` below is ``fspecial('average', k)`` applied with ``'replicate'`` borders
(:func:`.filters.box`); ``stdfilt`` is the sample standard deviation over k x k with
mirrored borders (:func:`.filters.sample_variance`); ``nlfilter`` windows are zero padded.
The few places where the toolbox's code cannot be followed literally are said at the
operator (GDER and SFIL: a kernel normalised by a sum that is zero).
The wavelet operators (WAVS, WAVV, WAVR, through PyWavelets) are in :mod:`.wavelets`.

Every operator is a function named by its acronym that takes a ``(B, H, W)`` floating
tensor and the window k and returns the focus measure as ``(B, H, W)``, same device and
dtype: the one definition of each operator, registered in
:data:`sffscan.stages.operators.FOCUS_OPERATORS` (GLVM and TENV also have OpenCV front
ends with the same definitions, :mod:`.opencv`).
"""

from __future__ import annotations

import math
from collections.abc import Callable

import numpy as np
import torch
from sffscan.stages.operators.filters import (
    box,
    correlate,
    local_sums,
    pad,
    sample_variance,
    sobel_energy,
    windows,
)

__all__ = [
    "acmo", "bren", "cheb", "cont", "curv", "dcte", "dctm", "dctr", "eigv", "gder", "gllv",
    "glva", "glvm", "glvn", "grae", "gras", "grat", "helm", "hise", "hisr", "lapd", "lape",
    "lapm", "lapv", "sfil", "sfrq", "tchebichef_polynomials", "teng", "tenv", "tenv_std",
    "vola", "vols",
]

_LAPLACIAN = np.array([[1.0, 4.0, 1.0], [4.0, -20.0, 4.0], [1.0, 4.0, 1.0]]) / 6.0
"""``fspecial('laplacian')`` (alpha 0.2): ``4 / (alpha + 1) * [a/4 (1-a)/4 a/4; ...]``."""


def _quantise(x: torch.Tensor) -> torch.Tensor:
    """``im2uint8`` of a 0..1 image: ``round(255 x)`` (halves away from zero), saturated."""
    return torch.floor(x.clamp(0.0, 1.0) * 255.0 + 0.5)


def _diff_next(x: torch.Tensor, dim: int, step: int = 1) -> torch.Tensor:
    """``D = I; D(1:end-step) = I(1+step:end) - I(1:end-step)`` along ``dim`` (the last
    ``step`` entries keep the image's own values, as the toolbox leaves them)."""
    n = x.size(dim)
    out = x.clone()
    out.narrow(dim, 0, n - step).copy_(x.narrow(dim, step, n - step) - x.narrow(dim, 0, n - step))
    return out


def _shift_up(x: torch.Tensor, step: int) -> torch.Tensor:
    """``I1 = I; I1(1:end-step, :) = I(1+step:end, :)``."""
    out = x.clone()
    n = x.shape[-2]
    out[..., : n - step, :] = x[..., step:, :]
    return out


def _gaussian_derivatives(window: int) -> tuple[np.ndarray, np.ndarray]:
    """GDER's kernels ``Gx = -x G / sig^2``, ``Gy = -y G / sig^2``, N = k // 2, sig = N / 3.

    The toolbox then divides each by its own sum, which is zero in exact arithmetic (an odd
    kernel): what MATLAB returns is round-off (1e-17-ish, or a division by 0). That scale
    is left out here: the kernels are used as ``-x G / sig^2`` with
    ``G = exp(-(x^2 + y^2) / (2 sig^2)) / (2 pi sig)``. A constant factor per window size,
    which leaves every depth method's result unchanged.
    """
    n = window // 2
    sig = n / 3.0
    y, x = np.mgrid[-n:n + 1, -n:n + 1].astype(np.float64)
    g = np.exp(-(x**2 + y**2) / (2 * sig**2)) / (2 * math.pi * sig)
    return -x * g / sig**2, -y * g / sig**2


# ----------------------------------------------------------------------------- operators


def acmo(x: torch.Tensor, k: int) -> torch.Tensor:
    """ACMO, absolute central moment (Shirvaikar 2004): ``nlfilter(I, [k k], @AcMomentum)``
    then MEANF. ``AcMomentum`` of a window: the histogram of its values in 256 bins
    (``imhist``: bin ``round(255 v)``), weighted by ``|bin - 255 mean|``, over the window's
    pixel count: ``mean(|round(255 v) - 255 mean(v)|)``, zero padded."""
    q = pad(_quantise(x), k // 2, k // 2, k // 2, k // 2, mode="zeros")
    mu255 = local_sums(x, k, mode="zeros") * (255.0 / (k * k))
    h, w = x.shape[-2:]
    acc = torch.zeros_like(x)
    for dy in range(k):
        for dx in range(k):
            acc += (q[..., dy:dy + h, dx:dx + w] - mu255).abs()
    return box(acc / (k * k), k)


def bren(x: torch.Tensor, k: int) -> torch.Tensor:
    """BREN, Brenner (Santos 1997): ``max(DH, DV)^2`` of the 2-px differences (zero in the
    last two rows / columns), then MEANF."""
    dv = torch.zeros_like(x)
    dh = torch.zeros_like(x)
    dv[..., :-2, :] = x[..., 2:, :] - x[..., :-2, :]
    dh[..., :, :-2] = x[..., :, 2:] - x[..., :, :-2]
    fm = torch.maximum(dh, dv)
    return box(fm * fm, k)


def tchebichef_polynomials(n: int, order: int = 2) -> np.ndarray:
    """The toolbox's normalised discrete Tchebichef polynomials, ``(order + 1, n)`` float64
    (``TchebichefPoly``: the recurrence scaled to [-1, 1], divided by ``sqrt(rho)``)."""
    x = np.arange(n, dtype=np.float64)
    p = np.zeros((order + 1, n))
    p[0] = 1.0
    p[1] = (1 - n + 2.0 * x) / n
    for q in range(2, order + 1):
        p[q] = ((2 * q - 1) * p[1] * p[q - 1]
                - (q - 1) * (1.0 - (q - 1) ** 2 / n**2) * p[q - 2]) / q
    rho = np.ones(n)
    for q in range(1, n):
        rho[q] = rho[q - 1] * (1.0 - q * q / n**2)
    rho *= n / (2 * np.arange(n) + 1.0)
    return p / np.sqrt(rho[: order + 1, None])


def _normalised_windows(x: torch.Tensor, k: int) -> torch.Tensor:
    """Zero-padded k x k windows of one image, ``(H*W, k, k)``: ``W / sqrt(sum W^2)`` minus
    its mean (the first lines of the toolbox's ``TchebiFocus`` and ``EigenFocus``)."""
    win = windows(x[None], k)[0]
    win = win / win.square().sum(dim=(-2, -1), keepdim=True).sqrt()
    return win - win.mean(dim=(-2, -1), keepdim=True)


def cheb(x: torch.Tensor, k: int) -> torch.Tensor:
    """CHEB, Chebyshev moments (Yap 2004): ``nlfilter(I, [k k], @TchebiFocus)`` then MEANF.

    Per window (normalised, mean removed): moments ``B = P I P'`` of order <= 2 in the
    toolbox's Tchebichef basis, the low-order ones kept (p + q <= 2),
    ``|sum I^2 - sum B^2| / |sum B^2|``."""
    poly = torch.as_tensor(tchebichef_polynomials(k, 2), dtype=x.dtype, device=x.device)
    low = torch.as_tensor(np.add.outer(np.arange(3), np.arange(3)) <= 2, device=x.device)
    out = []
    for img in x:
        win = _normalised_windows(img, k)
        b = poly @ win @ poly.T  # (H*W, 3, 3)
        b2 = (b.square() * low).sum(dim=(-2, -1))
        out.append(((win.square().sum(dim=(-2, -1)) - b2).abs() / b2.abs()).reshape(img.shape))
    return box(torch.stack(out), k)


def cont(x: torch.Tensor, k: int) -> torch.Tensor:
    """CONT, image contrast (Nanda 2001): ``sum |x - x_centre|`` over 3 x 3 (``nlfilter``,
    zero padded), then MEANF."""
    p = pad(x, 1, 1, 1, 1, mode="zeros")
    h, w = x.shape[-2:]
    fm = sum((p[..., dy:dy + h, dx:dx + w] - x).abs() for dy in range(3) for dx in range(3))
    assert isinstance(fm, torch.Tensor)
    return box(fm, k)


def curv(x: torch.Tensor, k: int) -> torch.Tensor:
    """CURV, image curvature (Helmli 2001), as the toolbox writes it (its P3 uses M2 twice,
    i.e. ``P3 = conv(I, M2) / 10``), then MEANF."""
    m1 = np.array([[-1.0, 0.0, 1.0]] * 3)
    m2 = np.array([[1.0, 0.0, 1.0]] * 3)
    c_m2 = correlate(x, m2, conv=True)
    p0 = correlate(x, m1, conv=True) / 6
    p1 = correlate(x, m1.T, conv=True) / 6
    p2 = 3 * c_m2 / 10 - correlate(x, m2.T, conv=True) / 5
    p3 = -c_m2 / 5 + 3 * c_m2 / 10
    return box(p0.abs() + p1.abs() + p2.abs() + p3.abs(), k)


def _dct_matrix(n: int) -> np.ndarray:
    """Orthonormal DCT-II matrix (MATLAB ``dct2``'s basis): ``D[u, x]``."""
    u, xx = np.mgrid[0:n, 0:n].astype(np.float64)
    d = np.sqrt(2.0 / n) * np.cos(math.pi * (2 * xx + 1) * u / (2 * n))
    d[0] = np.sqrt(1.0 / n)
    return d


def dcte(x: torch.Tensor, k: int) -> torch.Tensor:
    """DCTE, DCT energy ratio (Shen 2006): per zero-padded 8 x 8 window (``nlfilter``),
    ``(sum C^2 - C00^2) / C00^2`` of its orthonormal DCT; by Parseval ``sum C^2 = sum W^2``
    and ``C00 = sum W / 8``. Then MEANF."""
    s1 = local_sums(x, 8, mode="zeros")
    s2 = local_sums(x * x, 8, mode="zeros")
    dc2 = s1 * s1 / 64.0
    return box((s2 - dc2) / dc2, k)


def dctr(x: torch.Tensor, k: int) -> torch.Tensor:
    """DCTR, DCT reduced energy ratio (Lee 2009): per zero-padded 8 x 8 window,
    ``(C01^2 + C02^2 + C10^2 + C11^2 + C20^2) / C00^2``, then MEANF. Each coefficient
    ``C_uv = sum D[u, r] W[r, c] D[v, c]`` is a correlation with ``outer(D[u], D[v])``."""
    d = _dct_matrix(8)
    coef = [correlate(x, np.outer(d[u], d[v]), mode="zeros")
            for u, v in ((0, 0), (0, 1), (0, 2), (1, 0), (1, 1), (2, 0))]
    num = sum(c * c for c in coef[1:])
    return box(num / (coef[0] * coef[0]), k)


def dctm(x: torch.Tensor, k: int) -> torch.Tensor:
    """DCTM, modified DCT (Lee 2008): ``imfilter(I, M, 'replicate')`` with the 4 x 4 M
    (a correlation, origin at (2, 2)), *signed* as in the toolbox, then MEANF."""
    m = np.array([[1.0, 1, -1, -1], [1, 1, -1, -1], [-1, -1, 1, 1], [-1, -1, 1, 1]])
    return box(correlate(x, m), k)


def eigv(x: torch.Tensor, k: int) -> torch.Tensor:
    """EIGV, eigenvalues (Wee 2007): per zero-padded k x k window (normalised, mean
    removed), the sum of the 3 largest eigenvalues of ``I I' / (k^2 - 1)``, then MEANF."""
    out = []
    for img in x:
        win = _normalised_windows(img, k)
        cov = win @ win.transpose(-2, -1) / (k * k - 1)
        if cov.is_cuda:
            # cuSOLVER's batched eigensolver failed on an H200 (torch 2.11+cu130,
            # 2026-12-04: CUSOLVER_STATUS_INTERNAL_ERROR in cusolverDnXsyevBatched for 65,536
            # 9 x 9 float64 matrices): the small matrices go to LAPACK on the CPU, the
            # eigenvalues come back to the input's device
            ev = torch.linalg.eigvalsh(cov.cpu()).to(cov.device)
        else:
            ev = torch.linalg.eigvalsh(cov)  # ascending
        out.append(ev[..., -3:].sum(dim=-1).reshape(img.shape))
    return box(torch.stack(out), k)


def gder(x: torch.Tensor, k: int) -> torch.Tensor:
    """GDER, Gaussian derivative (Geusebroek 2000): ``Rx^2 + Ry^2`` of the image convolved
    (replicate borders) with the k x k Gaussian derivative kernels (see
    :func:`_gaussian_derivatives` for their scale), then MEANF."""
    gx, gy = _gaussian_derivatives(k)
    rx = correlate(x, gx, conv=True)
    ry = correlate(x, gy, conv=True)
    return box(rx * rx + ry * ry, k)


def gllv(x: torch.Tensor, k: int) -> torch.Tensor:
    """GLLV, grey-level local variance (Pech 2000): ``stdfilt(stdfilt(I)^2)^2``."""
    return sample_variance(sample_variance(x, k), k)


def glva(x: torch.Tensor, k: int) -> torch.Tensor:
    """GLVA, grey-level variance (Krotkov 1986): ``stdfilt(I)^2``, then MEANF."""
    return box(sample_variance(x, k), k)


def glvn(x: torch.Tensor, k: int) -> torch.Tensor:
    """GLVN, normalised grey-level variance (Santos 1997): ``stdfilt(I)^2 ./ MEANF(I)``."""
    return sample_variance(x, k) / box(x, k)


def glvm(x: torch.Tensor, k: int, *,
         mean: Callable[[torch.Tensor, int], torch.Tensor] = box) -> torch.Tensor:
    """GLVM, modified grey-level variance: ``MEANF((I - MEANF(I))^2)``.

    ``mean`` computes MEANF (default :func:`.filters.box`, separable window sums); the
    benchmarks pass the thesis' dense k x k convolution
    (:func:`sffscan.stages.focus_torch.glvm_conv2d_baseline`)."""
    d = x - mean(x, k)
    return mean(d * d, k)


def _gradients(x: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """The toolbox's ``Ix`` (column differences) and ``Iy`` (row differences); the last
    column / row keeps the image's values."""
    return _diff_next(x, -1), _diff_next(x, -2)


def grae(x: torch.Tensor, k: int) -> torch.Tensor:
    """GRAE, energy of gradient (Subbarao 1992): ``MEANF(Ix^2 + Iy^2)``."""
    ix, iy = _gradients(x)
    return box(ix * ix + iy * iy, k)


def gras(x: torch.Tensor, k: int) -> torch.Tensor:
    """GRAS, squared gradient (Eskicioglu 1995): ``MEANF(Ix^2)``."""
    ix = _diff_next(x, -1)
    return box(ix * ix, k)


def grat(x: torch.Tensor, k: int) -> torch.Tensor:
    """GRAT, thresholded gradient (Santos 1997; threshold 0 in the toolbox):
    ``MEANF(max(|Ix|, |Iy|))``."""
    ix, iy = _gradients(x)
    return box(torch.maximum(ix.abs(), iy.abs()), k)


def helm(x: torch.Tensor, k: int) -> torch.Tensor:
    """HELM, Helmli's mean method (2001): ``R = MEANF(I) ./ I`` (1 where I = 0); ``R`` where
    the mean exceeds the pixel, else ``1 / R``; then MEANF."""
    u = box(x, k)
    zero = x == 0
    r1 = torch.where(zero, torch.ones_like(x), u / torch.where(zero, torch.ones_like(x), x))
    return box(torch.where(u > x, r1, 1.0 / r1), k)


def hise(x: torch.Tensor, k: int) -> torch.Tensor:
    """HISE, histogram entropy (Krotkov 1986): ``entropyfilt(I, ones(k))`` (the image as
    uint8, 256 bins, mirrored borders, ``-sum p log2 p``), then MEANF.

    With ``p = c / n`` for the counts ``c`` of each grey level in the ``n = k^2`` window,
    ``-sum p log2 p = log2 n - (1 / n) sum c log2 c``: each grey level present in the
    image adds ``c log2 c`` of its window counts (a mirrored k x k sum of its indicator,
    exact integers), read from a table of ``n + 1`` values. Until 2026-12-04 each window's
    values were sorted and their runs counted: 2.15 s against 0.37 s for three 256 x 256
    float64 images (1.20 against 0.29 s in float32; one process with torch's 2 threads on
    the 2-core development VM, the results equal to 4e-15), the same to round-off."""
    n = k * k
    q = _quantise(x)
    c = torch.arange(n + 1, dtype=x.dtype, device=x.device)
    c_log_c = c * torch.log2(torch.where(c > 0, c, torch.ones_like(c)))
    acc = torch.zeros_like(x)
    for level in torch.unique(q).tolist():
        counts = local_sums((q == level).to(x.dtype), k, mode="symmetric")
        acc += c_log_c[counts.round().long()]
    return box(math.log2(n) - acc / n, k)


def hisr(x: torch.Tensor, k: int) -> torch.Tensor:
    """HISR, histogram range (Firestone 1991): ``rangefilt(I, ones(k))`` (max - min over the
    pixels of the window inside the image: the same as with replicated borders), then
    MEANF."""
    r = k // 2
    p = pad(x, r, r, r, r, mode="replicate").unsqueeze(1)
    mx = torch.nn.functional.max_pool2d(p, k, stride=1)
    mn = -torch.nn.functional.max_pool2d(-p, k, stride=1)
    return box((mx - mn)[:, 0], k)


def lapd(x: torch.Tensor, k: int) -> torch.Tensor:
    """LAPD, diagonal Laplacian (Thelen 2009): ``|F1| + |F2| + |F3| + |F4|`` of the 1-D and
    diagonal second differences (the diagonals divided by sqrt 2), then MEANF."""
    m1 = np.array([[-1.0, 2.0, -1.0]])
    m2 = np.array([[0.0, 0, -1], [0, 2, 0], [-1, 0, 0]]) / math.sqrt(2)
    m3 = np.array([[-1.0, 0, 0], [0, 2, 0], [0, 0, -1]]) / math.sqrt(2)
    fm = sum(correlate(x, m, conv=True).abs() for m in (m1, m2, m3, m1.T))
    assert isinstance(fm, torch.Tensor)
    return box(fm, k)


def lape(x: torch.Tensor, k: int) -> torch.Tensor:
    """LAPE, energy of Laplacian (Subbarao 1992): ``MEANF(L^2)``, L the image convolved with
    ``fspecial('laplacian')`` (replicate borders)."""
    lap = correlate(x, _LAPLACIAN, conv=True)
    return box(lap * lap, k)


def lapm(x: torch.Tensor, k: int) -> torch.Tensor:
    """LAPM, modified Laplacian (Nayar 1989): ``MEANF(|Lx| + |Ly|)`` with ``[-1 2 -1]`` and
    its transpose."""
    m = np.array([[-1.0, 2.0, -1.0]])
    return box(correlate(x, m, conv=True).abs() + correlate(x, m.T, conv=True).abs(), k)


def lapv(x: torch.Tensor, k: int) -> torch.Tensor:
    """LAPV, variance of Laplacian (Pech 2000): ``stdfilt(L)^2``."""
    return sample_variance(correlate(x, _LAPLACIAN, conv=True), k)


def sfil(x: torch.Tensor, k: int) -> torch.Tensor:
    """SFIL, steerable filters (Minhas 2009): the GDER responses ``R1``, ``R2`` and their
    combinations at 45, 135, 180, 225 and 315 degrees (the toolbox writes its 270-degree
    response into the slot it then overwrites with 315), the maximum over these 7, then
    MEANF. Kernel scale as in :func:`gder`."""
    gx, gy = _gaussian_derivatives(k)
    r1 = correlate(x, gx, conv=True)
    r2 = correlate(x, gy, conv=True)
    resp = [r1, r2] + [math.cos(math.radians(a)) * r1 + math.sin(math.radians(a)) * r2
                       for a in (45, 135, 180, 225, 315)]
    return box(torch.stack(resp).amax(dim=0), k)


def sfrq(x: torch.Tensor, k: int) -> torch.Tensor:
    """SFRQ, spatial frequency (Eskicioglu 1995): ``sqrt(MEANF(Iy^2) + MEANF(Ix^2))``."""
    ix, iy = _gradients(x)
    return torch.sqrt(box(iy * iy, k) + box(ix * ix, k))


def teng(x: torch.Tensor, k: int) -> torch.Tensor:
    """TENG, Tenengrad (Krotkov 1986): ``MEANF(Gx^2 + Gy^2)``, 3 x 3 Sobel."""
    return box(sobel_energy(x), k)


def tenv(x: torch.Tensor, k: int) -> torch.Tensor:
    """TENV, Tenengrad variance (Pech 2000): ``stdfilt(Gx^2 + Gy^2, ones(k))^2``."""
    return sample_variance(sobel_energy(x), k)


def tenv_std(x: torch.Tensor, k: int) -> torch.Tensor:
    """The thesis' TENV: the local standard deviation ``stdfilt(Gx^2 + Gy^2, ones(k))``."""
    return sample_variance(sobel_energy(x), k).sqrt()


def vola(x: torch.Tensor, k: int) -> torch.Tensor:
    """VOLA, Vollath's correlation (Santos 1997): ``MEANF(I .* (I1 - I2))``, I1 and I2 the
    image moved up by 1 and 2 rows (the last rows keep their own values)."""
    return box(x * (_shift_up(x, 1) - _shift_up(x, 2)), k)


def vols(x: torch.Tensor, k: int) -> torch.Tensor:
    """VOLS, Vollath's standard deviation (Santos 1997), as the toolbox writes it:
    ``U = k * MEANF(I)``, ``MEANF(I .* I1 - U^2)``."""
    u = k * box(x, k)
    return box(x * _shift_up(x, 1) - u * u, k)
