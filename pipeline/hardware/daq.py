"""The DAQ that drives the tunable lens and triggers the camera.

A :class:`Daq` takes one period of the two outputs (:class:`~.lens_waveform.Waveform`)
and regenerates it continuously from ``start`` until ``stop``. :class:`SimDaq` (the default,
``daq.kind = "sim"``) touches no hardware and records what it was asked; :class:`NidaqmxDaq`
writes both waves to one analogue-output task of an NI DAQ (thesis: USB-6343), so they
share one sample clock and one start trigger.

Synchronisation rule (what :mod:`sffscan.pipeline.hardware.camera_source` relies on): the
camera is armed
(acquisition started, waiting for triggers) before the DAQ starts; the first falling edge
of the trigger is at the centre of step 0, so the k-th frame after the start is at focus
level (k + camera.focus_phase) mod N.
"""

from __future__ import annotations

from typing import Any, Protocol

from sffscan.pipeline.config import ScanConfig
from sffscan.pipeline.hardware.lens_waveform import Waveform, make_waveform


class DaqNotFoundError(RuntimeError):
    """The NI-DAQmx driver is not installed: one sentence for the user."""


class Daq(Protocol):
    """Continuous regeneration of the lens staircase and camera trigger."""

    def start(self, waveform: Waveform) -> None: ...

    def stop(self) -> None: ...

    def close(self) -> None: ...


class SimDaq:
    """No hardware: records the waveform and the calls, for tests and simulated scans."""

    def __init__(self) -> None:
        self.waveform: Waveform | None = None
        self.calls: list[str] = []
        self.running = False

    def start(self, waveform: Waveform) -> None:
        self.waveform = waveform
        self.running = True
        self.calls.append("start")

    def stop(self) -> None:
        self.running = False
        self.calls.append("stop")

    def close(self) -> None:
        self.running = False
        self.calls.append("close")


def _not_found(err: BaseException) -> DaqNotFoundError:
    return DaqNotFoundError(
        "daq.kind = 'nidaqmx' but the NI-DAQmx driver is not installed on this machine "
        f"({type(err).__name__}); install NI-DAQmx or set daq.kind = 'sim'")


class NidaqmxDaq:
    """Both waves on one NI analogue-output task (shared clock and start trigger).

    Parameters
    ----------
    device : str
        NI-DAQmx device name (``Dev1``).
    lens_channel, trigger_channel : str
        Analogue outputs of the lens staircase and of the camera trigger (``ao0``, ``ao1``).
    lens_range_v : (float, float)
        Output range of the lens channel, V.
    trigger_v_high : float
        High level of the trigger, V.
    start_trigger : str or None
        Digital edge start trigger terminal (rising edge), or None to start at once.
    clock_source : str or None
        Sample clock terminal, or None for the onboard clock.
    """

    def __init__(self, *, device: str, lens_channel: str, trigger_channel: str,
                 lens_range_v: tuple[float, float], trigger_v_high: float,
                 start_trigger: str | None = None, clock_source: str | None = None) -> None:
        self.device = device
        self.lens_channel = lens_channel
        self.trigger_channel = trigger_channel
        self.lens_range_v = lens_range_v
        self.trigger_v_high = trigger_v_high
        self.start_trigger = start_trigger
        self.clock_source = clock_source
        self._task: Any = None

    def start(self, waveform: Waveform) -> None:
        try:
            import nidaqmx
            from nidaqmx.constants import AcquisitionType, Edge, RegenerationMode
            from nidaqmx.errors import DaqNotFoundError as NiNotFound
            from nidaqmx.errors import DaqNotSupportedError as NiNotSupported
        except ImportError as err:  # the Python package itself is missing
            raise _not_found(err) from None
        try:
            task = nidaqmx.Task("sffscan-lens-trigger")
        except (NiNotFound, NiNotSupported) as err:  # not DaqErrors: no driver library
            raise _not_found(err) from None
        self._task = task
        try:
            lo, hi = self.lens_range_v
            task.ao_channels.add_ao_voltage_chan(f"{self.device}/{self.lens_channel}",
                                                 min_val=lo, max_val=hi)
            task.ao_channels.add_ao_voltage_chan(f"{self.device}/{self.trigger_channel}",
                                                 min_val=0.0, max_val=self.trigger_v_high)
            task.timing.cfg_samp_clk_timing(waveform.rate_hz, source=self.clock_source or "",
                                            sample_mode=AcquisitionType.CONTINUOUS,
                                            samps_per_chan=waveform.samples)
            task.out_stream.regen_mode = RegenerationMode.ALLOW_REGENERATION
            if self.start_trigger:
                task.triggers.start_trigger.cfg_dig_edge_start_trig(self.start_trigger,
                                                                    trigger_edge=Edge.RISING)
            task.write(waveform.stacked(), auto_start=False)
            task.start()
        except BaseException:
            self.close()
            raise

    def stop(self) -> None:
        if self._task is not None:
            self._task.stop()

    def close(self) -> None:
        task, self._task = self._task, None
        if task is not None:
            task.close()


def waveform_for(cfg: ScanConfig) -> Waveform:
    """The staircase and trigger of a scan configuration."""
    d, o = cfg.daq, cfg.optics
    return make_waveform(o.n_levels, fps=o.fps, v_min=d.lens_v_min, v_max=d.lens_v_max,
                         bits=d.lens_dac_bits, full_scale_v=d.lens_full_scale_v,
                         samples_per_step=d.samples_per_step, v_high=d.trigger_v_high)


def open_daq(cfg: ScanConfig) -> Daq:
    """The DAQ of ``daq.kind`` (not started)."""
    d = cfg.daq
    if d.kind == "sim":
        return SimDaq()
    return NidaqmxDaq(device=d.device, lens_channel=d.lens_channel,
                      trigger_channel=d.trigger_channel,
                      lens_range_v=(0.0, d.lens_full_scale_v), trigger_v_high=d.trigger_v_high,
                      start_trigger=d.start_trigger, clock_source=d.clock_source)
