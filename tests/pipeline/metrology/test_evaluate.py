"""Accuracy against a truth (RMSE, CORR, PSNR, coverage) and the uncertainty's calibration
on it: known answers."""

from __future__ import annotations

import math

import numpy as np
import pytest
from sffscan.pipeline.metrology.evaluate import accuracy


def test_the_share_within_two_sigma_counts_the_pixels_with_a_sigma() -> None:
    ref = np.zeros((1, 6))
    est = np.array([[0.5, -1.5, 2.5, 3.0, np.nan, 1.0]])
    sigma = np.array([[1.0, 0.5, 1.25, np.nan, 1.0, 0.4]])
    a = accuracy(est, ref, max_depth=10.0, sigma=sigma)
    # rated: 0.5 <= 2, 1.5 > 1, 2.5 <= 2.5 (at the limit), 1.0 > 0.8; unknown sigma and a
    # missing height not rated
    assert (a.sigma_pixels, a.within_2sigma) == (4, 0.5)
    assert a.pixels == 5 and a.rmse_um == pytest.approx(math.sqrt((0.25 + 2.25 + 6.25 + 9 + 1)
                                                                   / 5))


def test_without_a_sigma_nothing_is_rated() -> None:
    a = accuracy(np.ones((2, 2)), np.zeros((2, 2)), max_depth=4.0)
    assert a.sigma_pixels == 0 and math.isnan(a.within_2sigma)
    b = accuracy(np.ones((2, 2)), np.zeros((2, 2)), max_depth=4.0,
                 sigma=np.full((2, 2), np.nan))
    assert b.sigma_pixels == 0 and math.isnan(b.within_2sigma)


def test_a_sigma_of_another_shape_is_refused() -> None:
    with pytest.raises(ValueError, match=r"sigma shape \(2, 3\) != estimate shape \(2, 2\)"):
        accuracy(np.ones((2, 2)), np.zeros((2, 2)), max_depth=4.0, sigma=np.ones((2, 3)))
