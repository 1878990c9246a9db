"""Registration: phase correlation at quarter resolution refines the speed-based positions.

The stage moves at constant commanded speed, but a real stage wobbles (stepper motor,
flexible coupling). Each frame's true position is its predicted position plus an unknown
wobble ``w_k`` (x, y). Pairs of frames measure differences of wobble:

- frames a few frames apart (k-1, k-2): large overlap, but different focus levels, so
  the in-focus content differs a little (slightly biased);
- frames one staircase period apart (k-N, k): the same focus level, so the same blur of
  the same world points (unbiased), but a smaller overlap and only differences across N.

Each pair is measured by phase correlation of the two frames, reduced to a quarter of
their resolution and cropped to their predicted overlap (SFF_NOTES section 4: at full
resolution few pixels are in focus in any one frame; measured here, half and full
resolution gave 0.4-1.1 px errors on pairs at different focus levels where a quarter gave
0.11 px). All measurements in a sliding window go into one least-squares solve for the
wobble, with a weak prior that the wobble has zero mean and anchors on the frames already
emitted, so chained biases cannot drift. A frame is emitted once the frame one period
after it has been measured (latency N + 1 frames). A pair is measured only if its
correlation is significant (:func:`sffscan.stages.phase_correlation.is_significant`:
featureless crops, and scenes with several equal peaks, are refused rather than measured
as noise). Measured on the default optics with a ±3 px wobble against the simulator's
truth, pairs at lags 1, 2 and N: 0.22 / 0.21 px RMS x / y (0.33 / 0.27 with five pairs
before the crops' mean was removed; bench/results/registration_accuracy.md).

Cost: for the short lags (predicted shift under a tenth of the width, none across) the
new frame's crop is a fixed central box, so its windowed spectrum is computed once and
shared by all its short-lag pairs; the old frame's crop is the same world area by the
prediction (the crops stay aligned, so the phase correlation measures only the residual,
as :func:`measure_shift` does). The period pair crops to its overlap. Integer frames are
reduced by exact integer sums.
"""

from __future__ import annotations

import collections
from collections.abc import Iterator
from dataclasses import dataclass

import cv2
import numpy as np
from sffscan.stages.bands import BandWorkers, row_bands
from sffscan.stages.messages import PlacedFrame
from sffscan.stages.phase_correlation import (
    correlate_spectra,
    is_significant,
    phase_correlate,
    windowed_spectrum,
)
from sffscan.stages.protocol import Stage


