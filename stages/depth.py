"""Depth from a focus volume: the depth methods by name (SFF_NOTES.md section 3).

Conventions
-----------
A focus volume is an ``(N, H, W)`` float array of focus-measure values (>= 0); axis 0 is
the focus level ``k = 0 .. N-1``. A pixel's focus curve is ``y_k = volume[k, row, col]``.
Depth is returned in *fractional level units* (0 = level 0, 1 = level 1, ...) and mapped to
height with :func:`levels_to_height`. Every method returns the same confidence,
``|H_1| / H_0`` (:mod:`sffscan.stages.depth_harmonics`).

This module holds the registry of depth methods, :data:`ESTIMATORS` (name -> estimator:
what :func:`depth_from_focus` runs; :data:`DEPTH_METHODS`, the methods of scan, replay and
stack, and :data:`CANDIDATE_METHODS` are its names; the estimators and the checked curves
they read, :class:`FocusCurves`, are :mod:`sffscan.stages.depth_estimators`'s), and is the
depth API's one namespace: it also exports the public names of the modules that compute,

* :mod:`sffscan.stages.depth_levels`: checks, the argmax, filters of level maps,
  levels <-> height, the all-in-focus image;
* :mod:`sffscan.stages.depth_harmonics`: the curve sums, the confidence and the methods
  that need only the sums (:func:`depth_from_harmonics`, the streaming path);
* :mod:`sffscan.stages.depth_peak`: the 3-point fits and the windowed centroid;
* :mod:`sffscan.stages.depth_adaptive`: ``adaptive``, the default's peak estimator, and
  its one-pass block reduction;
* :mod:`sffscan.stages.depth_choice`: the statistics by which the default chooses its
  estimator per stack or block (``shape_select``, ``adaptive_centroid``; SPC's tests in
  :mod:`sffscan.stages.depth_spc`);
* :mod:`sffscan.stages.depth_candidates`: the study's other candidates.

All functions are pure and vectorised (no Python loops over pixels).
"""

from __future__ import annotations

import numpy as np
from sffscan.stages.depth_adaptive import (
    ADAPTIVE_HALF_WINDOW,
    ADAPTIVE_MAX_SPREAD,
    adaptive_peak,
)
from sffscan.stages.depth_estimators import (
    CURVE_ESTIMATORS,
    Estimator,
    FocusCurves,
    shape_select_parts,
)
from sffscan.stages.depth_harmonics import (
    STREAMING_METHODS,
    confidence_from_sums,
    curve_moments,
    depth_from_harmonics,
    focus_confidence,
    focus_sums,
    harmonic_table,
    volume_strips,
)
from sffscan.stages.depth_levels import (
    all_in_focus,
    check_odd_size,
    check_volume,
    first_argmax,
    level_spread,
    levels_from_heights,
    levels_to_height,
    median_filter_levels,
    raise_not_finite,
)
from sffscan.stages.depth_peak import WCENTROID_HALF_WINDOW, windowed_centroid
from sffscan.stages.depth_warp import lens_asymmetry, unwarp_levels, warp_volume

__all__ = [
    "ADAPTIVE_HALF_WINDOW",
    "ADAPTIVE_MAX_SPREAD",
    "CANDIDATE_METHODS",
    "DEFAULT_METHOD",
    "DEPTH_METHODS",
    "ESTIMATORS",
    "STREAMING_METHODS",
    "WCENTROID_HALF_WINDOW",
    "Estimator",
    "FocusCurves",
    "adaptive_peak",
    "all_in_focus",
    "check_odd_size",
    "depth_from_focus",
    "depth_from_harmonics",
    "first_argmax",
    "focus_confidence",
    "focus_sums",
    "harmonic_table",
    "level_spread",
    "levels_from_heights",
    "levels_to_height",
    "median_filter_levels",
    "shape_select_with_bias",
    "volume_strips",
    "windowed_centroid",
]


# ----------------------------------------------------------------------------- the registry


# the one estimator beside the registry (sffscan.stages.depth_estimators holds the others):
# it runs depth_from_focus on the warped volume
def _warped_select(c: FocusCurves) -> np.ndarray:
    warp = lens_asymmetry(c.volume)
    if not warp.applied:
        return CURVE_ESTIMATORS["shape_select"].depth(c)
    warped = warp_volume(c.volume, warp.c)
    depth = depth_from_focus(warped, method="shape_select", median_size=c.median_size,
                             spread_size=c.spread_size)[0]
    return unwarp_levels(depth, warp.c, c.volume.shape[0])


