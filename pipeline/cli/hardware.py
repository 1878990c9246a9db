"""Hardware commands: ``sffscan plan`` (scan planner) and ``sffscan grab`` (acquire and
send frames over zmq to a running ``sffscan scan --source ADDRESS``)."""

from __future__ import annotations

import argparse
import logging
import sys
from collections.abc import Iterator
from typing import TYPE_CHECKING, Any

from sffscan.pipeline.cli.common import (
    EXIT_BAD_INPUT,
    EXIT_FAILED,
    EXIT_INTERRUPTED,
    EXIT_OK,
    json_option,
)
from sffscan.pipeline.config import ConfigError, ScanConfig, config_from_dict, load_config

if TYPE_CHECKING:
    from sffscan.stages.messages import Frame

log = logging.getLogger(__name__)


def cmd_plan(args: argparse.Namespace) -> int:
    from sffscan.pipeline.hardware.planner import PlanError, format_plan, plan_scan

    cfg = load_config(args.config) if args.config else ScanConfig()
    o = cfg.optics
    # the scan header's thesis limit uses motion.pass_overlap: the same overlap here
    overlap = args.overlap if args.overlap is not None else cfg.motion.pass_overlap
    pixel = args.pixel_um if args.pixel_um is not None else o.pixel_um
    if args.fov is not None:
        fov = (args.fov[0], args.fov[1])
    else:
        w, h = args.fov_px if args.fov_px is not None else (o.width_px, o.height_px)
        fov = (w * pixel / 1000.0, h * pixel / 1000.0)
    try:
        plan = plan_scan(fov_mm=fov, fps=args.fps if args.fps is not None else o.fps,
                         n_levels=args.levels if args.levels is not None else o.n_levels,
                         overlap=overlap, pixel_um=pixel,
                         area_mm=(args.area[0], args.area[1]), direction=args.direction,
                         speed_mm_s=args.speed)
    except PlanError as err:
        print(f"sffscan plan: refused: {err}", file=sys.stderr)
        return EXIT_BAD_INPUT
    if args.json:
        import dataclasses
        import json

        out = dataclasses.asdict(plan)
        for rule in ("thesis", "sliding"):
            out[rule]["total_time_s"] = getattr(plan, rule).total_time_s
        print(json.dumps(out))
    else:
        print(format_plan(plan))
    return EXIT_OK


def _grab_config(args: argparse.Namespace) -> ScanConfig:
    cfg = load_config(args.config)
    if args.frames is not None:
        data: dict[str, Any] = cfg.model_dump()
        data["camera"]["frames"] = args.frames
        cfg = config_from_dict(data, origin="command line")
    return cfg


def cmd_grab(args: argparse.Namespace) -> int:
    from sffscan.pipeline.formats.transport import (
        FrameSender,
        TransportError,
        keys_dir_of,
        stream_frames,
    )
    from sffscan.pipeline.hardware.camera_source import CameraError
    from sffscan.pipeline.hardware.daq import DaqNotFoundError

    cfg = _grab_config(args)
    address = args.to or cfg.source.address
    if cfg.source.kind == "tcp":
        raise ConfigError("source.kind = 'tcp': 'sffscan grab' acquires frames itself; set "
                          "source.kind to 'camera' (or 'sim')")
    frames: Iterator[Frame]
    if cfg.source.kind == "camera":
        from sffscan.pipeline.hardware.camera_source import camera_frames

        frames = camera_frames(cfg)
    else:
        from sffscan.pipeline.sim_source import simulate_frames

        frames = simulate_frames(cfg)
    log.info("grab: %s frames to %s", cfg.source.kind, address)
    sender = FrameSender(address, hwm=args.hwm, bind=args.bind,
                         keys_dir=keys_dir_of(cfg, getattr(args, "keys", None)))
    ok = False
    try:
        n = stream_frames(frames, sender)
        ok = True
    except KeyboardInterrupt:
        print("sffscan grab: interrupted", file=sys.stderr)
        return EXIT_INTERRUPTED
    except DaqNotFoundError as err:
        print(f"sffscan grab: {err}", file=sys.stderr)
        return EXIT_BAD_INPUT
    except (CameraError, TransportError) as err:
        print(f"sffscan grab: {err}", file=sys.stderr)
        return EXIT_FAILED
    finally:
        sender.close(linger_s=10.0 if ok else 0.0)
    print(f"grab: sent {n} frames ({sender.bytes / 1e6:.1f} MB), waited "
          f"{sender.blocked_s:.1f} s for the receiver", file=sys.stderr)
    return EXIT_OK


