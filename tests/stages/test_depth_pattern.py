"""Chapter 3 of the thesis reproduced on a stationary simulated stack.

The thesis: 60 images of 300 x 300 px of a sinusoidal surface, TENV 5 x 5, Gaussian noise
of variance 0.005 added to images in 0..1. PC and SPC gave about 35-38 % lower RMSE than
argmax; Gaussian and quadratic 3-point fits barely differed from argmax; the centroid was
worse than argmax. The bars: SPC <= 0.7 x argmax, centroid > argmax, gauss3 and
quadratic3 within 5 % of argmax.

The thesis' stack came from a simulation tool that blurs a texture image; the texture here
is likewise fine-grained (1-2 px scales). With the plate's default texture, whose energy
sits at 4-8 px, noise of variance 0.005 swamps the focus peak of most pixels and argmax
degrades so much (7.4 levels RMSE) that even the centroid beats it: measured, not hidden.
"""

from __future__ import annotations

import numpy as np
import pytest
from sffscan.stages.depth import DEPTH_METHODS, depth_from_focus
from sffscan.stages.focus_measure import focus_measure
from sffscan.stages.sim.chapter3 import STEP_UM, chapter3_stack


@pytest.fixture(scope="module")
def rmse_by_method() -> dict[str, float]:
    noisy, heights, truth_um = chapter3_stack(noise=0.005)
    vol = focus_measure(noisy, operator="tenv", window=5)
    truth = (truth_um - heights[0]) / STEP_UM
    out = {}
    for method in DEPTH_METHODS:
        depth, _ = depth_from_focus(vol, method=method)
        out[method] = float(np.sqrt(np.mean((depth - truth) ** 2)))
    print("\nchapter-3 pattern, RMSE in focus levels: "
          + ", ".join(f"{k} {v:.3f}" for k, v in out.items()))
    return out


def test_spc_beats_argmax_by_30_percent(rmse_by_method: dict[str, float]) -> None:
    assert rmse_by_method["spc"] <= 0.7 * rmse_by_method["argmax"]
    assert rmse_by_method["spc"] <= rmse_by_method["pc"] * 1.001


def test_centroid_is_worse_than_argmax(rmse_by_method: dict[str, float]) -> None:
    assert rmse_by_method["centroid"] > rmse_by_method["argmax"]


@pytest.mark.parametrize("method", ["gauss3", "quadratic3"])
def test_three_point_fits_barely_differ(rmse_by_method: dict[str, float], method: str) -> None:
    assert abs(rmse_by_method[method] / rmse_by_method["argmax"] - 1.0) <= 0.05
