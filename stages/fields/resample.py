"""Band-limited resampling of a frame by a scale and shift (no rotation): a separable
windowed sinc; :func:`warp_frame`, any affine map onto the reference grid.

Why not :func:`cv2.warpAffine` with ``INTER_LANCZOS4`` for focus breathing: an 8-tap kernel
attenuates a frame's finest texture by an amount that depends on the sub-pixel phase of
each output pixel, and a frame magnified by ``s`` runs through every phase (a moiré of
period ``1 / |s - 1|`` px). The reference frame of an aligned stack is not resampled at
all, so after alignment it is the sharpest frame of the stack: a focus measure then pulls
heights toward its level (measured on the synthetic families with 1.2 %/frame breathing,
:func:`sffscan.stages.sim.families.family_stack`: up to 1.20 x the RMSE of the same stack
without breathing with the true transforms, the alignment's estimate being right to 0.1 %;
docs/depth-study.md). A Lanczos kernel of :data:`TAPS` lobes on each side keeps the passband
flat almost to the Nyquist frequency, so that every frame keeps its texture.

A scale-and-shift map is separable (``x' = s_x x + t_x``, ``y' = s_y y + t_y``): two sparse
1-D resampling matrices, one per axis, each row ``2 TAPS`` weights (borders replicated).
:class:`ScaleResampler` applies them as dense blocks of :data:`BLOCK` output rows or columns
against the band of input rows or columns they read, one BLAS product each: a 1280 x 1024
frame in 4-5.5 ms of one core (float32), against ~38 ms for the sparse products in float64
and 60-70 ms for :func:`cv2.warpAffine` with ``INTER_LANCZOS4`` (measured 2026-12-03, AMD EPYC
VM). The continuous scan's breathing correction resamples every frame this way
(:func:`sffscan.pipeline.metrology.optics_correction.unbreathe_frame`).
"""

from __future__ import annotations

import math
from typing import TYPE_CHECKING, NamedTuple

import cv2
import numpy as np
from sffscan.stages.fields.aperture import equalise_aperture

if TYPE_CHECKING:
    import scipy.sparse

__all__ = ["BLOCK", "TAPS", "ScaleResampler", "is_separable", "resample_matrix", "scale_warp",
           "warp_frame"]

TAPS = 8
"""Lobes of the Lanczos (windowed sinc) kernel on each side: 16 weights per output pixel
and axis; pixels within ``TAPS`` px of the frame's border see its replicated edge."""


def is_separable(matrix: np.ndarray, *, tol: float = 1e-12) -> bool:
    """Whether an affine (2, 3) map has no rotation or shear (a scale and shift per axis)."""
    m = np.asarray(matrix, dtype=np.float64)
    return abs(float(m[0, 1])) <= tol and abs(float(m[1, 0])) <= tol


def _weights(n_out: int, n_in: int, scale: float, shift: float, taps: int
             ) -> tuple[np.ndarray, np.ndarray]:
    """Input index (clamped) and weight of each output sample's ``2 taps`` terms,
    (n_out, 2 taps) each: the entries of :func:`resample_matrix`."""
    x = scale * np.arange(n_out, dtype=np.float64) + shift
    base = np.floor(x).astype(np.intp)
    offs = np.arange(-taps + 1, taps + 1)
    idx = base[:, None] + offs[None, :]
    d = x[:, None] - idx
    w = np.sinc(d) * np.sinc(d / taps)
    w[np.abs(d) >= taps] = 0.0
    w /= w.sum(axis=1, keepdims=True)
    return np.clip(idx, 0, n_in - 1), w


def resample_matrix(n_out: int, n_in: int, scale: float, shift: float, *, taps: int = TAPS
                    ) -> scipy.sparse.csr_matrix:
    """Sparse (n_out, n_in) matrix ``R`` with ``(R f)[i] = f(scale * i + shift)``.

    Lanczos-``taps`` weights, normalised to sum 1 per row (a constant stays constant), input
    indices outside ``0 .. n_in - 1`` clamped (replicated border). An integer position gets
    the single weight 1: an identity map is exact.
    """
    import scipy.sparse  # here only: the scan imports this module, and needs no sparse form

    cols, w = _weights(n_out, n_in, scale, shift, taps)
    rows = np.repeat(np.arange(n_out), cols.shape[1])
    return scipy.sparse.csr_matrix((w.ravel(), (rows, cols.ravel())), shape=(n_out, n_in))


