"""Klipper link: a Moonraker *agent* (websocket JSON-RPC) that turns the ``SFFSCAN_LAYER``
macro's remote-method call into a layer event of the job service.

Protocol (Moonraker's documented agent API, ``docs/external_api/extensions.md``)::

    agent -> moonraker  server.connection.identify {client_name, version, type: "agent", url}
    agent -> moonraker  connection.register_remote_method {method_name: "sffscan_layer"}
    klipper macro       {action_call_remote_method("sffscan_layer", layer=.., z=.., ...)}
    moonraker -> agent  {"method": "sffscan_layer", "params": {...}}          (notification)
    agent -> moonraker  printer.gcode.script {script: "SFFSCAN_DONE ACTION=.. REASON=.."}
    agent -> moonraker  connection.send_event {event: "sffscan_verdict", data: record}
    moonraker -> agent  notify_history_changed {action: "finished", job: {...}}  -> job end

The macro (``printer_links/klipper/sffscan.cfg``) pauses the print after its scan moves
and waits (a ``delayed_gcode`` loop with a release timeout) until ``SFFSCAN_DONE`` clears
its ``busy`` variable; ``SFFSCAN_DONE ACTION=pause|cancel`` keeps it paused or cancels.
"""

from __future__ import annotations

import itertools
import json
import logging
import re
import threading
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

from sffscan.pipeline.formats.recording import RecordingError
from sffscan.pipeline.printjob.links_trapq import (
    TrapqStream,
    attach_trapq,
    await_reply,
    bridge_url,
)
from sffscan.pipeline.printjob.service import (
    JobEnd,
    JobService,
    JobStart,
    LayerEvent,
    LayerReply,
    ServiceError,
)

log = logging.getLogger(__name__)

METHOD = "sffscan_layer"
ACTION_KEYS = {"fail": "fail", "warn": "warn", "unknown": "unknown"}
_SAFE = re.compile(r"[^A-Za-z0-9._-]+")


class AgentError(RuntimeError):
    """Moonraker refused the agent (identify or registration), or did not answer."""


def job_id_for(filename: str, stamp: str) -> str:
    base = _SAFE.sub("-", filename.rsplit("/", 1)[-1]).strip("-.") or "job"
    return f"{base[:80]}-{stamp}"


def gcode_quote(text: str) -> str:
    """A Klipper G-code parameter value: one line, no double quotes."""
    return '"' + " ".join(text.replace('"', "'").split())[:200] + '"'


class ServiceBridge:
    """Layer calls of one printer -> a :class:`JobService`: starts a job at the first layer
    of a file, ends it when Moonraker reports the print finished.

    Parameters
    ----------
    service : JobService
    actions : dict, keyword-only
        Verdict -> ``none`` / ``pause`` / ``cancel`` (keys ``fail``, ``warn``, ``unknown``).
    """

    def __init__(self, service: JobService, *, actions: dict[str, str] | None = None,
                 printer: str = "klipper") -> None:
        self.service = service
        self.actions = {"fail": "pause", "warn": "none", "unknown": "none", **(actions or {})}
        bad = {k: v for k, v in self.actions.items() if v not in ("none", "pause", "cancel")}
        if bad:
            raise ValueError(f"actions: {bad} (each must be none, pause or cancel)")
        self.printer = printer
        self.job_id: str | None = None
        self._filename: str | None = None
        self._acted: set[int] = set()

    def layer(self, params: dict[str, Any]) -> tuple[str, str, LayerReply | None]:
        """(action, reason, reply) for one ``sffscan_layer`` call; never raises."""
        try:
            filename = str(params.get("filename") or "job")
            if self.job_id is None or filename != self._filename:
                if self.job_id is not None:
                    self.end("cancelled", reason=f"a new file started: {filename}")
                self.job_id = job_id_for(filename, time.strftime("%Y%m%dT%H%M%S"))
                self._filename, self._acted = filename, set()
                self.service.start_job(JobStart(job_id=self.job_id, printer=self.printer,
                                                gcode_name=filename))
            region = params.get("region")
            event = LayerEvent(layer=int(params["layer"]), z_mm=float(params["z"]),
                               region_mm=tuple(region) if region else None)
            reply = self.service.layer(self.job_id, event)
        except (ServiceError, ValueError, KeyError, TypeError) as err:
            reason = f"layer event {params} refused: {err}"
            log.error("%s", reason)
            return self.actions["unknown"], reason, None
        action, reason = "none", ""
        rank = {"none": 0, "pause": 1, "cancel": 2}
        for rec in [reply.record, *reply.alerts]:
            key = ACTION_KEYS.get(rec.verdict)
            if key is None or rec.layer in self._acted:
                continue
            act = self.actions[key]
            if act != "none":
                self._acted.add(rec.layer)
            if rank[act] > rank[action]:
                action = act
                reason = f"layer {rec.layer} verdict {rec.verdict}: {rec.reason or 'no reason'}"
        return action, reason, reply

    def recording_of(self, reply: LayerReply) -> Path | None:
        """The raw recording of a replied layer (beside its scan's output), if there is one."""
        out = reply.record.output
        if not out or reply.repeated:
            return None
        path = Path(self.service.store) / reply.job_id / Path(out).parent / "recording.zarr"
        return path if path.is_dir() else None

    def end(self, outcome: str, *, reason: str = "") -> None:
        job_id, self.job_id = self.job_id, None
        if job_id is None:
            return
        try:
            self.service.end_job(job_id, JobEnd(outcome=outcome, reason=reason))  # type: ignore[arg-type]
        except ServiceError as err:
            log.error("job %s: could not end it: %s", job_id, err)


