"""The sums of a focus curve (its first DFT harmonic), the confidence, and the depth methods
that need nothing else (SFF_NOTES.md section 3).

Every depth method returns the same confidence map

    confidence = |H_1| / H_0,   H_1 = sum_k y_k exp(-2 pi i k / N),   H_0 = sum_k y_k,

i.e. the relative strength of the first DFT harmonic: about 1 for a single narrow peak,
near 0 for a flat or noisy curve; set to 0 where ``H_0 <= 0`` and clipped to [0, 1].

The methods of :data:`STREAMING_METHODS` need only the sums ``harmonic_table(N) @ y``
(H_0, sum k y, Re H_1, Im H_1) and each curve's argmax: a streaming accumulator keeps them
as the levels arrive (:func:`depth_from_harmonics`), without an N-level volume. The public
names are also those of :mod:`sffscan.stages.depth`.
"""

from __future__ import annotations

import math
from collections.abc import Iterator

import numpy as np
import numpy.typing as npt
from sffscan.stages.depth_levels import check_odd_size, median_filter_levels

__all__ = [
    "STREAMING_METHODS",
    "STRIP_PIXELS",
    "blas_view",
    "confidence_from_sums",
    "curve_moments",
    "depth_from_harmonics",
    "depth_from_sums",
    "focus_confidence",
    "focus_sums",
    "harmonic_table",
    "magnitude",
    "pc_depth",
    "spc_depth",
    "strip_sums",
    "volume_strips",
]

STREAMING_METHODS = ("argmax", "centroid", "pc", "spc")
"""Methods that need only the sums of :func:`harmonic_table` and the argmax of each curve
(:func:`depth_from_harmonics`), so a streaming accumulator needs no N-level volume."""

STRIP_PIXELS = 4096
"""Pixels per strip of :func:`volume_strips`: N = 50 float32 levels of 4096 pixels are
800 KiB, which stay in cache."""


def magnitude(x: npt.ArrayLike, y: npt.ArrayLike) -> np.ndarray:
    """``sqrt(x^2 + y^2)`` element by element: ``|H_1|`` from Re H_1 and Im H_1, a
    gradient's size.

    Squares, a sum and a square root, each numpy's exact elementwise loop, so that a value
    never depends on where it lies in the array (a scan's block is bit for bit the same
    whatever its bands, threads or processes). Why not ``np.hypot``: its float32 loop took
    0.73 ms on a scan block's 1040 x 128 values against 0.095 ms for these three (2-core
    AMD VM, 2026-12-06), three times a block in the depth stage. ``cv2.magnitude`` (0.035
    ms) was tried and dropped: its vectorised body and scalar tail round differently, so
    the same pixel's value changed with the band's rows (tests/pipeline/test_band_processes.py).
    Within 2 units in the last place of ``np.hypot`` (1 on a block's values, measured),
    without its guard against overflow, which sums of focus values and gradients of levels
    are far from (float32 overflows past 1.8e19). NaN and infinities as ``np.hypot``, but
    for an infinity beside a NaN (NaN here).

    Parameters
    ----------
    x, y : array_like of float
        Broadcast as numpy does (integers go to ``np.hypot``).

    Returns
    -------
    ndarray
        Their float type (a new array).
    """
    xa, ya = np.asarray(x), np.asarray(y)
    if not (np.issubdtype(xa.dtype, np.floating) and np.issubdtype(ya.dtype, np.floating)):
        return np.asarray(np.hypot(xa, ya))
    out = np.asarray(np.multiply(xa, xa) + np.multiply(ya, ya))
    return np.sqrt(out, out=out)


def harmonic_table(n_levels: int) -> np.ndarray:
    """``(4, N)`` float64 weights of the curve sums: 1, k, cos(2 pi k / N), -sin(2 pi k / N).

    ``table @ y`` gives H_0 = sum y, sum k y, Re H_1 and Im H_1 of a focus curve ``y``; a
    streaming accumulator adds ``table[:, k] * y_k`` as level ``k`` arrives.
    """
    k = np.arange(n_levels, dtype=np.float64)
    theta = 2.0 * np.pi * k / n_levels
    return np.stack((np.ones(n_levels), k, np.cos(theta), -np.sin(theta)))


