"""Independent float64 numpy references of the toolbox's focus measures (``focusmeasure.m``).

Written from the published MATLAB definitions, not from the torch code: every filter is an
explicit sum over kernel offsets of an ``np.pad``-ed image (MATLAB's borders: ``'edge'`` for
``imfilter(..., 'replicate')``, ``'symmetric'`` for ``stdfilt`` / ``entropyfilt``, zeros for
``nlfilter``), ``stdfilt`` is the two-pass sample standard deviation of each window, the
DCT operators use ``scipy.fft.dctn(norm='ortho')`` (MATLAB's ``dct2``), histograms are
counted per grey level, eigenvalues come from ``np.linalg.eigvalsh``. Images (H, W) in 0..1.
"""

from __future__ import annotations

import math
from typing import Literal

import numpy as np
import scipy.fft

PadMode = Literal["constant", "edge", "symmetric"]
"""The numpy padding modes of MATLAB's borders (zeros, 'replicate', 'symmetric')."""


def _origin(size: int) -> int:
    return (size + 1) // 2 - 1  # MATLAB: floor((size + 1) / 2), 1-based


def imfilter(img: np.ndarray, h: np.ndarray, *, mode: PadMode = "edge", conv: bool = False
             ) -> np.ndarray:
    h = np.asarray(h, dtype=np.float64)
    if conv:
        h = np.rot90(h, 2)
    kh, kw = h.shape
    oy, ox = _origin(kh), _origin(kw)
    p = np.pad(img, ((oy, kh - 1 - oy), (ox, kw - 1 - ox)), mode=mode)
    out = np.zeros(img.shape)
    rows, cols = img.shape
    for i in range(kh):
        for j in range(kw):
            if h[i, j] != 0:
                out += h[i, j] * p[i:i + rows, j:j + cols]
    return out


def meanf(img: np.ndarray, k: int) -> np.ndarray:
    return imfilter(img, np.full((k, k), 1.0 / (k * k)))


def nl_windows(img: np.ndarray, size: int, mode: PadMode = "constant") -> np.ndarray:
    """(H, W, size, size) windows as nlfilter sees them (zero padded by default)."""
    o = _origin(size)
    p = np.pad(img, ((o, size - 1 - o), (o, size - 1 - o)), mode=mode)
    return np.lib.stride_tricks.sliding_window_view(p, (size, size))


def stdfilt2(img: np.ndarray, k: int) -> np.ndarray:
    """stdfilt(img, ones(k)).^2, two-pass sample variance of each mirrored window."""
    w = nl_windows(img, k, mode="symmetric").reshape(*img.shape, -1)
    return w.var(axis=-1, ddof=1)


