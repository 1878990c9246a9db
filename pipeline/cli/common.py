"""What the commands of :mod:`pipeline.cli.main` share: exit codes, scan options and overrides,
and running a scan with its summary and failure messages.

A command module (``pipeline.cmd_*``) defines ``register(sub)``, which adds its
sub-commands to the ``sffscan`` parser; :data:`pipeline.cli.main.COMMAND_MODULES` lists them.
"""

from __future__ import annotations

import argparse
import json
import math
import re
import sys
from collections.abc import Callable, Iterator, Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Any, get_args

from sffscan.pipeline.config import (
    ConfigError,
    ProcessingConfig,
    ScanConfig,
    max_speed_sliding_mm_s,
    max_speed_thesis_mm_s,
)
from sffscan.stages.operators import FOCUS_OPERATORS

if TYPE_CHECKING:
    from sffscan.pipeline.completeness import FrameAccount
    from sffscan.pipeline.run import Job
    from sffscan.pipeline.wiring import ScanReport
    from sffscan.stages.messages import Frame
    from sffscan.stages.protocol import Sink

EXIT_OK, EXIT_FAILED, EXIT_BAD_INPUT, EXIT_INTERRUPTED = 0, 1, 2, 130


def fail(msg: str) -> int:
    """Print ``sffscan: msg`` on stderr and return :data:`EXIT_BAD_INPUT` (a command's bad
    input: the message names the file or option)."""
    print(f"sffscan: {msg}", file=sys.stderr)
    return EXIT_BAD_INPUT
#: the scan ended cleanly but fewer frames than expected were received and processed (the
#: mosaic's status is 'incomplete'; see sffscan.pipeline.completeness)
EXIT_INCOMPLETE = 3
#: stopped by SIGTERM (128 + 15); the mosaic is 'failed' and resumable, as after Ctrl-C
EXIT_TERMINATED = 143

#: focus measure operators (the names alone: importing them loads no torch)
OPERATOR_CHOICES: tuple[str, ...] = tuple(FOCUS_OPERATORS)
#: depth methods, as the configuration model accepts them
DEPTH_METHOD_CHOICES: tuple[str, ...] = get_args(
    ProcessingConfig.model_fields["depth_method"].annotation)


def _option_type(convert: Callable[[str], Any], ok: Callable[[Any], bool], rule: str,
                 name: str) -> Callable[[str], Any]:
    """An argparse ``type``: ``convert`` the text, then ``ok`` or a usage error saying
    ``rule`` and the value given (argparse names the option)."""
    what = "an integer" if convert is int else "a number"

    def parse(text: str) -> Any:
        try:
            value = convert(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"not {what}: {text!r}") from None
        if not ok(value):
            raise argparse.ArgumentTypeError(f"{rule}, got {text}")
        return value

    parse.__name__ = name
    return parse


def check_distinct(paths: Sequence[str], what: str, *, first: int = 1, why: str) -> None:
    """No file or folder given twice in one command (overlapping globs, two spellings of
    one path): a ``ValueError`` naming it and both places (``what`` counted from
    ``first``), then ``why`` it matters."""
    seen: dict[Path, int] = {}
    for i, p in enumerate(paths):
        key = Path(p).resolve()
        if key in seen:
            raise ValueError(f"{p}: given twice ({what} {seen[key] + first} and {i + first}); "
                             f"{why}")
        seen[key] = i


#: ``--seed``: numpy's seeds are non-negative integers
seed = _option_type(int, lambda v: v >= 0, "a seed is a non-negative integer", "seed")
#: ``--bit-depth``: the images' integer samples, 1..16 bits
bit_depth = _option_type(int, lambda v: 1 <= v <= 16, "a bit depth is 1..16", "bit_depth")
#: a length or size: a finite number > 0
finite_positive = _option_type(float, lambda v: 0 < v < math.inf,
                               "must be a finite number > 0", "finite_positive")
