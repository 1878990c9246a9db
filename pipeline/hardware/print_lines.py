"""The thesis' binary interface to an industrial AM machine (chapter 7): a start and a stop
input line, and status output lines (ready, busy, alarm), on the NI DAQ's digital lines.

Protocol, as the machine sees it:

- ``ready`` high: the scanner may be started. A rising edge on ``start`` starts the scan
  of the next layer (layers count from 0); ``busy`` goes high and ``ready`` low at once.
- ``busy`` falls (and ``ready`` rises) when the scan motion is done, or after
  ``hold_timeout_s`` (the layer is then ``unknown``): the machine may go on printing.
- ``alarm`` rises when a layer's verdict is in ``alarm_on`` (``fail`` by default), even one
  that arrives after ``busy`` fell; it stays high until the next start edge.
- ``stop`` high aborts (a scan in progress is abandoned: ``abort``) and holds ``ready`` and
  ``busy`` low until ``stop`` falls.
- A start edge while busy is an ``overrun`` (the machine did not wait): reported, ignored.

:class:`PrintLineLogic` is that protocol as a pure state machine (inputs and time in,
outputs and actions out), tested exactly. :class:`NidaqmxLines` is the driver boundary
(one change-detection DI task for the inputs, one DO task for the outputs);
:class:`SimLines` replaces it in tests. :class:`PrintLinesLink` joins them to a job
service.
"""

from __future__ import annotations

import logging
import queue
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any, Literal, Protocol

log = logging.getLogger(__name__)

Action = Literal["scan", "abort", "overrun", "timeout", "late"]


@dataclass(frozen=True)
class LineOutputs:
    ready: bool = True
    busy: bool = False
    alarm: bool = False


@dataclass(frozen=True)
class Step:
    """What one input did: the outputs to write, and the actions (``scan`` carries
    :attr:`PrintLineLogic.layer`)."""

    outputs: LineOutputs
    actions: tuple[Action, ...] = ()


class PrintLineLogic:
    """The line protocol as a state machine; no I/O, no clock of its own (``t_s`` is given).

    Parameters
    ----------
    hold_timeout_s : float, keyword-only
        Longest ``busy``, s.
    alarm_on : tuple of str, keyword-only
        Verdicts that raise ``alarm``.
    """

    def __init__(self, *, hold_timeout_s: float = 120.0,
                 alarm_on: tuple[str, ...] = ("fail",)) -> None:
        if hold_timeout_s <= 0:
            raise ValueError("hold_timeout_s must be > 0")
        self.hold_timeout_s = hold_timeout_s
        self.alarm_on = alarm_on
        self.state: Literal["idle", "busy", "stopped"] = "idle"
        self.layer = -1
        self.outputs = LineOutputs()
        self._start = False
        self._since = 0.0

    def _set(self, actions: tuple[Action, ...] = (), **out: bool) -> Step:
        o = self.outputs
        self.outputs = LineOutputs(ready=out.get("ready", o.ready), busy=out.get("busy", o.busy),
                                   alarm=out.get("alarm", o.alarm))
        return Step(self.outputs, actions)

    def sample(self, start: bool, stop: bool, t_s: float) -> Step:
        """The input levels at time ``t_s`` (s, any monotonic origin)."""
        edge = start and not self._start
        self._start = start
        if stop:
            if self.state == "stopped":
                return Step(self.outputs)
            was_busy = self.state == "busy"
            self.state = "stopped"
            return self._set(("abort",) if was_busy else (), ready=False, busy=False)
        if self.state == "stopped":
            self.state = "idle"
            return self._set(ready=True)
        timed = self.tick(t_s)
        if not edge:
            return timed
        if self.state == "busy":
            return Step(self.outputs, timed.actions + ("overrun",))
        self.state, self.layer, self._since = "busy", self.layer + 1, t_s
        return self._set(timed.actions + ("scan",), ready=False, busy=True, alarm=False)

    def tick(self, t_s: float) -> Step:
        """Time passes: release a hold longer than ``hold_timeout_s``."""
        if self.state == "busy" and t_s - self._since >= self.hold_timeout_s:
            self.state = "idle"
            return self._set(("timeout",), ready=True, busy=False,
                             alarm=self.outputs.alarm or "unknown" in self.alarm_on)
        return Step(self.outputs)

    def scan_done(self, layer: int, t_s: float) -> Step:
        """The scan of ``layer`` ended (its motion is done)."""
        if self.state != "busy" or layer != self.layer:
            return Step(self.outputs, ("late",))
        self.state = "idle"
        return self._set(ready=True, busy=False)

    def verdict(self, layer: int, verdict: str) -> Step:
        """The verdict of ``layer`` (may come after ``scan_done``)."""
        if layer != self.layer or verdict not in self.alarm_on:
            return Step(self.outputs)
        return self._set(alarm=True)