ESTIMATORS: dict[str, Estimator] = {
    **CURVE_ESTIMATORS,
    "warped_select": Estimator(_warped_select, candidate=True),
}
"""Every depth method by name: the one list the others (and a configuration's choices)
derive from. Documented in :func:`depth_from_focus`."""

DEPTH_METHODS = tuple(name for name, e in ESTIMATORS.items() if not e.candidate)
"""The methods of scan, replay and stack (``ProcessingConfig.depth_method``)."""

CANDIDATE_METHODS = tuple(name for name, e in ESTIMATORS.items() if e.candidate)
"""The study's candidates, selectable by name in :func:`depth_from_focus` only."""

DEFAULT_METHOD = "shape_select"
"""The default depth method of scan, replay and stack (see ``"shape_select"`` in
:func:`depth_from_focus`; ``"adaptive_centroid"``, and ``"adaptive"`` before it, earlier
on 2026-12-02 and before)."""


# ----------------------------------------------------------------------------- public API


def depth_from_focus(
    volume: np.ndarray, *, method: str = DEFAULT_METHOD, median_size: int = 11,
    argmax: np.ndarray | None = None, spread_size: int = 9,
) -> tuple[np.ndarray, np.ndarray]:
    """Sub-level focus peak and its confidence for every pixel of a focus volume.

    Parameters
    ----------
    volume : (N, H, W) ndarray of float
        Focus volume (values >= 0), N >= 3 levels along axis 0; read as float32.
    method : str, keyword-only
        One of :data:`DEPTH_METHODS` or :data:`CANDIDATE_METHODS` (the names of
        :data:`ESTIMATORS`); default :data:`DEFAULT_METHOD` (``"shape_select"``), as scan,
        replay and stack (``"spc"`` before 2026-12-06):

        ``"argmax"``
            Index of the (first) largest value; integer-valued.
        ``"gauss3"``
            Gaussian through the argmax and its two neighbours (parabola on log values);
            exact for a sampled Gaussian.
        ``"quadratic3"``
            Parabola through the same three points.
            Both 3-point fits fall back to the argmax at the ends (argmax 0 or N-1), on a
            flat top (denominator >= 0) and, for ``gauss3``, on values <= 0.
        ``"centroid"``
            ``sum(k y_k) / sum(y_k)`` (argmax where the sum is <= 0).
        ``"pc"``
            Phase correlation: ``(-angle(H_1) N / (2 pi)) mod N``, in [0, N).
        ``"adaptive"``
            The argmax, median filtered as for SPC (``a_med``); where ``a_med`` spans at
            most :data:`ADAPTIVE_MAX_SPREAD` levels over the ``spread_size`` x
            ``spread_size`` focus window about the pixel, the curve's maximum next to
            ``a_med`` refined by a 3-point Gaussian; elsewhere the windowed centroid of
            the 2h + 1 = 11 levels about ``a_med``
            (:func:`~sffscan.stages.depth_adaptive.adaptive_peak`).
        ``"adaptive_centroid"`` (``"shape_select"``'s fallback)
            ``"adaptive"``, but the centroid of the 5 levels about ``a_med`` instead of
            the 3-point Gaussian where ``a_med`` spans at most
            :data:`ADAPTIVE_MAX_SPREAD` levels, if the volume's curves are even enough
            that a centroid is not pulled from their maxima, or the 3-point Gaussian is
            noisier than that pull (the median difference of the two about each curve's
            argmax within the larger of
            :data:`~sffscan.stages.depth_statistics.CENTROID_PULL_LIMIT` and the
            differences' robust spread:
            :func:`~sffscan.stages.depth_statistics.pull_statistics`). Five levels, not
            three: less noise. On clean lopsided curves (a thin lens' blur) it is
            ``"adaptive"``. Where ``a_med`` spans more, the 11-level centroid only if it
            does not depart from that peak estimator by more than their differences'
            spread over those pixels (:func:`~sffscan.stages.depth_choice.takes_wide_centroid`;
            else the peak estimator at every pixel: a smooth slope). The streaming depth
            stage judges each block of columns.
        ``"wcentroid"``
            Windowed centroid about the filtered peak: the argmax, median filtered over
            ``median_size`` x ``median_size`` pixels as for SPC (``a_med``), is the centre of
            a window of 2h + 1 = 9 levels (:data:`WCENTROID_HALF_WINDOW`, cut at the ends of
            the range); the window's minimum is subtracted and the centroid of the rest is
            the depth (:func:`~sffscan.stages.depth_peak.windowed_centroid`). The median
            keeps a noisy or flat curve's stray maximum from moving the window (what spoils
            argmax, gauss3 and quadratic3 with noise); the window keeps the curve's far tails
            and noise floor out of the estimate (what spoils centroid and PC).
        ``"spc"``
            Shifted phase correlation: argmax, median filtered over ``median_size`` x
            ``median_size`` pixels (``a_med``); per-pixel shift ``s = round(N/2) - a_med``
            that would move ``a_med`` to the centre; PC of the shifted curve; minus ``s``.
            The curve is not rolled: ``np.roll(y, s)`` multiplies ``H_1`` by
            ``exp(-2 pi i s / N)``, i.e. adds ``-2 pi s / N`` to its angle, so the rotation is
            applied to the angle directly: ``depth = ((phi + s) mod N) - s`` with
            ``phi = -angle(H_1) N / (2 pi)``. No modulo after undoing the shift: the result
            lies in ``[a_med - round(N/2), a_med - round(N/2) + N)``, unwrapped around the
            filtered argmax (the same result as rolling each curve, the test's reference).
        ``"shape_select"`` (the default of scan, replay and stack)
            One choice for the whole volume: ``"spc"`` where its focus curves are even and
            clean (:func:`sffscan.stages.depth_choice.shape_select` at
            :data:`~sffscan.stages.depth_spc.SHAPE_SELECT_LIMITS` and a centroid
            pull under :data:`~sffscan.stages.depth_spc.SPC_PULL_LIMIT`, tuned by
            the leave-one-family-out study; and SPC's departure from the peaks the
            fallback takes (3-point Gaussian or 5-level centroid) and its predicted
            noise (:func:`~sffscan.stages.depth_spc.spc_noise`) small enough that
            its mean squared error is predicted no larger than the fallback's,
            :func:`~sffscan.stages.depth_spc.spc_departure`,
            :func:`~sffscan.stages.depth_spc.takes_spc`), except at the pixels
            whose SPC depth lies within
            :data:`~sffscan.stages.depth_spc.SPC_END_REACH` curve widths of an end
            of the range (:func:`~sffscan.stages.depth_spc.spc_in_range`); else, and
            there, ``"adaptive_centroid"``, which a volume that does not take SPC trades for
            ``"wcentroid"`` where that map's scatter about its 5 x 5 median plus its
            departure from the fallback is under the fallback's scatter
            (:func:`sffscan.stages.depth_window.window_choice`, since 2026-12-05). The
            streaming depth stage makes the choice per
            block of columns (judged on a grid of its curves); a volume of 4 x 16384 or more
            curves is judged on an even grid of at least 16384
            (:func:`~sffscan.stages.depth_statistics.stack_sample`), and so is
            ``"adaptive_centroid"``'s pull.
        ``"gauss_window_fit"``, ``"window_pc"`` (:data:`CANDIDATE_METHODS`)
            The candidates of the leave-one-family-out study
            (:mod:`sffscan.stages.depth_candidates`), at the settings the study tuned on
            the training seeds of all its families: a weighted Gaussian fit over the
            2h + 1 = 7 levels about ``a_med`` (``adaptive`` where the fit fails), and phase
            correlation over a window of 3 x the curve's width about ``a_med``. Not methods
            of scan, replay or stack.
        ``"warped_select"`` (:data:`CANDIDATE_METHODS`)
            ``"shape_select"`` on the volume resampled onto levels evenly spaced in
            ``g(k) = k / (1 + s k)``, where a thin lens' lopsided curves are even, the
            depth mapped back (:mod:`sffscan.stages.depth_warp`), where the curves' half-height
            crossings give a warp clearly away from none; else ``"shape_select"``. Stacks
            only (``stack --method``): a scan's blocks are not warped yet.
    median_size : int, keyword-only
        Odd median-filter size for ``"spc"``, ``"wcentroid"`` and ``"adaptive"`` (1 = no
        filtering).
        Default 11. The thesis used
        10 x 10; an even window has no centre pixel (the median would be shifted by half a
        pixel and an average of two levels), and ``cv2.medianBlur`` requires an odd size, so
        the nearest odd size above is the default. Validated for every method.
    argmax : (H, W) ndarray of int, optional, keyword-only
        Each curve's first maximum, if already known (a streaming accumulator keeps it as
        the levels arrive); computed from ``volume`` when not given (unused by ``"pc"``).
    spread_size : int, keyword-only
        Odd window, px, over which ``"adaptive"`` measures the spread of the filtered
        peaks: the focus measure's window k. Default 9. Validated for every method.

    Returns
    -------
    depth : (H, W) ndarray of float32
        Peak position in fractional level units.
    confidence : (H, W) ndarray of float32
        ``|H_1| / H_0`` in [0, 1] (0 where ``H_0 <= 0``), the same for every method.

    Raises
    ------
    ValueError
        If ``volume`` is not 3-D, has fewer than 3 levels, contains NaN or inf (the message
        names the first such level), or ``method`` / ``median_size`` is invalid.
    """

    curves = _checked_curves(volume, method=method, median_size=median_size, argmax=argmax,
                             spread_size=spread_size)
    h0, _, re, im = curves.moments
    return ESTIMATORS[method].depth(curves), confidence_from_sums(h0, re, im)