#: a coordinate or level: a finite number
finite = _option_type(float, math.isfinite, "must be a finite number", "finite")


def processing_choices(p: argparse.ArgumentParser) -> None:
    """Options that choose how frames are processed: registration, depth method, operator,
    window, calibration (scan, replay, batch)."""
    p.add_argument("--no-registration", action="store_true",
                   help="place frames by speed only")
    p.add_argument("--method", choices=DEPTH_METHOD_CHOICES,
                   help="depth method (default shape_select)")
    p.add_argument("--operator", type=str.lower, choices=OPERATOR_CHOICES, metavar="OPERATOR",
                   help="focus measure operator, a toolbox acronym in any case (default glvm): "
                        + ", ".join(OPERATOR_CHOICES))
    p.add_argument("--window", type=int, help="focus measure window k, odd, px")
    p.add_argument("--calibration", metavar="FILE",
                   help="calibration JSON ('sffscan calibrate'): its z response, vignetting, "
                        "magnification per focus level and field curvature are corrected")


def processing_options(p: argparse.ArgumentParser) -> None:
    """Options that change how frames are processed and shown (scan and replay)."""
    processing_choices(p)
    p.add_argument("--execution", choices=["auto", "threads", "processes"],
                   help="run the stages in worker processes (frames in shared memory) or in "
                        "threads of one process (default auto: processes for large scans)")
    p.add_argument("--viewer", metavar="MODE", default=None,
                   help="live view in Rerun, one word: spawn (native viewer), serve (web viewer on "
                        "this machine), save (to the --rrd file), auto (spawn where a display "
                        "exists, else serve), off")
    p.add_argument("--rrd", metavar="PATH",
                   help="Rerun recording (.rrd) that '--viewer save' writes (--rrd alone "
                        "implies --viewer save)")


def json_option(p: argparse.ArgumentParser, what: str) -> None:
    """``--json``: the command's result as one JSON object on stdout, for scripts."""
    p.add_argument("--json", action="store_true",
                   help=f"print {what} as one JSON object on stdout (for scripts), instead "
                        "of the text lines")


def scan_options(p: argparse.ArgumentParser, *,
                 output_help: str = "mosaic path, a Zarr v3 group") -> None:
    """Options of the commands that acquire a scan (demo, scan)."""
    p.add_argument("-o", "--output", help=output_help)
    p.add_argument("--overwrite", action="store_true", help="replace an existing mosaic")
    p.add_argument("--record", metavar="PATH",
                   help="also record the raw stream (frames, headers, configuration) into "
                        "this Zarr v3 group, for 'sffscan replay'")
    p.add_argument("--speed", type=float, help="stage speed, mm/s")
    p.add_argument("--wobble", type=float, help="sim: stage wobble, ± px along and across")
    p.add_argument("--seed", type=seed, help="sim: seed of texture and noise")
    p.add_argument("--source", metavar="ADDRESS",
                   help="receive frames from 'sffscan grab' at tcp://HOST:PORT or ipc://PATH")
    processing_options(p)


def override(cfg: ScanConfig, args: argparse.Namespace, *,
             own_overwrite: bool = True) -> ScanConfig:
    """Apply command-line overrides, re-validating the whole configuration.

    ``own_overwrite=False`` (a replay: the configuration is the recording's, not the
    user's): ``output.overwrite`` is ``--overwrite`` alone, never the recorded value."""
    from sffscan.pipeline.run import with_overrides

    motion: dict[str, Any] = {}
    processing: dict[str, Any] = {}
    source: dict[str, Any] = {}
    if getattr(args, "speed", None) is not None:
        motion["speed_mm_s"] = args.speed
    if getattr(args, "wobble", None) is not None:
        motion.update(wobble_along_px=args.wobble, wobble_across_px=args.wobble)
    if getattr(args, "no_registration", False):
        processing["registration"] = False
    for option, key in (("execution", "execution"), ("method", "depth_method"),
                        ("operator", "focus_operator")):
        if getattr(args, option, None):
            processing[key] = getattr(args, option)
    if getattr(args, "window", None) is not None:
        processing["window"] = args.window
    if getattr(args, "calibration", None):
        processing["calibration"] = str(args.calibration)
    if getattr(args, "seed", None) is not None:
        source["seed"] = args.seed
    overwrite = True if getattr(args, "overwrite", False) else (None if own_overwrite else False)
    return with_overrides(cfg, origin="command line", output=getattr(args, "output", None) or None,
                          overwrite=overwrite, motion=motion, processing=processing,
                          source=source)


