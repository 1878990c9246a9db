"""Klipper's motion queue for the Moonraker agent: the toolhead's trapezoidal motion queue
streamed from Klipper's API server (``motion_report/dump_trapq``) through Moonraker's
*bridge* websocket (``ws://host:7125/klippysocket``, Moonraker's documented passthrough to
Klipper's API server for the "dump" requests), and stored with the layer's raw recording.

Protocol (Klipper ``docs/API_Server.md``)::

    agent -> klippy  {"id": 1, "method": "motion_report/dump_trapq",
                      "params": {"name": "toolhead", "response_template": {"q": ...}}}
    klippy -> agent  {"id": 1, "result": {"header": ["time", "duration", "start_velocity",
                      "acceleration", "start_position", "direction"]}}
    klippy -> agent  {"params": {"data": [[time, duration, v0, a, [x, y, z], [dx, dy, dz]],
                      ...]}, "q": ...}                    (a batch every ~0.5 s, while subscribed)

The frames' time stamps are tied to print time at the trigger: the macro waits for the
moves (``M400``) and sets the trigger pin, which Klipper schedules at the start of the
raster's first move, and the camera's first frame is exposed at that edge. So the first
frame's time stamp is the print time at which the first move from a standstill at the
region's start begins, among the rows streamed since the layer's call
(:func:`~sffscan.pipeline.formats.recording_motion.trigger_print_time`), and the stage
origin is the printer position that puts the first frame where its header says (the scan
configuration's start).
"""

from __future__ import annotations

import json
import logging
import threading
import time
from collections import deque
from collections.abc import Callable
from pathlib import Path
from typing import Any
from urllib.parse import urlsplit, urlunsplit

from sffscan.pipeline.formats.recording import FrameClock, MotionQueue
from sffscan.pipeline.formats.recording_motion import (
    MotionQueueError,
    add_motion_queue,
    motion_queue_for,
    segments_from_dump,
    trigger_print_time,
)

log = logging.getLogger(__name__)

METHOD = "motion_report/dump_trapq"
HEADER = ["time", "duration", "start_velocity", "acceleration", "start_position", "direction"]
#: rows kept (the oldest go first; the agent clears them at each layer call): about 3 rows
#: per move, a layer's moves and its raster
MAX_ROWS = 50_000


def bridge_url(agent_url: str) -> str:
    """Moonraker's bridge websocket beside its main one: ``.../websocket`` ->
    ``.../klippysocket``."""
    parts = urlsplit(agent_url)
    path = parts.path.rsplit("/", 1)[0] + "/klippysocket"
    return urlunsplit((parts.scheme, parts.netloc, path, "", ""))


def await_reply(ws: Any, rid: int, *, timeout_s: float,
                on_other: Callable[[dict[str, Any]], None],
                no_answer: Callable[[], Exception]) -> dict[str, Any]:
    """The JSON-RPC message answering request ``rid`` on the websocket ``ws``; each message
    received before it (notifications, other answers) goes to ``on_other``. Raises
    ``no_answer()`` when nothing answers within ``timeout_s``. The Moonraker agent's calls
    and the motion-queue subscription both wait so."""
    deadline = time.monotonic() + timeout_s
    while True:
        left = deadline - time.monotonic()
        if left <= 0:
            raise no_answer()
        msg = json.loads(ws.recv(timeout=left))
        if msg.get("id") == rid:
            return dict(msg)
        on_other(msg)


