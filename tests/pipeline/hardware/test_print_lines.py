"""The industrial binary interface: the line protocol exactly, the link with a job service,
and the driver at nidaqmx's boundary (mocked Task, calls bound to the real signatures)."""

from __future__ import annotations

import inspect
import threading
from pathlib import Path
from unittest import mock

import pytest
from sffscan.pipeline.hardware.print_lines import (
    LineOutputs,
    NidaqmxLines,
    PrintLineLogic,
    PrintLinesLink,
    SimLines,
)
from sffscan.pipeline.printjob.service import (
    Analysis,
    JobService,
    JobStart,
    LayerEvent,
    ScanResult,
)

READY = LineOutputs(ready=True, busy=False, alarm=False)
BUSY = LineOutputs(ready=False, busy=True, alarm=False)


def test_line_protocol_exact_sequence() -> None:
    m = PrintLineLogic(hold_timeout_s=10)
    assert m.sample(False, False, 0.0).outputs == READY
    s = m.sample(True, False, 1.0)  # rising edge: layer 0
    assert (s.outputs, s.actions, m.layer) == (BUSY, ("scan",), 0)
    assert m.sample(True, False, 1.5).actions == ()  # level, no edge
    s = m.sample(False, False, 2.0)
    assert s.outputs == BUSY and s.actions == ()
    assert m.sample(True, False, 2.5).actions == ("overrun",)  # the machine did not wait
    assert m.scan_done(0, 3.0).outputs == READY
    assert m.verdict(0, "pass").outputs == READY
    assert m.verdict(0, "fail").outputs == LineOutputs(ready=True, alarm=True)
    assert m.verdict(5, "fail").actions == ()  # not the current layer: ignored
    m.sample(False, False, 3.5)
    s = m.sample(True, False, 4.0)  # layer 1 clears the alarm
    assert (s.outputs, s.actions, m.layer) == (BUSY, ("scan",), 1)
    assert m.tick(13.9).actions == ()
    s = m.tick(14.0)  # the hold timeout releases the machine
    assert (s.outputs, s.actions) == (READY, ("timeout",))
    assert m.scan_done(1, 15.0).actions == ("late",)
    m.sample(False, False, 15.5)
    m.sample(True, False, 16.0)  # layer 2
    s = m.sample(True, True, 16.5)  # stop while busy
    assert (s.outputs, s.actions) == (LineOutputs(ready=False, busy=False), ("abort",))
    assert m.sample(False, True, 17.0).actions == ()  # still stopped: start ignored
    assert m.sample(True, True, 17.5).actions == ()
    assert m.sample(False, False, 18.0).outputs == READY
    assert m.scan_done(2, 18.5).actions == ("late",)


def test_timeout_raises_the_alarm_when_unknown_is_an_alarm() -> None:
    m = PrintLineLogic(hold_timeout_s=1, alarm_on=("fail", "unknown"))
    m.sample(True, False, 0.0)
    assert m.tick(1.0).outputs == LineOutputs(ready=True, busy=False, alarm=True)
    with pytest.raises(ValueError, match="hold_timeout_s"):
        PrintLineLogic(hold_timeout_s=0)


class Handler:
    def scan(self, job: JobStart, event: LayerEvent, folder: Path) -> ScanResult:
        return ScanResult()

    def analyse(self, job: JobStart, event: LayerEvent, scan: ScanResult,
                folder: Path) -> Analysis:
        return Analysis(verdict="fail" if event.layer == 1 else "pass")