def describe(cfg: ScanConfig) -> str:
    o, m = cfg.optics, cfg.motion
    return (f"scan: {m.passes} pass(es) over x {m.x_start_mm:g}..{m.x_end_mm:g} mm at "
            f"{m.speed_mm_s:g} mm/s; {o.width_px}x{o.height_px} px, {o.pixel_um:g} µm/px, "
            f"{o.fps:g} fps, N = {o.n_levels} levels of {o.z_step_um:g} µm; speed limit "
            f"{max_speed_sliding_mm_s(cfg):.1f} mm/s (sliding window), thesis per-stack "
            f"limit {max_speed_thesis_mm_s(cfg, overlap=m.pass_overlap):.1f} mm/s (overlap "
            f"{100 * m.pass_overlap:g} % = motion.pass_overlap, as 'sffscan plan --overlap')")


def viewer_mode(viewer: str | None, rrd: str | None, *, default: str = "off") -> list[str]:
    """The viewer words of ``--viewer MODE`` and ``--rrd PATH`` (``["save", PATH]`` for a
    saved recording); a ``--rrd`` without ``save``, or ``save`` without ``--rrd``, is a
    usage error (:class:`ConfigError`)."""
    if rrd is not None:
        if viewer not in (None, "save"):
            raise ConfigError(f"--rrd {rrd}: only with --viewer save (got --viewer {viewer})")
        return ["save", rrd]
    mode = viewer or default
    if mode == "save":
        raise ConfigError("--viewer save: give the recording's path with --rrd PATH")
    return [mode]


def viewer_sink(cfg: ScanConfig, viewer: str | None, *, default: str = "off",
                rrd: str | None = None) -> Sink | None:
    """The live-view sink ``--viewer`` (and ``--rrd``) ask for, or None for ``off``. A
    served view that should stay up after the scan waits in :func:`hold_views`, after the
    summary, not in the sink's ``close``."""
    mode = viewer_mode(viewer, rrd, default=default)
    if mode == ["off"]:
        return None
    from sffscan.pipeline.viz.sink import native_viewer_possible, viz_sink_for

    if mode == ["spawn"] and not native_viewer_possible():
        raise ConfigError("--viewer spawn: no display to open the native viewer on (neither "
                          "DISPLAY nor WAYLAND_DISPLAY is set); use '--viewer serve' (a web "
                          "viewer on this machine) or '--rrd PATH.rrd' (a recording to open "
                          "later with 'rerun PATH.rrd')")

    return viz_sink_for(cfg, mode)


def hold_views(sinks: list[Sink] | None) -> None:
    """A served live view that stays up after the scan (``waiting``: run from a terminal)
    is kept until Enter; called after the summary is printed."""
    for sink in sinks or ():
        if not getattr(sink, "waiting", False):
            continue
        address = getattr(sink, "wait_at_end", "")
        print(f"sffscan: scan done; the live view stays at {address} until you press Enter",
              file=sys.stderr, flush=True)
        try:
            input()
        except (EOFError, KeyboardInterrupt):
            pass
        finally:
            sink.release()  # type: ignore[attr-defined]


