"""Commands ``sffscan replay`` and ``sffscan info``: re-process and summarise recordings.

``sffscan scan --record PATH`` writes a recording
(:mod:`sffscan.pipeline.formats.recording_writer`); ``replay`` runs
the same pipeline over its frames (as fast as possible, or paced by the recorded time
stamps with ``--realtime``), with the recorded configuration and the processing options
given on the command line; ``--resume`` completes an interrupted mosaic. ``info``
summarises a recording (frames, duration, gaps and other defects, configuration) or a
mosaic (status, tiles complete / incomplete, journal).
"""

from __future__ import annotations

import argparse
import json
import logging
import sys
from pathlib import Path
from typing import TYPE_CHECKING, Any

from sffscan.pipeline.cli.common import (
    EXIT_FAILED,
    EXIT_INCOMPLETE,
    EXIT_OK,
    describe,
    fail,
    json_option,
    override,
    plain_json,
    processing_options,
    report_job,
    viewer_sink,
)

if TYPE_CHECKING:
    from sffscan.pipeline.formats.recording_reader import Recording

log = logging.getLogger(__name__)

#: the height range ``info`` prints is read from the finest level with at most this many px
RANGE_MAX_PX = 64 * 2**20


def _print_report(rec: Recording) -> None:
    """The recording's report: what it holds as status lines, each defect as a warning."""
    for line in rec.report.lines():
        if line.startswith(("recording ", "frames ", "frame_id ")):
            log.info(line)
        else:
            log.warning(line)


def _complete_from(path: str | Path, recording: str | Path) -> bool:
    """Whether ``path`` is an sffscan mosaic made from ``recording`` whose status is
    'complete' (another recording's is refused by the resume, naming it)."""
    import zarr
    from sffscan.pipeline.mosaic.layout import mosaic_array, present_arrays
    from sffscan.pipeline.run import identity_mismatch, recording_identity, stored_identity

    try:
        group = zarr.open_group(str(path), mode="r", use_consolidated=False)
        attrs = group.attrs.asdict()
        if not (attrs.get("format") == "sffscan-mosaic" and attrs.get("status") == "complete"
                and identity_mismatch(stored_identity(attrs),
                                      recording_identity(recording)) is None):
            return False
        for name in present_arrays(group):  # complete, and every array still readable
            mosaic_array(group, name)
    except Exception:  # noqa: BLE001 - not a mosaic, or a damaged one: the resume says why
        return False
    return True


def cmd_replay(args: argparse.Namespace) -> int:
    from sffscan.pipeline.formats.recording import RecordingError
    from sffscan.pipeline.formats.recording_reader import open_recording
    from sffscan.pipeline.run import Job

    try:
        rec = open_recording(args.recording)
    except RecordingError as err:
        return fail(str(err))
    _print_report(rec)
    if args.strict and rec.report.defects:
        return fail(f"{args.recording}: {rec.report.defects} defect(s) and --strict given; "
              "nothing replayed")
    if args.resume:
        args.overwrite = False
        if _complete_from(args.output, args.recording):  # nothing wrong, nothing to do
            print(f"sffscan: {args.output} is complete already (status 'complete'): nothing "
                  "to resume; 'sffscan info' summarises it, --overwrite re-processes it",
                  file=sys.stderr)
            return EXIT_OK
    # the recorded [output] overwrite is the recording's, never this command's
    cfg = override(rec.config, args, own_overwrite=False)
    if not args.resume and not cfg.output.overwrite and Path(cfg.output.path).exists():
        return fail(f"-o {cfg.output.path}: exists; add --overwrite to replace it (or "
              "--resume to complete an interrupted mosaic, or choose another path)")
    log.info(describe(cfg))
    world = None
    if args.evaluate and not args.resume and cfg.source.kind == "sim":
        from sffscan.pipeline.sim_source import make_world

        world = make_world(cfg)
    job = Job(cfg, recording=rec, rrd=args.rrd, resume=args.resume, realtime=args.realtime,
              progress=not args.quiet,
              sinks=lambda: [k for k in (viewer_sink(cfg, args.viewer, default="off",
                                                     rrd=args.rrd),) if k is not None])
    kept = (f"{cfg.output.path} can be resumed again; it holds what was completed"
            if args.resume else "")
    code = report_job(job, world=world, kept=kept, as_json=args.json)
    if rec.report.corrupt:  # found while reading the frames
        log.warning("%d frame chunk(s) could not be decoded and were left out (lost "
                    "frames): frame_id %s", len(rec.report.corrupt),
                    ", ".join(map(str, rec.report.corrupt[:20])))
    if args.strict and rec.report.defects and code == EXIT_OK:
        return EXIT_FAILED
    return code