def _gradients(img: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    ix = img.copy()
    iy = img.copy()
    ix[:, :-1] = np.diff(img, axis=1)
    iy[:-1, :] = np.diff(img, axis=0)
    return ix, iy


def _sobel_g(img: np.ndarray) -> np.ndarray:
    sx = np.array([[1.0, 2, 1], [0, 0, 0], [-1, -2, -1]])
    gx = imfilter(img, sx, conv=True)
    gy = imfilter(img, sx.T, conv=True)
    return gx**2 + gy**2


def _gauss_kernels(k: int) -> tuple[np.ndarray, np.ndarray]:
    n = k // 2
    sig = n / 3
    x, y = np.meshgrid(np.arange(-n, n + 1.0), np.arange(-n, n + 1.0))
    g = np.exp(-(x**2 + y**2) / (2 * sig**2)) / (2 * math.pi * sig)
    # the toolbox divides by sum(Gx(:)) = 0 (round-off): left out, see the torch docstring
    return -x * g / sig**2, -y * g / sig**2


LAPLACIAN = (4 / 1.2) * np.array([[0.05, 0.2, 0.05], [0.2, -1.0, 0.2], [0.05, 0.2, 0.05]])


def _u8(img: np.ndarray) -> np.ndarray:
    return np.floor(np.clip(img, 0, 1) * 255 + 0.5)


def _level_counts(q: np.ndarray, k: int, mode: PadMode) -> np.ndarray:
    """(256, H, W): how many pixels of each grey level each k x k window holds."""
    o = _origin(k)
    qp = np.pad(q, ((o, k - 1 - o), (o, k - 1 - o)), mode=mode)
    counts = np.zeros((256, *q.shape))
    for v in np.unique(qp).astype(int):
        ind = (qp == v).astype(np.float64)
        c = np.cumsum(np.cumsum(np.pad(ind, ((1, 0), (1, 0))), axis=0), axis=1)
        counts[v] = c[k:, k:] - c[:-k, k:] - c[k:, :-k] + c[:-k, :-k]
    return counts


def acmo(img: np.ndarray, k: int) -> np.ndarray:
    w = nl_windows(img, k)
    mu = w.mean(axis=(-2, -1))
    q = _u8(img)
    counts = _level_counts(q, k, "constant")  # the zero padding counts in bin 0
    levels = np.arange(256.0).reshape(-1, 1, 1)
    fm = (np.abs(levels - 255 * mu[None]) * counts).sum(axis=0) / (k * k)
    return meanf(fm, k)


def bren(img: np.ndarray, k: int) -> np.ndarray:
    m, n = img.shape
    dh = np.zeros((m, n))
    dv = np.zeros((m, n))
    dv[: m - 2, :] = img[2:, :] - img[:-2, :]
    dh[:, : n - 2] = img[:, 2:] - img[:, :-2]
    return meanf(np.maximum(dh, dv) ** 2, k)


def _tchebichef(n: int, order: int) -> np.ndarray:
    p = np.zeros((order + 1, n))
    for x in range(n):
        p[0, x] = 1.0
        p[1, x] = (1 - n + 2.0 * x) / n
        for q in range(2, order + 1):
            p[q, x] = ((2 * q - 1) * p[1, x] * p[q - 1, x]
                       - (q - 1) * (1.0 - (q - 1) ** 2 / n**2) * p[q - 2, x]) / q
    r = np.zeros(n)
    r[0] = 1.0
    for q in range(1, n):
        r[q] = r[q - 1] * (1.0 - q * q / n**2)
    for q in range(n):
        r[q] = r[q] * n / (2 * q + 1)
    for x in range(n):
        for q in range(order + 1):
            p[q, x] = p[q, x] / math.sqrt(r[q])
    return p


def _normalised(w: np.ndarray) -> np.ndarray:
    k = w.shape[-1]
    w = w / np.sqrt(k * k * (w**2).mean(axis=(-2, -1), keepdims=True))
    return w - w.mean(axis=(-2, -1), keepdims=True)


def cheb(img: np.ndarray, k: int) -> np.ndarray:
    p = _tchebichef(k, 2)
    i = _normalised(nl_windows(img, k))
    b = np.einsum("pa,...ab,qb->...pq", p, i, p)
    b = np.fliplr(np.triu(np.fliplr(np.ones((3, 3))), 0)) * b  # low orders kept
    b2 = (b**2).sum(axis=(-2, -1))
    return meanf(np.abs((i**2).sum(axis=(-2, -1)) - b2) / np.abs(b2), k)


def cont(img: np.ndarray, k: int) -> np.ndarray:
    w = nl_windows(img, 3).reshape(*img.shape, 9)
    return meanf(np.abs(w - w[..., 4:5]).sum(axis=-1), k)


def curv(img: np.ndarray, k: int) -> np.ndarray:
    m1 = np.array([[-1.0, 0, 1], [-1, 0, 1], [-1, 0, 1]])
    m2 = np.array([[1.0, 0, 1], [1, 0, 1], [1, 0, 1]])
    p0 = imfilter(img, m1, conv=True) / 6
    p1 = imfilter(img, m1.T, conv=True) / 6
    p2 = 3 * imfilter(img, m2, conv=True) / 10 - imfilter(img, m2.T, conv=True) / 5
    p3 = -imfilter(img, m2, conv=True) / 5 + 3 * imfilter(img, m2, conv=True) / 10
    return meanf(np.abs(p0) + np.abs(p1) + np.abs(p2) + np.abs(p3), k)


def _dct_windows(img: np.ndarray) -> np.ndarray:
    return scipy.fft.dctn(nl_windows(img, 8), axes=(-2, -1), norm="ortho")


def dcte(img: np.ndarray, k: int) -> np.ndarray:
    mt = _dct_windows(img) ** 2
    return meanf((mt.sum(axis=(-2, -1)) - mt[..., 0, 0]) / mt[..., 0, 0], k)


def dctr(img: np.ndarray, k: int) -> np.ndarray:
    m = _dct_windows(img)
    num = m[..., 0, 1]**2 + m[..., 0, 2]**2 + m[..., 1, 0]**2 + m[..., 1, 1]**2 + m[..., 2, 0]**2
    return meanf(num / m[..., 0, 0] ** 2, k)


def dctm(img: np.ndarray, k: int) -> np.ndarray:
    m = np.array([[1.0, 1, -1, -1], [1, 1, -1, -1], [-1, -1, 1, 1], [-1, -1, 1, 1]])
    return meanf(imfilter(img, m), k)


def eigv(img: np.ndarray, k: int) -> np.ndarray:
    i = _normalised(nl_windows(img, k))
    cov = i @ np.swapaxes(i, -1, -2) / (k * k - 1)
    ev = -np.sort(-np.linalg.eigvalsh(cov), axis=-1)
    return meanf(ev[..., :3].sum(axis=-1), k)


def gder(img: np.ndarray, k: int) -> np.ndarray:
    gx, gy = _gauss_kernels(k)
    return meanf(imfilter(img, gx, conv=True) ** 2 + imfilter(img, gy, conv=True) ** 2, k)


def gllv(img: np.ndarray, k: int) -> np.ndarray:
    return stdfilt2(stdfilt2(img, k), k)


def glva(img: np.ndarray, k: int) -> np.ndarray:
    return meanf(stdfilt2(img, k), k)


def glvn(img: np.ndarray, k: int) -> np.ndarray:
    return stdfilt2(img, k) / meanf(img, k)


def glvm(img: np.ndarray, k: int) -> np.ndarray:
    return meanf((img - meanf(img, k)) ** 2, k)


def grae(img: np.ndarray, k: int) -> np.ndarray:
    ix, iy = _gradients(img)
    return meanf(ix**2 + iy**2, k)


def gras(img: np.ndarray, k: int) -> np.ndarray:
    ix, _ = _gradients(img)
    return meanf(ix**2, k)


def grat(img: np.ndarray, k: int) -> np.ndarray:
    ix, iy = _gradients(img)
    return meanf(np.maximum(np.abs(ix), np.abs(iy)), k)


def helm(img: np.ndarray, k: int) -> np.ndarray:
    u = meanf(img, k)
    with np.errstate(divide="ignore", invalid="ignore"):
        r1 = u / img
    r1[img == 0] = 1
    fm = 1 / r1
    index = u > img
    fm[index] = r1[index]
    return meanf(fm, k)


def hise(img: np.ndarray, k: int) -> np.ndarray:
    p = _level_counts(_u8(img), k, "symmetric") / (k * k)
    logp = np.log2(np.where(p > 0, p, 1.0))
    return meanf(-(p * logp).sum(axis=0), k)


def hisr(img: np.ndarray, k: int) -> np.ndarray:
    r = k // 2
    w = np.lib.stride_tricks.sliding_window_view(
        np.pad(img, r, mode="constant", constant_values=np.nan), (k, k))
    return meanf(np.nanmax(w, axis=(-2, -1)) - np.nanmin(w, axis=(-2, -1)), k)


def lape(img: np.ndarray, k: int) -> np.ndarray:
    return meanf(imfilter(img, LAPLACIAN, conv=True) ** 2, k)


def lapm(img: np.ndarray, k: int) -> np.ndarray:
    m = np.array([[-1.0, 2, -1]])
    return meanf(np.abs(imfilter(img, m, conv=True)) + np.abs(imfilter(img, m.T, conv=True)), k)


def lapv(img: np.ndarray, k: int) -> np.ndarray:
    return stdfilt2(imfilter(img, LAPLACIAN, conv=True), k)


def lapd(img: np.ndarray, k: int) -> np.ndarray:
    m1 = np.array([[-1.0, 2, -1]])
    m2 = np.array([[0.0, 0, -1], [0, 2, 0], [-1, 0, 0]]) / math.sqrt(2)
    m3 = np.array([[-1.0, 0, 0], [0, 2, 0], [0, 0, -1]]) / math.sqrt(2)
    fm = sum(np.abs(imfilter(img, m, conv=True)) for m in (m1, m2, m3, m1.T))
    return meanf(fm, k)


def sfil(img: np.ndarray, k: int) -> np.ndarray:
    gx, gy = _gauss_kernels(k)
    r = np.zeros((7, *img.shape))
    r[0] = imfilter(img, gx, conv=True)
    r[1] = imfilter(img, gy, conv=True)
    cosd, sind = (lambda a: math.cos(math.radians(a))), (lambda a: math.sin(math.radians(a)))
    r[2] = cosd(45) * r[0] + sind(45) * r[1]
    r[3] = cosd(135) * r[0] + sind(135) * r[1]
    r[4] = cosd(180) * r[0] + sind(180) * r[1]
    r[5] = cosd(225) * r[0] + sind(225) * r[1]
    r[6] = cosd(270) * r[0] + sind(270) * r[1]
    r[6] = cosd(315) * r[0] + sind(315) * r[1]  # the toolbox overwrites slot 7
    return meanf(r.max(axis=0), k)


def sfrq(img: np.ndarray, k: int) -> np.ndarray:
    ix, iy = _gradients(img)
    return np.sqrt(meanf(iy**2, k) + meanf(ix**2, k))


def teng(img: np.ndarray, k: int) -> np.ndarray:
    return meanf(_sobel_g(img), k)


def tenv(img: np.ndarray, k: int) -> np.ndarray:
    return stdfilt2(_sobel_g(img), k)


def tenv_std(img: np.ndarray, k: int) -> np.ndarray:
    return np.sqrt(stdfilt2(_sobel_g(img), k))


def vola(img: np.ndarray, k: int) -> np.ndarray:
    i1 = img.copy()
    i1[:-1, :] = img[1:, :]
    i2 = img.copy()
    i2[:-2, :] = img[2:, :]
    return meanf(img * (i1 - i2), k)


def vols(img: np.ndarray, k: int) -> np.ndarray:
    u = k * meanf(img, k)
    i1 = img.copy()
    i1[:-1, :] = img[1:, :]
    return meanf(img * i1 - u**2, k)


REFERENCES = {name: fn for name, fn in globals().items()
              if callable(fn) and name in (
                  "acmo bren cheb cont curv dcte dctm dctr eigv gder gllv glva glvm glvn grae "
                  "gras grat helm hise hisr lapd lape lapm lapv sfil sfrq teng tenv tenv_std "
                  "vola vols").split()}
