"""Command line: ``sffscan demo | scan | config | schemas``.

Exit codes: 0 success; 1 a pipeline stage failed (its name and cause are printed, what was
already written stays readable); 2 bad configuration, bad input or bad usage; 130
interrupted (Ctrl-C; the mosaic keeps what was completed).
"""

from __future__ import annotations

import argparse
import sys
from collections.abc import Sequence
from pathlib import Path

from pipeline.config import (
    ConfigError,
    ScanConfig,
    config_from_dict,
    config_to_toml,
    demo_config,
    load_config,
    max_speed_sliding_mm_s,
    max_speed_thesis_mm_s,
)
from pipeline.runtime import StageFailed

EXIT_OK, EXIT_FAILED, EXIT_BAD_INPUT, EXIT_INTERRUPTED = 0, 1, 2, 130


def _override(cfg: ScanConfig, args: argparse.Namespace) -> ScanConfig:
    """Apply command-line overrides, re-validating the whole configuration."""
    data = cfg.model_dump()
    if getattr(args, "output", None):
        data["output"]["path"] = str(args.output)
    if getattr(args, "overwrite", False):
        data["output"]["overwrite"] = True
    if getattr(args, "speed", None) is not None:
        data["motion"]["speed_mm_s"] = args.speed
    if getattr(args, "wobble", None) is not None:
        data["motion"]["wobble_along_px"] = args.wobble
        data["motion"]["wobble_across_px"] = args.wobble
    if getattr(args, "no_registration", False):
        data["processing"]["registration"] = False
    if getattr(args, "method", None):
        data["processing"]["depth_method"] = args.method
    if getattr(args, "operator", None):
        data["processing"]["focus_operator"] = args.operator
    if getattr(args, "seed", None) is not None:
        data["source"]["seed"] = args.seed
    return config_from_dict(data, origin="command line")


def _describe(cfg: ScanConfig) -> str:
    o, m = cfg.optics, cfg.motion
    return (f"scan: {m.passes} pass(es) over x {m.x_start_mm:g}..{m.x_end_mm:g} mm at "
            f"{m.speed_mm_s:g} mm/s; {o.width_px}x{o.height_px} px, {o.pixel_um:g} µm/px, "
            f"{o.fps:g} fps, N = {o.n_levels} levels of {o.z_step_um:g} µm; speed limit "
            f"{max_speed_sliding_mm_s(cfg):.1f} mm/s (sliding window), thesis per-stack "
            f"limit {max_speed_thesis_mm_s(cfg):.1f} mm/s")


def _run(cfg: ScanConfig, *, evaluate: bool, progress: bool) -> int:
    from pipeline.wiring import evaluate_sim, format_summary, run_scan
    from stages.sim_scanner import make_world, simulate_frames

    print(_describe(cfg), file=sys.stderr)
    world = make_world(cfg)
    try:
        report = run_scan(cfg, frames=simulate_frames(cfg, world=world), progress=progress)
    except StageFailed as err:
        print(f"sffscan: {err}", file=sys.stderr)
        print(f"sffscan: the mosaic at {cfg.output.path} holds what was completed before the "
              "failure (status 'failed')", file=sys.stderr)
        return EXIT_FAILED
    except KeyboardInterrupt:
        print(f"sffscan: interrupted; the mosaic at {cfg.output.path} holds what was "
              "completed (status 'failed')", file=sys.stderr)
        return EXIT_INTERRUPTED
    if evaluate:
        evaluate_sim(report, world)
    print(format_summary(report))
    return EXIT_OK


DEMO_OUTPUT = "sffscan-demo.zarr"


def cmd_demo(args: argparse.Namespace) -> int:
    if args.output is None:  # the demo's own default output is replaced on every run
        args.output, args.overwrite = DEMO_OUTPUT, True
    cfg = demo_config(passes=args.passes)
    cfg = _override(cfg, args)
    return _run(cfg, evaluate=True, progress=not args.quiet)


def cmd_scan(args: argparse.Namespace) -> int:
    cfg = _override(load_config(args.config), args)
    return _run(cfg, evaluate=not args.no_evaluate, progress=not args.quiet)


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
    from pipeline.schema_gen import check_schemas, write_schemas

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

    def scan_options(p: argparse.ArgumentParser) -> None:
        p.add_argument("-o", "--output",
                       help="mosaic path, a Zarr v3 group (demo: sffscan-demo.zarr, replaced)")
        p.add_argument("--overwrite", action="store_true", help="replace an existing mosaic")
        p.add_argument("--speed", type=float, help="stage speed, mm/s")
        p.add_argument("--wobble", type=float, help="sim: stage wobble, ± px along and across")
        p.add_argument("--no-registration", action="store_true",
                       help="place frames by speed only")
        p.add_argument("--method", choices=["argmax", "gauss3", "quadratic3", "centroid", "pc",
                                            "spc"], help="depth method (default spc)")
        p.add_argument("--operator", choices=["glvm", "tenv"], help="focus measure operator")
        p.add_argument("--seed", type=int, help="sim: seed of texture and noise")
        p.add_argument("-q", "--quiet", action="store_true", help="no progress line")

    p = sub.add_parser("demo", help="simulated scan of the characterisation plate at 15 mm/s",
                       description="Simulated scan of the characterisation plate (thesis optics: "
                                   "1280x1024 px, 8.5 µm/px, 150 fps, N = 50, 15 mm/s), then "
                                   "the mosaic's accuracy against the true surface.")
    p.add_argument("--passes", type=int, default=1, help="parallel passes (default 1)")
    scan_options(p)
    p.set_defaults(func=cmd_demo)

    p = sub.add_parser("scan", help="run the pipeline from a TOML configuration")
    p.add_argument("--config", required=True, help="TOML file (see 'sffscan config')")
    p.add_argument("--no-evaluate", action="store_true",
                   help="skip the comparison with the simulated true surface")
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
