"""The focus volumes the depth benchmarks score, as the held-out protocol sees them
(:mod:`sffscan.stages.depth_study`): a synthetic family's stack (64 px, GLVM 9, the focus
window's reach left out of the scored pixels) and pertuz-simu02 (BSD-3-Clause, read in
place from ../shared/datasets), each with its true depth in focus levels.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
from sffscan.stages.depth_levels import levels_from_heights
from sffscan.stages.focus_measure import focus_measure
from sffscan.stages.sim.families import Family, family_stack

PERTUZ = (Path(__file__).resolve().parents[2] / "shared" / "datasets" / "pertuz-simu02"
          / "imdata.mat")

Scored = tuple[np.ndarray, np.ndarray, np.ndarray]
"""(focus volume (N, H, W) float32, true depth (H, W) in levels, scored pixels (H, W) bool)"""


def family_volume(family: str | Family, seed: int, *, size_px: int = 64, window: int = 9) -> Scored:
    """A family's stack as the study scores it (GLVM, ``window`` px)."""
    st = family_stack(family, seed, size_px=size_px)
    vol = focus_measure(st.images, operator="glvm", window=window)
    m = window // 2
    mask = np.zeros(st.truth_um.shape, bool)
    mask[m:-m, m:-m] = True  # the focus window's reach left out, as the study does
    truth = (st.truth_um - st.focus_um[0]) / (st.focus_um[1] - st.focus_um[0])
    return vol, truth, mask


def pertuz_volume(path: Path = PERTUZ, *, window: int = 9) -> Scored:
    """pertuz-simu02 (its ROI scored), GLVM ``window`` px."""
    from sffscan.pipeline.cli.study_stacks import read_imdata

    pz = read_imdata(path)
    vol = focus_measure(pz.images, operator="glvm", window=window)
    return vol, levels_from_heights(pz.truth_um, focus_heights_um=pz.focus_um), pz.mask
