"""HTTP front of the job service (stdlib ``http.server``, JSON bodies, pydantic models).

Endpoints (bodies and answers are the models of :mod:`.service`)::

    GET  /health                          {"ok": true}
    POST /jobs                            JobStart   -> JobStatus
    GET  /jobs/{job_id}                               -> JobStatus
    POST /jobs/{job_id}/layers            LayerEvent -> LayerReply   (holds until scanned)
    GET  /jobs/{job_id}/layers/{layer}                -> LayerRecord
    POST /jobs/{job_id}/end               JobEnd     -> JobStatus

Errors answer ``{"error": "..."}`` with 400 (a body that does not validate: the message
names the field), 401 (token), 404, 409 (out of order, job not open), 413 (body too large).

Security rule (as the frame transport's): the server listens on loopback by default; it
binds another address only with a bearer token, and then every request must carry
``Authorization: Bearer TOKEN``.
"""

from __future__ import annotations

import hmac
import ipaddress
import json
import logging
import re
import threading
from http import HTTPStatus
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer
from typing import Any

from pydantic import BaseModel, ValidationError
from sffscan.pipeline.printjob.service import (
    JobEnd,
    JobService,
    JobStart,
    LayerEvent,
    ServiceError,
)

log = logging.getLogger(__name__)

MAX_BODY_BYTES = 1 << 20
_JOB = r"/jobs/(?P<job>[A-Za-z0-9][A-Za-z0-9._-]{0,99})"
_ROUTES: list[tuple[str, re.Pattern[str], str]] = [
    ("GET", re.compile(r"^/health$"), "health"),
    ("POST", re.compile(r"^/jobs$"), "start"),
    ("GET", re.compile(rf"^{_JOB}$"), "status"),
    ("POST", re.compile(rf"^{_JOB}/layers$"), "layer"),
    ("GET", re.compile(rf"^{_JOB}/layers/(?P<layer>\d{{1,7}})$"), "record"),
    ("POST", re.compile(rf"^{_JOB}/end$"), "end"),
]


def is_loopback_host(host: str) -> bool:
    """``localhost`` or a loopback IP address (``127.0.0.0/8``, ``::1``)."""
    if host == "localhost":
        return True
    try:
        return ipaddress.ip_address(host.strip("[]")).is_loopback
    except ValueError:
        return False


class _Server(ThreadingHTTPServer):
    daemon_threads = False  # server_close() joins the request threads
    block_on_close = True
    service: JobService
    token: str | None