def _height_range(path: Path, levels: list[dict[str, Any]]) -> dict[str, Any] | None:
    """Lowest and highest finite height (µm), read one row of chunks at a time from the
    finest level of at most :data:`RANGE_MAX_PX` px (``level`` says which; above level 0
    the values are the pyramid's block means), and the finite pixels counted there."""
    import numpy as np
    import zarr
    from sffscan.pipeline.mosaic.layout import mosaic_array

    fits = [lv for lv in levels if lv["shape"][0] * lv["shape"][1] <= RANGE_MAX_PX]
    if not fits:
        return None
    lv = fits[0]
    height = mosaic_array(zarr.open_group(str(path), mode="r", use_consolidated=False), lv["path"])
    lo, hi, step, count = np.inf, -np.inf, int(height.chunks[0]), 0
    for r in range(0, int(height.shape[0]), step):
        block = np.asarray(height[r:r + step])
        finite = block[np.isfinite(block)]
        count += int(finite.size)
        if finite.size:
            lo, hi = min(lo, float(finite.min())), max(hi, float(finite.max()))
    if not np.isfinite(lo):
        return None
    return {"min_um": lo, "max_um": hi, "level": lv["level"], "finite_px": count}


def mosaic_info(path: Path) -> dict[str, Any]:
    """What ``info MOSAIC`` shows, as plain JSON values: status, writer, tiles, journal,
    levels, processing, accuracy, valid pixels, height range (µm), frames, recording.
    ``ValueError`` / ``KeyError`` for an unreadable mosaic."""
    import zarr
    from sffscan.pipeline import locks
    from sffscan.pipeline.mosaic.reader import pyramid_levels, tile_states

    _, info = tile_states(path)
    levels = pyramid_levels(path)
    attrs = zarr.open_group(str(path), mode="r", use_consolidated=False).attrs.asdict()
    holder = locks.holder(path)
    shape = levels[0]["shape"] if levels else None
    height_range = _height_range(path, levels)
    valid = attrs.get("valid_pixels")
    if valid is None and height_range is not None and height_range["level"] == 0:
        valid = height_range["finite_px"]  # not stored (an older or unfinished mosaic)
    out = {
        "mosaic": str(path), "status": info["status"],
        "writer": None if holder is None else locks.describe_holder(holder),
        "tiles": {k: info[k] for k in ("tiles", "complete", "incomplete", "empty")},
        "journal": {"writes_done": info["writes_done"], "writing": info["writing"],
                    "rebuild": info["rebuild"]},
        "levels": [{**lv, "shape": list(lv["shape"])} for lv in levels],
        "pyramid_stale": attrs.get("pyramid_stale"),
        "pixel_um": attrs.get("pixel_um"), "origin_px": attrs.get("origin_px"),
        "processing": attrs.get("processing"),
        "accuracy": attrs.get("accuracy"),
        "valid_pixels": valid,
        "pixels": None if shape is None else int(shape[0]) * int(shape[1]),
        "height_range": height_range,
        "frames_expected": attrs.get("frames_expected"),
        "frames_received": attrs.get("frames_received"),
        "recording": attrs.get("recording"),
    }
    return plain_json(out)


def _processing_line(p: Any) -> str:
    """A mosaic's ``processing`` attribute as words: the operator, window, depth method and
    registration first, every other setting as ``name value``."""
    if not isinstance(p, dict):
        return str(p)
    p = dict(p)
    head = []
    if "focus_operator" in p:
        head.append(f"{p.pop('focus_operator')} k={p.pop('window', '?')}")
    if "depth_method" in p:
        head.append(str(p.pop("depth_method")))
    if "registration" in p:
        head.append(f"registration {'on' if p.pop('registration') else 'off'}")
    rest = [f"{k.replace('_', ' ')} {'none' if v in (None, []) else v}" for k, v in p.items()]
    return ", ".join(head + rest)


