"""The DAQ boundary: nidaqmx calls (mocked Task), the missing-driver path, the simulated DAQ."""

from __future__ import annotations

from pathlib import Path
from unittest import mock

import numpy as np
import pytest
from nidaqmx.constants import AcquisitionType, Edge, RegenerationMode
from sffscan.pipeline.cli.main import main
from sffscan.pipeline.config import config_from_dict, config_to_toml
from sffscan.pipeline.hardware.daq import (
    DaqNotFoundError,
    NidaqmxDaq,
    SimDaq,
    open_daq,
    waveform_for,
)


def _cfg(**daq: object):
    return config_from_dict({"optics": {"n_levels": 50, "fps": 150.0},
                             "daq": {"kind": "nidaqmx", "device": "Dev3", **daq}})


def test_nidaqmx_calls_at_the_library_boundary() -> None:
    cfg = _cfg(start_trigger="/Dev3/PFI0")
    wave = waveform_for(cfg)
    daq = open_daq(cfg)
    assert isinstance(daq, NidaqmxDaq)
    with mock.patch("nidaqmx.Task") as task_cls:
        task = task_cls.return_value
        daq.start(wave)
        task_cls.assert_called_once_with("sffscan-lens-trigger")
        # both outputs in ONE task: one sample clock, one start trigger
        assert task.ao_channels.add_ao_voltage_chan.call_args_list == [
            mock.call("Dev3/ao0", min_val=0.0, max_val=5.0),
            mock.call("Dev3/ao1", min_val=0.0, max_val=5.0),
        ]
        task.timing.cfg_samp_clk_timing.assert_called_once_with(
            3000.0, source="", sample_mode=AcquisitionType.CONTINUOUS, samps_per_chan=1000)
        assert task.out_stream.regen_mode == RegenerationMode.ALLOW_REGENERATION
        task.triggers.start_trigger.cfg_dig_edge_start_trig.assert_called_once_with(
            "/Dev3/PFI0", trigger_edge=Edge.RISING)
        (data,), kwargs = task.write.call_args
        assert kwargs == {"auto_start": False}
        np.testing.assert_array_equal(data, np.vstack([wave.lens, wave.trigger]))
        # written before started
        names = [c[0] for c in task.method_calls]
        assert names.index("write") < names.index("start")
        task.start.assert_called_once_with()
        task.stop.assert_not_called()
        daq.stop()
        task.stop.assert_called_once_with()
        daq.close()
        task.close.assert_called_once_with()
        daq.close()  # idempotent
        task.close.assert_called_once_with()


def test_no_start_trigger_and_external_clock() -> None:
    cfg = _cfg(clock_source="/Dev3/PFI5")
    with mock.patch("nidaqmx.Task") as task_cls:
        task = task_cls.return_value
        open_daq(cfg).start(waveform_for(cfg))
        task.triggers.start_trigger.cfg_dig_edge_start_trig.assert_not_called()
        assert task.timing.cfg_samp_clk_timing.call_args.kwargs["source"] == "/Dev3/PFI5"


def test_a_failing_call_closes_the_task() -> None:
    cfg = _cfg()
    with mock.patch("nidaqmx.Task") as task_cls:
        task = task_cls.return_value
        task.write.side_effect = RuntimeError("buffer")
        with pytest.raises(RuntimeError, match="buffer"):
            open_daq(cfg).start(waveform_for(cfg))
        task.start.assert_not_called()
        task.close.assert_called_once_with()


def test_missing_driver_is_one_clear_sentence() -> None:
    """The real nidaqmx here has no NI-DAQmx driver: its DaqNotFoundError (not a DaqError)."""
    import nidaqmx.errors

    assert not issubclass(nidaqmx.errors.DaqNotFoundError, nidaqmx.errors.DaqError)
    cfg = _cfg()
    with pytest.raises(DaqNotFoundError) as info:
        open_daq(cfg).start(waveform_for(cfg))
    msg = str(info.value)
    assert "NI-DAQmx driver is not installed" in msg and "daq.kind = 'sim'" in msg
    assert msg.count(". ") == 0 and "\n" not in msg  # one sentence


def test_sim_daq_is_the_default() -> None:
    cfg = config_from_dict({})
    daq = open_daq(cfg)
    assert isinstance(daq, SimDaq)
    wave = waveform_for(cfg)
    daq.start(wave)
    assert daq.running and daq.waveform is wave
    daq.stop()
    daq.close()
    assert daq.calls == ["start", "stop", "close"] and not daq.running


class _TriggeredCamera:
    """A camera with a hardware trigger (viky has none, and with daq.kind = 'nidaqmx' an
    untriggered camera is refused before the DAQ is reached)."""

    def __init__(self) -> None:
        self.calls: list[str] = []

    def configure(self, cfg: object) -> list[str]:
        self.calls.append("configure")
        return []

    def start(self) -> None:
        self.calls.append("start")

    def fetch(self, timeout_s: float, *, out: object = None) -> object:
        raise AssertionError("no frame may be fetched without the DAQ")

    def underruns(self) -> int | None:
        return 0

    def stop(self) -> None:
        self.calls.append("stop")

    def close(self) -> None:
        self.calls.append("close")


