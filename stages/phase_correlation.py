"""Phase correlation of two crops, with the significance of its peak.

The primitives of the registration stage (:mod:`sffscan.stages.registration`): each crop's
mean is removed and it is Hann-windowed (:func:`windowed_spectrum`), the normalised
cross-power spectrum is weighted by a Gaussian (:func:`correlate_spectra`), and a peak is
kept only where two unrelated crops would rarely reach it (:func:`null_peak_threshold`).
"""

from __future__ import annotations

import functools
from statistics import NormalDist
from typing import NamedTuple

import cv2
import numpy as np


class Correlation(NamedTuple):
    """A phase correlation's result: b(p) ~= a(p - s), px; the peak's height (about 1 for
    identical images, near 0 for unrelated ones) and the highest value of the surface
    outside the peak's neighbourhood (3 ``peak_sigma``), on the same scale."""

    sx: float
    sy: float
    peak: float
    runner_up: float


def _peak_offset(minus: float, centre: float, plus: float) -> float:
    """Sub-pixel offset of a peak from three samples: Gaussian fit, else parabola."""
    if minus > 0 and centre > 0 and plus > 0:
        lm, l0, lp = np.log(minus), np.log(centre), np.log(plus)
        curv = lm - 2 * l0 + lp
        if curv < 0:
            return float(0.5 * (lm - lp) / curv)
    curv = minus - 2 * centre + plus
    return 0.5 * (minus - plus) / curv if curv < 0 else 0.0


@functools.lru_cache(maxsize=16)
def _hann(h: int, w: int) -> np.ndarray:
    """Hann window (h, w), float32."""
    return cv2.createHanningWindow((w, h), cv2.CV_32F)


@functools.lru_cache(maxsize=16)
def _pc_weight(h: int, w: int, peak_sigma: float) -> np.ndarray:
    """Gaussian spectral weight (h, w // 2 + 1), float32."""
    fy = np.fft.fftfreq(h)[:, None]
    fx = np.fft.rfftfreq(w)[None, :]
    return np.exp(-2.0 * np.pi**2 * peak_sigma**2 * (fx * fx + fy * fy)).astype(np.float32)


def phase_correlate(a: np.ndarray, b: np.ndarray, *, peak_sigma: float = 1.5
                    ) -> Correlation:
    """Translation of image b relative to image a by phase correlation.

    Both images have their mean removed and are multiplied by a Hann window (windowed
    with its mean, an image correlates with the window itself at zero lag, which pulled
    every shift toward 0: measured, each pair recovered only 0.6-0.7 of the true shift on
    the scans of bench/bench_registration_accuracy.py). The normalised cross-power spectrum is
    weighted by a Gaussian, so that the correlation peak is a Gaussian of ``peak_sigma``
    px whatever the images' blur (frames at different focus levels have no common
    high-frequency content; there the phase is noise, and an unweighted peak is ragged).
    The peak is then located with a three-point Gaussian fit. Measured on simulated frames
    up to 7 focus levels apart with sensor noise: 0.1 px RMS error, against 0.3 px for the
    unweighted peak with Foroosh's estimator. (cv2.phaseCorrelate is not used: with OpenCV
    5.0 it reports shifts off by half a pixel whenever its DFT size is odd.)

    Parameters
    ----------
    a, b : ndarray, float32, (h, w)
    peak_sigma : float
        Width of the correlation peak, px.

    Returns
    -------
    Correlation
        (sx, sy, peak, runner_up).
    """
    h, w = a.shape
    return correlate_spectra(windowed_spectrum(a), windowed_spectrum(b), (h, w),
                             peak_sigma=peak_sigma)


def windowed_spectrum(image: np.ndarray) -> np.ndarray:
    """Spectrum of the image less its mean, Hann-windowed (what :func:`phase_correlate`
    correlates).

    OpenCV's real-input DFT, in its packed CCS layout (the ``h x (w // 2 + 1)`` complex
    half-spectrum of ``rfft2`` packed into ``h x w`` reals): about twice as fast as
    ``scipy.fft.rfft2`` on the 256 x 256 crops of the registration, and correlated without
    unpacking (:func:`correlate_spectra`).

    Parameters
    ----------
    image : ndarray, float32, (h, w)
        May be a strided view (a crop): the window's product is the contiguous copy.

    Returns
    -------
    ndarray, float32, (h, w)
        CCS-packed spectrum (``cv2.dft`` of a real image without flags).
    """
    h, w = image.shape
    # the crop's mean removed first: windowed, a constant is the window itself, whose
    # correlation peaks at zero lag and pulls every measured shift toward 0
    centred = np.subtract(image, np.float32(cv2.mean(image)[0]), dtype=np.float32)
    return cv2.dft(np.multiply(centred, _hann(h, w), out=centred))


# correlation, across the spectrum of a Hann-windowed white noise, of bins 0, 1 and 2 apart
# (the DFT of the window's square, 3/8 - cos / 2 + cos 2 / 8, normalised)
_HANN_BIN_CORR = (1.0, 2.0 / 3.0, 1.0 / 6.0)