BLOCK = 32
"""Output rows (columns) per dense block of :class:`ScaleResampler`: a block reads ~``BLOCK s
+ 2 TAPS`` input rows (~48), of which each output row weighs ``2 TAPS`` (16), so the dense
products do ~3x the sparse products' multiplications, in BLAS, and still take ~1/7 of their
time. Blocks of 32 against 64 (1280 x 1024 uint16 frame, one BLAS thread, 12 rounds
alternating, twice; 2026-12-03, AMD EPYC VM): 5.1-5.4 against 6.6-6.7 ms a frame, faster in
24 of 24 pairs, the same values bit for bit there; 24 about as fast as 32, 48 between,
128 slower (8.9 ms). An earlier, not interleaved, comparison had found 32 no faster."""


class _Band(NamedTuple):
    out0: int  # output rows (columns) [out0, out1)
    out1: int
    in0: int  # input rows (columns) [in0, in1) they read
    in1: int
    weights: np.ndarray  # (out1 - out0, in1 - in0)


def _bands(n: int, scale: float, shift: float, taps: int, block: int, dtype: type
           ) -> tuple[_Band, ...]:
    """:func:`resample_matrix` (n, n) cut into dense blocks of ``block`` rows, each over
    the columns its rows read."""
    cols, w = _weights(n, n, scale, shift, taps)
    bands = []
    for a in range(0, n, block):
        b = min(a + block, n)
        c, ww = cols[a:b], w[a:b]
        c0, c1 = int(c.min()), int(c.max()) + 1
        dense = np.zeros((b - a, c1 - c0))
        np.add.at(dense, (np.repeat(np.arange(b - a), c.shape[1]), (c - c0).ravel()),
                  ww.ravel())  # clamped border taps add up, as in the sparse matrix
        bands.append(_Band(a, b, c0, c1, dense.astype(dtype)))
    return tuple(bands)


class ScaleResampler:
    """:func:`resample_matrix` along both axes of (H, W) frames, prepared once, applied to
    many frames (the continuous scan resamples every frame of a focus level by the same
    map).

    Parameters
    ----------
    shape : (H, W)
        Frame shape, px.
    matrix : (2, 3) array_like
        Output px -> image px, no rotation or shear (:func:`is_separable`).
    taps : int, keyword-only
        Kernel lobes per side.
    dtype : numpy dtype, keyword-only
        Of the weights and the arithmetic: float32 (default) or float64.

    Notes
    -----
    The weights are :func:`resample_matrix`'s; each block of :data:`BLOCK` output columns
    (rows) is one matrix product with the band of input columns (rows) it reads. Per pixel
    the same sums as the sparse products, in another order (equal to round-off).
    """

    def __init__(self, shape: tuple[int, int], matrix: np.ndarray, *, taps: int = TAPS,
                 dtype: type = np.float32) -> None:
        m = np.asarray(matrix, dtype=np.float64)
        if not is_separable(m):
            raise ValueError(f"ScaleResampler needs a map without rotation or shear, got "
                             f"{m.tolist()}")
        h, w = (int(v) for v in shape)
        self.shape = (h, w)
        self.dtype = np.dtype(dtype)
        self._cols = _bands(w, m[0, 0], m[0, 2], taps, BLOCK, self.dtype.type)
        self._rows = _bands(h, m[1, 1], m[1, 2], taps, BLOCK, self.dtype.type)

    def buffers(self) -> tuple[np.ndarray, np.ndarray]:
        """Two arrays for :meth:`__call__`'s ``buffers``: a caller that resamples many frames
        keeps them (new 5 MB arrays each frame cost ~3.5 ms of page faults, measured)."""
        return np.empty(self.shape, self.dtype), np.empty(self.shape, self.dtype)

    def __call__(self, image: np.ndarray, *,
                 buffers: tuple[np.ndarray, np.ndarray] | None = None) -> np.ndarray:
        """The resampled frame, (H, W) of :attr:`dtype`, not clipped nor rounded.

        ``buffers`` (:meth:`buffers`, any resampler of the same shape and dtype): the
        intermediate and the result are written there (the result is ``buffers[1]``).

        Raises
        ------
        ValueError
            If ``image`` or a buffer is not of :attr:`shape` (or a buffer not of
            :attr:`dtype`).
        """
        img = np.asarray(image)
        if img.shape != self.shape:
            raise ValueError(f"image of shape {img.shape}, the resampler's is {self.shape}")
        if buffers is None:
            buffers = self.buffers()
        tmp, out = buffers
        for buf in buffers:
            if buf.shape != self.shape or buf.dtype != self.dtype:
                raise ValueError(f"buffers must be {self.dtype} of shape {self.shape}, got "
                                 f"{buf.dtype} {buf.shape}")
        if img.dtype == self.dtype:
            f = img
        else:  # converted into the result's array, free until the second pass
            f = out
            np.copyto(f, img, casting="unsafe")
        for b in self._cols:  # along the rows: tmp[:, out] = f[:, in] @ W.T
            np.matmul(f[:, b.in0:b.in1], b.weights.T, out=tmp[:, b.out0:b.out1])
        for b in self._rows:  # down the columns
            np.matmul(b.weights, tmp[b.in0:b.in1], out=out[b.out0:b.out1])
        return out


