"""``sffscan serve``: the print-job service next to the printer.

It listens on loopback (HTTP, JSON: ``POST /jobs``, ``POST /jobs/ID/layers``, ``GET
/jobs/ID/layers/N``, ``POST /jobs/ID/end``; see ``docs/printer-links.md``) for the
OctoPrint plug-in or any client; with ``--moonraker`` it also runs the Klipper agent. Each
layer event is scanned with the configuration's source (the simulator by default) into
``--store/JOB``, compared with the job's G-code when ``--gcode-dir`` holds it, and
answered; only the scan holds the print unless ``--strict``. Another address than
loopback needs a bearer token (``--token-file`` or ``SFFSCAN_TOKEN``). Ctrl-C or SIGTERM
stops it cleanly; an open job is resumed when the service starts again and the printer
starts the same job id.
"""

from __future__ import annotations

import argparse
import json
import logging
import os
import signal
import sys
import threading
from pathlib import Path
from typing import Any

from sffscan.pipeline.cli.common import EXIT_BAD_INPUT, EXIT_OK

log = logging.getLogger(__name__)


def register(sub: Any) -> None:
    p = sub.add_parser("serve", help="the print-job service: scan every layer a printer "
                                     "announces (OctoPrint plug-in, Klipper agent)",
                       description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--config", help="TOML scan configuration of one layer (default: the "
                                    "simulated scan of 'sffscan job demo')")
    p.add_argument("--store", default="sffscan-jobs", help="folder of the job folders "
                                                           "(default sffscan-jobs)")
    p.add_argument("--gcode-dir", help="folder of the G-code files the printer prints (to "
                                       "compare each layer with); without it verdicts are "
                                       "'unknown'")
    p.add_argument("--mapping", help="JSON file of the printer -> mosaic mapping "
                                     "({\"offset_um\": [x, y], \"rotation_deg\": a})")
    p.add_argument("--host", default="127.0.0.1", help="address to listen on (default "
                                                        "127.0.0.1; others need a token)")
    p.add_argument("--port", type=int, default=8765, help="TCP port (default 8765)")
    p.add_argument("--token-file", help="file holding the bearer token (or SFFSCAN_TOKEN)")
    p.add_argument("--strict", action="store_true",
                   help="hold each layer until its verdict (default: until its scan)")
    p.add_argument("--scan-timeout-s", type=float, default=120.0,
                   help="longest hold for a scan, s (then the layer is 'unknown')")
    p.add_argument("--verdict-timeout-s", type=float, default=30.0,
                   help="--strict: longest wait for a verdict after the scan, s")
    p.add_argument("--moonraker", metavar="WS_URL",
                   help="also run the Klipper agent: Moonraker's websocket "
                        "(ws://127.0.0.1:7125/websocket)")
    p.add_argument("--moonraker-api-key-file", help="Moonraker API key, for a connection "
                                                    "Moonraker does not trust")
    p.add_argument("--viewer", metavar="MODE", default=None,
                   help="watch the jobs live in Rerun (spawn, serve, save with --rrd, auto, "
                        "off; default off)")
    p.add_argument("--rrd", metavar="PATH", help="Rerun recording (.rrd) of the live view")
    p.set_defaults(func=cmd_serve)


def _read_secret(path: str | None, env: str) -> str | None:
    if path:
        return Path(path).read_text(encoding="utf-8").strip() or None
    return os.environ.get(env) or None


def cmd_serve(args: argparse.Namespace) -> int:
    from sffscan.pipeline.cli.common import viewer_mode
    from sffscan.pipeline.config import ConfigError, load_config
    from sffscan.pipeline.printjob import demo
    from sffscan.pipeline.printjob.expected import PrinterMapping
    from sffscan.pipeline.printjob.links_http import ServiceServer
    from sffscan.pipeline.printjob.links_store import JobStoreHandler
    from sffscan.pipeline.printjob.service import JobService

    if args.config:
        cfg, mapping = load_config(args.config), PrinterMapping()
    else:
        cfg, mapping = demo.demo_config(), demo.DEMO_MAPPING
    if args.mapping:
        try:
            mapping = PrinterMapping.model_validate(json.loads(Path(args.mapping).read_text()))
        except ValueError as err:
            print(f"sffscan serve: --mapping {args.mapping}: {err}", file=sys.stderr)
            return EXIT_BAD_INPUT
    token = _read_secret(args.token_file, "SFFSCAN_TOKEN")
    view = None
    try:
        mode = viewer_mode(args.viewer, args.rrd)
        if mode != ["off"]:  # rerun is imported only for a view
            from sffscan.pipeline.printjob.live_view import shared_job_views

            view = shared_job_views(mode)
    except ConfigError as err:
        print(f"sffscan serve: {err}", file=sys.stderr)
        return EXIT_BAD_INPUT
    handler = JobStoreHandler(cfg, gcode_dir=args.gcode_dir, mapping=mapping, view=view)
    try:
        service = JobService(args.store, handler, strict=args.strict,
                             scan_timeout_s=args.scan_timeout_s,
                             verdict_timeout_s=args.verdict_timeout_s)
    except ValueError as err:
        print(f"sffscan serve: {err}", file=sys.stderr)
        return EXIT_BAD_INPUT
    try:
        server = ServiceServer(service, host=args.host, port=args.port, token=token)
    except ValueError as err:
        service.close()
        print(f"sffscan serve: {err}", file=sys.stderr)
        return EXIT_BAD_INPUT
    stop = threading.Event()
    previous = {s: signal.signal(s, lambda *_: stop.set())
                for s in (signal.SIGINT, signal.SIGTERM)}
    threads: list[threading.Thread] = []
    try:
        server.start()
        print(f"sffscan serve: listening on {server.url} (store {args.store}, "
              f"{'strict' if args.strict else 'scan-only hold'})", file=sys.stderr)
        if args.moonraker:
            threads.append(_start_agent(args, service, stop))
        while not stop.wait(3600):
            pass
    finally:
        stop.set()
        for t in threads:
            t.join(15)
        server.close()
        for s, h in previous.items():
            signal.signal(s, h)
        print("sffscan serve: stopped", file=sys.stderr)
    return EXIT_OK


def _start_agent(args: argparse.Namespace, service: Any, stop: threading.Event
                 ) -> threading.Thread:
    from sffscan.pipeline.printjob.links_moonraker import MoonrakerAgent, ServiceBridge

    bridge = ServiceBridge(service)
    agent = MoonrakerAgent(args.moonraker, on_layer=bridge.layer,
                           on_finished=lambda outcome: bridge.end(outcome),
                           recording_of=bridge.recording_of,
                           api_key=_read_secret(args.moonraker_api_key_file,
                                                "SFFSCAN_MOONRAKER_API_KEY"))

    def run() -> None:
        while not stop.is_set():  # reconnect after Moonraker restarts
            try:
                agent.run(stop)
            except Exception as err:
                log.warning("moonraker agent: %s; retrying in 5 s", err)
            stop.wait(5.0)

    t = threading.Thread(target=run, name="sffscan-moonraker", daemon=True)
    t.start()
    return t