def _print_mosaic_info(m: dict[str, Any]) -> None:
    print(f"mosaic      {m['mosaic']} (status {m['status']})")
    if m["writer"] is not None:
        print(f"writer      being written now by {m['writer']}")
    t, j = m["tiles"], m["journal"]
    print(f"tiles       {t['tiles']}: {t['complete']} complete, {t['incomplete']} incomplete, "
          f"{t['empty']} empty")
    print(f"journal     {j['writes_done']} writes done"
          + (f"; torn write at world px box {j['writing']}" if j["writing"] else "")
          + (f"; rebuilding {j['rebuild']}" if j["rebuild"] else ""))
    print(f"levels      {len(m['levels'])} (OME-Zarr multiscales; level: rows x cols, pixel "
          "size)")
    for lv in m["levels"]:
        print(f"  {lv['level']:>2}        {lv['shape'][0]} x {lv['shape'][1]} px, "
              f"{lv['pixel_um']:g} µm  ({lv['path']})")
    if m["pyramid_stale"]:
        print(f"pyramid     levels over world px box {m['pyramid_stale']} not written yet "
              "(a scan in progress, or recomputed by 'replay --resume')")
    print(f"processing  {_processing_line(m['processing'])}")
    if m["valid_pixels"] is not None:
        share = (f" ({100 * m['valid_pixels'] / m['pixels']:.1f} % of {m['pixels']})"
                 if m["pixels"] else "")
        print(f"valid       {m['valid_pixels']} px with a height{share}")
    r = m["height_range"]
    if r is not None:
        print(f"height      {r['min_um']:.1f} .. {r['max_um']:.1f} µm"
              + (f" (pyramid level {r['level']}: block means)" if r["level"] else ""))
    a = m["accuracy"]
    if isinstance(a, dict):
        print(f"accuracy    RMSE {a.get('rmse_um', float('nan')):.1f} µm, CORR "
              f"{a.get('corr', float('nan')):.4f}, PSNR {a.get('psnr_db', float('nan')):.1f} dB "
              f"over {a.get('pixels')} px (stored; against {a.get('truth', 'a true surface')})")
        if a.get("sigma_pixels") and a.get("within_2sigma") is not None:
            from sffscan.pipeline.metrology.evaluate import uncertainty_line

            print(uncertainty_line(a["within_2sigma"], a["sigma_pixels"], truth="that truth"))
    else:
        print("accuracy    not stored (scored only against a simulation's true surface: "
              "'sffscan demo', 'replay --evaluate')")
    if m["frames_expected"] is not None or m["frames_received"] is not None:
        print(f"frames      {m['frames_received']} of {m['frames_expected']} expected frames "
              "received and processed")
    rec = m["recording"]
    ident = rec.get("identity") if isinstance(rec, dict) else None
    if isinstance(ident, dict) and ident.get("live"):
        print(f"recorded    into {ident.get('path')} (a live scan)")
    elif isinstance(rec, dict) and "frames" not in rec:
        print(f"replaying   from {rec.get('path')} (not finished)")
    elif isinstance(rec, dict):
        print(f"replayed    from {rec.get('path')} ({rec.get('frames')} frames, "
              f"{rec.get('frames_lost')} lost)")
    if t["incomplete"]:
        print("incomplete tiles hold untrustworthy values: complete them with "
              "'sffscan replay RECORDING -o MOSAIC --resume'")


def _info_mosaic(path: Path, *, as_json: bool = False) -> int:
    try:
        m = mosaic_info(path)
    except (ValueError, KeyError) as err:
        where = "" if str(path) in str(err) else f"{path}: unreadable mosaic: "
        return fail(f"{where}{err}")
    except Exception as err:  # noqa: BLE001 - a corrupt zarr.json or chunk of the mosaic
        return fail(f"{path}: unreadable mosaic ({type(err).__name__}: {err})")
    if as_json:
        print(json.dumps(m))
    else:
        _print_mosaic_info(m)
    return EXIT_OK