def shape_select_with_bias(volume: np.ndarray, *, median_size: int = 11,
                           argmax: np.ndarray | None = None, spread_size: int = 9
                           ) -> tuple[np.ndarray, np.ndarray, float, float]:
    """``depth_from_focus(volume, method="shape_select", ...)``'s depth and confidence, the
    bias (levels) the height uncertainty of a stack so reconstructed adds in quadrature
    (:mod:`sffscan.stages.depth_uncertainty`'s b): :attr:`sffscan.stages.depth_choice.
    StackChoice.bias`, and where the stack takes the 9-level centroid, that centroid's
    (:func:`sffscan.stages.depth_window.window_choice`) beside it; and the locking it adds
    where the scatter cannot show it (:attr:`sffscan.stages.depth_choice.StackChoice.
    locking`, ``L`` of :func:`sffscan.stages.depth_uncertainty.depth_uncertainty`). From one
    pass: what a stack's height and its uncertainty need
    (:func:`sffscan.stages.fields.stationary.reconstruct_field`, the depth study)."""
    curves = _checked_curves(volume, method="shape_select", median_size=median_size,
                             argmax=argmax, spread_size=spread_size)
    depth, bias, locking = shape_select_parts(curves)
    h0, _, re, im = curves.moments
    return depth, confidence_from_sums(h0, re, im), bias, locking


def _checked_curves(volume: np.ndarray, *, method: str, median_size: int,
                    argmax: np.ndarray | None, spread_size: int) -> FocusCurves:
    """:func:`depth_from_focus`'s arguments checked, as the estimator reads them."""
    estimator = ESTIMATORS.get(method)
    if estimator is None:
        raise ValueError(f"method must be one of {DEPTH_METHODS} or a candidate "
                         f"{CANDIDATE_METHODS}, got {method!r}")
    median_size = check_odd_size(median_size, name="median_size", minimum=1)
    spread_size = check_odd_size(spread_size, name="spread_size", minimum=1)
    vol = check_volume(volume)

    moments = curve_moments(vol)
    if not np.isfinite(moments[0]).all():  # NaN / inf in a curve makes its sum non-finite
        raise_not_finite(vol)
    a: np.ndarray | None = None
    if argmax is not None and estimator.uses_argmax:
        a = np.asarray(argmax)
        if a.shape != vol.shape[1:]:
            raise ValueError(f"argmax shape {a.shape} differs from the volume's {vol.shape[1:]}")
        a = a.astype(np.intp, copy=False)
    elif estimator.uses_argmax:
        a = first_argmax(vol)
    return FocusCurves(vol, moments, a, median_size, spread_size)