class TrapqStream:
    """A subscription to ``motion_report/dump_trapq`` kept open in a thread.

    Parameters
    ----------
    url : str
        Moonraker's bridge websocket (:func:`bridge_url`), or any websocket that speaks
        Klipper's API protocol without the ``0x03`` terminator.
    name : str, keyword-only
        The motion queue (``toolhead``).
    timeout_s : float, keyword-only
        Longest wait for the connection and the subscription's answer, s.
    max_rows : int, keyword-only
        Rows kept, the oldest dropped first.
    retry_s : float or None, keyword-only
        When the connection cannot be opened or is lost (Moonraker answers 503 while Klippy
        is not connected, a firmware restart, a dropped socket), try again after this many
        seconds until :meth:`close`; None: give up (:attr:`error` says why). A refusal
        by Klipper itself (an error or an unknown header) is never retried.
    """

    def __init__(self, url: str, *, name: str = "toolhead", timeout_s: float = 10.0,
                 max_rows: int = MAX_ROWS, retry_s: float | None = None) -> None:
        self.url, self.name, self.timeout_s, self.retry_s = url, name, timeout_s, retry_s
        self._rows: deque[list[Any]] = deque(maxlen=max_rows)
        self._cond = threading.Condition()
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self._ready = threading.Event()
        self.error: str | None = None  # why the stream stopped, if it did

    def start(self) -> TrapqStream:
        """Connect and subscribe, in the stream's thread; returns when Klipper has answered
        (raises ``MotionQueueError`` when it refuses, or nothing answers in time)."""
        self._ready = threading.Event()
        self._thread = threading.Thread(target=self._run, name="sffscan-trapq", daemon=True)
        self._thread.start()
        if not self._ready.wait(self.timeout_s + 1.0):
            why = f" (last: {self.error})" if self.error else ""
            if self.retry_s is None:
                self.close()
            raise MotionQueueError(f"{self.url}: no answer to {METHOD} within "
                                   f"{self.timeout_s:g} s{why}"
                                   + ("; still trying" if self.retry_s is not None else ""))
        if self.error is not None:
            self.close()
            raise MotionQueueError(self.error)
        return self

    def _subscribe(self, ws: Any) -> None:
        ws.send(json.dumps({"id": 1, "method": METHOD, "params": {
            "name": self.name, "response_template": {"q": "sffscan_trapq"}}}))
        msg = await_reply(ws, 1, timeout_s=self.timeout_s, on_other=self._take,
                          no_answer=lambda: MotionQueueError(
                              f"{self.url}: no answer to {METHOD} within "
                              f"{self.timeout_s:g} s"))
        if "error" in msg or list((msg.get("result") or {}).get("header", [])) != HEADER:
            raise MotionQueueError(f"{self.url}: {METHOD} {self.name!r} answered "
                                   f"{msg.get('error') or msg.get('result')!r}, expected "
                                   f"the header {HEADER}")

    def _take(self, msg: dict[str, Any]) -> None:
        data = (msg.get("params") or {}).get("data")
        if isinstance(data, list) and data:
            with self._cond:
                self._rows.extend(data)
                self._cond.notify_all()

    def _run(self) -> None:
        from websockets.exceptions import ConnectionClosed, InvalidHandshake
        from websockets.sync.client import connect

        while not self._stop.is_set():
            try:
                with connect(self.url, open_timeout=self.timeout_s, close_timeout=2.0) as ws:
                    self._subscribe(ws)
                    self.error = None
                    self._ready.set()
                    while not self._stop.is_set():
                        try:
                            raw = ws.recv(timeout=0.5)  # wakes to see ``_stop``
                        except TimeoutError:
                            continue
                        self._take(json.loads(raw))
            except MotionQueueError as err:  # Klipper refused: asking again changes nothing
                self.error = str(err)
                break
            except (ConnectionClosed, InvalidHandshake, OSError, ValueError,
                    TimeoutError) as err:
                lost = self._ready.is_set() and self.error is None
                self.error = f"{self.url}: {type(err).__name__}: {err}"
                if lost:
                    log.warning("motion queue stream stopped: %s%s", self.error,
                                "" if self.retry_s is None else "; reconnecting")
                if self.retry_s is None:
                    break
            if self._stop.wait(self.retry_s or 0.0):
                break
        self._ready.set()
        with self._cond:
            self._cond.notify_all()

    def rows(self) -> list[list[Any]]:
        with self._cond:
            return list(self._rows)

    def clear(self) -> None:
        """Forget the rows received so far (the agent does at each layer call: the layer's
        raster comes after it)."""
        with self._cond:
            self._rows.clear()

    def wait_for(self, predicate: Callable[[list[list[Any]]], bool], *,
                 timeout_s: float) -> bool:
        """Wait (woken by each batch, up to ``timeout_s``) until ``predicate(rows)``; False
        when it never holds, or the stream stopped."""
        deadline = time.monotonic() + timeout_s
        with self._cond:
            while True:
                if predicate(list(self._rows)):
                    return True
                left = deadline - time.monotonic()
                if left <= 0 or self._thread is None or not self._thread.is_alive():
                    return False
                self._cond.wait(left)

    def wait_until(self, print_time_s: float, *, timeout_s: float) -> bool:
        """Wait until the rows reach ``print_time_s`` (a segment ends at or after it)."""
        return self.wait_for(lambda rows: any(float(r[0]) + float(r[1]) >= print_time_s
                                              for r in rows[-64:]), timeout_s=timeout_s)

    def close(self) -> None:
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout=self.timeout_s + 3.0)


