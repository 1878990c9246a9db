"""The 5-level centroid's peak locking (depth_choice.centroid_locking), against the
estimator itself: the height uncertainty's term for it is the estimator's own error on
noise-free Gaussian curves, not a fitted constant."""

from __future__ import annotations

import math

import numpy as np
import pytest
from sffscan.stages.depth_choice import centroid_locking, peak_locking
from sffscan.stages.depth_peak import windowed_centroid
from sffscan.stages.depth_statistics import takes_centroid


def _gaussians(width: float, fractions: np.ndarray, n: int = 21) -> np.ndarray:
    """(n, 1, F) noise-free Gaussian curves of sigma ``width`` levels peaking at level
    n // 2 + fraction."""
    z = np.arange(n, dtype=np.float64)[:, None, None]
    return np.exp(-((z - (n // 2 + fractions[None, None, :])) ** 2)
                  / (2.0 * width * width)).astype(np.float32)


@pytest.mark.parametrize("width", [0.6, 1.0, 1.5, 2.0, 3.0, 6.0])
def test_locking_is_the_centroids_own_rms_error(width: float) -> None:
    """RMS over the true fraction of windowed_centroid's error (the estimator the fallback
    runs, float32) equals centroid_locking to float32 round-off."""
    t = (np.arange(400) + 0.5) / 400 - 0.5
    vol = _gaussians(width, t)
    centre = np.full((1, t.size), 10, np.intp)
    err = windowed_centroid(vol, centre, half_window=2)[0].astype(np.float64) - (10 + t)
    assert math.sqrt(float(np.mean(err ** 2))) == pytest.approx(centroid_locking(width),
                                                                abs=2e-5)


def test_locking_pushes_away_from_the_level_and_has_known_values() -> None:
    """The window's minimum is its far end: a peak just above a level reads higher still
    (the error has the fraction's sign); RMS 0.018 / 0.039 / 0.049 / 0.062 levels at
    sigma 1 / 1.5 / 2 / 10, none for a NaN width."""
    t = np.array([0.1, 0.2, 0.3])
    got = windowed_centroid(_gaussians(2.0, t), np.full((1, 3), 10, np.intp))[0] - (10 + t)
    assert (got > 0).all()
    for w, want in ((1.0, 0.018), (1.5, 0.039), (2.0, 0.049), (10.0, 0.062)):
        assert centroid_locking(w) == pytest.approx(want, abs=1e-3)
    assert centroid_locking(float("nan")) == 0.0


def test_peak_locking_only_where_the_centroid_is_taken() -> None:
    """The 3-point Gaussian (taken where the pull exceeds the limit and the noise) is exact
    on a Gaussian curve: no locking; the centroid's where it is taken; none for NaN."""
    assert takes_centroid(0.0, noise=0.01)
    assert peak_locking(0.0, 0.01, 2.0) == centroid_locking(2.0)
    assert not takes_centroid(0.5, noise=0.01)
    assert peak_locking(0.5, 0.01, 2.0) == 0.0
    assert peak_locking(float("nan"), float("nan"), 2.0) == 0.0


def test_each_method_has_its_constants() -> None:
    """The fitted constants are the default method's; a method with its own fit
    (fitted_constants.METHOD_CONSTANTS) takes it, every other method the ones fitted on
    the default's errors before the locking term (OTHER_METHODS_CONSTANTS)."""
    from sffscan.stages.depth import DEFAULT_METHOD, DEPTH_METHODS
    from sffscan.stages.fitted_constants import (
        DEFAULT_CONSTANTS_METHOD,
        FLOOR_LEVELS,
        METHOD_CONSTANTS,
        OTHER_METHODS,
        OTHER_METHODS_CONSTANTS,
        RELIEF_SCALE,
        SCATTER_SCALE,
        uncertainty_constants,
    )

    assert DEFAULT_CONSTANTS_METHOD == DEFAULT_METHOD
    assert uncertainty_constants(DEFAULT_METHOD) == (SCATTER_SCALE, RELIEF_SCALE, FLOOR_LEVELS)
    assert set(METHOD_CONSTANTS) < set(DEPTH_METHODS) - {DEFAULT_METHOD}
    # every depth method in exactly one list: none left to a silent default
    lists = [[DEFAULT_CONSTANTS_METHOD], list(METHOD_CONSTANTS), list(OTHER_METHODS)]
    assert sorted(m for names in lists for m in names) == sorted(DEPTH_METHODS)
    for m in DEPTH_METHODS:
        if m != DEFAULT_METHOD:
            assert uncertainty_constants(m) == METHOD_CONSTANTS.get(m, OTHER_METHODS_CONSTANTS)


@pytest.mark.parametrize("method", ["warped_select", "shape-select", ""])
def test_uncertainty_constants_refuse_a_method_without_them(method: str) -> None:
    """A name with no fitted constants (a study's candidate, a typo) is an error naming it,
    not the other methods' constants in its place."""
    from sffscan.stages.fitted_constants import uncertainty_constants

    with pytest.raises(ValueError, match=f"method {method!r}: no height uncertainty") as err:
        uncertainty_constants(method)
    assert "shape_select" in str(err.value)


DRIFT_METHODS = ("shape_select", "gauss3", "adaptive_centroid", "argmax", "centroid")
"""The default, and the methods whose constants were refitted for a term of their own (the
argmax's departure bias, the centroid's departure from its curves' phase): +4 s."""


@pytest.fixture(scope="module")
def training_samples() -> dict[str, list[list[object]]]:
    """Each of DRIFT_METHODS' uncertainty samples on the twenty families' training seeds
    0..5, one group a family (what the shipped constants are fitted on)."""
    from sffscan.stages.depth_study import uncertainty_sample
    from sffscan.stages.focus_measure import focus_measure
    from sffscan.stages.sim.families import family_names, family_stack

    out: dict[str, list[list[object]]] = {m: [] for m in DRIFT_METHODS}
    for f in family_names(crossed=True):
        groups: dict[str, list[object]] = {m: [] for m in DRIFT_METHODS}
        for seed in range(6):
            st = family_stack(f, seed, size_px=64)
            vol = focus_measure(st.images, operator="glvm", window=9)
            mask = np.zeros(st.truth_um.shape, bool)
            mask[4:-4, 4:-4] = True
            truth = (st.truth_um - st.focus_um[0]) / (st.focus_um[1] - st.focus_um[0])
            for m in DRIFT_METHODS:
                groups[m].append(uncertainty_sample(vol, truth, mask, spread_size=9, method=m))
        for m in DRIFT_METHODS:
            out[m].append(groups[m])
    return out


@pytest.mark.parametrize("method", DRIFT_METHODS)
def test_shipped_constants_are_the_fit_on_the_training_seeds(
        method: str, training_samples: dict[str, list[list[object]]]) -> None:
    """The shipped constants are what the quantile fit gives on the twenty families'
    training seeds 0..5 with the method's own errors (``sffscan study --families --crossed
    --seeds 6``'s fit on every family; a drift test: a change to the depth or to a term of
    the uncertainty must refit them)."""
    from sffscan.stages.fitted_constants import uncertainty_constants
    from sffscan.stages.uncertainty_fit import fit_uncertainty

    fitted = fit_uncertainty(training_samples[method])  # type: ignore[arg-type]
    np.testing.assert_allclose(fitted, uncertainty_constants(method), rtol=2e-3)


def test_locking_is_seen_by_the_relief_where_the_height_runs_through_levels() -> None:
    """locking_visibility: 1 on a flat, |sinc(k g)| on a plane of gradient g levels a px (0
    where it runs through a level every k px: the relief's box averages the ripple out);
    depth_uncertainty adds (L v)^2 to sigma^2 at each pixel, nothing else."""
    from sffscan.stages.depth_uncertainty import depth_uncertainty, locking_visibility

    y, x = np.mgrid[0:40, 0:40].astype(np.float32)
    np.testing.assert_array_equal(locking_visibility(np.full((40, 40), 7.0, np.float32),
                                                     window=9), 1.0)
    for g in (0.02, 0.05, 1 / 9, 0.2):
        v = locking_visibility(3.0 + g * x, window=9)
        np.testing.assert_allclose(v, abs(np.sinc(9 * g)), atol=1e-5)
    assert locking_visibility(3.0 + x / 9, window=9).max() < 1e-5
    depth = (5.0 + 0.05 * x + 0.03 * y).astype(np.float32)
    width = np.full(depth.shape, 2.0, np.float32)
    plain = depth_uncertainty(depth, width, bias_levels=0.1).astype(np.float64)
    locked = depth_uncertainty(depth, width, bias_levels=0.1,
                               locking_levels=0.06).astype(np.float64)
    import cv2

    seen = locking_visibility(cv2.medianBlur(depth, 5), window=9).astype(np.float64)
    assert 0.3 < seen[20, 20] < 0.9
    np.testing.assert_allclose(locked ** 2, plain ** 2 + (0.06 * seen) ** 2, rtol=1e-5)


def test_a_blocks_uncertainty_with_locking_is_the_same_in_any_bands() -> None:
    """block_uncertainty of rows [r0, r1) with a locking term (whose visibility reads the
    depth's median gradient: 3 rows beyond a band) is the whole block's, bit for bit, for
    any split into bands, and the term adds to it."""
    from sffscan.stages.block_depth import block_uncertainty

    rng = np.random.default_rng(0)
    rows, cols, n = 120, 40, 30
    y, x = np.mgrid[0:rows, 0:cols]
    depth = (10 + 0.03 * x + 0.01 * y + rng.normal(0, 0.1, (rows, cols))).astype(np.float32)
    sums = np.stack([np.full((rows, cols), 50.0), rng.random((rows, cols)) * 10,
                     rng.random((rows, cols)) * 10]).astype(np.float32)
    low = np.full((rows, cols), 0.5, np.float32)
    kw = dict(method="shape_select", n_levels=n, focus_heights_um=np.arange(n) * 2.0,
              window=9, bias_levels=0.05)
    whole = block_uncertainty(depth, sums, low, (0, rows), locking_levels=0.06, **kw)
    for k in (2, 3, 7):
        edges = np.linspace(0, rows, k + 1).astype(int)
        parts = np.concatenate([block_uncertainty(depth, sums, low, (a, b),
                                                  locking_levels=0.06, **kw)
                                for a, b in zip(edges[:-1], edges[1:], strict=True)])
        assert parts.tobytes() == whole.tobytes()
    assert (whole > block_uncertainty(depth, sums, low, (0, rows), **kw)).all()


def test_peak_departure_is_the_median_offset_from_the_three_point_peak() -> None:
    """On noise-free Gaussian curves the 3-point Gaussian is exact: a map offset by 0.25
    level departs by 0.25; curves within 2 levels of an end, masked ones and NaN depths are
    not judged; none judged is NaN."""
    from sffscan.stages.depth_statistics import peak_departure

    n, frac = 21, np.linspace(-0.4, 0.4, 9)
    peaks = np.r_[8.0 + frac, 1.0, 19.5]  # the last two lie near the ends
    z = np.arange(n, dtype=np.float64)[:, None]
    vol = np.exp(-((z - peaks[None, :]) ** 2) / (2 * 1.5 ** 2)).astype(np.float32)[:, None, :]
    centre = np.rint(peaks).astype(np.intp)[None, :]
    depth = (peaks + 0.25)[None, :]
    depth[0, -2:] += 5.0  # far off, but not judged
    assert peak_departure(depth, vol, centre) == pytest.approx(0.25, abs=1e-5)
    depth[0, :4] = np.nan  # the others still give 0.25
    assert peak_departure(depth, vol, centre) == pytest.approx(0.25, abs=1e-5)
    mask = np.zeros(centre.shape, bool)
    mask[0, 4] = True
    assert peak_departure(depth - 0.5, vol, centre, mask) == pytest.approx(-0.25, abs=1e-5)
    assert np.isnan(peak_departure(depth, vol, centre, ~np.ones(centre.shape, bool)))


def test_a_block_departure_bias_reads_the_judged_grid() -> None:
    """A scan block's bias for the 9-level centroid: the size of its depth's departure from
    the 3-point peaks at the curves block_choice judges (every 16th row, 8th column);
    0.0 for a block without data; a centre of another shape is refused."""
    from sffscan.stages.block_depth import block_departure_bias, judged_centre

    rng = np.random.default_rng(3)
    n, rows, cols = 25, 64, 32
    peaks = 6.0 + 12.0 * rng.random((rows, cols))
    z = np.arange(n, dtype=np.float64)[:, None, None]
    vol = np.exp(-((z - peaks[None]) ** 2) / (2 * 1.8 ** 2)).astype(np.float32)
    argmax = np.rint(peaks).astype(np.intp)
    centre = judged_centre(argmax, 1)
    assert block_departure_bias(vol, argmax, peaks - 0.3, centre) == pytest.approx(0.3,
                                                                                  abs=1e-4)
    # only the judged grid counts: the other pixels' depth is not read
    off = peaks - 0.3
    off[1::16] += 7.0
    assert block_departure_bias(vol, argmax, off, centre) == pytest.approx(0.3, abs=1e-4)
    assert block_departure_bias(np.zeros_like(vol), argmax, peaks, centre) == 0.0
    with pytest.raises(ValueError, match="judged curves' "):
        block_departure_bias(vol, argmax, peaks, argmax)


def test_a_focus_measure_the_constants_were_not_fitted_with_is_named() -> None:
    """The constants are fitted with GLVM 9 (the families' stacks): that measure, in any
    case, passes; any other operator or window gets a reason naming both, for a warning."""
    from sffscan.stages.fitted_constants import FITTED_FOCUS_MEASURE, uncalibrated_focus_measure

    assert FITTED_FOCUS_MEASURE == ("glvm", 9)
    assert uncalibrated_focus_measure("GLVM", 9) is None
    for op, k in (("lapm", 9), ("glvm", 5), ("tenv", 11)):
        why = uncalibrated_focus_measure(op, k)
        assert why is not None and f"{op.upper()} k={k}" in why and "GLVM k=9" in why
