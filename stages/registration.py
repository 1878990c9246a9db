"""Registration: phase correlation refines the speed-based frame positions.

The stage moves at constant commanded speed, but a real stage wobbles (stepper motor,
flexible coupling). Each frame's true position is its predicted position plus an unknown
wobble ``w_k`` (x, y). Two kinds of frame pairs measure differences of wobble:

- consecutive frames (k-1, k): large overlap, but one focus level apart (slightly
  different blur, so slightly biased);
- frames one staircase period apart (k-N, k): the same focus level, so the same blur of
  the same world points (unbiased), but a smaller overlap and only differences across N.

Each pair is measured by phase correlation of the two frames cropped to their predicted
overlap, first at a quarter of the resolution (robust: few pixels are in focus in any one
frame), then refined at half resolution around that estimate. All measurements in a
sliding window of frames go into one weighted least-squares solve for the wobble, with a
weak prior that the wobble has zero mean and anchors on the frames already emitted, so
chained biases cannot drift (SFF_NOTES section 4). A frame is emitted once the frame one
period after it has been measured (latency N + 1 frames).
"""

from __future__ import annotations

import collections
from collections.abc import Iterator
from dataclasses import dataclass

import cv2
import numpy as np

from pipeline.messages import PlacedFrame
from pipeline.runtime import Stage


