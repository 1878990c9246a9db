"""Screenshot of the live web viewer with a scan loaded, taken by headless Chromium.

Runs a simulated scan with the viewer served on this machine (``--viewer serve``), keeps
the gRPC server up after the scan, opens the web viewer's address in headless Chromium
(Debian packages ``chromium`` and ``chromium-driver``, driven through chromedriver's
WebDriver interface) with a fresh profile, waits, and saves the screenshot. Usage::

    python docs/viewer_screenshot.py [--out docs/live-view.png] [--demo] [--wait-s 20]

``--demo`` scans the full demo configuration (1280 x 1024 px); by default the small test
optics scan a 20 mm strip. Exits 1 if no image was written; prints the browser console.
"""

from __future__ import annotations

import argparse
import base64
import json
import shutil
import socket
import subprocess
import sys
import tempfile
import threading
import time
import urllib.error
import urllib.request
from pathlib import Path
from typing import Any

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

CHROMIUM_FLAGS = ["--headless", "--no-sandbox", "--disable-gpu",
                  "--disable-background-networking", "--disable-component-update",
                  "--disable-sync"]


def main() -> int:
    from sffscan.pipeline.config import demo_config
    from sffscan.pipeline.sim_source import simulate_frames
    from sffscan.pipeline.viz.sink import VizSink, open_recording
    from sffscan.pipeline.wiring import run_scan

    from tests.scan_helpers import small_config

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", default=str(ROOT / "docs" / "live-view.png"))
    ap.add_argument("--demo", action="store_true", help="the demo's optics and strip")
    ap.add_argument("--wait-s", type=float, default=20.0,
                    help="seconds the page gets to load before the screenshot")
    ap.add_argument("--size", default="1600,1000", help="window size W,H")
    ap.add_argument("--extra-flag", action="append", default=[],
                    help="extra Chromium flag (repeatable)")
    args = ap.parse_args()

    cfg = demo_config() if args.demo else small_config()
    scanned, release = threading.Event(), threading.Event()

    class Held(VizSink):
        def close(self, *, failed: bool) -> None:
            self.rec.flush()
            scanned.set()
            release.wait()
            super().close(failed=failed)

    rec, address = open_recording(["serve"])
    assert address is not None
    sink = Held(cfg, rec)
    tmp = Path(tempfile.mkdtemp(prefix="sffscan-shot-"))
    def scan() -> None:
        try:
            run_scan(cfg, frames=simulate_frames(cfg), output=tmp / "m.zarr", overwrite=True,
                     progress=False, sinks=[sink])
        finally:
            scanned.set()  # also when the scan could not start

    worker = threading.Thread(target=scan)
    worker.start()
    scanned.wait()
    print(f"scan done; screenshot of {address}", file=sys.stderr)
    try:
        logs = shoot(address, out=Path(args.out), size=args.size, wait_s=args.wait_s,
                     profile=tmp / "profile", extra=args.extra_flag)
    finally:
        release.set()
        worker.join()
        shutil.rmtree(tmp, ignore_errors=True)
    for line in logs:
        if not line.startswith("DEBUG"):
            print("console:", line[:300], file=sys.stderr)
    ok = Path(args.out).is_file()
    print(f"wrote {args.out}: {ok}", file=sys.stderr)
    return 0 if ok else 1


def _call(base: str, method: str, path: str, body: dict[str, Any] | None = None) -> Any:
    data = json.dumps(body).encode() if body is not None else None
    req = urllib.request.Request(base + path, data=data, method=method,
                                 headers={"Content-Type": "application/json"})
    with urllib.request.urlopen(req, timeout=120) as resp:
        return json.loads(resp.read())["value"]


def shoot(url: str, *, out: Path, size: str, wait_s: float, profile: Path,
          extra: list[str]) -> list[str]:
    """Open ``url`` in headless Chromium through chromedriver's WebDriver REST interface,
    wait ``wait_s`` seconds of real time, save a PNG; returns the browser console lines."""
    driver = shutil.which("chromedriver")
    if driver is None:
        raise SystemExit("chromedriver not found (apt-get install -y chromium-driver)")
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    proc = subprocess.Popen([driver, f"--port={port}"], stdout=subprocess.DEVNULL,
                            stderr=subprocess.DEVNULL)
    base = f"http://127.0.0.1:{port}"
    try:
        for _ in range(100):
            try:
                _call(base, "GET", "/status")
                break
            except OSError:
                time.sleep(0.1)
        flags = [*CHROMIUM_FLAGS, f"--user-data-dir={profile}", f"--window-size={size}", *extra]
        caps = {"capabilities": {"alwaysMatch": {
            "browserName": "chrome", "goog:chromeOptions": {"args": flags},
            "goog:loggingPrefs": {"browser": "ALL"}}}}
        session = _call(base, "POST", "/session", caps)["sessionId"]
        try:
            _call(base, "POST", f"/session/{session}/url", {"url": url})
            time.sleep(wait_s)
            png = _call(base, "GET", f"/session/{session}/screenshot")
            out.write_bytes(base64.b64decode(png))
            try:
                entries = _call(base, "POST", f"/session/{session}/se/log", {"type": "browser"})
            except urllib.error.HTTPError:
                entries = []
            return [f"{e.get('level')} {e.get('message')}" for e in entries]
        finally:
            _call(base, "DELETE", f"/session/{session}")
    finally:
        proc.terminate()
        proc.wait(10)


if __name__ == "__main__":
    raise SystemExit(main())
