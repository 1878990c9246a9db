"""Registration's gate: which pairs are measured, and when a peak is trusted (issue 28).

With the crops' mean removed, a featureless crop no longer correlates with the window at
zero lag (which used to pull its shift to the prediction): it correlates noise. A peak is
kept only above what unrelated crops reach (:func:`null_peak_threshold`) and above its
runner-up by more than noise (:func:`runner_up_margin`).
"""

from __future__ import annotations

import math

import cv2
import numpy as np
import pytest
from sffscan.stages.messages import FrameHeader, PlacedFrame
from sffscan.stages.phase_correlation import (
    null_peak_threshold,
    phase_correlate,
    runner_up_margin,
)
from sffscan.stages.registration import RegistrationStage, measure_shift


def _noise_peaks(h: int, w: int, n: int, seed: int) -> np.ndarray:
    rng = np.random.default_rng(seed)
    return np.array([phase_correlate(rng.normal(size=(h, w)).astype(np.float32),
                                     rng.normal(size=(h, w)).astype(np.float32))[2]
                     for _ in range(n)])


@pytest.mark.parametrize(("h", "w"), [(64, 64), (48, 96)])
def test_null_threshold_bounds_the_peaks_of_unrelated_crops(h: int, w: int) -> None:
    """Measured on 200 pairs of pure-noise crops: the share above the threshold stays at
    or below the asked rate, and the bound is not vacuous (measured 0.07-0.11 at 0.5)."""
    peaks = _noise_peaks(h, w, 200, seed=h + w)
    rates = {p: float((peaks >= null_peak_threshold(h, w, false_alarm=p)).mean())
             for p in (0.5, 0.1, 0.01)}
    assert rates[0.5] <= 0.5 and rates[0.1] <= 0.1 and rates[0.01] <= 0.02
    assert rates[0.5] >= 0.02
    # rarer alarms, larger crops: the threshold moves the right way
    assert (null_peak_threshold(h, w, false_alarm=1e-6) > null_peak_threshold(h, w)
            > null_peak_threshold(2 * h, 2 * w))
    with pytest.raises(ValueError, match="false_alarm"):
        null_peak_threshold(h, w, false_alarm=1.0)


def test_a_featureless_pair_is_not_measured() -> None:
    """Sensor noise on a flat grey: without the gate some shift comes out (the noise's
    peak, anywhere in the crop); with it, no measurement. A textured pair still passes."""
    rng = np.random.default_rng(4)
    flat_a = (100 + rng.normal(0, 2, (128, 160))).astype(np.float32)
    flat_b = (100 + rng.normal(0, 2, (128, 160))).astype(np.float32)
    assert measure_shift(flat_a, flat_b, predicted_px=(8.0, 0.0), scale=4) is not None
    assert measure_shift(flat_a, flat_b, predicted_px=(8.0, 0.0), scale=4,
                         false_alarm=1e-3) is None
    img = rng.random((300, 400)).astype(np.float32)
    world = cv2.GaussianBlur(img, (0, 0), 1.5)
    got = measure_shift(world[20:148, 30:190], world[21:149, 33:193], predicted_px=(8.0, 0.0),
                        scale=4, false_alarm=1e-3)
    assert got is not None
    assert got[0] == pytest.approx(12.0, abs=0.3) and got[1] == pytest.approx(4.0, abs=0.3)


def _scan(n: int, *, flat: range, n_levels: int) -> tuple[list[PlacedFrame], np.ndarray]:
    rng = np.random.default_rng(7)
    img = rng.random((400, 3000)).astype(np.float32)
    world = cv2.GaussianBlur(img, (0, 0), 1.0) + 0.3 * cv2.GaussianBlur(img, (0, 0), 4.0)
    frames, truth = [], []
    for k in range(n):
        pred_x = 50 + k * 9.3
        true_x = int(round(pred_x + 3.0 * math.sin(2 * math.pi * k / 13)))
        if k in flat:  # out of focus over a flat part: grey and sensor noise
            image = np.clip(120 + rng.normal(0, 2, (256, 320)), 0, 255).astype(np.uint8)
        else:
            image = (world[40:40 + 256, true_x:true_x + 320] * 200).astype(np.uint8)
        hdr = FrameHeader(frame_id=k, timestamp_ns=k, focus_index=k % n_levels,
                          stage_x_um=pred_x, stage_y_um=40.0)
        frames.append(PlacedFrame(hdr, image, (pred_x, 40.0), (round(pred_x), 40)))
        truth.append(true_x)
    return frames, np.array(truth, float)


def test_featureless_frames_stay_at_the_prediction() -> None:
    """Frames 30-44 are featureless: their pairs are refused (not measured as noise) and
    their positions stay near the prediction, while the textured frames on either side
    keep their wobble recovered."""
    flat = range(30, 45)
    frames, truth = _scan(80, flat=flat, n_levels=8)
    stage = RegistrationStage(n_levels=8)
    out = [o for pf in frames for o in stage.process(pf)] + list(stage.finish())
    assert [o.header.frame_id for o in out] == list(range(80))
    corr = np.array([o.correction_px for o in out])
    in_flat = np.isin(np.arange(80), list(flat))
    # |wobble| <= 3 px: a featureless frame's correction is no larger (noise peaks are
    # anywhere in the crop, tens of px)
    assert np.abs(corr[in_flat]).max() <= 3.5
    # each side of the stretch has its own free constant (nothing measures across it)
    est = np.array([o.predicted_px[0] + o.correction_px[0] for o in out]) - truth
    for side in (slice(0, 30), slice(45, 80)):
        err = est[side] - est[side].mean()
        assert np.sqrt((err ** 2).mean()) < 0.3
    # every pair that touches the stretch (lags 1, 2 and 8): 16 + 17 + 23 = 56
    assert stage.extra_stats()["pairs_rejected"] >= 50


def test_a_periodic_scene_is_not_measured() -> None:
    """A grating: every period gives a peak of about the same height, and the highest is a
    guess (on the sinusoid scans, pairs across the focus staircase's wrap matched 170-230
    px off this way). Refused by the runner-up margin; without the gate a shift comes out."""
    rng = np.random.default_rng(5)
    tile = rng.random((200, 16)).astype(np.float32)
    grating = cv2.GaussianBlur(np.tile(tile, (1, 25)), (0, 0), 1.0)[:, 16:-16]  # period 16 px
    a = grating[20:148, 30:190] + rng.normal(0, 0.05, (128, 160)).astype(np.float32)
    b = grating[20:148, 35:195] + rng.normal(0, 0.05, (128, 160)).astype(np.float32)
    c = phase_correlate(a, b)
    assert c.peak >= null_peak_threshold(128, 160)  # strong, but not unique
    assert c.peak - c.runner_up < runner_up_margin(128, 160)
    assert measure_shift(a, b, predicted_px=(0.0, 0.0), scale=1) is not None
    assert measure_shift(a, b, predicted_px=(0.0, 0.0), scale=1, false_alarm=1e-3) is None