@functools.lru_cache(maxsize=16)
def null_peak_threshold(h: int, w: int, *, peak_sigma: float = 1.5,
                        false_alarm: float = 1e-3) -> float:
    """Peak height that two unrelated crops exceed with probability at most ``false_alarm``.

    The cross-power spectrum of :func:`correlate_spectra` is normalised to unit magnitude
    at every frequency, so for unrelated crops (featureless ones: sensor noise only) its
    phases are random whatever the images: the correlation surface is a Gaussian field
    whose variance follows from the spectral weight and the Hann window alone (the window
    correlates neighbouring bins, which raises the variance near zero lag and lowers it
    far from it). The probability that its maximum exceeds ``u`` is bounded by the
    expected Euler characteristic of the excursion set (Adler and Taylor, *Random Fields
    and Geometry*, 2007), summed over the surface with the local variance. The threshold
    depends only on the crop shape, ``peak_sigma`` and the chosen rate, not on any scene;
    measured on pure-noise crops the bound is conservative (at the 1 % point of the noise
    peaks it predicts 0.16-0.48 instead of 0.01; tests/stages/test_registration_gate.py).

    Parameters
    ----------
    h, w : int
        Crop shape, px.
    peak_sigma : float
        As in :func:`phase_correlate`.
    false_alarm : float
        Probability that unrelated crops pass, per pair.

    Returns
    -------
    float
        Threshold on the ``peak`` returned by :func:`correlate_spectra`.
    """
    if not 0.0 < false_alarm < 1.0:
        raise ValueError(f"false_alarm must be in (0, 1), got {false_alarm}")
    std, lam = _null_moments(h, w, peak_sigma)
    local = std * np.sqrt(_relative_variance())
    density = h * w * lam / (2 * np.pi) ** 1.5  # per unit of the normalised lag grid

    def alarm(u: float) -> float:
        z = u / local
        return float(density * (z * np.exp(-0.5 * z * z)).mean())

    lo, hi = float(local.max()), 1.0  # alarm() decreases above every local std
    for _ in range(40):
        mid = 0.5 * (lo + hi)
        lo, hi = (mid, hi) if alarm(mid) > false_alarm else (lo, mid)
    return hi


def runner_up_margin(h: int, w: int, *, peak_sigma: float = 1.5,
                     false_alarm: float = 1e-3) -> float:
    """How far a peak must stand above the runner-up for it not to be a tie by chance.

    Both values carry the surface's noise (at most the largest local standard deviation of
    :func:`null_peak_threshold`'s field); their difference, ``sqrt(2)`` times it, exceeds
    the returned margin with probability ``false_alarm`` (one-sided normal quantile).
    A periodic scene, or two frames whose in-focus detail differs, give several peaks of
    about the same height: the highest is then a guess. Measured on the sinusoid scans,
    such pairs stood 0.1-1.8 noise standard deviations above their runner-up, 170-230 px
    off, where the true matches stood 16-32 above.
    """
    if not 0.0 < false_alarm < 1.0:
        raise ValueError(f"false_alarm must be in (0, 1), got {false_alarm}")
    std, _ = _null_moments(h, w, peak_sigma)
    worst = std * float(np.sqrt(_relative_variance().max()))
    return NormalDist().inv_cdf(1.0 - false_alarm) * np.sqrt(2.0) * worst


def is_significant(c: Correlation, shape: tuple[int, int], *, peak_sigma: float = 1.5,
                   false_alarm: float = 1e-3) -> bool:
    """Whether a correlation of crops of ``shape`` (h, w) is a measurement: its peak above
    what unrelated crops reach (:func:`null_peak_threshold`) and above its runner-up by
    more than noise (:func:`runner_up_margin`), each at rate ``false_alarm``."""
    h, w = shape
    return (c.peak >= null_peak_threshold(h, w, peak_sigma=peak_sigma, false_alarm=false_alarm)
            and c.peak - c.runner_up >= runner_up_margin(h, w, peak_sigma=peak_sigma,
                                                         false_alarm=false_alarm))


@functools.lru_cache(maxsize=16)
def _null_moments(h: int, w: int, peak_sigma: float) -> tuple[float, float]:
    """Mean standard deviation of the null correlation surface (on the peak's scale) and
    the geometric mean of its second spectral moments along y and x."""
    fy = np.fft.fftfreq(h)[:, None]
    fx = np.fft.fftfreq(w)[None, :]
    w2 = np.exp(-4.0 * np.pi**2 * peak_sigma**2 * (fx * fx + fy * fy))  # weight squared
    total = float(w2.sum())
    # std of corr = idft(unit phasors x weight) / mean weight (the peak's scale)
    std = float(np.sqrt(total) / (h * w) / float(_pc_weight(h, w, peak_sigma).mean()))
    lam = float(np.sqrt(float((w2 * (2 * np.pi * fx) ** 2).sum() / total)
                        * float((w2 * (2 * np.pi * fy) ** 2).sum() / total)))
    return std, lam