def test_link_scans_each_start_edge_through_the_service(tmp_path: Path) -> None:
    lines = SimLines()
    with JobService(tmp_path, Handler(), strict=True) as service:
        service.start_job(JobStart(job_id="line-job"))

        def scan(layer: int) -> str | None:
            return service.layer("line-job", LayerEvent(layer=layer,
                                                        z_mm=0.2 * (layer + 1))).record.verdict

        link = PrintLinesLink(lines, scan, logic=PrintLineLogic(hold_timeout_s=30))
        stop = threading.Event()
        runner = threading.Thread(target=link.run, args=(stop,), kwargs={"wake_s": 0.1})
        runner.start()
        try:
            assert lines.wait_for(lambda w: len(w) == 1, 10)  # the initial levels: ready
            for layer in range(3):
                k = len(lines.written)
                lines.set(True)
                # busy, then ready again with the layer's alarm (strict: the verdict is in)
                alarm = layer == 1
                assert lines.wait_for(lambda w, k=k, a=alarm: any(o.busy for o in w[k:]) and (
                    w[-1].ready and not w[-1].busy and w[-1].alarm is a), 10), layer
                lines.set(False)
        finally:
            stop.set()
            runner.join(10)
        assert not runner.is_alive()
        assert service.status("line-job").counts == {"pass": 2, "fail": 1}
    assert [a for a in link.actions if a[0] == "scan"] == [("scan", 0), ("scan", 1),
                                                           ("scan", 2)]


def test_nidaqmx_lines_at_the_library_boundary() -> None:
    from nidaqmx.constants import AcquisitionType, LineGrouping
    from nidaqmx.errors import DaqReadError
    from nidaqmx.task import Task
    from nidaqmx.task._timing import Timing
    from nidaqmx.task.collections import DIChannelCollection, DOChannelCollection

    real = {"di_channels.add_di_chan": DIChannelCollection.add_di_chan,
            "do_channels.add_do_chan": DOChannelCollection.add_do_chan,
            "timing.cfg_change_detection_timing": Timing.cfg_change_detection_timing,
            "read": Task.read, "write": Task.write, "start": Task.start, "close": Task.close,
            "__enter__": Task.__enter__, "__exit__": Task.__exit__}
    with mock.patch("nidaqmx.Task") as task_cls:
        first = task_cls.return_value.__enter__.return_value
        first.read.return_value = [True, False]
        lines = NidaqmxLines(device="Dev1", start_line="port0/line0", stop_line="port0/line1",
                             ready_line="port1/line0", busy_line="port1/line1",
                             alarm_line="port1/line2").open()
        assert lines.initial == (True, False)
        di = task_cls.return_value
        di.read.return_value = [[False], [True]]
        assert lines.read(0.5) == (False, True)
        di.read.side_effect = DaqReadError("no sample", -200284, 0)
        assert lines.read(0.5) is None
        di.read.side_effect = DaqReadError("device gone", -200279, 0)
        with pytest.raises(DaqReadError, match="device gone"):
            lines.read(0.5)
        lines.write(LineOutputs(ready=False, busy=True, alarm=False))
        lines.close()
        calls = task_cls.return_value.method_calls + first.method_calls
    assert [c.args[0] for c in task_cls.call_args_list] == [
        "sffscan-lines-initial", "sffscan-lines-in", "sffscan-lines-out"]
    di_chans = [c for c in calls if c[0] == "di_channels.add_di_chan"]
    assert [c.args[0] for c in di_chans] == ["Dev1/port0/line0", "Dev1/port0/line1"] * 2
    assert all(c.kwargs["line_grouping"] == LineGrouping.CHAN_PER_LINE for c in di_chans)
    cd = next(c for c in calls if c[0] == "timing.cfg_change_detection_timing")
    assert cd.kwargs == {"rising_edge_chan": "Dev1/port0/line0,Dev1/port0/line1",
                         "falling_edge_chan": "Dev1/port0/line0,Dev1/port0/line1",
                         "sample_mode": AcquisitionType.CONTINUOUS}
    do_chans = [c.args[0] for c in calls if c[0] == "do_channels.add_do_chan"]
    assert do_chans == ["Dev1/port1/line0", "Dev1/port1/line1", "Dev1/port1/line2"]
    w = next(c for c in calls if c[0] == "write")
    assert w.args == ([False, True, False],) and w.kwargs == {"auto_start": True}
    for name, args, kwargs in calls:
        if name in real:
            inspect.signature(real[name]).bind(None, *args, **kwargs)  # raises if wrong
