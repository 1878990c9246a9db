"""Commands ``sffscan replay`` and ``sffscan info``: re-process and summarise recordings.

``sffscan scan --record PATH`` writes a recording (:mod:`sffscan.stages.recorder`); ``replay`` runs
the same pipeline over its frames (as fast as possible, or paced by the recorded time
stamps with ``--realtime``), with the recorded configuration and the processing options
given on the command line; ``--resume`` completes an interrupted mosaic. ``info``
summarises a recording (frames, duration, gaps and other defects, configuration) or a
mosaic (status, tiles complete / incomplete, journal).
"""

from __future__ import annotations

import argparse
import logging
import sys
from pathlib import Path

import zarr
from sffscan.pipeline.cli.common import (
    EXIT_BAD_INPUT,
    EXIT_FAILED,
    EXIT_OK,
    describe,
    override,
    processing_options,
    report_job,
    viewer_sink,
)
from sffscan.pipeline.formats.recording import (
    Recording,
    RecordingError,
    open_recording,
)

log = logging.getLogger(__name__)


def _print_report(rec: Recording) -> None:
    """The recording's report: what it holds as status lines, each defect as a warning."""
    for line in rec.report.lines():
        if line.startswith(("recording ", "frames ", "frame_id ")):
            log.info(line)
        else:
            log.warning(line)


def cmd_replay(args: argparse.Namespace) -> int:
    from sffscan.pipeline.run import Job

    try:
        rec = open_recording(args.recording)
    except RecordingError as err:
        print(f"sffscan: {err}", file=sys.stderr)
        return EXIT_BAD_INPUT
    _print_report(rec)
    if args.strict and rec.report.defects:
        print(f"sffscan: {args.recording}: {rec.report.defects} defect(s) and --strict given; "
              "nothing replayed", file=sys.stderr)
        return EXIT_BAD_INPUT
    if args.resume:
        args.overwrite = False
    # the recorded [output] overwrite is the recording's, never this command's
    cfg = override(rec.config, args, own_overwrite=False)
    if not args.resume and not cfg.output.overwrite and Path(cfg.output.path).exists():
        print(f"sffscan: -o {cfg.output.path}: exists; add --overwrite to replace it (or "
              "--resume to complete an interrupted mosaic, or choose another path)",
              file=sys.stderr)
        return EXIT_BAD_INPUT
    log.info(describe(cfg))
    world = None
    if args.evaluate and not args.resume and cfg.source.kind == "sim":
        from sffscan.stages.sim.scanner import make_world

        world = make_world(cfg)
    job = Job(cfg, recording=rec, rrd=args.rrd, resume=args.resume, realtime=args.realtime,
              progress=not args.quiet,
              sinks=lambda: [k for k in (viewer_sink(cfg, args.viewer, default="off",
                                                     rrd=args.rrd),) if k is not None])
    kept = (f"{cfg.output.path} can be resumed again; it holds what was completed"
            if args.resume else "")
    code = report_job(job, world=world, kept=kept)
    if rec.report.corrupt:  # found while reading the frames
        log.warning("%d frame chunk(s) could not be decoded and were left out (lost "
                    "frames): frame_id %s", len(rec.report.corrupt),
                    ", ".join(map(str, rec.report.corrupt[:20])))
    if args.strict and rec.report.defects and code == EXIT_OK:
        return EXIT_FAILED
    return code


