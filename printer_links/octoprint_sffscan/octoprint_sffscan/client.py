"""A small client of the sffscan job service (``sffscan serve``), standard library only."""

from __future__ import annotations

import json
import re
import urllib.error
import urllib.request
from typing import Any


class ServiceError(RuntimeError):
    """The service could not be reached, or refused the request (the message says why)."""


class SffscanClient:
    """HTTP client of the job service.

    Parameters
    ----------
    url : str
        Base address, ``http://127.0.0.1:8765``.
    token : str, optional
        Bearer token (needed when the service listens beyond loopback).
    timeout_s : float
        Longest wait for one answer, s; a layer call holds until the scan is done, so this
        must exceed the service's scan timeout.
    """

    def __init__(self, url: str, *, token: str | None = None, timeout_s: float = 180.0):
        self.url = url.rstrip("/")
        self.token = token or None
        self.timeout_s = timeout_s

    def _call(self, method: str, path: str, body: dict | None = None,
              timeout_s: float | None = None) -> Any:
        data = None if body is None else json.dumps(body).encode()
        req = urllib.request.Request(self.url + path, data=data, method=method)
        req.add_header("Accept", "application/json")
        if data is not None:
            req.add_header("Content-Type", "application/json")
        if self.token:
            req.add_header("Authorization", "Bearer " + self.token)
        try:
            with urllib.request.urlopen(req, timeout=timeout_s or self.timeout_s) as resp:
                return json.loads(resp.read().decode() or "null")
        except urllib.error.HTTPError as err:
            try:
                detail = json.loads(err.read().decode()).get("error", "")
            except ValueError:
                detail = ""
            raise ServiceError(f"{method} {path}: HTTP {err.code} {detail}".strip()) from None
        except (urllib.error.URLError, OSError) as err:
            raise ServiceError(f"{method} {path}: service at {self.url} unreachable "
                               f"({err})") from None

    def start_job(self, job_id: str, *, gcode_name: str = "", printer: str = "",
                  strict: bool | None = None) -> Any:
        return self._call("POST", "/jobs", {"job_id": job_id, "gcode_name": gcode_name,
                                            "printer": printer, "strict": strict},
                          timeout_s=10.0)

    def layer(self, job_id: str, layer: int, z_mm: float, **extra: Any) -> Any:
        body = {"layer": int(layer), "z_mm": float(z_mm)}
        body.update(extra)
        return self._call("POST", f"/jobs/{job_id}/layers", body)

    def record(self, job_id: str, layer: int) -> Any:
        return self._call("GET", f"/jobs/{job_id}/layers/{int(layer)}", timeout_s=10.0)

    def end_job(self, job_id: str, outcome: str = "completed", reason: str = "") -> Any:
        return self._call("POST", f"/jobs/{job_id}/end",
                          {"outcome": outcome, "reason": reason}, timeout_s=30.0)


_SAFE = re.compile(r"[^A-Za-z0-9._-]+")


def job_id_for(name: str, stamp: str) -> str:
    """A job id the service accepts: the file's name (unsafe characters as '-'), a stamp."""
    base = _SAFE.sub("-", name.rsplit("/", 1)[-1]).strip("-.") or "job"
    return f"{base[:80]}-{stamp}"


def parse_parameters(parameters: str) -> dict:
    """``LAYER=3 Z=0.6`` (Klipper style, keys case-insensitive) -> {"layer": 3, "z": 0.6};
    a bare first number is the layer. Raises ValueError naming the bad word."""
    out: dict = {}
    for i, word in enumerate(parameters.split()):
        key, sep, value = word.partition("=")
        try:
            if not sep and i == 0:
                out["layer"] = int(key)
            elif key.upper() == "LAYER":
                out["layer"] = int(value)
            elif key.upper() == "Z":
                out["z"] = float(value)
            else:
                raise ValueError
        except ValueError:
            raise ValueError(f"@SFFSCAN: cannot read {word!r} (expected LAYER=<int> "
                             "Z=<mm>)") from None
    return out