def _triggered_camera_with_ni_daq(tmp_path: Path, monkeypatch: pytest.MonkeyPatch
                                  ) -> tuple[_TriggeredCamera, Path]:
    """A fake triggered camera in place of the real one, and a configuration file that
    asks for it with daq.kind = 'nidaqmx'."""
    import genicam
    import sffscan.pipeline.hardware.camera_source

    cam = _TriggeredCamera()
    monkeypatch.setattr(sffscan.pipeline.hardware.camera_source, "open_camera", lambda cfg: cam)
    cfg = config_from_dict({
        "source": {"kind": "camera"},
        "optics": {"width_px": 160, "height_px": 100, "pixel_um": 17.0, "n_levels": 10,
                   "fps": 200.0, "bit_depth": 8},
        "motion": {"speed_mm_s": 20.0, "x_end_mm": 10.0},
        "camera": {"cti": str(Path(genicam.__file__).parent / "viky.cti"),
                   "pixel_format": "Mono8"},
        "daq": {"kind": "nidaqmx"}})
    path = tmp_path / "c.toml"
    path.write_text(config_to_toml(cfg), encoding="utf-8")
    return cam, path


def test_grab_without_the_driver_says_so_in_one_sentence(
        tmp_path: Path, capsys: pytest.CaptureFixture[str],
        monkeypatch: pytest.MonkeyPatch) -> None:
    """`sffscan grab` with a triggered camera and daq.kind = 'nidaqmx': the camera is
    configured, armed and released, then the missing driver is reported; exit 2."""
    cam, path = _triggered_camera_with_ni_daq(tmp_path, monkeypatch)
    assert main(["grab", "--config", str(path), "--to", "tcp://127.0.0.1:5599"]) == 2
    err = capsys.readouterr().err
    assert "sffscan grab: daq.kind = 'nidaqmx' but the NI-DAQmx driver is not installed" in err
    assert "camera: 0 frames" in err  # the camera was released (its summary printed)
    assert cam.calls == ["configure", "start", "stop", "close"]


def test_an_unsupported_platform_is_one_clear_sentence_too() -> None:
    """nidaqmx raises DaqNotSupportedError (not a DaqError either) on e.g. macOS."""
    import nidaqmx.errors

    cfg = _cfg()
    with mock.patch("nidaqmx.Task", side_effect=nidaqmx.errors.DaqNotSupportedError(
            "NI-DAQmx Python is not supported on this platform: darwin")):
        with pytest.raises(DaqNotFoundError, match="daq.kind = 'sim'") as info:
            open_daq(cfg).start(waveform_for(cfg))
    assert "\n" not in str(info.value)


def test_the_mocked_calls_exist_in_nidaqmx_with_these_arguments() -> None:
    """The mock accepts anything: bind every call made to the real nidaqmx signatures."""
    import inspect

    from nidaqmx.task import Task
    from nidaqmx.task._out_stream import OutStream
    from nidaqmx.task._timing import Timing
    from nidaqmx.task.collections import AOChannelCollection
    from nidaqmx.task.triggering._start_trigger import StartTrigger

    real = {"ao_channels.add_ao_voltage_chan": AOChannelCollection.add_ao_voltage_chan,
            "timing.cfg_samp_clk_timing": Timing.cfg_samp_clk_timing,
            "triggers.start_trigger.cfg_dig_edge_start_trig":
                StartTrigger.cfg_dig_edge_start_trig,
            "write": Task.write, "start": Task.start, "stop": Task.stop, "close": Task.close}
    assert isinstance(OutStream.regen_mode, property)
    cfg = _cfg(start_trigger="/Dev3/PFI0")
    with mock.patch("nidaqmx.Task") as task_cls:
        daq = open_daq(cfg)
        daq.start(waveform_for(cfg))
        daq.stop()
        daq.close()
        calls = task_cls.return_value.method_calls
    assert {c[0] for c in calls} == set(real)
    for name, args, kwargs in calls:
        inspect.signature(real[name]).bind(None, *args, **kwargs)  # raises if wrong


def test_scan_without_the_driver_exits_2_like_grab(
        tmp_path: Path, capsys: pytest.CaptureFixture[str],
        monkeypatch: pytest.MonkeyPatch) -> None:
    """`sffscan scan` from a triggered camera with daq.kind = 'nidaqmx' and no driver: the
    missing driver is a set-up problem, exit 2 (not a stage failure, exit 1)."""
    cam, path = _triggered_camera_with_ni_daq(tmp_path, monkeypatch)
    assert main(["scan", "--config", str(path), "-o", str(tmp_path / "m.zarr"), "-q",
                 "--no-evaluate"]) == 2
    err = capsys.readouterr().err
    assert "NI-DAQmx driver is not installed" in err
    assert cam.calls[-1] == "close"
