"""The height uncertainty on a textured, continuous surface with no edge: it follows the
error, it does not flag a clean part as unknown.

4261f8c's width excess (how much wider a curve is than the mean of those about it) took the
pixel-to-pixel scatter of the curves' widths on such a surface for a window seeing two
heights: the clean demo print was ``unknown`` on every object (a third of its pixels with a
sigma above the 0.5 level tolerance, its error 0.03 level RMS). The stacks here are flat
plates (slightly tilted) under a band-limited texture with wide focus curves (2.4 .. 2.6
levels, the demo's 3.5), rendered by the study's generator with draws of their own (not a
family of the fit; the test asserts the surface is clean: every error well within the
tolerance).
"""

from __future__ import annotations

import numpy as np
import pytest
from sffscan.stages.depth import depth_from_focus, first_argmax, focus_sums
from sffscan.stages.depth_choice import method_bias
from sffscan.stages.depth_uncertainty import height_uncertainty_um
from sffscan.stages.focus_measure import focus_measure
from sffscan.stages.sim.families import STEP_UM, Family, family_stack

TEXTURED_FLATS = (
    Family("textured-flat", surface="flat", noise="light", texture_px=(1.5, 2.5),
           contrast=(0.15, 0.25), blur_per_level_px=(0.2, 0.3)),
    Family("textured-flat", surface="flat", noise="light", texture_px=(1.0, 2.0),
           contrast=(0.15, 0.25), blur_per_level_px=(0.15, 0.25)),
)

RMS_MULTIPLE = 3.0
"""How far above the error's RMS the uncertainty's 75th percentile may lie. A calibrated one
sigma (|error| <= 2 sigma for 90 .. 98 % of the pixels) is about the RMS of the errors it
describes (Gaussian errors: 95 % within 2 RMS); a factor of 3 leaves room for the sigma's
spread from pixel to pixel and for a model fitted on other families being conservative on
this one, not for a term that does not shrink with the error."""

TOLERANCE_LEVELS = 0.5
"""A tolerance, levels (the demo job's: 100 µm at 200 µm per level)."""


@pytest.mark.parametrize("family", TEXTURED_FLATS, ids=("coarser", "finer"))
def test_uncertainty_follows_the_error_on_a_textured_flat(family: Family) -> None:
    s = family_stack(family, 0, size_px=96, n_levels=30)
    vol = focus_measure(s.images, window=9)
    d = depth_from_focus(vol, method="adaptive")[0]
    bias = method_bias(vol, first_argmax(vol), "adaptive")  # as a stack or scan adds it
    sigma = height_uncertainty_um(d, focus_sums(vol), vol.min(axis=0), method="adaptive",
                                  n_levels=30,
                                  focus_heights_um=s.focus_um, bias_levels=bias) / STEP_UM
    inner = (slice(4, -4), slice(4, -4))
    err = np.abs(d - s.truth_um / STEP_UM)[inner]
    sig = sigma[inner]
    rms = float(np.sqrt(np.mean(err**2)))
    p75 = float(np.percentile(sig, 75))
    over = float(np.mean(sig > TOLERANCE_LEVELS))
    covered = float(np.mean(err <= 2.0 * sig))
    p99 = float(np.percentile(err, 99))
    print(f"grain {family.texture_px} px: error RMS {rms:.3f}, p99 {p99:.3f} levels; "
          f"sigma p75 {p75:.3f} ({p75 / rms:.2f} x RMS), {over:.4f} above "
          f"{TOLERANCE_LEVELS}, {covered:.3f} within 2 sigma")
    # the stack is what the test means: a clean surface, every error well within tolerance
    assert p99 < TOLERANCE_LEVELS / 2
    # the uncertainty follows the error (4261f8c's: 4.9 and 6.2 x)
    assert p75 <= RMS_MULTIPLE * rms
    # and does not make the clean part unknown: a sigma above the tolerance is twice the
    # largest errors (4261f8c's: 12 and 17 % of the pixels)
    assert over <= 0.01
    # while still covering the errors (not a sigma shrunk to nothing)
    assert covered >= 0.90