class _Handler(BaseHTTPRequestHandler):
    server: _Server
    protocol_version = "HTTP/1.1"
    timeout = 30  # s without a byte from the client: the connection is dropped

    def log_message(self, format: str, *args: Any) -> None:  # noqa: A002 - stdlib's name
        log.debug("%s %s", self.address_string(), format % args)

    def do_GET(self) -> None:  # noqa: N802 - stdlib's name
        self._dispatch("GET")

    def do_POST(self) -> None:  # noqa: N802
        self._dispatch("POST")

    def _dispatch(self, method: str) -> None:
        try:
            self._authorise()
            path = self.path.split("?", 1)[0]
            for m, pattern, name in _ROUTES:
                match = pattern.match(path)
                if match and m == method:
                    self._send(200, getattr(self, "_" + name)(**match.groupdict()))
                    return
            raise ServiceError(404, f"no endpoint {method} {path}")
        except ServiceError as err:
            self._send(err.status, {"error": str(err)})
        except ValidationError as err:
            self._send(400, {"error": _describe(err)})
        except Exception as err:  # a bug: say so, keep serving
            log.exception("request %s %s failed", method, self.path)
            self._send(500, {"error": f"{type(err).__name__}: {err}"})

    def _authorise(self) -> None:
        token = self.server.token
        if token is None:
            return
        given = self.headers.get("Authorization", "")
        if not hmac.compare_digest(given.encode(), f"Bearer {token}".encode()):
            raise ServiceError(401, "missing or wrong bearer token")

    def _body(self, model: type[BaseModel]) -> Any:
        try:
            size = int(self.headers.get("Content-Length", "0"))
        except ValueError:
            raise ServiceError(400, "Content-Length is not a number") from None
        if size > MAX_BODY_BYTES:
            self.close_connection = True
            raise ServiceError(413, f"body of {size} bytes over the limit ({MAX_BODY_BYTES})")
        raw = self.rfile.read(size) if size > 0 else b"{}"
        try:
            json.loads(raw)
        except ValueError as err:
            raise ServiceError(400, f"body is not JSON: {err}") from None
        return model.model_validate_json(raw)

    def _send(self, status: int, payload: Any) -> None:
        if isinstance(payload, BaseModel):
            data = payload.model_dump_json().encode()
        else:
            data = json.dumps(payload).encode()
        self.send_response(status, HTTPStatus(status).phrase)
        self.send_header("Content-Type", "application/json")
        self.send_header("Content-Length", str(len(data)))
        self.send_header("Connection", "close")  # one request per connection: nothing idles
        self.end_headers()
        self.close_connection = True
        self.wfile.write(data)

    # --- endpoints ------------------------------------------------------------------------

    def _health(self) -> Any:
        return {"ok": True}

    def _start(self) -> Any:
        return self.server.service.start_job(self._body(JobStart))

    def _status(self, job: str) -> Any:
        return self.server.service.status(job)

    def _layer(self, job: str) -> Any:
        return self.server.service.layer(job, self._body(LayerEvent))

    def _record(self, job: str, layer: str) -> Any:
        return self.server.service.record(job, int(layer))

    def _end(self, job: str) -> Any:
        return self.server.service.end_job(job, self._body(JobEnd))


def _describe(err: ValidationError) -> str:
    parts = []
    for e in err.errors():
        where = ".".join(str(p) for p in e["loc"]) or "body"
        parts.append(f"{where}: {e['msg']}")
    return "; ".join(parts)


class ServiceServer:
    """The HTTP server of a :class:`JobService`, serving in a background thread.

    Parameters
    ----------
    service : JobService
    host : str, keyword-only
        Address to bind; anything but loopback needs ``token``.
    port : int, keyword-only
        TCP port; 0 picks a free one (:attr:`port` says which).
    token : str or None, keyword-only
        Bearer token every request must carry (required beyond loopback).
    """

    def __init__(self, service: JobService, *, host: str = "127.0.0.1", port: int = 8765,
                 token: str | None = None) -> None:
        if token is not None and len(token) < 16:
            raise ValueError("the bearer token must be at least 16 characters")
        if not is_loopback_host(host) and token is None:
            raise ValueError(f"refusing to listen on {host} (beyond loopback) without a "
                             "bearer token: give --token-file or SFFSCAN_TOKEN")
        self.service = service
        self._httpd = _Server((host, port), _Handler)
        self._httpd.service = service
        self._httpd.token = token
        self._thread: threading.Thread | None = None

    @property
    def port(self) -> int:
        return int(self._httpd.server_address[1])

    @property
    def url(self) -> str:
        host = str(self._httpd.server_address[0])
        return f"http://{'[' + host + ']' if ':' in host else host}:{self.port}"

    def start(self) -> ServiceServer:
        self._thread = threading.Thread(target=self._httpd.serve_forever,
                                        kwargs={"poll_interval": 0.2},
                                        name="sffscan-serve", daemon=True)
        self._thread.start()
        return self

    def close(self, timeout_s: float = 10.0) -> None:
        """Stop accepting, finish the requests in progress, stop the service's workers."""
        if self._thread is not None:
            self._httpd.shutdown()
            self._thread.join(timeout_s)
        self._httpd.server_close()
        self.service.close(timeout_s)

    def __enter__(self) -> ServiceServer:
        return self.start()

    def __exit__(self, *exc: object) -> None:
        self.close()