def run_and_report(cfg: ScanConfig, frames: Iterator[Frame], *, world: Any | None,
                   progress: bool, sinks: list[Sink] | None = None, kept: str = "",
                   account: FrameAccount | None = None) -> int:
    """Run a scan over ``frames`` through the one run path (:func:`report_job`), print its
    summary (scored against ``world`` if given) and return the exit code."""
    from sffscan.pipeline.run import Job

    return report_job(Job(cfg, frames=frames, progress=progress, sinks=list(sinks or []),
                          account=account), world=world, kept=kept)


def report_job(job: Job, *, world: Any | None = None, evaluate: bool = False,
               kept: str = "", as_json: bool = False) -> int:
    """Run ``job`` (:func:`sffscan.pipeline.run.execute`: pre-flight, clash checks, writer
    lock, completeness), print its summary (scored against ``world``, or the simulated
    feed's world with ``evaluate``) and return the exit code; failures print the stage, the
    cause and what was kept (``kept`` replaces the default sentence). A scan that received
    fewer frames than expected ends :data:`EXIT_INCOMPLETE`. Bad input
    (:class:`ConfigError`, nothing changed) is raised for the caller to report. With
    ``as_json`` the summary is one JSON object (:func:`summary_dict`) on stdout."""
    from sffscan.pipeline.run import Terminated, execute
    from sffscan.pipeline.runtime import StageFailed
    from sffscan.pipeline.wiring import evaluate_sim, format_summary

    cfg = job.cfg
    kept = kept or f"the mosaic at {cfg.output.path} holds what was completed"
    try:
        run = execute(job)
    except StageFailed as err:
        print(f"sffscan: {err}", file=sys.stderr)
        print(f"sffscan: {kept} before the failure (status 'failed')", file=sys.stderr)
        from sffscan.pipeline.hardware.daq import DaqNotFoundError

        # hardware that is not there is a set-up problem, like a bad configuration
        return EXIT_BAD_INPUT if isinstance(err.cause, DaqNotFoundError) else EXIT_FAILED
    except Terminated:
        print(f"sffscan: terminated (SIGTERM); {kept} (status 'failed')", file=sys.stderr)
        return EXIT_TERMINATED
    except KeyboardInterrupt:
        print(f"sffscan: interrupted; {kept} (status 'failed')", file=sys.stderr)
        return EXIT_INTERRUPTED
    if run is None:  # check_only: every check passed
        print("configuration, device, paths and memory checked: ready to scan",
              file=sys.stderr)
        return EXIT_OK
    report, account = run.report, run.account
    world = world if world is not None else (run.world if evaluate else None)
    if world is not None:
        evaluate_sim(report, world)
    if as_json:
        print(json.dumps(summary_dict(report, account)), flush=True)
    else:
        print(format_summary(report), flush=True)
        if account is not None:
            print(f"frames      {account.describe()}", flush=True)
    hold_views(run.sinks)
    if run.annotate_error:
        print(f"sffscan: {run.annotate_error}", file=sys.stderr)
        return EXIT_FAILED
    if account is not None and not account.complete:
        print(f"sffscan: INCOMPLETE: {account.describe()}; the mosaic at {report.output} has "
              "status 'incomplete'", file=sys.stderr)
        return EXIT_INCOMPLETE
    return EXIT_OK


def summary_dict(report: ScanReport, account: FrameAccount | None = None) -> dict[str, Any]:
    """A scan's or replay's summary as plain JSON values: mosaic path, frames, wall time (s),
    dropped frames, each stage's and queue's counters, the accuracy (µm, dB) when scored,
    and the frame account (expected, received, complete)."""
    import dataclasses

    r = report.result
    out: dict[str, Any] = {
        "mosaic": str(report.output),
        "frames": report.frames,
        "wall_s": r.wall_s,
        "frames_per_s": report.frames / r.wall_s if r.wall_s else 0.0,
        "dropped": r.dropped,
        "stages": [{**dataclasses.asdict(st), "per_s": st.frames_per_s} for st in r.stages],
        "queues": [dataclasses.asdict(q) for q in r.queues],
        "extras": r.extras,
        "accuracy": (None if report.accuracy is None
                     else dataclasses.asdict(report.accuracy)),
    }
    if account is not None:
        out["account"] = {"planned": account.planned, "sent": account.sent,
                          "expected": account.expected, "received": account.received,
                          "complete": account.complete}
    return plain_json(out)


