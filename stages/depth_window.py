"""The default's fallback on a wider window: the 9-level centroid where it errs less.

``"shape_select"``'s fallback (``"adaptive_centroid"``'s estimator) reads the peak of each
curve from 3 or 5 levels about the filtered argmax. Where the curves are wide for the noise
(many levels, a thin lens' long flanks, a 12-bit flat whose curves are flat-topped) a peak
read from so few levels scatters from pixel to pixel, and the baseline-free centroid of the
9 levels about the same argmax (``"wcentroid"``,
:func:`sffscan.stages.depth_peak.windowed_centroid`) averages more of the curve. On
lopsided curves that centroid is pulled into the longer flank: a bias no scatter shows.

:func:`takes_window_centroid` weighs the two with no tuned constant, as the default's other
tests do (:func:`sffscan.stages.depth_spc.takes_spc`): the wider window's mean squared
error, its scatter squared plus its departure from the fallback squared (the fallback's
peak taken as the reference, as SPC's departure takes it), against the fallback's scatter
squared. The scatter of a map is measured on the map itself: its RMS about its own 5 x 5
median (:func:`map_scatter`), which a smooth surface leaves and pixel-to-pixel noise does
not. The two maps come from the same curves and the same focus window, so the noise both
scatters miss (errors that vary slowly, over the focus window) is about the same; the
comparison, not either number, is what is used.

Measured (docs/depth-method-log.md, 2026-12-05; ``bench/bench_window_choice.py``): on seeds
72..77, declared before and scored once, the default's rows over 1.05x the best single
method 4 -> 1 of 21 (flat-lens-12bit 1.23x -> 1.00x, slopes-lens-pillbox 1.25x -> 1.00x;
slopes-8bit-fine 1.00x -> 1.02x), its worst family unchanged (even-noisy, SPC's choice); on
the sets of six seeds scored before (0..71) rows over 1.05x 31 -> 20 of 240, seeds 12..17
1.50x -> 1.08x. Where the two maps' scatters tie under heavy noise it can take the centroid
that errs a little more (the breathing test's stack: +3.8 %).
"""

from __future__ import annotations

import math

import cv2
import numpy as np

__all__ = ["WINDOW_STRIPS", "map_scatter", "takes_window_centroid", "window_choice"]

WINDOW_STRIPS = (16, 128)
"""A scan block is judged on strips of 16 rows out of every 128 (rows ``r`` with
``r % 128 < 16``): an eighth of its pixels (a 1040-row block of 64 columns: 9 strips, 9216
pixels), in runs long enough for the 5 x 5 median (its 2 rows of context beyond each strip
read too). Judging every row cost the depth stage 1.3x ``adaptive_centroid``'s CPU a frame,
a quarter of them 1.04-1.14x (bench_depth_default.py, best of the rounds and their median
ratio); a stack, judged once, and a block of fewer than 512 rows take every row."""


def _strips(height: int, strips: tuple[int, int] | None) -> list[tuple[int, int]]:
    if strips is None:
        return [(0, height)]
    run, every = strips
    return [(r0, min(r0 + run, height)) for r0 in range(0, height, every)]


def map_scatter(depth: np.ndarray, judged: np.ndarray, *, valid: np.ndarray | None = None,
                strips: tuple[int, int] | None = None) -> float:
    """RMS (levels) of a depth map about its own 5 x 5 median over the ``judged`` pixels;
    NaN where none is judged.

    Parameters
    ----------
    depth : (H, W) ndarray of float
        Depth map, levels.
    judged : (H, W) ndarray of bool
        The pixels the RMS is taken over.
    valid : (H, W) ndarray of bool, optional, keyword-only
        The pixels whose depth means something (a scan block's whole curves); the others
        are set to the valid ones' median (of the strip) before the median filter, so that
        their values do not count as their neighbours' scatter. All when None.
    strips : (int, int), optional, keyword-only
        Only the rows of strips of ``strips[0]`` rows every ``strips[1]`` rows
        (:data:`WINDOW_STRIPS`) and 2 rows beyond each are read; every row when None.
    """
    judged = np.asarray(judged, bool)
    d = np.ascontiguousarray(depth, np.float32)
    ok = None if valid is None else np.asarray(valid, bool)
    parts = []
    height = d.shape[0]
    for r0, r1 in _strips(height, strips):
        lo, hi = max(r0 - 2, 0), min(r1 + 2, height)
        own = judged[r0:r1]
        if not own.any():
            continue
        piece = d[lo:hi]
        if ok is not None and not ok[lo:hi].all():
            good = ok[lo:hi]
            piece = np.where(good, piece, np.float32(np.median(piece[good]))
                             ).astype(np.float32)
        r = piece[r0 - lo:r1 - lo] - cv2.medianBlur(piece, 5)[r0 - lo:r1 - lo]
        parts.append(r[own])
    if not parts:
        return math.nan
    r = np.concatenate(parts).astype(np.float64)
    return math.sqrt(float(np.mean(r * r)))


