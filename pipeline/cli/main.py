"""Command line: ``sffscan demo | scan | config | schemas`` and the commands of
:data:`COMMAND_MODULES`.

Exit codes: 0 success; 1 a pipeline stage failed (its name and cause are printed, what was
already written stays readable); 2 bad configuration, bad input or bad usage; 3 the scan
ended cleanly but incomplete: fewer frames than expected (the plan's, or the count the
sender's end message gave) were received and processed, and the mosaic's status is
'incomplete' with both counts (``sffscan info MOSAIC`` shows them); 130
interrupted (Ctrl-C; the mosaic keeps what was completed); 141 the output pipe was closed
by its reader (``sffscan info ... | head``), said nowhere.

Logging: ``-q`` (warnings and errors only, no progress display) and ``-v`` (debug lines
with their logger's names) go before or after the sub-command (``sffscan -q demo`` =
``sffscan demo -q``); :mod:`sffscan.pipeline.cli.logsetup` installs the one handler.
Results (summaries, reports, tables) go to stdout; status lines, warnings, errors and the
progress display to stderr.
"""

from __future__ import annotations

import argparse
import importlib
import sys
from collections.abc import Sequence
from pathlib import Path

from sffscan.pipeline.cli.common import (
    EXIT_BAD_INPUT,
    EXIT_FAILED,
    EXIT_OK,
    describe,
    override,
    run_and_report,
    scan_options,
    viewer_sink,
)
from sffscan.pipeline.config import (
    REALISTIC_OPTICS,
    ConfigError,
    ScanConfig,
    config_to_toml,
    demo_config,
    load_config,
)

#: Modules that add sub-commands; each defines ``register(sub)``.
COMMAND_MODULES: tuple[str, ...] = (
    "sffscan.pipeline.cli.record", "sffscan.pipeline.cli.hardware",
    "sffscan.pipeline.cli.calibrate", "sffscan.pipeline.cli.metrology",
    "sffscan.pipeline.cli.batch", "sffscan.pipeline.cli.study")


def _run(cfg: ScanConfig, args: argparse.Namespace, *, evaluate: bool, viewer_default: str) -> int:
    from sffscan.pipeline.preflight import preflight
    from sffscan.pipeline.sources import open_feed

    print(describe(cfg), file=sys.stderr)
    source = getattr(args, "source", None)
    # every check before anything is created or deleted (--overwrite included)
    preflight(cfg, record=getattr(args, "record", None),
              simulated=source is None and cfg.source.kind == "sim")
    if getattr(args, "check", False):
        print("configuration, device, paths and memory checked: ready to scan",
              file=sys.stderr)
        return EXIT_OK
    feed = open_feed(cfg, source=getattr(args, "source", None))
    sinks = [k for k in (viewer_sink(cfg, args.viewer, default=viewer_default),) if k]
    if getattr(args, "record", None):
        from sffscan.stages.recorder import recorder_sink

        sinks.append(recorder_sink(cfg, args.record, account=feed.account))
    return run_and_report(cfg, feed.frames, world=feed.world if evaluate else None,
                          progress=not args.quiet, sinks=sinks, account=feed.account)


DEMO_OUTPUT = "sffscan-demo.zarr"


def cmd_demo(args: argparse.Namespace) -> int:
    if args.output is None:  # the demo's own default output is replaced on every run
        args.output, args.overwrite = DEMO_OUTPUT, True
    optics = dict(REALISTIC_OPTICS) if getattr(args, "realistic", False) else {}
    cfg = override(demo_config(passes=args.passes, optics=optics), args)
    return _run(cfg, args, evaluate=True, viewer_default="auto")


def cmd_scan(args: argparse.Namespace) -> int:
    cfg = override(load_config(args.config), args)
    return _run(cfg, args, evaluate=not args.no_evaluate, viewer_default="off")


def cmd_config(args: argparse.Namespace) -> int:
    cfg = demo_config(passes=args.passes)
    text = config_to_toml(cfg)
    if args.output:
        Path(args.output).write_text(text, encoding="utf-8")
        print(f"wrote {args.output}", file=sys.stderr)
    else:
        print(text)
    return EXIT_OK


def cmd_schemas(args: argparse.Namespace) -> int:
    from sffscan.pipeline.formats.schema_gen import check_schemas, write_schemas

    if args.check:
        stale = check_schemas(Path(args.dir))
        if stale:
            print("schemas out of date: " + ", ".join(stale) + " (run 'sffscan schemas')",
                  file=sys.stderr)
            return EXIT_FAILED
        print("schemas up to date")
        return EXIT_OK
    for path in write_schemas(Path(args.dir)):
        print(f"wrote {path}")
    return EXIT_OK


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="sffscan",
        description="Shape-from-focus in continuous motion: scan a part while it prints and "
                    "write a Zarr height mosaic.")
    sub = parser.add_subparsers(dest="command", required=True)

    p = sub.add_parser("demo", help="simulated scan of the characterisation plate at 15 mm/s",
                       description="Simulated scan of the characterisation plate (thesis optics: "
                                   "1280x1024 px, 8.5 µm/px, 150 fps, N = 50, 15 mm/s), then "
                                   "the mosaic's accuracy against the true surface.")
    p.add_argument("--passes", type=int, default=1, help="parallel passes (default 1)")
    p.add_argument("--realistic", action="store_true",
                   help="real non-telecentric tunable-lens optics: +2 %% magnification over "
                        "the focus range, 150 µm field curvature at the corner, 20 %% "
                        "vignetting (default: ideal optics)")
    scan_options(p)
    p.set_defaults(func=cmd_demo)

    p = sub.add_parser("scan", help="run the pipeline from a TOML configuration")
    p.add_argument("--config", required=True, help="TOML file (see 'sffscan config')")
    p.add_argument("--no-evaluate", action="store_true",
                   help="skip the comparison with the simulated true surface")
    p.add_argument("--check", action="store_true",
                   help="check the configuration, device, paths and memory, then exit "
                        "without scanning (0 = ready, 2 = the error names the field)")
    scan_options(p)
    p.set_defaults(func=cmd_scan)

    p = sub.add_parser("config", help="print the demo configuration as TOML, to edit")
    p.add_argument("--passes", type=int, default=1)
    p.add_argument("-o", "--output", help="write to this file instead of stdout")
    p.set_defaults(func=cmd_config)

    p = sub.add_parser("schemas", help="write (or --check) the JSON Schemas in schemas/")
    p.add_argument("--dir", default="schemas", help="schema folder (default schemas)")
    p.add_argument("--check", action="store_true", help="fail if the files differ")
    p.set_defaults(func=cmd_schemas)
    for module in COMMAND_MODULES:
        importlib.import_module(module).register(sub)
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    try:
        return int(args.func(args))
    except (ConfigError, OSError) as err:  # bad configuration, or an unusable path
        print(f"sffscan: {err}", file=sys.stderr)
        return EXIT_BAD_INPUT


if __name__ == "__main__":  # pragma: no cover
    raise SystemExit(main())