def register(sub: Any) -> None:
    p = sub.add_parser("plan", help="maximum speed, exposure, frames, time and passes of a scan",
                       description="Plan a continuous-motion scan of an area: the maximum "
                       "speed under the thesis' per-stack rule (eq. 6.1-6.3) and under "
                       "sffscan's sliding window, the maximum exposure, frames and time per "
                       "pass, and passes. Defaults: the thesis optics.")
    p.add_argument("--config", help="take the optics from this TOML configuration")
    p.add_argument("--fov", type=float, nargs=2, metavar=("W_MM", "H_MM"),
                   help="field of view, mm (camera x, y)")
    p.add_argument("--fov-px", type=int, nargs=2, metavar=("W_PX", "H_PX"),
                   help="field of view, px (with --pixel-um)")
    p.add_argument("--pixel-um", type=float, help="object-side pixel scale, µm/px")
    p.add_argument("--fps", type=float, help="frame rate, frames/s")
    p.add_argument("--levels", type=int, help="focus levels N")
    p.add_argument("--overlap", type=float, default=None,
                   help="overlap between stacks and passes, fraction (default: "
                        "motion.pass_overlap of --config, else 0.15)")
    p.add_argument("--direction", choices=["x", "y"], default="x",
                   help="camera axis of the motion (default x)")
    p.add_argument("--area", type=float, nargs=2, default=[100.0, 100.0],
                   metavar=("ALONG_MM", "ACROSS_MM"), help="area to cover, mm (default 100 100)")
    p.add_argument("--speed", type=float, help="requested speed, mm/s (default: each rule's "
                   "maximum)")
    json_option(p, "the plan (both rules; speeds mm/s, times s, exposure µs)")
    p.set_defaults(func=cmd_plan)

    p = sub.add_parser("grab", help="acquire frames and send them to 'sffscan scan --source'",
                       description="Acquire frames (source.kind 'camera', or 'sim') in this "
                       "process and send them over zmq to a running 'sffscan scan --source "
                       "ADDRESS'. The receiver's and sender's high-water marks are the "
                       "bounded queue between them.")
    p.add_argument("--config", required=True, help="TOML scan configuration")
    p.add_argument("--to", metavar="ADDRESS",
                   help="receiver, tcp://HOST:PORT or ipc://PATH (default source.address)")
    p.add_argument("--frames", type=int, help="frames to acquire (camera; default: the plan's)")
    p.add_argument("--hwm", type=int, default=8, help="send high-water mark, frames (default 8)")
    p.add_argument("--bind", action="store_true", help="bind instead of connecting")
    p.add_argument("--keys", metavar="DIR", help="CURVE keys folder for a receiver beyond "
                   "loopback (default source.keys_dir; see 'sffscan keys')")
    p.set_defaults(func=cmd_grab)

    p = sub.add_parser("keys", help="make the CURVE keys of a transport beyond loopback",
                       description="Make the receiver's and the sender's CURVE key pairs "
                       "(zmq) for 'sffscan scan --source tcp://HOST:PORT' fed by 'sffscan "
                       "grab' from another machine, and authorise the sender. Keep the "
                       "folder on the receiving machine; copy sender.key_secret and "
                       "receiver.key into the sending machine's keys folder (same "
                       "source.keys_dir). On loopback no keys are needed: each scan draws "
                       "its own pairing secret.")
    p.add_argument("--dir", help="keys folder (default source.keys_dir, else "
                   "$XDG_CONFIG_HOME/sffscan/keys or ~/.config/sffscan/keys)")
    p.add_argument("--overwrite", action="store_true", help="replace existing keys")
    p.set_defaults(func=cmd_keys)


def cmd_keys(args: argparse.Namespace) -> int:
    from sffscan.pipeline.formats.transport_auth import keys_dir_of, make_keys

    folder = keys_dir_of(None, args.dir)
    for path in make_keys(folder, overwrite=args.overwrite):
        print(f"wrote {path}")
    print(f"receiver: keep {folder}; sender: copy {folder / 'sender.key_secret'} and "
          f"{folder / 'receiver.key'} to its keys folder")
    return EXIT_OK
