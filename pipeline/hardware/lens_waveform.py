"""Lens staircase and camera trigger: the two analogue outputs of the DAQ (pure functions).

The tunable lens steps through N focus levels in a repeating staircase; the camera is
triggered on the falling edges of a square wave whose falling edges sit at the centre of
each step (thesis chapter 6.2.1, ``SFF_NOTES.md`` section 4). One frame per step, so the
staircase period is N frames and the step lasts 1 / fps. Both waves are written to one
analogue-output task and share its sample clock and start trigger, so they cannot drift.

Layout of one step of ``S`` samples (``S`` even)::

    lens     : v_k for all S samples
    trigger  : high for samples [0, S/2), low for [S/2, S): the falling edge is the
               transition into sample S/2, i.e. at the step's centre in time

The lens has half a step (1 / (2 fps)) to settle before the trigger; the exposure starts
at the centre and must end before the next step, and must be short enough not to smear
a moving point over more than one pixel (pixel scale / speed).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


def sample_rate_hz(fps: float, samples_per_step: int) -> float:
    """Output sample rate for one staircase step per frame, S/s (fps x samples per step)."""
    if fps <= 0:
        raise ValueError(f"fps must be > 0, got {fps}")
    if samples_per_step < 2 or samples_per_step % 2:
        raise ValueError(f"samples_per_step must be even and >= 2, got {samples_per_step}")
    return fps * samples_per_step


def step_voltages(n_levels: int, *, v_min: float, v_max: float, bits: int = 10,
                  full_scale_v: float = 5.0) -> np.ndarray:
    """Lens voltage of each focus level, quantised to the driver's input resolution.

    Parameters
    ----------
    n_levels : int
        Focus levels N (>= 2).
    v_min, v_max : float
        Voltage of level 0 and of level N-1, V, inside ``0..full_scale_v``.
    bits : int
        Resolution of the driver's analogue input (the Optotune driver: 10 bits).
    full_scale_v : float
        The driver's input range is 0..full_scale_v, V, in ``2**bits - 1`` steps.

    Returns
    -------
    ndarray, float64, shape (N,)
        Voltages on the driver's code grid (``code * full_scale_v / (2**bits - 1)``),
        strictly increasing. Raises ``ValueError`` if two levels would share a code.
    """
    if n_levels < 2:
        raise ValueError(f"n_levels must be >= 2, got {n_levels}")
    if not 0.0 <= v_min < v_max <= full_scale_v:
        raise ValueError(f"need 0 <= v_min < v_max <= {full_scale_v:g} V, got {v_min:g}, "
                         f"{v_max:g}")
    lsb = full_scale_v / (2**bits - 1)
    ideal = np.linspace(v_min, v_max, n_levels)
    codes = np.round(ideal / lsb)
    if np.any(np.diff(codes) <= 0):
        raise ValueError(f"{n_levels} levels across {v_min:g}..{v_max:g} V are closer than the "
                         f"driver's {bits}-bit step of {lsb * 1000:.2f} mV")
    return codes * lsb


def staircase(voltages: np.ndarray, *, samples_per_step: int) -> np.ndarray:
    """One period of the lens staircase, float64, shape (N * samples_per_step,), V."""
    return np.repeat(np.asarray(voltages, dtype=np.float64), samples_per_step)


def trigger_wave(n_levels: int, *, samples_per_step: int, v_high: float = 5.0,
                 v_low: float = 0.0) -> np.ndarray:
    """One period of the camera trigger, float64, shape (N * samples_per_step,), V.

    High over the first half of every step, low over the second: one falling edge per
    step, at its centre (sample ``k * S + S / 2``).
    """
    if samples_per_step < 2 or samples_per_step % 2:
        raise ValueError(f"samples_per_step must be even and >= 2, got {samples_per_step}")
    half = samples_per_step // 2
    step = np.concatenate([np.full(half, v_high), np.full(half, v_low)])
    return np.tile(step, n_levels)


def falling_edges(wave: np.ndarray, *, periodic: bool = True) -> np.ndarray:
    """Sample indices where ``wave`` goes from above to below its mid level (int64).

    Index i means the transition happens between sample i - 1 and sample i; with
    ``periodic`` the last sample is followed by the first (continuous regeneration).
    """
    w = np.asarray(wave, dtype=np.float64)
    mid = 0.5 * (w.max() + w.min())
    high = w > mid
    prev = np.roll(high, 1) if periodic else np.concatenate([[False], high[:-1]])
    return np.flatnonzero(prev & ~high)


def max_exposure_us(pixel_um: float, speed_mm_s: float) -> float:
    """Longest exposure before a moving point smears over one pixel, µs.

    ``pixel scale / speed``: 8.5 µm at 15 mm/s gives 566.7 µs.
    """
    if pixel_um <= 0 or speed_mm_s <= 0:
        raise ValueError("pixel_um and speed_mm_s must be > 0")
    return pixel_um / speed_mm_s * 1000.0


def exposure_window_us(fps: float) -> float:
    """Time from the trigger (step centre) to the next step, µs: 1 / (2 fps)."""
    return 0.5e6 / fps


@dataclass(frozen=True)
class Waveform:
    """One period of both outputs, ready for continuous regeneration.

    ``lens`` and ``trigger`` are float64 (N * S,), V; ``rate_hz`` the shared sample rate;
    ``voltages`` the (N,) quantised step voltages.
    """

    lens: np.ndarray
    trigger: np.ndarray
    rate_hz: float
    samples_per_step: int
    voltages: np.ndarray

    @property
    def samples(self) -> int:
        return int(self.lens.shape[0])

    @property
    def period_s(self) -> float:
        """Duration of one staircase period (N frames), s."""
        return self.samples / self.rate_hz

    def stacked(self) -> np.ndarray:
        """(2, samples) array in channel order lens, trigger: what the DAQ task writes."""
        return np.vstack([self.lens, self.trigger])


def make_waveform(n_levels: int, *, fps: float, v_min: float, v_max: float, bits: int = 10,
                  full_scale_v: float = 5.0, samples_per_step: int = 20,
                  v_high: float = 5.0) -> Waveform:
    """The lens staircase and camera trigger for N levels at ``fps`` frames/s."""
    rate = sample_rate_hz(fps, samples_per_step)
    volts = step_voltages(n_levels, v_min=v_min, v_max=v_max, bits=bits,
                          full_scale_v=full_scale_v)
    return Waveform(staircase(volts, samples_per_step=samples_per_step),
                    trigger_wave(n_levels, samples_per_step=samples_per_step, v_high=v_high),
                    rate, samples_per_step, volts)