def downsample(image: np.ndarray, *, factor: int) -> np.ndarray:
    """Area-average an image by an integer factor, float32 out, shape (H//f, W//f).

    uint8 / uint16 images whose sides divide by ``factor`` sum each group of ``factor``
    rows exactly in integers first (contiguous rows, a quarter of the float32 traffic),
    then average along the rows with ``cv2.resize(..., INTER_AREA)``: the same values as
    the area resize of the whole float32 image, without its float32 copy. When ``factor``
    is a power of two, every ``factor`` x ``factor`` block is summed in 16-bit integers
    (OpenCV's saturating adds, one pass over the frame) and scaled once: the same float32
    values again (the sums are exact and the scale is a power of two), about twice as fast;
    a block whose sum could have saturated (a sum reaching 65535, possible with 16-bit
    data) sends the image down the exact 32-bit path instead.
    """
    if factor < 1:
        raise ValueError(f"factor must be >= 1, got {factor}")
    h, w = image.shape
    top = np.iinfo(image.dtype).max if image.dtype in (np.uint8, np.uint16) else None
    if factor > 1 and top is not None and h % factor == 0 and w % factor == 0:
        if factor & (factor - 1) == 0:
            out = _block_sum16(image, factor)
            if out is not None:
                return np.multiply(out, np.float32(1.0 / (factor * factor)), dtype=np.float32)
        acc = np.uint16 if factor * top < 1 << 16 else np.uint32
        rows = image[0::factor].astype(acc)
        for i in range(1, factor):
            np.add(rows, image[i::factor], out=rows)
        out = cv2.resize(rows.astype(np.float32), (w // factor, h // factor),
                         interpolation=cv2.INTER_AREA)
        return np.multiply(out, np.float32(1.0 / factor), dtype=np.float32)
    img = image.astype(np.float32, copy=False)
    if factor == 1:
        return img
    return cv2.resize(img, (w // factor, h // factor), interpolation=cv2.INTER_AREA)


def _block_sum16(image: np.ndarray, factor: int) -> np.ndarray | None:
    """Sums of the ``factor`` x ``factor`` blocks of a uint8/uint16 image as uint16 (pairwise
    saturating adds: rows, then columns); None if any sum reached 65535 (saturation sticks
    at 65535, so a result below it everywhere is exact)."""

    def tree(parts: list[np.ndarray], dtype: int) -> np.ndarray:
        while len(parts) > 1:
            parts = [cv2.add(parts[i], parts[i + 1], dtype=dtype)
                     for i in range(0, len(parts), 2)]
        return parts[0]

    rows = tree([image[i::factor] for i in range(factor)], cv2.CV_16U)
    out = tree([rows[:, i::factor] for i in range(factor)], cv2.CV_16U)
    if int(out.max()) >= np.iinfo(np.uint16).max:
        return None
    return out


def _dft_size_at_most(n: int) -> int:
    """Largest even size <= n with small prime factors (fast FFT)."""
    while n > 2 and (n % 2 or cv2.getOptimalDFTSize(n) != n):
        n -= 1
    return n


def measure_shift(
    a: np.ndarray,
    b: np.ndarray,
    *,
    predicted_px: tuple[float, float],
    scale: int,
    max_crop: int = 256,
    min_overlap: int = 24,
    false_alarm: float | None = None,
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
    false_alarm : float or None
        If given, a correlation that is not significant at this rate
        (:func:`sffscan.stages.phase_correlation.is_significant`: a peak unrelated crops
        could reach, or one no higher than its runner-up by more than noise) returns None.

    Returns
    -------
    (dx, dy, response) or None
        Measured relative position of b, full-resolution px, and the correlation peak
        response (0..1); None if the overlap is too small or the peak is not significant.
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
    crop_a = a[y0:y0 + ch, x0:x0 + cw]
    crop_b = b[y0 - iy:y0 - iy + ch, x0 - ix:x0 - ix + cw]
    sx, sy, peak, _ = c = phase_correlate(crop_a, crop_b)
    if false_alarm is not None and not is_significant(c, (ch, cw), false_alarm=false_alarm):
        return None
    # crop_b(p) = crop_a(p + r) for a true residual r, so the measured shift is -r.
    return (ix - sx) * scale, (iy - sy) * scale, peak


def solve_wobble(
    n: int,
    pairs: list[tuple[int, int, float, float, float]] | np.ndarray,
    anchors: dict[int, tuple[float, float]],
    *,
    prior_weight: float = 0.2,
    anchor_weight: float = 10.0,
) -> np.ndarray:
    """Least-squares wobble of ``n`` frames from pairwise differences.

    Parameters
    ----------
    n : int
        Number of frames (unknowns 0..n-1).
    pairs : list of (i, j, dx, dy, weight), or an (M, 5) array of them
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
    # normal equations, assembled directly: every row touches one or two unknowns
    ata = np.eye(n) * prior_weight**2
    atb = np.zeros((n, 2))
    if len(pairs):
        p = np.asarray(pairs, dtype=np.float64)
        i, j = p[:, 0].astype(np.intp), p[:, 1].astype(np.intp)
        w2 = p[:, 4] ** 2
        d = p[:, 2:4] * w2[:, None]
        flat = np.concatenate((i * n + i, j * n + j, i * n + j, j * n + i))
        ata += np.bincount(flat, np.concatenate((w2, w2, -w2, -w2)),
                           minlength=n * n).reshape(n, n)
        for c in range(2):
            atb[:, c] += np.bincount(j, d[:, c], minlength=n) - np.bincount(i, d[:, c],
                                                                           minlength=n)
    for k, (ax, ay) in anchors.items():
        ata[k, k] += anchor_weight**2
        atb[k] += (anchor_weight**2 * ax, anchor_weight**2 * ay)
    return np.linalg.solve(ata, atb)


@dataclass
class _Entry:
    index: int
    placed: PlacedFrame
    reduced: np.ndarray


class RegistrationStage(Stage):
    """Refines frame offsets; emits frames N + 1 frames late with corrected offsets.

    Parameters
    ----------
    n_levels : int
        Focus levels per staircase period, N (the period pair's lag).
    scale : int
        Reduction factor of the frames before correlation.
    lags : tuple of int
        Short lags paired with each new frame (those below N); the period N is added.
        Measured on the demo optics, ±3 px wobble, 3 seeds: lags 1, 2 (three pairs per
        frame) 0.223 / 0.209 px RMS x / y, lags 1-4 (five) 0.172 / 0.151, where the five
        pairs without the crops' mean removed gave 0.328 / 0.269
        (bench/results/registration_accuracy.md).
    false_alarm : float
        Rate at which a pair of unrelated crops (featureless, or several equal peaks)
        would pass as a measurement (:func:`sffscan.stages.phase_correlation.is_significant`);
        a pair that fails is not measured, and a frame without measurements stays at the
        prediction (the solve's zero-mean prior).
    shared_spectra : bool
        Short-lag pairs use the new frame's one central-crop spectrum.
    workers : int
        Pair workers: a frame's pairs (one per lag) measured at once in that many threads
        (:class:`sffscan.stages.bands.BandWorkers`; the caller's thread takes the first),
        at most one per pair, and an integer frame downsampled in as many bands of rows;
        the new frame's shared spectrum and the solve stay in the stage's thread. Results
        bit-identical for any number.
    """

    name = "registration"

    def __init__(self, *, n_levels: int, scale: int = 4, lags: tuple[int, ...] = (1, 2),
                 false_alarm: float = 1e-3, shared_spectra: bool = True,
                 workers: int = 1) -> None:
        self.n_levels = n_levels
        self.shared_spectra = shared_spectra
        self.scale = scale
        self.lags = tuple(lag for lag in lags if lag < n_levels) + (n_levels,)
        self.false_alarm = false_alarm  # per pair: unrelated crops measured (none kept)
        self.window = 2 * n_levels + 8
        if workers < 1:
            raise ValueError(f"workers must be >= 1, got {workers}")
        self.workers = min(workers, len(self.lags))
        self._workers: BandWorkers | None = None  # made at the first frame
        self._reset()
        self.pairs_measured = 0
        self.pairs_rejected = 0
        self.pairs_shared = 0
        self.max_correction = 0.0
        self._sq_sum = 0.0
        self._emitted_total = 0

    def _reset(self) -> None:
        self._pass: int | None = None
        self._count = 0
        self._recent: collections.deque[_Entry] = collections.deque(maxlen=self.n_levels + 1)
        self._pending: collections.deque[_Entry] = collections.deque()
        self._pairs: list[tuple[int, int, float, float, float]] = []  # since the last emit
        self._pair_arr = np.empty((0, 5))  # (i, j, dx, dy, weight) of the window, float64
        self._emitted: dict[int, tuple[float, float]] = {}

    def _crop(self, new: _Entry, pred: tuple[float, float]
              ) -> tuple[int, int, int, int, int, int] | None:
        """The fixed crop of a short-lag pair predicted ``pred`` px apart, (bx, by, cw, ch,
        ix, iy): the new frame's central box and the predicted shift at the reduced scale;
        None where the pair is measured on its overlap instead (:func:`measure_shift`)."""
        h, w = new.reduced.shape
        ix, iy = int(round(pred[0] / self.scale)), int(round(pred[1] / self.scale))
        mx, my = w // 10, 0  # shift the fixed crop allows (none across: y is constant)
        if not (self.shared_spectra and abs(ix) <= mx and abs(iy) <= my):
            return None
        ch, cw = _dft_size_at_most(min(h - 2 * my, 256)), _dft_size_at_most(min(w - 2 * mx, 256))
        return (w - cw) // 2, (h - ch) // 2, cw, ch, ix, iy

    def _pair(self, old: _Entry, new: _Entry, pred: tuple[float, float],
              crop: tuple[int, int, int, int, int, int] | None, fixed: np.ndarray | None
              ) -> tuple[float, float, float] | None:
        """One pair's measured shift (x, y, peak; full-resolution px), None where the
        correlation is not significant. ``pred``: the predicted shift, px; ``crop``: the
        pair's fixed crop (:meth:`_crop`); ``fixed``: the new frame's windowed central-crop
        spectrum, which such pairs share. Reads the two entries only: the pairs of a frame
        may run at once (:attr:`workers`)."""
        if crop is None:
            return measure_shift(old.reduced, new.reduced, predicted_px=pred, scale=self.scale,
                                 false_alarm=self.false_alarm)
        # the new frame's crop is fixed (its spectrum computed once, for all its short
        # lags); the old frame's crop is the same world area by the prediction
        assert fixed is not None
        bx, by, cw, ch, ix, iy = crop
        ax, ay = bx + ix, by + iy
        fa = windowed_spectrum(old.reduced[ay:ay + ch, ax:ax + cw])
        c = correlate_spectra(fa, fixed, (ch, cw))
        if not is_significant(c, (ch, cw), false_alarm=self.false_alarm):
            return None
        return (ix - c.sx) * self.scale, (iy - c.sy) * self.scale, c.peak

    def _measure(self, olds: list[_Entry], new: _Entry) -> None:
        """Measure the pairs (each of ``olds`` with ``new``), at once where there are
        pair workers, and keep the significant ones in the order of ``olds``."""
        pb = new.placed.predicted_px
        preds = [(pb[0] - o.placed.predicted_px[0], pb[1] - o.placed.predicted_px[1])
                 for o in olds]
        crops = [self._crop(new, pred) for pred in preds]
        fixed = None
        shared = next((c for c in crops if c is not None), None)
        if shared is not None:
            bx, by, cw, ch, _, _ = shared
            fixed = windowed_spectrum(new.reduced[by:by + ch, bx:bx + cw])
        pairs = list(zip(olds, preds, crops, strict=True))
        if self._workers is None:
            got = [self._pair(old, new, pred, crop, fixed) for old, pred, crop in pairs]
        else:
            got = self._workers.map(
                lambda opc: self._pair(opc[0], new, opc[1], opc[2], fixed), pairs,
                name=lambda opc: f"registration pair worker for frames "
                f"{opc[0].placed.header.frame_id} and {new.placed.header.frame_id}")
        for (old, pred, crop), g in zip(pairs, got, strict=True):
            self.pairs_shared += crop is not None
            if g is None:
                self.pairs_rejected += 1
                continue
            self.pairs_measured += 1
            self._pairs.append((old.index, new.index, g[0] - pred[0], g[1] - pred[1], 1.0))

    def _emit_oldest(self) -> PlacedFrame:
        entry = self._pending.popleft()
        newest = self._count - 1
        lo = max(0, newest - self.window + 1)
        # the window's pairs as an array, in the order measured: the kept ones, then the
        # new ones (converting only those, not the whole window's list, every frame)
        kept = self._pair_arr
        if self._pairs:
            kept = np.concatenate((kept, np.asarray(self._pairs, dtype=np.float64)))
            self._pairs = []
        kept = self._pair_arr = kept[kept[:, 0] >= lo]
        self._emitted = {k: v for k, v in self._emitted.items() if k >= lo}
        pairs = kept.copy()
        pairs[:, :2] -= lo
        sol = solve_wobble(newest - lo + 1, pairs,
                           {k - lo: v for k, v in self._emitted.items()})
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
        if self.workers > 1 and self._workers is None:
            self._workers = BandWorkers(self.workers, name="registration-pair")
        entry = _Entry(self._count, item, self._reduce(item.image))
        self._count += 1
        olds = [self._recent[-lag] for lag in self.lags if len(self._recent) >= lag and (
            lag < self.n_levels
            or self._recent[-lag].placed.header.focus_index == item.header.focus_index)]
        if olds:
            self._measure(olds, entry)
        self._recent.append(entry)
        self._pending.append(entry)
        while len(self._pending) > self.n_levels + 1:
            yield self._emit_oldest()

    def finish(self) -> Iterator[PlacedFrame]:
        while self._pending:
            yield self._emit_oldest()

    def _reduce(self, image: np.ndarray) -> np.ndarray:
        """:func:`downsample` of a frame; with pair workers, an integer frame whose sides
        divide by the scale in bands of rows at once (exact integer sums: the same values
        for any band; the frame's first read from memory, most of the downsampling's time,
        is then shared too)."""
        f, (h, w) = self.scale, image.shape
        if self._workers is None or h % f or w % f or image.dtype.kind != "u":
            return downsample(image, factor=f)
        bands = [(a * f, b * f) for a, b in row_bands(0, h // f, self.workers)]
        return np.concatenate(self._workers.run(
            lambda r0, r1: downsample(image[r0:r1], factor=f), bands))

    def close(self, *, failed: bool) -> None:
        if self._workers is not None:
            self._workers.close()
            self._workers = None

    def extra_stats(self) -> dict[str, float]:
        n = max(self._emitted_total, 1)
        return {
            "pairs_measured": self.pairs_measured,
            "pairs_rejected": self.pairs_rejected,
            "pairs_shared_spectrum": self.pairs_shared,
            "max_correction_px": round(self.max_correction, 2),
            "rms_correction_px": round(float(np.sqrt(self._sq_sum / n)), 2),
        }