def _recording_info(rec: Recording) -> dict[str, Any]:
    """What ``info RECORDING`` shows, as plain JSON values."""
    a, p = rec.attrs, rec.config.processing
    rate = (rec.report.frames - 1) / rec.report.duration_s if rec.report.duration_s else 0.0
    planned = rec.account().planned
    out = {"kind": "recording", "report": rec.report.as_dict(),
           "defects": rec.report.defects, "notes": rec.report.notes,
           "first_id": rec.report.first_id, "last_id": rec.report.last_id,
           "duration_s": rec.report.duration_s, "rate_frames_per_s": rate,
           "format": a.format, "format_version": a.format_version,
           "frame_shape": list(a.frame_shape), "dtype": str(a.dtype), "codec": a.codec,
           "writer": a.writer, "created": a.created,
           "frames_expected": planned,
           "expected_from": "live scan" if a.frames_planned is not None else "plan",
           "replay_complete": planned is not None and rec.report.frames >= planned,
           "processing": {"focus_operator": p.focus_operator, "window": p.window,
                          "depth_method": p.depth_method, "registration": p.registration},
           "scan_config": rec.config.model_dump(mode="json")}
    return plain_json(out)


def cmd_info(args: argparse.Namespace) -> int:
    import zarr
    from sffscan.pipeline.formats.recording import RecordingError
    from sffscan.pipeline.formats.recording_reader import open_recording

    path = Path(args.path)
    try:
        fmt = zarr.open_group(str(path), mode="r", use_consolidated=False).attrs.get("format")
    except Exception:  # noqa: BLE001 - reported by open_recording below
        fmt = None
    if fmt == "sffscan-mosaic":
        return _info_mosaic(path, as_json=args.json)
    bad: list[int] = []
    try:
        rec = open_recording(path)
        if args.verify:
            bad = rec.verify()
    except RecordingError as err:
        return fail(str(err))
    info = _recording_info(rec)
    if args.json:
        if args.verify:
            info["verified"] = {"corrupt": rec.report.corrupt,
                                "misplaced": rec.report.misplaced}
        print(json.dumps(info))
    else:
        for line in rec.report.lines():
            print(line)
        a = rec.attrs
        print(f"format      {a.format} v{a.format_version}, frames {list(a.frame_shape)} "
              f"{a.dtype}, codec {a.codec or 'unknown'}, written by {a.writer or 'unknown'} "
              f"{a.created or ''}".rstrip())
        print(f"rate        {info['rate_frames_per_s']:.1f} frames/s (from the time stamps)")
        print(f"expected    {info['frames_expected']} frames ("
              + ("the live scan's count" if a.frames_planned is not None else "the plan's")
              + f"), {rec.report.frames} usable: a replay would be "
              + ("complete" if info["replay_complete"] else "incomplete"))
        print(describe(rec.config))
        p = rec.config.processing
        print(f"processing  {p.focus_operator} k={p.window}, {p.depth_method}, registration "
              f"{'on' if p.registration else 'off'}")
        if args.verify:
            print(f"verified    every usable frame decoded; {len(rec.report.corrupt)} corrupt, "
                  f"{len(rec.report.misplaced)} misplaced")
    if bad:
        corrupt = [i for i in bad if i in rec.report.corrupt]
        misplaced = [i for i in bad if i in rec.report.misplaced]
        what = "; ".join(f"{name} frame_id {', '.join(map(str, ids[:20]))}"
                         + (f" ... (+{len(ids) - 20})" if len(ids) > 20 else "")
                         for name, ids in (("corrupt", corrupt), ("misplaced", misplaced))
                         if ids)
        print(f"sffscan: {path}: --verify found {len(bad)} frame(s) that a replay leaves out: "
              f"{what}", file=sys.stderr)
        return EXIT_INCOMPLETE
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
    json_option(p, "the summary")
    p.set_defaults(func=cmd_replay)

    p = sub.add_parser("info", help="summarise a recording (or a mosaic)",
                       description="Summarise a recording (frames, duration, gaps and other "
                                   "defects, configuration) or a mosaic (status, tiles, "
                                   "journal, levels, processing, valid pixels, height range, "
                                   "stored accuracy). Exit 0; with --verify, 3 when frames "
                                   "are corrupt or misplaced (named on stderr).")
    p.add_argument("path", help="recording or mosaic (Zarr v3 group)")
    p.add_argument("--verify", action="store_true",
                   help="recording: decode every frame (finds corrupt and misplaced frames; "
                        "reads the whole recording); exit 3 if any")
    json_option(p, "the summary")
    p.set_defaults(func=cmd_info)
