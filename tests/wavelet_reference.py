"""Independent float64 numpy references of the toolbox's wavelet focus measures (WAVS,
WAVV, WAVR of ``focusmeasure.m``), written from MATLAB's algorithms, without PyWavelets.

- the db6 filters from Daubechies' construction (the roots of ``P(y) = sum_k
  C(N - 1 + k, k) y^k`` mapped inside the unit circle, times ``(1 + z)^N``; MATLAB's
  ``dbwavf`` / ``orthfilt``): ``Lo_R`` normalised to sum sqrt(2), ``Lo_D = wrev(Lo_R)``,
  ``Hi_R = qmf(Lo_R)`` (reversed, every second sign changed), ``Hi_D = wrev(Hi_R)``;
- ``dwt2`` as MATLAB's: each axis extended by ``lf - 1`` half-point symmetric samples
  (``wextend`` 'sym'), convolved ``'valid'`` (an explicit sum over the taps), the samples
  2, 4, ... (1-based) kept;
- ``upsconv2`` as MATLAB's: ``dyadup(x, 0)`` (a zero after every coefficient but the
  last), full convolution, then ``wkeep2(., s, 'c')``: the central ``s``, ``floor`` of the
  surplus dropped at the start;
- ``wrcoef2``: details ``upsconv2`` with ``{Hi_R, Lo_R}`` ('h'), ``{Lo_R, Hi_R}`` ('v'),
  ``{Hi_R, Hi_R}`` ('d'); approximations of level n from ``appcoef2`` (the level-L
  approximation brought up to level n by ``idwt2`` = the sum of the four branches'
  ``upsconv2``), then n ``upsconv2`` steps with ``{Lo_R, Lo_R}`` down to the image's size.
"""

from __future__ import annotations

import math

import numpy as np

from tests.fm_reference import meanf, stdfilt2


def daubechies_filters(n: int = 6) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """``Lo_D, Hi_D, Lo_R, Hi_R`` of ``dbN`` (MATLAB's ``wfilters('dbN')``)."""
    p = [math.comb(n - 1 + k, k) for k in range(n)]  # P(y), increasing powers
    zeros = []
    for y in np.roots(p[::-1]):
        # y = (1 - (z + 1/z) / 2) / 2  ->  z^2 - (2 - 4y) z + 1 = 0; the root inside
        r = np.roots([1.0, -(2.0 - 4.0 * y), 1.0])
        zeros.append(r[np.argmin(np.abs(r))])
    poly = np.real(np.poly(np.concatenate([-np.ones(n), zeros])))
    lo_r = math.sqrt(2.0) * poly / poly.sum()
    hi_r = lo_r[::-1].copy()
    hi_r[1::2] *= -1.0
    return lo_r[::-1].copy(), hi_r[::-1].copy(), lo_r, hi_r


LO_D, HI_D, LO_R, HI_R = daubechies_filters(6)


def _convolve(x: np.ndarray, f: np.ndarray, axis: int, *, full: bool) -> np.ndarray:
    """``conv`` along ``axis``: ``y[i] = sum_j f[j] x[i - j]``, 'valid' or 'full'."""
    x = np.moveaxis(x, axis, -1)
    lf, n = len(f), x.shape[-1]
    if full:
        x = np.concatenate([np.zeros((*x.shape[:-1], lf - 1)), x,
                            np.zeros((*x.shape[:-1], lf - 1))], axis=-1)
        n = x.shape[-1]
    m = n - lf + 1
    out = np.zeros((*x.shape[:-1], m))
    for j in range(lf):
        out += f[j] * x[..., lf - 1 - j:lf - 1 - j + m]
    return np.moveaxis(out, -1, axis)


def dwt_axis(x: np.ndarray, f: np.ndarray, axis: int) -> np.ndarray:
    """One analysis filter of MATLAB's ``dwt`` / ``dwt2`` ('sym' mode) along ``axis``."""
    lf = len(f)
    pad = [(0, 0)] * x.ndim
    pad[axis] = (lf - 1, lf - 1)
    y = _convolve(np.pad(x, pad, mode="symmetric"), f, axis, full=False)
    return np.take(y, np.arange(1, y.shape[axis], 2), axis=axis)