def scale_warp(image: np.ndarray, matrix: np.ndarray, *, taps: int = TAPS,
               aperture: bool = False, resampler: ScaleResampler | None = None,
               buffers: tuple[np.ndarray, np.ndarray] | None = None,
               dtype: np.dtype | type | None = None) -> np.ndarray:
    """``out(x, y) = image(matrix [x, y, 1])`` for a map without rotation or shear.

    Parameters
    ----------
    image : (H, W) array of uint8, uint16 or float
    matrix : (2, 3) array_like
        Output px -> image px; ``matrix[0, 1] == matrix[1, 0] == 0``.
    taps : int, keyword-only
        Kernel lobes per side.
    aperture : bool, keyword-only
        Also give the result the reference pixel's aperture
        (:func:`~sffscan.stages.fields.aperture.equalise_aperture`).
    resampler : ScaleResampler, optional, keyword-only
        Prepared for ``matrix`` and ``image``'s shape (reused over frames); made here if
        None, in float64 for a float64 image, else float32.
    buffers : (ndarray, ndarray), optional, keyword-only
        Work arrays reused over frames (:meth:`ScaleResampler.buffers`); the result is
        always a new array. ``image`` may be ``buffers[1]`` (a frame prepared there).
    dtype : numpy dtype, optional, keyword-only
        Of the result (default ``image``'s): an integer dtype rounds. For a frame of
        integer values held in a float array.

    Returns
    -------
    (H, W) array of ``image``'s dtype, clipped to the image's own range (the sinc's ringing
    must not push a 10-bit frame past its full scale; integers rounded).

    Raises
    ------
    ValueError
        If the map rotates or shears.
    """
    img = np.asarray(image)
    m = np.asarray(matrix, dtype=np.float64)
    if not is_separable(m):
        raise ValueError(f"scale_warp needs a map without rotation or shear, got {m.tolist()}")
    if resampler is None:
        resampler = ScaleResampler(img.shape, m, taps=taps,
                                   dtype=np.float64 if img.dtype == np.float64 else np.float32)
    lo, hi = float(img.min()), float(img.max())  # before: img may be the result's buffer
    out = resampler(img, buffers=buffers)
    if aperture:
        out = equalise_aperture(out, float(m[0, 0]), float(m[1, 1]))
    np.clip(out, lo, hi, out=out)
    to = np.dtype(img.dtype if dtype is None else dtype)
    if np.issubdtype(to, np.integer):
        np.rint(out, out=out)
    return out.astype(to)


def warp_frame(image: np.ndarray, matrix: np.ndarray, *, aperture: bool = True) -> np.ndarray:
    """Frame resampled onto the reference grid: ``out(x) = image(matrix [x, 1])``.

    :func:`scale_warp` for a scale and shift, else OpenCV's Lanczos; with ``aperture``, given
    the reference pixel's aperture (:mod:`~sffscan.stages.fields.aperture`; for a rotation
    or shear, with the magnification ``sqrt |det|``). Returns an array of ``image``'s shape
    and dtype, clipped to the frame's own range (the kernel's ringing must not push a 10-bit
    frame past its full scale); pixels mapping outside the frame replicate its border
    (:func:`~sffscan.stages.fields.align.align_stack` reports them as not valid).
    """
    if is_separable(matrix):
        return scale_warp(image, matrix, aperture=aperture)
    img = np.asarray(image)
    h, w = img.shape
    m = np.asarray(matrix, dtype=np.float64)
    out = cv2.warpAffine(img.astype(np.float64), m, (w, h),
                         flags=cv2.INTER_LANCZOS4 | cv2.WARP_INVERSE_MAP,
                         borderMode=cv2.BORDER_REPLICATE)
    if aperture:
        s = math.sqrt(abs(float(np.linalg.det(m[:, :2]))))
        out = equalise_aperture(out, s, s)
    np.clip(out, float(img.min()), float(img.max()), out=out)
    if np.issubdtype(img.dtype, np.integer):
        np.rint(out, out=out)
    return out.astype(img.dtype)