@functools.lru_cache(maxsize=1)
def _relative_variance(n: int = 64) -> np.ndarray:
    """Variance of the null correlation surface relative to its mean, (n, n) samples of
    the lag as a fraction of the crop (the same for every crop shape): the phasors'
    correlation between bins (d_x, d_y) apart, squared (two independent crops), summed as
    cosines of the lag."""
    t = np.arange(n) / n
    var = np.zeros((n, n))
    for dy in range(-2, 3):
        for dx in range(-2, 3):
            r = _HANN_BIN_CORR[abs(dx)] * _HANN_BIN_CORR[abs(dy)]
            var += _phasor_correlation(r) ** 2 * np.cos(
                2 * np.pi * (dx * t[None, :] + dy * t[:, None]))
    return np.maximum(var, 1e-12)


def _phasor_correlation(r: float) -> float:
    """E[exp(i (arg z1 - arg z2))] of two circular complex Gaussians of correlation r
    (0 <= r <= 1): (pi / 4) r 2F1(1/2, 1/2; 2; r^2), summed as its series."""
    if r >= 1.0:
        return 1.0
    term, total = 1.0, 1.0
    for k in range(200):
        term *= (k + 0.5) ** 2 / ((k + 2) * (k + 1)) * r * r
        total += term
        if term < 1e-12:
            break
    return np.pi / 4 * r * total


@functools.lru_cache(maxsize=16)
def _ccs_weight(h: int, w: int, peak_sigma: float
                ) -> tuple[np.ndarray, np.ndarray, np.ndarray, float]:
    """:func:`_pc_weight` in the CCS layout: the weight of the interior complex columns
    ``(h, (w - 1) // 2)``; of the real-packed edge columns (the first, and the last for
    even ``w``) by frequency along the rows, ``(edges, h // 2 + 1)``; the edge columns'
    indices; and the mean of the whole half-spectrum's weight."""
    full = _pc_weight(h, w, peak_sigma)
    freq = [0, w // 2] if w % 2 == 0 else [0]
    edges = np.ascontiguousarray(full[:h // 2 + 1, freq].T)
    cols = np.array([0, w - 1] if w % 2 == 0 else [0])
    return (np.ascontiguousarray(full[:, 1:1 + (w - 1) // 2]), edges, cols,
            float(full.mean()))


def _normalise(z: np.ndarray, weight: np.ndarray) -> None:
    """In place: ``z * weight / (|z| + 1e-12)`` (complex or real values)."""
    mag = np.abs(z)
    mag += np.float32(1e-12)
    np.divide(weight, mag, out=mag)
    z *= mag


def correlate_spectra(fa: np.ndarray, fb: np.ndarray, shape: tuple[int, int], *,
                      peak_sigma: float = 1.5) -> Correlation:
    """:func:`phase_correlate` from the two images' :func:`windowed_spectrum`.

    A frame's spectrum can so be computed once and correlated with several others.
    ``shape`` is the images' (h, w); returns a :class:`Correlation` as
    :func:`phase_correlate`.
    The cross-power spectrum stays CCS-packed: its interior columns are (re, im) pairs,
    normalised through a complex view; the first column (and the last, for even ``w``)
    packs a real column's spectrum along the rows: real at row 0 (and at row h - 1 for
    even ``h``), (re, im) pairs between.
    """
    h, w = shape
    weight, we, cols, mean = _ccs_weight(h, w, peak_sigma)
    cross = cv2.mulSpectrums(fb, fa, 0, conjB=True)
    last = w - 1 if w % 2 == 0 else w  # the interior columns are [1, last)
    _normalise(cross[:, 1:last].view(np.complex64), weight)
    top = h - 1 if h % 2 == 0 else h  # along an edge column, the pairs are rows [1, top)
    edge = np.ascontiguousarray(cross[:, cols].T)  # (edges, h)
    _normalise(edge[:, 1:top].view(np.complex64), we[:, 1:1 + (top - 1) // 2])
    real = [0, h - 1] if h % 2 == 0 else [0]  # the real values: frequencies 0 (and h / 2)
    vals = edge[:, real]
    _normalise(vals, we[:, [0, h // 2]] if h % 2 == 0 else we[:, :1])
    edge[:, real] = vals
    cross[:, cols] = edge.T
    corr = cv2.idft(cross, flags=cv2.DFT_REAL_OUTPUT | cv2.DFT_SCALE)
    py, px = np.unravel_index(int(np.argmax(corr)), corr.shape)
    c0 = float(corr[py, px])
    sx = px + _peak_offset(float(corr[py, (px - 1) % w]), c0, float(corr[py, (px + 1) % w]))
    sy = py + _peak_offset(float(corr[(py - 1) % h, px]), c0, float(corr[(py + 1) % h, px]))
    if sx > w / 2:
        sx -= w
    if sy > h / 2:
        sy -= h
    r = int(np.ceil(3 * peak_sigma))  # the peak's neighbourhood, cleared for the runner-up
    corr[np.ix_(np.arange(py - r, py + r + 1) % h, np.arange(px - r, px + r + 1) % w)] = -np.inf
    # the Gaussian weighting lowers the peak; scale it back to ~1 for identical images
    return Correlation(sx, sy, c0 / mean, float(corr.max()) / mean)