def curve_moments(vol: np.ndarray) -> np.ndarray:
    """``(4, H, W)`` float64: H_0 = sum y, sum k y, Re H_1, Im H_1 of every focus curve.

    One matrix product with the ``(4, N)`` :func:`harmonic_table`, accumulated in float64
    (float32 accumulation costs up to ~1e-3 levels of PC phase on curves whose first harmonic
    is weak). Done over blocks of rows so the float64 copy of the volume stays in cache; a
    strided view (a block of a ring buffer) is read in place.
    """
    n, height, width = vol.shape
    table = harmonic_table(n)
    out = np.empty((4, height * width), dtype=np.float64)
    rows = max(1, max(256, (1 << 17) // n) // max(1, width))  # ~1 MiB of float64 (L2)
    buf = np.empty((n, min(rows, height) * width), dtype=np.float64)
    for i in range(0, height, rows):
        r = min(rows, height - i)
        np.copyto(buf[:, :r * width].reshape(n, r, width), vol[:, i:i + r])
        np.matmul(table, buf[:, :r * width], out=out[:, i * width:(i + r) * width])
    return out.reshape((4, height, width))


def confidence_from_sums(h0: np.ndarray, re: np.ndarray, im: np.ndarray) -> np.ndarray:
    """``|H_1| / H_0`` clipped to [0, 1], 0 where ``H_0 <= 0``; float32."""
    positive = h0 > 0
    confidence = magnitude(re, im) / np.where(positive, h0, 1.0)
    return np.clip(np.where(positive, confidence, 0.0), 0.0, 1.0).astype(np.float32)


def focus_confidence(volume: np.ndarray) -> np.ndarray:
    """The confidence every method of :func:`sffscan.stages.depth.depth_from_focus` returns,
    alone.

    The three sums come from a float32 matrix product (numpy's BLAS; 3x faster than
    ``cv2.gemm`` on these shapes, measured) over chunks of ~4096 pixels copied out of the
    (strided) volume: faster than :func:`curve_moments`' float64 product, and within 1e-7 of
    it for N = 50 (a confidence needs no more; the phase methods do).

    Parameters
    ----------
    volume : (N, H, W) ndarray of float32
        Focus volume (finite; not checked), e.g. a strided view of a ring buffer.

    Returns
    -------
    (H, W) ndarray of float32
        ``|H_1| / H_0`` in [0, 1] (0 where ``H_0 <= 0``).
    """
    h0, re, im = focus_sums(volume)
    return confidence_from_sums(h0, re, im)


def focus_sums(volume: np.ndarray) -> np.ndarray:
    """``(3, H, W)`` float32: H_0, Re H_1 and Im H_1 of every curve (the sums of
    :func:`focus_confidence`: float32 products over strips of rows, :func:`strip_sums`)."""
    n, height, width = volume.shape
    table = harmonic_table(n)[[0, 2, 3]].astype(np.float32)
    sums = np.empty((3, height, width), np.float32)
    vol = blas_view(volume)
    rows = max(1, STRIP_PIXELS // max(1, width))
    for r0 in range(0, height, rows):
        strip_sums(table, vol[:, r0:r0 + rows], out=sums[:, r0:r0 + rows])
    return sums


def blas_view(volume: np.ndarray) -> np.ndarray:
    """``volume`` itself if float32 with positive strides, columns adjacent (a block of a
    ring buffer), else a C-ordered float32 copy."""
    if volume.dtype != np.float32 or volume.strides[-1] != 4 or any(
            st <= 0 or st % 4 for st in volume.strides):
        return np.ascontiguousarray(volume, dtype=np.float32)
    return volume


def strip_sums(table: np.ndarray, block: np.ndarray, *, out: np.ndarray) -> None:
    """``out[:, i, j] = table @ block[:, i, j]``: the curve sums of a strip of rows.

    Float32 BLAS products. Where the width is a multiple of 16 (the scan's blocks) the strip
    is read in place (a block of a ring: no copy), one product of the ``(S, N)`` table with
    the ``(N, W)`` levels per row; else the strip is copied into one ``(N, rows W)`` matrix
    first, as :func:`volume_strips` does. OpenBLAS (this machine's numpy, AMD EPYC) sums
    each pixel over its levels in the same order in both cases when the width is a
    multiple of 16 (N = 3..200, 1386 shapes, one thread or two, checked), not always
    otherwise (the columns its kernels leave to the end of a product), hence the rule:
    the sums are those of the copied strips either way (another BLAS could round the
    two differently).
    :func:`focus_sums` and :func:`sffscan.stages.depth_adaptive.adaptive_block` both take their
    sums from here, over the same strips, so they agree bit for bit on any machine.

    Parameters
    ----------
    table : (S, N) ndarray of float32
        Weights (rows of :func:`harmonic_table`).
    block : (N, r, W) ndarray of float32
        Levels of the strip; positive strides, columns adjacent (:func:`blas_view`).
    out : (S, r, W) ndarray of float32, keyword-only
        Receives the sums.
    """
    n, rows, width = block.shape
    if width % 16 == 0:
        np.matmul(table, block.transpose(1, 0, 2), out=out.transpose(1, 0, 2))
    else:
        flat = np.ascontiguousarray(block).reshape(n, rows * width)
        out[...] = np.matmul(table, flat).reshape(out.shape)


def volume_strips(volume: np.ndarray) -> Iterator[tuple[int, int, np.ndarray]]:
    """The volume in strips of whole rows, about :data:`STRIP_PIXELS` pixels each, each
    copied into one C-ordered ``(N, P)`` float32 buffer (reused: a strip is valid until the
    next is yielded): ``(first pixel, end pixel, strip)``, pixels counted row by row.

    A strided volume (a block of a ring buffer) is read once, in pieces that stay in cache
    for whatever the caller does with each strip.
    """
    n, height, width = volume.shape
    rows = max(1, STRIP_PIXELS // max(1, width))
    buf = np.empty((n, min(rows, height) * width), np.float32)
    for i in range(0, height, rows):
        r = min(rows, height - i)
        strip = buf[:, :r * width]
        np.copyto(strip.reshape(n, r, width), volume[:, i:i + r])
        yield i * width, (i + r) * width, strip


def _wrap(x: np.ndarray, n: int) -> np.ndarray:
    """``x mod n`` in [0, n) (``np.mod`` can round a tiny negative ``x`` up to exactly ``n``)."""
    out = np.mod(x, float(n))
    out[out >= n] -= n
    return out


def spc_depth(re: np.ndarray, im: np.ndarray, centre: np.ndarray, *, n_levels: int
              ) -> np.ndarray:
    """SPC's depth (float32 fractional levels) from each curve's first harmonic and its
    filtered argmax, as :func:`depth_from_sums` computes it for ``"spc"``.

    Parameters
    ----------
    re, im : (H, W) ndarray of float
        Re H_1 and Im H_1 (:func:`harmonic_table`'s last two rows times the curve).
    centre : (H, W) ndarray of int
        The argmax median filtered as for SPC (``a_med``), levels.
    n_levels : int, keyword-only
        N.
    """
    # the shift s = round(N/2) - a_med that would move the filtered argmax to the
    # centre (MATLAB's round: halves away from zero, round(N/2) = (N + 1) // 2)
    s = (n_levels + 1) // 2 - np.asarray(centre)
    depth = _wrap(_phase_levels(re, im, n_levels) + s, n_levels) - s
    return depth.astype(np.float32, copy=False)


def _phase_levels(re: np.ndarray, im: np.ndarray, n: int) -> np.ndarray:
    """The first harmonic's phase in levels, ``-angle(H_1) N / (2 pi)``."""
    return np.arctan2(im, re) * (-n / (2.0 * math.pi))


def pc_depth(re: np.ndarray, im: np.ndarray, *, n_levels: int) -> np.ndarray:
    """PC's depth (fractional levels in [0, N)) from each curve's first harmonic, as
    :func:`depth_from_sums` computes it for ``"pc"``: ``-angle(H_1) N / (2 pi) mod N``.

    Parameters
    ----------
    re, im : (H, W) ndarray of float
        Re H_1 and Im H_1 (:func:`harmonic_table`'s last two rows times the curve).
    n_levels : int, keyword-only
        N.
    """
    return _wrap(_phase_levels(re, im, n_levels), n_levels)


def depth_from_sums(h0: np.ndarray, hk: np.ndarray, re: np.ndarray, im: np.ndarray,
                    argmax: np.ndarray | None, *, n_levels: int, method: str,
                    median_size: int) -> np.ndarray:
    """Depth of a method of :data:`STREAMING_METHODS` from checked sums and argmax.

    The core of :func:`depth_from_harmonics` (documented there) without its checks: ``h0``,
    ``hk``, ``re``, ``im`` are the four rows of ``harmonic_table(N) @ y``; ``argmax`` is
    an intp map (None for ``"pc"`` only). Returns float32 fractional levels, (H, W).
    """
    n = n_levels
    positive = h0 > 0
    if method == "pc":
        depth = pc_depth(re, im, n_levels=n)
    elif method == "spc":
        assert argmax is not None
        depth = spc_depth(re, im, median_filter_levels(argmax, median_size, n), n_levels=n)
    else:
        assert argmax is not None
        if method == "argmax":
            depth = argmax.astype(np.float32)
        else:  # centroid
            depth = np.where(positive, hk / np.where(positive, h0, 1.0), argmax)
    return depth.astype(np.float32, copy=False)


def depth_from_harmonics(
    sums: np.ndarray, argmax: np.ndarray | None, *, n_levels: int, method: str = "spc",
    median_size: int = 11,
) -> tuple[np.ndarray, np.ndarray]:
    """Depth and confidence from each curve's sums and argmax, without the curves.

    What :func:`sffscan.stages.depth.depth_from_focus` computes for the methods in
    :data:`STREAMING_METHODS`, from the quantities a streaming accumulator can keep as the
    levels arrive one by one: ``sums = harmonic_table(N) @ y`` and the index of the curve's
    (first) maximum.

    Parameters
    ----------
    sums : (4, H, W) ndarray of float
        H_0 = sum y, sum k y, Re H_1, Im H_1 of every pixel's curve (see
        :func:`harmonic_table`). Computed in float32 when given float32 (sums accumulated
        in float32 hold no more than that), else in float64.
    argmax : (H, W) ndarray of int, or None
        Level of each curve's first maximum, 0..N-1; may be None for ``"pc"`` only.
    n_levels : int, keyword-only
        Number of focus levels N >= 3.
    method : {"argmax", "centroid", "pc", "spc"}, keyword-only
        As in :func:`sffscan.stages.depth.depth_from_focus`.
    median_size : int, keyword-only
        Odd SPC median-filter size, as in :func:`sffscan.stages.depth.depth_from_focus`.

    Returns
    -------
    depth, confidence : (H, W) ndarray of float32
        As :func:`sffscan.stages.depth.depth_from_focus`: fractional levels, and
        ``|H_1| / H_0`` in [0, 1].

    Raises
    ------
    ValueError
        Unknown ``method`` (or one that needs the curve), bad ``median_size``, N < 3, shapes
        that do not match, non-finite sums, or a missing ``argmax``.
    """
    if method not in STREAMING_METHODS:
        raise ValueError(f"method must be one of {STREAMING_METHODS}, got {method!r}")
    median_size = check_odd_size(median_size, name="median_size", minimum=1)
    if n_levels < 3:
        raise ValueError(f"n_levels must be at least 3, got {n_levels}")
    sums = np.asarray(sums)
    if sums.dtype != np.float32:
        sums = sums.astype(np.float64)
    if sums.ndim != 3 or sums.shape[0] != 4:
        raise ValueError(f"sums must be (4, H, W), got shape {sums.shape}")
    if not np.isfinite(sums).all():
        raise ValueError("sums contain NaN or inf")
    a = None
    if argmax is not None:
        a = np.asarray(argmax)
        if a.shape != sums.shape[1:]:
            raise ValueError(f"argmax shape {a.shape} differs from the sums' {sums.shape[1:]}")
        a = a.astype(np.intp, copy=False)
    elif method != "pc":
        raise ValueError(f"method {method!r} needs the argmax of every curve")
    h0, hk, re, im = sums
    confidence = confidence_from_sums(h0, re, im)
    return depth_from_sums(h0, hk, re, im, a, n_levels=n_levels, method=method,
                           median_size=median_size), confidence
