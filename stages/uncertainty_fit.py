"""The height uncertainty's constants fitted, and its coverage scored, on pixels whose
errors are known (the synthetic families' training and held-out seeds,
:func:`sffscan.stages.depth_study.leave_one_family_out`).

The uncertainty (:mod:`sffscan.stages.depth_uncertainty`) is
``sigma = sqrt((a scatter)^2 + (excess / 2)^2 + b^2 + c^2)`` levels (``b`` SPC's bias
where the stack took SPC, not fitted); :func:`fit_uncertainty` chooses ``a`` and ``c`` by a
quantile fit, :func:`uncertainty_coverage` is the bar's
measure: the share of pixels with ``|error| <= 2 sigma`` (the bar: 0.90 .. 0.98 on every
held-out family). Pure computation.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from typing import Protocol

import numpy as np
from scipy.optimize import minimize
from sffscan.stages.depth_uncertainty import MIX_SCALE

__all__ = ["COVERAGE_TARGET", "UncertaintyTerms", "fit_uncertainty", "uncertainty_coverage"]

COVERAGE_TARGET = 0.94
"""Share of pixels with |error| <= 2 sigma the uncertainty's constants aim at: the quantile
of the fit (the bar: 0.90 .. 0.98 on every held-out family)."""


class UncertaintyTerms(Protocol):
    """One stack's scored pixels: the depth's errors and the uncertainty's terms, levels,
    1-D arrays of one length (:func:`sffscan.stages.depth_study.uncertainty_sample`)."""

    error: np.ndarray
    scatter: np.ndarray
    excess: np.ndarray
    bias: np.ndarray
    """SPC's bias where the stack took SPC, else 0 (levels; added in quadrature, not
    fitted: :func:`sffscan.stages.depth_uncertainty.depth_uncertainty`'s ``b``)."""


def _sigma(scores: Sequence[UncertaintyTerms], a: float, c: float) -> tuple[np.ndarray, np.ndarray]:
    """|error| and sigma (levels) of the pixels of ``scores`` for the constants (a, c)."""
    e = np.abs(np.concatenate([x.error for x in scores])).astype(np.float64)
    s = np.concatenate([x.scatter for x in scores]).astype(np.float64)
    x = np.concatenate([x.excess for x in scores]).astype(np.float64)
    b = np.concatenate([x.bias for x in scores]).astype(np.float64)
    return e, np.sqrt((a * s) ** 2 + (MIX_SCALE * x) ** 2 + b * b + c * c)


def uncertainty_coverage(scores: Sequence[UncertaintyTerms], a: float, c: float) -> float:
    """Share of the pixels of ``scores`` with |error| <= 2 sigma for the constants (a, c)."""
    e, sg = _sigma(scores, a, c)
    return float(np.mean(e <= 2.0 * sg))


_FIT_BOUNDS = [(math.log(0.1), math.log(100.0)), (math.log(1e-4), math.log(10.0))]


def fit_uncertainty(groups: Sequence[Sequence[UncertaintyTerms]]) -> tuple[float, float]:
    """The constants (a, c) of :func:`sffscan.stages.depth_uncertainty.depth_uncertainty`
    by a quantile fit: the least mean over the groups (families, equal weights) of the
    pinball loss at :data:`COVERAGE_TARGET` of ``log(|error|) - log(2 sigma)`` (so that
    about that share of each group's pixels has |error| <= 2 sigma, no group deciding alone);
    Nelder-Mead on (log a, log c) from a few starts, a in 0.1 .. 100, c in 1e-4 .. 10
    levels."""
    data = []
    for g in groups:
        e, _ = _sigma(g, 1.0, 0.0)
        s = np.concatenate([x.scatter for x in g]).astype(np.float64)
        x = MIX_SCALE * np.concatenate([x.excess for x in g]).astype(np.float64)
        b = np.concatenate([x.bias for x in g]).astype(np.float64)
        data.append((np.log(e + 1e-3), s * s, x * x + b * b))
    tau = COVERAGE_TARGET

    def loss(p: np.ndarray) -> float:
        a2, c2 = math.exp(2 * p[0]), math.exp(2 * p[1])
        total = 0.0
        for le, s2, x2 in data:
            r = le - np.log(2.0 * np.sqrt(a2 * s2 + x2 + c2) + 1e-3)
            total += float(np.mean(np.maximum(tau * r, (tau - 1.0) * r)))
        return total / len(data)

    best = None
    for a0 in (1.0, 4.0):
        for c0 in (0.01, 0.1):
            r = minimize(loss, np.log([a0, c0]), method="Nelder-Mead", bounds=_FIT_BOUNDS,
                         options={"xatol": 1e-3, "fatol": 1e-9})
            if best is None or r.fun < best.fun:
                best = r
    assert best is not None
    return float(np.exp(best.x[0])), float(np.exp(best.x[1]))