def takes_window_centroid(scatter: tuple[float, float], departure: float) -> bool:
    """Whether the 9-level centroid errs less than the fallback: ``s_w^2 + d^2 < s_f^2``,
    with ``scatter = (s_f, s_w)`` the fallback's and the centroid's :func:`map_scatter` and
    ``d`` the median of the centroid minus the fallback (levels); not for NaN."""
    s_f, s_w = scatter
    return bool(s_w * s_w + departure * departure < s_f * s_f)


def window_choice(depth: np.ndarray, wide: np.ndarray, *, valid: np.ndarray | None = None,
                  margin: int = 0, strips: tuple[int, int] | None = None) -> float | None:
    """The fallback's choice of the 9-level centroid for a stack or a scan's block, in place:
    where :func:`takes_window_centroid` takes it, ``depth`` becomes ``wide``.

    Parameters
    ----------
    depth : (H, W) ndarray of float32
        The fallback's depth (``"adaptive_centroid"``'s, its wide centroid judged), levels;
        changed in place.
    wide : (H, W) ndarray of float32
        :func:`sffscan.stages.depth_peak.windowed_centroid` about the same filtered argmax.
    valid : (H, W) ndarray of bool, optional, keyword-only
        The pixels judged (a block's whole curves); all when None.
    margin : int, keyword-only
        Pixels left out at each edge of the map (a stack's: the focus window's reach, where
        its focus measure reads reflected texture), as the invalid ones; 0 keeps them.
    strips : (int, int), optional, keyword-only
        Judge the rows of these strips only (:data:`WINDOW_STRIPS`, a scan's block); every
        row when None or when the map has fewer than 4 strips' periods of rows.

    Returns
    -------
    float or None
        Where the centroid was taken, the bias (levels) the height uncertainty adds in
        quadrature: ``sqrt(d^2 + s_f^2 - s_w^2)``, its departure and the scatter the
        fallback's map showed that the centroid's does not (a map pulled towards the
        filtered argmax scatters less without erring as much less: on held-out seeds
        78..83 the thin-lens 12-bit flat's coverage fell under the band, 0.884, while the
        centroid added no bias of its own); else None.
    """
    # the pixels whose depth means something: the others take the median before the
    # median filter (map_scatter); of those, the strips' are judged
    ok = np.isfinite(depth) & np.isfinite(wide)
    if valid is not None:
        ok &= np.asarray(valid, bool)
    if margin > 0:
        inner = np.zeros_like(ok)
        inner[margin:-margin, margin:-margin] = True
        ok &= inner
    judged = ok.copy()
    if strips is not None and judged.shape[0] < 4 * strips[1]:
        strips = None  # a short block: every row (a few strips would judge it on little)
    if strips is not None:
        run, every = strips
        judged &= (np.arange(judged.shape[0]) % every < run)[:, None]
    if not judged.any():
        return None
    scatter = (map_scatter(depth, judged, valid=ok, strips=strips),
               map_scatter(wide, judged, valid=ok, strips=strips))
    departure = float(np.median(np.subtract(wide, depth, dtype=np.float32)[judged]))
    if not takes_window_centroid(scatter, departure):
        return None
    np.copyto(depth, wide)
    return math.sqrt(departure * departure + max(scatter[0] ** 2 - scatter[1] ** 2, 0.0))