class MoonrakerAgent:
    """The websocket agent (``websockets``' synchronous client).

    Parameters
    ----------
    url : str
        Moonraker's websocket, ``ws://127.0.0.1:7125/websocket``.
    on_layer : callable
        ``params -> (action, reason, reply)`` (:meth:`ServiceBridge.layer`).
    on_finished : callable, optional
        ``outcome -> None`` when Moonraker reports the print finished.
    api_key : str, optional
        Moonraker API key (for a connection that is not a trusted client).
    timeout_s : float
        Longest wait for Moonraker's answer to identify / register, s.
    recording_of : callable, optional
        ``reply -> path or None``: the layer's raw recording (:meth:`ServiceBridge.
        recording_of`). With it, the agent subscribes to Klipper's motion queue through
        Moonraker's bridge websocket (``trapq_url``, default beside ``url``) and stores
        the queue over each layer's scan with its recording
        (:func:`~sffscan.pipeline.printjob.links_trapq.attach_trapq`); without the bridge
        (no Klippy, an older Moonraker) the layers are scanned as before and a warning says
        why.
    """

    def __init__(self, url: str, *, on_layer: Callable[[dict[str, Any]], tuple[str, str, Any]],
                 on_finished: Callable[[str], None] | None = None, api_key: str | None = None,
                 timeout_s: float = 10.0,
                 recording_of: Callable[[LayerReply], Path | None] | None = None,
                 trapq_url: str | None = None) -> None:
        self.url = url
        self.on_layer = on_layer
        self.on_finished = on_finished
        self.api_key = api_key
        self.timeout_s = timeout_s
        self.recording_of = recording_of
        self.trapq_url = trapq_url or bridge_url(url)
        self.trapq: TrapqStream | None = None
        self.trapq_notes: list[str] = []  # why a layer has no motion queue, per layer
        self._ids = itertools.count(1)
        self.sent: list[dict[str, Any]] = []  # what the agent asked of Moonraker, in order

    def _send(self, ws: Any, method: str, params: dict[str, Any], *,
              want_id: bool = True) -> int | None:
        msg: dict[str, Any] = {"jsonrpc": "2.0", "method": method, "params": params}
        rid = next(self._ids) if want_id else None
        if rid is not None:
            msg["id"] = rid
        self.sent.append(msg)
        ws.send(json.dumps(msg))
        return rid

    def _call(self, ws: Any, method: str, params: dict[str, Any]) -> Any:
        """Send a request and wait for its answer (notifications before it are handled)."""
        rid = self._send(ws, method, params)
        assert rid is not None
        msg = await_reply(ws, rid, timeout_s=self.timeout_s,
                          on_other=lambda m: self._handle(ws, m),
                          no_answer=lambda: AgentError(f"{method}: no answer from {self.url} "
                                                       f"within {self.timeout_s:g} s"))
        if "error" in msg:
            raise AgentError(f"{method}: {msg['error'].get('message', msg['error'])}")
        return msg.get("result")

    def run(self, stop: threading.Event) -> None:
        """Connect, identify, register, then serve calls until ``stop`` is set or the
        connection closes."""
        from websockets.sync.client import connect

        with connect(self.url, open_timeout=self.timeout_s,
                     close_timeout=self.timeout_s) as ws:
            ident: dict[str, Any] = {"client_name": "sffscan", "version": "0.1.0",
                                     "type": "agent", "url": "https://github.com/sffscan"}
            if self.api_key:
                ident["api_key"] = self.api_key
            self._call(ws, "server.connection.identify", ident)
            self._call(ws, "connection.register_remote_method", {"method_name": METHOD})
            log.info("moonraker agent registered %s at %s", METHOD, self.url)
            if self.recording_of is not None:
                self._subscribe_trapq()
            try:
                self._serve(ws, stop)
            finally:
                if self.trapq is not None:
                    self.trapq.close()
                    self.trapq = None

    def _subscribe_trapq(self) -> None:
        # the stream reconnects on its own (Klippy restarting, Moonraker's 503 while Klippy
        # is not connected); a layer called before it is up keeps the scanner's positions
        stream = TrapqStream(self.trapq_url, timeout_s=self.timeout_s, retry_s=2.0)
        try:
            self.trapq = stream.start()
        except Exception as err:  # noqa: BLE001 - no bridge: positions from the headers
            alive = stream.error is None or "still trying" in str(err)
            self.trapq = stream if alive else None
            if not alive:
                stream.close()
            note = (f"no motion queue from {self.trapq_url} yet ({type(err).__name__}: "
                    f"{err}); frames keep the scanner's positions until it answers")
            self.trapq_notes.append(note)
            log.warning("%s", note)

    def _serve(self, ws: Any, stop: threading.Event) -> None:
        from websockets.exceptions import ConnectionClosed

        while not stop.is_set():
            try:
                raw = ws.recv(timeout=0.5)  # wakes to see ``stop``
            except TimeoutError:
                continue
            except ConnectionClosed:
                log.warning("moonraker closed the connection")
                return
            try:
                self._handle(ws, json.loads(raw))
            except ConnectionClosed:  # closed while the agent answered
                log.warning("moonraker closed the connection before the answer was sent")
                return

    def _store_trapq(self, reply: LayerReply, params: dict[str, Any]) -> None:
        """The motion queue over the layer's scan, into its recording (after the printer
        was answered: it never holds the print)."""
        if self.trapq is None or self.recording_of is None:
            return
        path = self.recording_of(reply)
        region = params.get("region")
        if path is None or not region:
            return
        try:
            attach_trapq(path, self.trapq, region_start_mm=(float(region[0]),
                                                            float(region[1])))
        except (RecordingError, OSError, ValueError) as err:
            note = f"layer {reply.record.layer}: no motion queue stored: {err}"
            self.trapq_notes.append(note)
            log.warning("%s", note)

    def _handle(self, ws: Any, msg: dict[str, Any]) -> None:
        method = msg.get("method")
        if method == METHOD:
            params = msg.get("params") or {}
            if isinstance(params, list):  # positional form: [{...}]
                params = params[0] if params else {}
            if self.trapq is not None:
                self.trapq.clear()  # the layer's raster comes after its call
            action, reason, reply = self.on_layer(params)
            script = f"SFFSCAN_DONE ACTION={action.upper()}"
            if reason:
                script += f" REASON={gcode_quote(reason)}"
            self._send(ws, "printer.gcode.script", {"script": script})
            if reply is not None:
                self._send(ws, "connection.send_event",
                           {"event": "sffscan_verdict", "data": reply.record.model_dump()},
                           want_id=False)
                self._store_trapq(reply, params)
        elif method == "notify_history_changed":
            for item in msg.get("params") or []:
                if isinstance(item, dict) and item.get("action") == "finished":
                    status = str((item.get("job") or {}).get("status", "completed"))
                    outcome = {"completed": "completed", "cancelled": "cancelled",
                               "error": "failed", "klippy_shutdown": "failed",
                               "klippy_disconnect": "disconnected"}.get(status, "failed")
                    if self.on_finished is not None:
                        self.on_finished(outcome)
        elif "error" in msg:
            log.error("moonraker answered request %s with an error: %s", msg.get("id"),
                      msg["error"])