def plain_json(value: Any) -> Any:
    """``value`` as plain JSON values: numpy scalars as numbers, paths and other objects as
    strings, tuples as lists."""
    def convert(obj: Any) -> Any:
        item = getattr(obj, "item", None)  # a numpy scalar
        return item() if callable(item) and getattr(obj, "ndim", None) == 0 else str(obj)

    return json.loads(json.dumps(value, default=convert))


#: one coordinate of ``--region``: a number and an optional unit
_COORD = re.compile(r"^\s*([-+]?(?:\d+\.?\d*|\.\d+)(?:[eE][-+]?\d+)?)\s*(px|mm|um|µm|μm)?\s*$")
#: µm per unit of a ``--region`` coordinate (px: the mosaic's pixel size)
REGION_UNITS_UM = {"mm": 1000.0, "um": 1.0, "µm": 1.0, "μm": 1.0}
REGION_HELP = ("box X0,Y0,X1,Y1 in world coordinates, each with a unit: mm, µm (or um) or "
               "px (a plain number is world px), e.g. 1mm,0,5mm,2mm")


def is_region(text: str) -> bool:
    """Whether ``text`` reads as a ``--region`` box (four coordinates)."""
    parts = text.split(",")
    return len(parts) == 4 and all(_COORD.match(v) for v in parts)


def parse_region(text: str | None, *, pixel_um: float | None = None
                 ) -> tuple[int, int, int, int] | None:
    """World px box ``(x0, y0, x1, y1)`` of ``--region X0,Y0,X1,Y1``; each coordinate a
    number with an optional unit (``mm``, ``µm``/``um``, ``px``; none: world px), converted
    with ``pixel_um`` (µm/px, the mosaic's) to the world px box that covers it (starts
    rounded down, ends up). None for None; ``ValueError`` naming the option otherwise."""
    if text is None:
        return None
    parts = text.split(",") if "," in text else text.split()
    matches = [_COORD.match(v) for v in parts]
    if len(parts) != 4 or not all(matches):
        raise ValueError(f"--region must be four coordinates X0,Y0,X1,Y1, each a number with "
                         f"an optional unit mm, µm or px (world px without one), e.g. "
                         f"1mm,0,5mm,2mm; got {text!r}")
    box: list[int] = []
    for k, m in enumerate(matches):
        assert m is not None
        value, unit = float(m.group(1)), m.group(2) or "px"
        if not math.isfinite(value):  # 1e400: a number the regular expression lets through
            raise ValueError(f"--region {text}: {parts[k].strip()}: not a finite number")
        if unit == "px":
            if value != int(value):
                raise ValueError(f"--region {text}: {parts[k].strip()}: a px coordinate is a "
                                 "whole number")
            box.append(int(value))
            continue
        if pixel_um is None:
            raise ValueError(f"--region {text}: {unit} needs the pixel size (give px)")
        px = value * REGION_UNITS_UM[unit] / pixel_um
        # starts down, ends up, to cover the box asked for (a hair of rounding forgiven)
        box.append(math.floor(px + 1e-9) if k < 2 else math.ceil(px - 1e-9))
    x0, y0, x1, y1 = box
    if x1 <= x0 or y1 <= y0:
        raise ValueError(f"--region {text}: empty box (world px {x0},{y0},{x1},{y1}); X1 must "
                         "exceed X0 and Y1 exceed Y0")
    return x0, y0, x1, y1