def dwt2(x: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """MATLAB's ``[a, h, v, d] = dwt2(x, 'db6')``: 'h' low-pass along the rows (x),
    high-pass along the columns (y)."""
    lo = dwt_axis(x, LO_D, 1)
    hi = dwt_axis(x, HI_D, 1)
    return (dwt_axis(lo, LO_D, 0), dwt_axis(lo, HI_D, 0), dwt_axis(hi, LO_D, 0),
            dwt_axis(hi, HI_D, 0))


def upsconv2(x: np.ndarray, f_rows: np.ndarray, f_cols: np.ndarray,
             size: tuple[int, int], *, ceil_first: bool = False) -> np.ndarray:
    """MATLAB's ``upsconv2(x, {F1, F2}, s)``: ``F1`` along the columns' direction (y),
    ``F2`` along the rows (x), then the central ``size`` (``ceil_first``: the other
    rounding of an odd surplus, which MATLAB does not use; for the tests)."""
    y = x
    for axis, f in ((0, f_rows), (1, f_cols)):
        m = y.shape[axis]
        shape = list(y.shape)
        shape[axis] = 2 * m - 1
        up = np.zeros(shape)
        idx = [slice(None)] * 2
        idx[axis] = slice(0, None, 2)
        up[tuple(idx)] = y
        y = _convolve(up, f, axis, full=True)
    first = [(y.shape[i] - size[i] + ceil_first) // 2 for i in range(2)]  # 1 + floor(d)
    return y[first[0]:first[0] + size[0], first[1]:first[1] + size[1]]


Level = tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]


def wavedec2(x: np.ndarray, level: int) -> tuple[list[Level], list[tuple]]:
    """The level-``level`` decomposition: ``[(a, h, v, d)]`` per level (1 first) and the
    bookkeeping sizes (the image's first, then each level's)."""
    out, sizes, a = [], [x.shape], x
    for _ in range(level):
        a, h, v, d = dwt2(a)
        out.append((a, h, v, d))
        sizes.append(a.shape)
    return out, sizes


def idwt2(a: np.ndarray, h: np.ndarray, v: np.ndarray, d: np.ndarray,
          size: tuple[int, int], *, ceil_first: bool = False) -> np.ndarray:
    out = np.zeros(size)
    for c, f1, f2 in ((a, LO_R, LO_R), (h, HI_R, LO_R), (v, LO_R, HI_R), (d, HI_R, HI_R)):
        out += upsconv2(c, f1, f2, size, ceil_first=ceil_first)
    return out


def wrcoef2(kind: str, dec: list[Level], sizes: list[tuple], n: int) -> np.ndarray:
    """MATLAB's ``wrcoef2(kind, C, S, 'db6', n)`` of the decomposition ``dec``."""
    top = len(dec)
    if kind == "a":
        x = dec[top - 1][0]  # appcoef2: from the deepest level up to level n
        for lev in range(top, n, -1):
            _, h, v, d = dec[lev - 1]
            x = idwt2(x, h, v, d, sizes[lev - 1])
        f1 = f2 = LO_R
    else:
        x = dec[n - 1][{"h": 1, "v": 2, "d": 3}[kind]]
        f1, f2 = {"h": (HI_R, LO_R), "v": (LO_R, HI_R), "d": (HI_R, HI_R)}[kind]
    x = upsconv2(x, f1, f2, sizes[n - 1])
    for p in range(2, n + 1):
        x = upsconv2(x, LO_R, LO_R, sizes[n - p])
    return x


def wavs(img: np.ndarray, k: int) -> np.ndarray:
    dec, sizes = wavedec2(img, 1)
    h, v, d = (wrcoef2(c, dec, sizes, 1) for c in "hvd")
    return meanf(np.abs(h) + np.abs(v) + np.abs(d), k)


def wavv(img: np.ndarray, k: int) -> np.ndarray:
    dec, sizes = wavedec2(img, 1)
    h, v, d = (np.abs(wrcoef2(c, dec, sizes, 1)) for c in "hvd")
    return stdfilt2(h, k) + stdfilt2(v, k) + stdfilt2(d, k)


def wavr(img: np.ndarray, k: int) -> np.ndarray:
    dec, sizes = wavedec2(img, 3)
    h, v, d = (np.abs(wrcoef2(c, dec, sizes, 1)) for c in "hvd")
    a = sum(np.abs(wrcoef2("a", dec, sizes, n)) for n in (1, 2, 3))
    return meanf(h**2 + v**2 + d**2, k) / meanf(a**2, k)


WAVELET_REFERENCES = {"wavs": wavs, "wavv": wavv, "wavr": wavr}
