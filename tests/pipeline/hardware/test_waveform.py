"""Lens staircase and camera trigger (sffscan.pipeline.hardware.lens_waveform): known answers."""

from __future__ import annotations

import numpy as np
import pytest
from sffscan.pipeline.config import config_from_dict
from sffscan.pipeline.hardware.daq import waveform_for
from sffscan.pipeline.hardware.lens_waveform import (
    exposure_window_us,
    falling_edges,
    make_waveform,
    max_exposure_us,
    sample_rate_hz,
    staircase,
    step_voltages,
    trigger_wave,
)


def test_step_voltages_sit_on_the_10_bit_grid_and_span_the_range() -> None:
    v = step_voltages(50, v_min=0.0, v_max=5.0, bits=10, full_scale_v=5.0)
    lsb = 5.0 / 1023
    assert v.shape == (50,)
    assert v[0] == 0.0 and v[-1] == pytest.approx(5.0, abs=1e-12)
    codes = v / lsb
    np.testing.assert_allclose(codes, np.round(codes), atol=1e-9)  # quantised to codes
    # ideal step 1023/49 = 20.88 codes; rounding keeps every level within half a code
    np.testing.assert_allclose(codes, np.linspace(0, 1023, 50), atol=0.5 + 1e-9)
    assert set(np.diff(np.round(codes)).astype(int)) <= {20, 21}


def test_step_voltages_refuse_levels_closer_than_one_code() -> None:
    with pytest.raises(ValueError, match="10-bit step"):
        step_voltages(50, v_min=1.0, v_max=1.1, bits=10)  # 0.1 V = 20 codes < 49 steps
    with pytest.raises(ValueError, match="v_min < v_max"):
        step_voltages(5, v_min=2.0, v_max=1.0)


def test_staircase_holds_each_level_for_one_step() -> None:
    v = np.array([0.5, 1.0, 1.5])
    s = staircase(v, samples_per_step=4)
    np.testing.assert_array_equal(s, [0.5] * 4 + [1.0] * 4 + [1.5] * 4)


def test_every_falling_edge_is_at_a_step_centre() -> None:
    n, spp = 50, 20
    w = make_waveform(n, fps=150.0, v_min=0.0, v_max=5.0, samples_per_step=spp)
    edges = falling_edges(w.trigger)
    assert edges.shape == (n,)  # one trigger per step, also across the period wrap
    np.testing.assert_array_equal(edges, np.arange(n) * spp + spp // 2)
    # the lens does not change within a step, and each edge's step holds its level
    steps = np.flatnonzero(np.diff(w.lens)) + 1
    np.testing.assert_array_equal(steps, np.arange(1, n) * spp)
    np.testing.assert_array_equal(w.lens[edges], w.voltages)
    # the edge is preceded by half a step of settling and followed by half a step
    assert np.all(w.trigger[edges - 1] == 5.0) and np.all(w.trigger[edges] == 0.0)


def test_periods_and_sample_rate() -> None:
    w = make_waveform(50, fps=150.0, v_min=0.0, v_max=5.0, samples_per_step=20)
    assert sample_rate_hz(150.0, 20) == 3000.0
    assert w.rate_hz == 3000.0
    assert w.samples == 1000
    assert w.period_s == pytest.approx(50 / 150.0)  # one staircase = N frames
    # trigger period = one frame
    assert np.diff(falling_edges(w.trigger)).tolist() == [20] * 49
    assert w.stacked().shape == (2, 1000)
    assert trigger_wave(3, samples_per_step=2).tolist() == [5.0, 0.0] * 3
    with pytest.raises(ValueError, match="even"):
        sample_rate_hz(150.0, 3)


def test_exposure_limit_is_pixel_scale_over_speed() -> None:
    assert max_exposure_us(8.5, 15.0) == pytest.approx(566.667, abs=1e-3)
    assert max_exposure_us(8.5, 30.0) == pytest.approx(283.333, abs=1e-3)
    assert exposure_window_us(150.0) == pytest.approx(3333.333, abs=1e-3)
    with pytest.raises(ValueError):
        max_exposure_us(8.5, 0.0)


def test_waveform_from_configuration() -> None:
    cfg = config_from_dict({"optics": {"n_levels": 40, "fps": 100.0},
                            "daq": {"lens_v_min": 1.0, "lens_v_max": 4.0,
                                    "samples_per_step": 10}})
    w = waveform_for(cfg)
    assert w.rate_hz == 1000.0 and w.samples == 400
    assert w.voltages[0] == pytest.approx(round(1.0 / (5 / 1023)) * 5 / 1023)
    assert w.voltages[-1] == pytest.approx(round(4.0 / (5 / 1023)) * 5 / 1023)