def _info_mosaic(path: Path) -> int:
    from sffscan.stages.mosaic import pyramid_levels, tile_states

    try:
        _, info = tile_states(path)
        levels = pyramid_levels(path)
    except (ValueError, KeyError) as err:
        where = "" if str(path) in str(err) else f"{path}: unreadable mosaic: "
        print(f"sffscan: {where}{err}", file=sys.stderr)
        return EXIT_BAD_INPUT
    except Exception as err:  # noqa: BLE001 - a corrupt zarr.json or chunk of the mosaic
        print(f"sffscan: {path}: unreadable mosaic ({type(err).__name__}: {err})",
              file=sys.stderr)
        return EXIT_BAD_INPUT
    from sffscan.pipeline import locks

    attrs = zarr.open_group(str(path), mode="r").attrs.asdict()
    print(f"mosaic      {path} (status {info['status']})")
    holder = locks.holder(path)
    if holder is not None:
        print(f"writer      being written now by {locks.describe_holder(holder)}")
    print(f"tiles       {info['tiles']}: {info['complete']} complete, {info['incomplete']} "
          f"incomplete, {info['empty']} empty")
    print(f"journal     {info['writes_done']} writes done"
          + (f"; torn write at world px box {info['writing']}" if info["writing"] else "")
          + (f"; rebuilding {info['rebuild']}" if info["rebuild"] else ""))
    print(f"levels      {len(levels)} (OME-Zarr multiscales; level: rows x cols, pixel size)")
    for lv in levels:
        print(f"  {lv['level']:>2}        {lv['shape'][0]} x {lv['shape'][1]} px, "
              f"{lv['pixel_um']:g} µm  ({lv['path']})")
    if attrs.get("pyramid_stale"):
        print(f"pyramid     levels over world px box {attrs['pyramid_stale']} not written yet "
              "(a scan in progress, or recomputed by 'replay --resume')")
    print(f"processing  {attrs.get('processing')}")
    if attrs.get("frames_expected") is not None or attrs.get("frames_received") is not None:
        print(f"frames      {attrs.get('frames_received')} of {attrs.get('frames_expected')} "
              "expected frames received and processed")
    rec = attrs.get("recording")
    ident = rec.get("identity") if isinstance(rec, dict) else None
    if isinstance(ident, dict) and ident.get("live"):
        print(f"recorded    into {ident.get('path')} (a live scan)")
    elif isinstance(rec, dict) and "frames" not in rec:
        print(f"replaying   from {rec.get('path')} (not finished)")
    elif isinstance(rec, dict):
        print(f"replayed    from {rec.get('path')} ({rec.get('frames')} frames, "
              f"{rec.get('frames_lost')} lost)")
    if info["incomplete"]:
        print("incomplete tiles hold untrustworthy values: complete them with "
              "'sffscan replay RECORDING -o MOSAIC --resume'")
    return EXIT_OK


def cmd_info(args: argparse.Namespace) -> int:
    path = Path(args.path)
    try:
        fmt = zarr.open_group(str(path), mode="r").attrs.get("format")
    except Exception:  # noqa: BLE001 - reported by open_recording below
        fmt = None
    if fmt == "sffscan-mosaic":
        return _info_mosaic(path)
    try:
        rec = open_recording(path)
        if args.verify:
            rec.verify()
    except RecordingError as err:
        print(f"sffscan: {err}", file=sys.stderr)
        return EXIT_BAD_INPUT
    for line in rec.report.lines():
        print(line)
    a = rec.attrs
    rate = (rec.report.frames - 1) / rec.report.duration_s if rec.report.duration_s else 0.0
    print(f"format      {a.format} v{a.format_version}, frames {list(a.frame_shape)} {a.dtype}, "
          f"codec {a.codec or 'unknown'}, written by {a.writer or 'unknown'} "
          f"{a.created or ''}".rstrip())
    print(f"rate        {rate:.1f} frames/s (from the time stamps)")
    planned = rec.account().planned
    print(f"expected    {planned} frames ("
          + ("the live scan's count" if a.frames_planned is not None else "the plan's")
          + f"), {rec.report.frames} usable: a replay would be "
          + ("complete" if planned is not None and rec.report.frames >= planned
             else "incomplete"))
    print(describe(rec.config))
    p = rec.config.processing
    print(f"processing  {p.focus_operator} k={p.window}, {p.depth_method}, registration "
          f"{'on' if p.registration else 'off'}")
    if args.verify:
        print(f"verified    every usable frame decoded; {len(rec.report.corrupt)} corrupt")
    return EXIT_OK


def register(sub: argparse._SubParsersAction) -> None:  # type: ignore[type-arg]
    p = sub.add_parser("replay", help="re-process a recording into a mosaic",
                       description="Run the pipeline over a recording made with 'sffscan scan "
                                   "--record': the recorded configuration, with the processing "
                                   "options given here. With the same configuration the "
                                   "mosaic is bit for bit the live run's.")
    p.add_argument("recording", help="recording (Zarr v3 group)")
    p.add_argument("-o", "--output", required=True, help="mosaic path (Zarr v3 group)")
    p.add_argument("--overwrite", action="store_true", help="replace an existing mosaic")
    p.add_argument("--resume", action="store_true",
                   help="complete an interrupted mosaic at --output (same configuration)")
    p.add_argument("--realtime", action="store_true",
                   help="pace the frames by their recorded time stamps (live monitoring)")
    p.add_argument("--evaluate", action="store_true",
                   help="score a simulated recording against the simulation's true surface")
    p.add_argument("--strict", action="store_true",
                   help="refuse a recording with any defect (gaps, duplicates, corrupt chunks)")
    processing_options(p)
    p.set_defaults(func=cmd_replay)

    p = sub.add_parser("info", help="summarise a recording (or a mosaic)")
    p.add_argument("path", help="recording or mosaic (Zarr v3 group)")
    p.add_argument("--verify", action="store_true", help="decode every frame (finds corrupt "
                                                           "chunks; reads the whole recording)")
    p.set_defaults(func=cmd_info)
