"""OctoPrint plug-in: scan every layer with the sffscan job service.

Put ``M400`` then ``@SFFSCAN LAYER=[layer_num] Z=[layer_z]`` (PrusaSlicer placeholders) in
the slicer's layer-change G-code. When OctoPrint is about to send that line, the plug-in
puts the job on hold (no further line of the file is sent), asks the service to scan the
layer (``POST /jobs/{id}/layers``, which returns when the scan is done, or with the
verdict in strict mode), then releases the hold. When a verdict asks for it (settings
``on_fail``, ``on_warn``, ``on_unknown``, ``on_error``: ``none``, ``pause`` or ``cancel``)
the print is paused or cancelled *before* the hold is released, so it stops at that layer;
the reason goes to octoprint.log and to the terminal.

The plug-in does not import sffscan: it talks to ``sffscan serve`` over HTTP (urllib).
"""

from __future__ import annotations

import threading
import time

import octoprint.plugin

from .client import ServiceError, SffscanClient, job_id_for, parse_parameters

ACTIONS = ("none", "pause", "cancel")
_RANK = {"none": 0, "pause": 1, "cancel": 2}


class SffscanPlugin(octoprint.plugin.SettingsPlugin, octoprint.plugin.EventHandlerPlugin,
                    octoprint.plugin.StartupPlugin):

    def __init__(self):
        self._lock = threading.Lock()
        self._job_id = None
        self._job_started = False
        self._layer_count = 0
        self._acted = set()

    # --- settings -------------------------------------------------------------------

    def get_settings_defaults(self):
        return {
            "service_url": "http://127.0.0.1:8765",
            "token": "",
            "strict": False,      # wait for each layer's verdict before the print goes on
            "on_fail": "pause",
            "on_warn": "none",
            "on_unknown": "none",
            "on_error": "none",   # the service unreachable or refusing the layer
            "timeout_s": 180.0,   # longest hold for one layer, s (above the service's)
            # G-code sent while the job is held, after the service was asked to scan (the
            # raster moves of a scanner on the print head, ending with M400); {layer} and
            # {z} are replaced. Empty: the scanner moves itself.
            "scan_gcode": "",
        }

    def _action(self, key):
        value = str(self._settings.get([key]) or "none").lower()
        if value not in ACTIONS:
            self._logger.error("sffscan: setting %s = %r is not one of %s; using 'none'",
                               key, value, ", ".join(ACTIONS))
            return "none"
        return value

    def _client(self):
        return SffscanClient(self._settings.get(["service_url"]),
                             token=self._settings.get(["token"]) or None,
                             timeout_s=float(self._settings.get_float(["timeout_s"]) or 180.0))

    def on_after_startup(self):
        self._logger.info("sffscan: job service at %s, strict=%s, on_fail=%s",
                          self._settings.get(["service_url"]),
                          self._settings.get_boolean(["strict"]), self._action("on_fail"))

    # --- job events -----------------------------------------------------------------

    def on_event(self, event, payload):
        if event == "PrintStarted":
            name = (payload or {}).get("name") or (payload or {}).get("path") or "job"
            with self._lock:
                self._job_id = job_id_for(name, time.strftime("%Y%m%dT%H%M%S"))
                self._job_started = False
                self._layer_count = 0
                self._acted = set()
            self._start_job(name)
        elif event in ("PrintDone", "PrintFailed", "PrintCancelled"):
            outcome = {"PrintDone": "completed", "PrintFailed": "failed",
                       "PrintCancelled": "cancelled"}[event]
            with self._lock:
                job_id, started = self._job_id, self._job_started
                self._job_id, self._job_started = None, False
            if job_id and started:
                thread = threading.Thread(target=self._end_job, args=(job_id, outcome),
                                          name="sffscan-end", daemon=True)
                thread.start()

    def _start_job(self, name):
        job_id = self._job_id
        if job_id is None:
            return False
        try:
            self._client().start_job(job_id, gcode_name=name,
                                     strict=self._settings.get_boolean(["strict"]))
        except ServiceError as err:
            self._logger.error("sffscan: could not start job %s: %s", job_id, err)
            return False
        with self._lock:
            self._job_started = True
        self._logger.info("sffscan: job %s started", job_id)
        return True

    def _end_job(self, job_id, outcome):
        try:
            status = self._client().end_job(job_id, outcome)
            self._logger.info("sffscan: job %s ended (%s): layers %s, verdicts %s", job_id,
                              outcome, len(status.get("layers_done", [])),
                              status.get("counts"))
        except ServiceError as err:
            self._logger.error("sffscan: could not end job %s: %s", job_id, err)

    # --- the at-command -------------------------------------------------------------

    def on_atcommand_sending(self, comm, phase, command, parameters, tags=None, *args,
                             **kwargs):
        if command.upper() != "SFFSCAN":
            return
        try:
            params = parse_parameters(parameters or "")
        except ValueError as err:
            self._logger.error("sffscan: %s; layer not scanned", err)
            return
        with self._lock:
            job_id = self._job_id
            layer = params.get("layer", self._layer_count)
            self._layer_count = layer + 1
        if job_id is None:
            self._logger.warning("sffscan: @SFFSCAN outside a print job: ignored")
            return
        z = params.get("z")
        if z is None:
            z = (self._printer.get_current_data().get("currentZ") or 0.0)
        # hold the job: OctoPrint sends no further line of the file until released
        self._printer.set_job_on_hold(True)
        thread = threading.Thread(target=self._scan_layer, args=(job_id, layer, float(z)),
                                  name=f"sffscan-layer-{layer}", daemon=True)
        thread.start()

    def _layer_call(self, job_id, layer, z):
        """The service's layer call; with ``scan_gcode``, the scan moves are sent (they
        pass the job's hold) while the call is in progress."""
        template = (self._settings.get(["scan_gcode"]) or "").strip()
        client = self._client()
        if not template:
            return client.layer(job_id, layer, z)
        out = {}

        def call():
            try:
                out["reply"] = client.layer(job_id, layer, z)
            except ServiceError as err:
                out["error"] = err

        caller = threading.Thread(target=call, name=f"sffscan-call-{layer}", daemon=True)
        caller.start()
        text = template.replace("{layer}", str(layer)).replace("{z}", f"{z:.3f}")
        lines = [ln.strip() for ln in text.splitlines() if ln.strip()]
        self._printer.commands(lines, tags={"source:plugin", "plugin:sffscan"})
        caller.join(client.timeout_s + 5.0)
        if caller.is_alive():
            raise ServiceError(f"no answer for layer {layer} within {client.timeout_s:g} s")
        if "error" in out:
            raise out["error"]
        return out["reply"]

    def _scan_layer(self, job_id, layer, z):
        action, why = "none", ""
        t0 = time.monotonic()
        try:
            if not self._job_started and not self._start_job(job_id):
                raise ServiceError("the job could not be started on the service")
            reply = self._layer_call(job_id, layer, z)
            rec = reply.get("record", {})
            verdict = rec.get("verdict", "unknown")
            self._logger.info("sffscan: layer %d (z %.3f mm) scanned in %.1f s: %s%s",
                              layer, z, time.monotonic() - t0, verdict,
                              f" ({rec.get('reason')})" if rec.get("reason") else "")
            candidates = [rec] + list(reply.get("alerts", []))
            for r in candidates:
                n, v = r.get("layer"), r.get("verdict")
                key = {"fail": "on_fail", "warn": "on_warn", "unknown": "on_unknown"}.get(v)
                if key is None or n in self._acted:
                    continue
                a = self._action(key)
                if a != "none":
                    self._acted.add(n)
                if _RANK[a] > _RANK[action]:
                    action = a
                    why = f"layer {n} verdict {v}: {r.get('reason') or 'no reason given'}"
        except ServiceError as err:
            action = self._action("on_error")
            why = f"layer {layer} not scanned: {err}"
            self._logger.error("sffscan: %s", why)
        except Exception:  # never leave the job on hold
            self._logger.exception("sffscan: layer %d: unexpected error", layer)
        finally:
            try:
                if action != "none":
                    msg = f"sffscan: {action} the print: {why}"
                    self._logger.warning(msg)
                    self._printer.log_lines(msg)
                    tags = {"source:plugin", "plugin:sffscan"}
                    if action == "pause":
                        self._printer.pause_print(tags=tags)
                    else:
                        self._printer.cancel_print(tags=tags)
            finally:
                self._printer.set_job_on_hold(False)


__plugin_name__ = "sffscan"
__plugin_pythoncompat__ = ">=3.9,<4"


def __plugin_load__():
    global __plugin_implementation__, __plugin_hooks__
    plugin = SffscanPlugin()
    __plugin_implementation__ = plugin
    __plugin_hooks__ = {
        "octoprint.comm.protocol.atcommand.sending": plugin.on_atcommand_sending,
    }
