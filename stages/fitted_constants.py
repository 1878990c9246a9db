"""The height uncertainty's fitted constants, per depth method.

:func:`sffscan.stages.depth_uncertainty.depth_uncertainty` adds its terms in quadrature,
``sigma^2 = (a * scatter)^2 + (r * relief)^2 + excess^2 + b^2 + c^2``; ``a``, ``r`` and ``c``
are fitted on the *training* seeds 0..5 of the twenty synthetic families
(:mod:`sffscan.stages.sim.families`: the depth study's ten and the ten crossed from them) by
:func:`sffscan.stages.uncertainty_fit.fit_uncertainty` (a quantile fit: the
:data:`~sffscan.stages.uncertainty_fit.COVERAGE_TARGET` quantile of ``|error| / (2 sigma)``
equal to 1), to the errors of a depth method. The default method's are its own; some other
methods have their own, fitted the same way (:data:`METHOD_CONSTANTS`); the rest take
:data:`OTHER_METHODS_CONSTANTS`. ``sffscan study --families`` refits them without each
family in turn and reports the coverage (share of |error| <= 2 sigma) on the held-out
family (docs/depth-study.md); ``python bench/bench_method_constants.py`` does it per method.
Nothing here is fitted on the repository's data sets. Every refit, with the values before
it: docs/depth-method-log.md, "The height uncertainty's constants, refit by refit".
"""

from __future__ import annotations

__all__ = ["DEFAULT_CONSTANTS_METHOD", "FITTED_FOCUS_MEASURE", "FLOOR_LEVELS", "METHOD_CONSTANTS",
           "OTHER_METHODS", "OTHER_METHODS_CONSTANTS", "RELIEF_SCALE", "SCATTER_SCALE",
           "uncalibrated_focus_measure", "uncertainty_constants"]

SCATTER_SCALE = 0.9943
"""``a`` of the default depth method (``"shape_select"``), fitted on the twenty families'
training seeds 0..5 to its errors (``sffscan study --families --crossed --seeds 6``, the row
"fit on every family's training seeds": the constants the protocol's held-out rows are
fitted like; docs/depth-study.md)."""

RELIEF_SCALE = 1.1744
"""``r`` of the default depth method: fitted with :data:`SCATTER_SCALE`."""

FLOOR_LEVELS = 0.01363
"""``c`` of the default depth method, levels: fitted with :data:`SCATTER_SCALE`."""

DEFAULT_CONSTANTS_METHOD = "shape_select"
"""The depth method :data:`SCATTER_SCALE`, :data:`RELIEF_SCALE` and :data:`FLOOR_LEVELS` are
fitted to: the default (``sffscan.stages.depth.DEFAULT_METHOD``; a test holds them equal)."""

OTHER_METHODS_CONSTANTS = (1.634, 1.116, 0.0406)
"""``(a, r, c)`` of the depth methods without constants of their own (:data:`OTHER_METHODS`):
the default's before its centroid's peak locking joined ``b`` (fitted on the default's
errors, not on each method's own). With the locking term the default's refitted floor fell
from 0.0406 to 0.0054 levels (the locking now carries what the floor did on the flat
families), which left the 3-point peak of ``"adaptive"`` under-covered on a textured flat
(0.882 within 2 sigma, tests/stages/test_uncertainty_scan.py); its own fit over-covers that
flat (its 75th percentile 3.05 x the error's RMS)."""

METHOD_CONSTANTS: dict[str, tuple[float, float, float]] = {
    "argmax": (0.3666, 0.909, 0.1335),
    "gauss3": (0.6347, 0.9797, 0.07076),
    "quadratic3": (0.62, 0.9612, 0.08809),
    "centroid": (4.621, 0.02828, 0.5208),
    "adaptive_centroid": (1.379, 1.161, 0.0001),
}
"""``(a, r, c)`` fitted on each method's own errors, as the default's are on its own (the
twenty families' training seeds 0..5; ``python bench/bench_method_constants.py``), for the
methods whose own constants (refitted without each family in turn) put at least as many
held-out (seed set, family) rows in the 90-98 % band and no more under it than
:data:`OTHER_METHODS_CONSTANTS`, on seeds 6..47 (the rule stated 2026-12-05 evening; the
clean checks and every refit since: docs/depth-method-log.md)."""

OTHER_METHODS = ("pc", "spc", "wcentroid", "adaptive")
"""The depth methods that take :data:`OTHER_METHODS_CONSTANTS`. With
:data:`DEFAULT_CONSTANTS_METHOD` and :data:`METHOD_CONSTANTS`' keys, every one of
``sffscan.stages.depth.DEPTH_METHODS`` (which this module cannot import: depth imports the
uncertainty; a test holds the lists equal)."""

FITTED_FOCUS_MEASURE = ("glvm", 9)
"""The focus measure (operator, window k) every constant here was fitted with: the synthetic
families' stacks are measured with GLVM 9 (:func:`sffscan.stages.depth_study.uncertainty_sample`
's callers, ``bench/bench_method_constants.py``)."""


def uncalibrated_focus_measure(operator: str, window: int) -> str | None:
    """None for the focus measure the uncertainty was fitted with
    (:data:`FITTED_FOCUS_MEASURE`), else why its uncertainty is not calibrated, for a
    warning: measured on pertuz-simu02 (``sffscan study``, 2026-12-05), LAPM 5 and 9 put
    0.75-0.92 of the pixels within 2 sigma for most methods, GLVM 5 0.86 for the default."""
    op, k = FITTED_FOCUS_MEASURE
    if operator.lower() == op and window == k:
        return None
    return (f"the height uncertainty's constants were fitted with the focus measure "
            f"{op.upper()} k={k}; with {operator.upper()} k={window} it is not calibrated "
            "(on pertuz-simu02 LAPM put 0.75-0.92 of the pixels within 2 sigma, GLVM 5 "
            "0.86): check it on a surface you know with 'sffscan study'")


def uncertainty_constants(method: str) -> tuple[float, float, float]:
    """The constants ``(a, r, c)`` of the height uncertainty of a depth taken by ``method``:
    the default method's own fit, another method's own (:data:`METHOD_CONSTANTS`), or
    :data:`OTHER_METHODS_CONSTANTS` (:data:`OTHER_METHODS`).

    Raises
    ------
    ValueError
        For a name none of those lists holds (a study's candidate method, a typo): its
        uncertainty was never fitted, and no constants are given in its place.
    """
    if method == DEFAULT_CONSTANTS_METHOD:
        return SCATTER_SCALE, RELIEF_SCALE, FLOOR_LEVELS
    if method in METHOD_CONSTANTS:
        return METHOD_CONSTANTS[method]
    if method in OTHER_METHODS:
        return OTHER_METHODS_CONSTANTS
    known = sorted((DEFAULT_CONSTANTS_METHOD, *METHOD_CONSTANTS, *OTHER_METHODS))
    raise ValueError(f"method {method!r}: no height uncertainty constants for it; "
                     f"depth methods with them: {', '.join(known)}")