def downsample(image: np.ndarray, *, factor: int) -> np.ndarray:
    """Area-average an image by an integer factor, float32 out, shape (H//f, W//f)."""
    if factor < 1:
        raise ValueError(f"factor must be >= 1, got {factor}")
    img = image.astype(np.float32, copy=False)
    if factor == 1:
        return img
    h, w = img.shape
    return cv2.resize(img, (w // factor, h // factor), interpolation=cv2.INTER_AREA)


def _dft_size_at_most(n: int) -> int:
    """Largest even size <= n with small prime factors (fast FFT)."""
    while n > 2 and (n % 2 or cv2.getOptimalDFTSize(n) != n):
        n -= 1
    return n


def phase_correlate(a: np.ndarray, b: np.ndarray) -> tuple[float, float, float]:
    """Translation of image b relative to image a by phase correlation.

    Both are multiplied by a Hann window; the peak of the normalised cross-power
    spectrum's inverse is located to sub-pixel precision with Foroosh et al.'s estimator
    (2002), c1 / (c1 + c0) along each axis, which suits the sinc-like peak better than a
    centroid. (cv2.phaseCorrelate was not used: with OpenCV 5.0 it reports shifts off by half
    a pixel whenever its DFT size is odd, and its centroid is biased.)

    Parameters
    ----------
    a, b : ndarray, float32, (h, w)

    Returns
    -------
    (sx, sy, peak)
        b(p) ~= a(p - s); ``peak`` is the correlation peak height (1 for identical images,
        near 0 for unrelated ones).
    """
    h, w = a.shape
    win = cv2.createHanningWindow((w, h), cv2.CV_32F)
    fa = np.fft.rfft2(a * win)
    fb = np.fft.rfft2(b * win)
    cross = fb * np.conj(fa)
    cross /= np.abs(cross) + 1e-12
    corr = np.fft.irfft2(cross, s=(h, w))
    py, px = np.unravel_index(int(np.argmax(corr)), corr.shape)
    c0 = float(corr[py, px])

    def subpixel(minus: float, plus: float) -> float:
        if plus > minus and plus > 0:
            return plus / (plus + c0)
        if minus > 0:
            return -minus / (minus + c0)
        return 0.0

    sx = px + subpixel(float(corr[py, (px - 1) % w]), float(corr[py, (px + 1) % w]))
    sy = py + subpixel(float(corr[(py - 1) % h, px]), float(corr[(py + 1) % h, px]))
    if sx > w / 2:
        sx -= w
    if sy > h / 2:
        sy -= h
    return sx, sy, c0


def measure_shift(
    a: np.ndarray,
    b: np.ndarray,
    *,
    predicted_px: tuple[float, float],
    scale: int,
    max_crop: int = 256,
    min_overlap: int = 24,
) -> tuple[float, float, float] | None:
    """Measure the position of frame b relative to frame a by phase correlation.

    Parameters
    ----------
    a, b : ndarray, float32, (h, w)
        The two frames, already reduced by ``scale``.
    predicted_px : (float, float)
        Predicted (x, y) position of b minus that of a, full-resolution px.
    scale : int
        Reduction factor of ``a`` and ``b`` (4 = quarter resolution).
    max_crop : int
        Largest crop edge used for the correlation, reduced px (centre of the overlap).
    min_overlap : int
        Smallest overlap (reduced px) worth measuring; smaller returns None.

    Returns
    -------
    (dx, dy, response) or None
        Measured relative position of b, full-resolution px, and the correlation peak
        response (0..1); None if the overlap is too small.
    """
    h, w = a.shape
    ix = int(round(predicted_px[0] / scale))
    iy = int(round(predicted_px[1] / scale))
    # In a's coordinates the overlap is [x0, x1) x [y0, y1); in b it is shifted by -(ix, iy).
    x0, x1 = max(0, ix), min(w, w + ix)
    y0, y1 = max(0, iy), min(h, h + iy)
    cw, ch = min(x1 - x0, max_crop), min(y1 - y0, max_crop)
    if cw < min_overlap or ch < min_overlap:
        return None
    cw, ch = _dft_size_at_most(cw), _dft_size_at_most(ch)
    x0 += (x1 - x0 - cw) // 2
    y0 += (y1 - y0 - ch) // 2
    crop_a = np.ascontiguousarray(a[y0:y0 + ch, x0:x0 + cw])
    crop_b = np.ascontiguousarray(b[y0 - iy:y0 - iy + ch, x0 - ix:x0 - ix + cw])
    sx, sy, peak = phase_correlate(crop_a, crop_b)
    # crop_b(p) = crop_a(p + r) for a true residual r, so the measured shift is -r.
    return (ix - sx) * scale, (iy - sy) * scale, peak


def measure_pair(
    a: tuple[np.ndarray, np.ndarray],
    b: tuple[np.ndarray, np.ndarray],
    *,
    predicted_px: tuple[float, float],
    scales: tuple[int, int] = (4, 2),
    min_response: float = 0.02,
) -> tuple[float, float] | None:
    """Coarse-to-fine relative position of b to a, full-resolution px, or None.

    ``a`` and ``b`` are (coarse, fine) reduced images at ``scales``. The fine estimate is
    rejected (coarse kept) if it moves by more than one coarse pixel.
    """
    coarse = measure_shift(a[0], b[0], predicted_px=predicted_px, scale=scales[0])
    if coarse is None or coarse[2] < min_response:
        return None
    fine = measure_shift(a[1], b[1], predicted_px=coarse[:2], scale=scales[1])
    if fine is None or fine[2] < min_response or max(
        abs(fine[0] - coarse[0]), abs(fine[1] - coarse[1])
    ) > scales[0]:
        return coarse[0], coarse[1]
    return fine[0], fine[1]


def solve_wobble(
    n: int,
    pairs: list[tuple[int, int, float, float, float]],
    anchors: dict[int, tuple[float, float]],
    *,
    prior_weight: float = 0.1,
    anchor_weight: float = 10.0,
) -> np.ndarray:
    """Least-squares wobble of ``n`` frames from pairwise differences.

    Parameters
    ----------
    n : int
        Number of frames (unknowns 0..n-1).
    pairs : list of (i, j, dx, dy, weight)
        Measured w_j - w_i = (dx, dy), px.
    anchors : dict
        Frame index -> (x, y) already decided; held with ``anchor_weight``.
    prior_weight : float
        Weight of the zero-mean prior on every w_k (ties the otherwise free offset).

    Returns
    -------
    ndarray, float64, (n, 2)
        Wobble estimate per frame, px.
    """
    rows = len(pairs) + n + len(anchors)
    mat = np.zeros((rows, n))
    rhs = np.zeros((rows, 2))
    r = 0
    for i, j, dx, dy, wt in pairs:
        mat[r, j], mat[r, i] = wt, -wt
        rhs[r] = (wt * dx, wt * dy)
        r += 1
    mat[r:r + n, :] = np.eye(n) * prior_weight
    r += n
    for k, (ax, ay) in anchors.items():
        mat[r, k] = anchor_weight
        rhs[r] = (anchor_weight * ax, anchor_weight * ay)
        r += 1
    sol, *_ = np.linalg.lstsq(mat, rhs, rcond=None)
    return np.asarray(sol)


@dataclass
class _Entry:
    index: int
    placed: PlacedFrame
    reduced: tuple[np.ndarray, np.ndarray]


class RegistrationStage(Stage):
    """Refines frame offsets; emits frames N + 1 frames late with corrected offsets."""

    name = "registration"

    def __init__(self, *, n_levels: int, scales: tuple[int, int] = (4, 2),
                 period_weight: float = 2.0) -> None:
        self.n_levels = n_levels
        self.scales = scales
        self.period_weight = period_weight
        self.window = 3 * n_levels + 4
        self._reset()
        self.pairs_measured = 0
        self.pairs_rejected = 0
        self.max_correction = 0.0
        self._sq_sum = 0.0
        self._emitted_total = 0

    def _reset(self) -> None:
        self._pass: int | None = None
        self._count = 0
        self._recent: collections.deque[_Entry] = collections.deque(maxlen=self.n_levels + 1)
        self._pending: collections.deque[_Entry] = collections.deque()
        self._pairs: list[tuple[int, int, float, float, float]] = []
        self._emitted: dict[int, tuple[float, float]] = {}

    def _measure(self, old: _Entry, new: _Entry, weight: float) -> None:
        pa, pb = old.placed.predicted_px, new.placed.predicted_px
        pred = (pb[0] - pa[0], pb[1] - pa[1])
        got = measure_pair(old.reduced, new.reduced, predicted_px=pred, scales=self.scales)
        if got is None:
            self.pairs_rejected += 1
            return
        self.pairs_measured += 1
        self._pairs.append((old.index, new.index, got[0] - pred[0], got[1] - pred[1], weight))

    def _emit_oldest(self) -> PlacedFrame:
        entry = self._pending.popleft()
        newest = self._count - 1
        lo = max(0, newest - self.window + 1)
        self._pairs = [p for p in self._pairs if p[0] >= lo]
        self._emitted = {k: v for k, v in self._emitted.items() if k >= lo}
        sol = solve_wobble(
            newest - lo + 1,
            [(i - lo, j - lo, dx, dy, w) for i, j, dx, dy, w in self._pairs],
            {k - lo: v for k, v in self._emitted.items()},
        )
        cx, cy = (float(v) for v in sol[entry.index - lo])
        self._emitted[entry.index] = (cx, cy)
        pf = entry.placed
        px, py = pf.predicted_px
        self.max_correction = max(self.max_correction, abs(cx), abs(cy))
        self._sq_sum += cx * cx + cy * cy
        self._emitted_total += 1
        return PlacedFrame(pf.header, pf.image, pf.predicted_px,
                           (round(px + cx), round(py + cy)), (cx, cy))

    def process(self, item: PlacedFrame) -> Iterator[PlacedFrame]:
        if self._pass is not None and item.header.pass_index != self._pass:
            yield from self.finish()
            self._reset()
        self._pass = item.header.pass_index
        entry = _Entry(self._count, item, tuple(  # type: ignore[arg-type]
            downsample(item.image, factor=s) for s in self.scales))
        self._count += 1
        if self._recent:
            self._measure(self._recent[-1], entry, 1.0)
        if len(self._recent) >= self.n_levels:
            old = self._recent[-self.n_levels]
            if old.placed.header.focus_index == item.header.focus_index:
                self._measure(old, entry, self.period_weight)
        self._recent.append(entry)
        self._pending.append(entry)
        while len(self._pending) > self.n_levels + 1:
            yield self._emit_oldest()

    def finish(self) -> Iterator[PlacedFrame]:
        while self._pending:
            yield self._emit_oldest()

    def extra_stats(self) -> dict[str, float]:
        n = max(self._emitted_total, 1)
        return {
            "pairs_measured": self.pairs_measured,
            "pairs_rejected": self.pairs_rejected,
            "max_correction_px": round(self.max_correction, 2),
            "rms_correction_px": round(float(np.sqrt(self._sq_sum / n)), 2),
        }