class Lines(Protocol):
    """Digital lines: ``read`` blocks until an input changes (or ``timeout_s``: None)."""

    def read(self, timeout_s: float) -> tuple[bool, bool] | None: ...

    def write(self, outputs: LineOutputs) -> None: ...

    def close(self) -> None: ...


class SimLines:
    """No hardware: inputs come from :meth:`set`, outputs are recorded."""

    def __init__(self) -> None:
        self._inputs: queue.Queue[tuple[bool, bool]] = queue.Queue(maxsize=1024)
        self.written: list[LineOutputs] = []
        self.changed = threading.Condition()

    def set(self, start: bool, stop: bool = False) -> None:
        self._inputs.put((start, stop), timeout=5)

    def read(self, timeout_s: float) -> tuple[bool, bool] | None:
        try:
            return self._inputs.get(timeout=timeout_s)
        except queue.Empty:
            return None

    def write(self, outputs: LineOutputs) -> None:
        with self.changed:
            self.written.append(outputs)
            self.changed.notify_all()

    def wait_for(self, pred: Callable[[list[LineOutputs]], bool], timeout_s: float) -> bool:
        """Wait until ``pred(outputs written so far)`` is true."""
        with self.changed:
            return self.changed.wait_for(lambda: pred(self.written), timeout=timeout_s)

    def close(self) -> None:
        pass


class NidaqmxLines:
    """The lines on an NI DAQ: inputs by change detection (``read`` wakes on an edge),
    outputs on demand.

    Parameters
    ----------
    device : str
        NI-DAQmx device (``Dev1``).
    start_line, stop_line : str
        Input lines (``port0/line0``, ``port0/line1``).
    ready_line, busy_line, alarm_line : str
        Output lines (``port1/line0``...).
    """

    def __init__(self, *, device: str, start_line: str, stop_line: str, ready_line: str,
                 busy_line: str, alarm_line: str) -> None:
        self.inputs = [f"{device}/{start_line}", f"{device}/{stop_line}"]
        self.outputs = [f"{device}/{ready_line}", f"{device}/{busy_line}",
                        f"{device}/{alarm_line}"]
        self._di: Any = None
        self._do: Any = None
        self.initial: tuple[bool, bool] = (False, False)

    def open(self) -> NidaqmxLines:
        from sffscan.pipeline.hardware.daq import _not_found

        try:
            import nidaqmx
            from nidaqmx.constants import AcquisitionType, LineGrouping
            from nidaqmx.errors import DaqNotFoundError as NiNotFound
            from nidaqmx.errors import DaqNotSupportedError as NiNotSupported
        except ImportError as err:
            raise _not_found(err) from None
        per_line = LineGrouping.CHAN_PER_LINE
        try:
            with nidaqmx.Task("sffscan-lines-initial") as first:  # the levels at start
                for line in self.inputs:
                    first.di_channels.add_di_chan(line, line_grouping=per_line)
                start, stop = first.read()
                self.initial = (bool(start), bool(stop))
            self._di = nidaqmx.Task("sffscan-lines-in")
            self._do = nidaqmx.Task("sffscan-lines-out")
        except (NiNotFound, NiNotSupported) as err:
            self.close()
            raise _not_found(err) from None
        try:
            for line in self.inputs:
                self._di.di_channels.add_di_chan(line, line_grouping=per_line)
            both = ",".join(self.inputs)
            self._di.timing.cfg_change_detection_timing(
                rising_edge_chan=both, falling_edge_chan=both,
                sample_mode=AcquisitionType.CONTINUOUS)
            for line in self.outputs:
                self._do.do_channels.add_do_chan(line, line_grouping=per_line)
            self._di.start()
        except BaseException:
            self.close()
            raise
        return self

    def read(self, timeout_s: float) -> tuple[bool, bool] | None:
        from nidaqmx.errors import DaqError

        try:
            start, stop = self._di.read(number_of_samples_per_channel=1, timeout=timeout_s)
        except DaqError as err:
            if err.error_code == -200284:  # DAQmxErrors.SAMPLES_NOT_YET_AVAILABLE: no edge
                return None
            raise
        return bool(start[0]), bool(stop[0])

    def write(self, outputs: LineOutputs) -> None:
        self._do.write([outputs.ready, outputs.busy, outputs.alarm], auto_start=True)

    def close(self) -> None:
        for name in ("_di", "_do"):
            task = getattr(self, name)
            setattr(self, name, None)
            if task is not None:
                task.close()