def attach_trapq(recording: str | Path, stream: TrapqStream, *,
                 region_start_mm: tuple[float, float], timeout_s: float = 3.0,
                 margin_s: float = 1.0, axis_sign: tuple[int, int] = (1, 1)) -> MotionQueue:
    """Store the motion queue over a layer's scan with its recording.

    The raster's start is the first move from a standstill at ``region_start_mm`` in the
    rows received (:func:`trigger_print_time`; the agent clears the rows at the layer call,
    so it is this layer's); the first frame's time stamp is that print time; the rows are
    waited for (up to ``timeout_s`` in all) until they hold that start and cover the last
    frame, and those within ``margin_s`` of the frames are stored.

    Raises
    ------
    MotionQueueError
        No raster start in the rows, rows that do not reach the last frame in time, or a
        queue that does not cover every frame (nothing is then written).
    """
    from sffscan.pipeline.formats.recording_reader import open_recording

    rec = open_recording(recording, motion=False)
    ts = rec.meta["timestamp_ns"][rec.order]
    first = int(rec.order[0])
    span_s = float(ts.max() - ts.min()) * 1e-9
    where = f"{stream.url} {METHOD}"

    def started(rows: list[list[Any]]) -> bool:
        try:
            trigger_print_time(segments_from_dump(rows, where=where), region_start_mm)
        except MotionQueueError:
            return False
        return True

    t_wait = time.monotonic()
    if not stream.wait_for(started, timeout_s=timeout_s):
        rows = stream.rows()
        if not rows:
            raise MotionQueueError(f"{recording}: no row of the motion queue received "
                                   f"within {timeout_s:g} s "
                                   f"({stream.error or 'nothing streamed'})")
        trigger_print_time(segments_from_dump(rows, where=where), region_start_mm)  # raises
    t0 = trigger_print_time(segments_from_dump(stream.rows(), where=where), region_start_mm)
    left = max(0.0, timeout_s - (time.monotonic() - t_wait))
    if not stream.wait_until(t0 + span_s, timeout_s=left):
        raise MotionQueueError(f"{recording}: the motion queue did not reach the last frame "
                               f"(print time {t0 + span_s:.3f} s) within {timeout_s:g} s")
    seg = segments_from_dump(stream.rows(), where=where)
    keep = (seg[:, 0] + seg[:, 1] >= t0 - margin_s) & (seg[:, 0] <= t0 + span_s + margin_s)
    seg = seg[keep]
    h = rec.header(first)
    sx = 0.0 if h.stage_x_um is None else h.stage_x_um
    sy = 0.0 if h.stage_y_um is None else h.stage_y_um
    origin = (region_start_mm[0] - axis_sign[0] * sx / 1000.0,
              region_start_mm[1] - axis_sign[1] * sy / 1000.0)
    clock = FrameClock(timestamp_ns_at=int(ts.min()), print_time_s_at=t0,
                       how=f"trigger: the first frame at the start of the raster's first "
                           f"move from ({region_start_mm[0]:g}, {region_start_mm[1]:g}) mm")
    motion = motion_queue_for(seg, clock=clock, stage_origin_mm=origin, axis_sign=axis_sign)
    add_motion_queue(recording, seg, motion)
    log.info("%s: motion queue stored (%d segments, %.3f-%.3f s)", recording, len(seg),
             motion.start_s, motion.end_s)
    return motion


__all__ = ["TrapqStream", "attach_trapq", "await_reply", "bridge_url", "METHOD", "HEADER"]