class PrintLinesLink:
    """Lines -> logic -> a layer callback; the callback (``scan(layer) -> verdict or None``)
    runs in one worker thread, so the lines keep being read while a layer is scanned.

    Parameters
    ----------
    lines : Lines
    scan : callable
        ``layer -> verdict`` (``None`` while the verdict is still pending); it returns
        when the scan motion is done. Later verdicts come in through :meth:`verdict`.
    logic : PrintLineLogic
    initial : (bool, bool)
        The input levels when the link starts.
    """

    def __init__(self, lines: Lines, scan: Callable[[int], str | None], *,
                 logic: PrintLineLogic | None = None,
                 initial: tuple[bool, bool] = (False, False)) -> None:
        self.lines = lines
        self.scan = scan
        self.logic = logic or PrintLineLogic()
        self.actions: list[tuple[Action, int]] = []
        self._lock = threading.Lock()
        self._work: queue.Queue[int | None] = queue.Queue(maxsize=1)
        self._worker = threading.Thread(target=self._scan_loop, name="sffscan-lines-scan",
                                        daemon=True)
        self._initial = initial

    def _apply(self, step: Step) -> None:  # with the lock held
        for a in step.actions:
            self.actions.append((a, self.logic.layer))
            if a in ("abort", "overrun", "timeout", "late"):
                log.warning("print lines: %s at layer %d", a, self.logic.layer)
            if a == "scan":
                try:
                    self._work.put_nowait(self.logic.layer)
                except queue.Full:  # a timed-out scan still running: this layer waits
                    log.error("print lines: layer %d not scanned: the scanner is busy",
                              self.logic.layer)
        self.lines.write(step.outputs)

    def _scan_loop(self) -> None:
        while True:
            layer = self._work.get()
            if layer is None:
                return
            try:
                verdict = self.scan(layer)
            except Exception:
                log.exception("print lines: the scan of layer %d failed", layer)
                verdict = "unknown"
            with self._lock:
                self._apply(self.logic.scan_done(layer, time.monotonic()))
                if verdict is not None:
                    self._apply(self.logic.verdict(layer, verdict))

    def verdict(self, layer: int, verdict: str) -> None:
        with self._lock:
            self._apply(self.logic.verdict(layer, verdict))

    def run(self, stop: threading.Event, *, wake_s: float = 0.5) -> None:
        """Serve until ``stop`` is set; ``read`` wakes at least every ``wake_s`` s for the
        hold timeout."""
        self._worker.start()
        try:
            with self._lock:
                self._apply(self.logic.sample(*self._initial, time.monotonic()))
            while not stop.is_set():
                levels = self.lines.read(wake_s)
                with self._lock:
                    now = time.monotonic()
                    step = (self.logic.tick(now) if levels is None
                            else self.logic.sample(levels[0], levels[1], now))
                    self._apply(step)
        finally:
            try:
                self._work.put(None, timeout=5)
            except queue.Full:
                log.error("print lines: the scan worker is still busy at shutdown")
            self._worker.join(10)
