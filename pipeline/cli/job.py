"""Command ``sffscan job``: print jobs scanned layer by layer.

``sffscan job demo`` prints the shipped plate (four objects, 20 layers, sliced by
PrusaSlicer) in the simulator, with injected defects (under-extrusion gaps, blobs, a lifted
corner, a missing object, a layer shift), scans every layer at 15 mm/s into a job folder
and prints each layer's verdict per object as it comes. ``sffscan job show JOB`` prints the
verdicts of a job folder. Exit codes: 0 done (whatever the verdicts), 2 bad input (a job
folder that is not one, a layer out of order), 130 interrupted (the done layers stay; rerun
to resume).
"""

from __future__ import annotations

import argparse
import shutil
import sys
import time
from pathlib import Path

from sffscan.pipeline.cli.common import (
    DEPTH_METHOD_CHOICES,
    EXIT_FAILED,
    EXIT_OK,
    fail,
    seed,
)


def _print_verdict(layer: int, v: object, timings: dict[str, float], n: int) -> None:
    from sffscan.pipeline.printjob.deviation import LayerVerdict

    assert isinstance(v, LayerVerdict)
    objs = "  ".join(f"{o.name.removesuffix('.stl')}:{o.verdict}" for o in v.objects)
    scan = timings.get("scan_s")
    ready = timings.get("verdict_s")
    extra = (f"  scan {scan:.1f} s" if scan is not None else "") + (
        f", verdict +{ready:.2f} s" if ready is not None else "")
    print(f"layer {layer + 1:>3}/{n}  z {v.z_mm:5.2f} mm  {v.verdict.upper():<7}  {objs}{extra}",
          flush=True)
    for o in v.objects:
        if o.verdict in ("warn", "fail") and o.defect_xy_mm is not None:
            print(f"      {o.name}: {o.area_out_mm2:.2f} mm² out of tolerance (missing "
                  f"{o.missing_mm2:.2f}, excess {o.excess_mm2:.2f}), largest at printer "
                  f"({o.defect_xy_mm[0]:.1f}, {o.defect_xy_mm[1]:.1f}) mm, p95 |dev| "
                  f"{o.p95_abs_um:.0f} µm", flush=True)


def cmd_demo(args: argparse.Namespace) -> int:
    from sffscan.pipeline.cli.common import viewer_mode
    from sffscan.pipeline.config import ConfigError
    from sffscan.pipeline.printjob.demo import (
        demo_config,
        demo_defects,
        demo_gcode,
        run_simulated_print,
    )
    from sffscan.pipeline.printjob.gcode import read_gcode
    from sffscan.pipeline.printjob.jobstore import JobError
    from sffscan.pipeline.printjob.live_view import open_job_view

    out = Path(args.output)
    if out.exists() and any(out.iterdir()) and not (out / "manifest.json").is_file():
        return fail(f"{out} exists and is not a job folder")
    if args.overwrite and out.exists():
        shutil.rmtree(out)
    program = read_gcode(demo_gcode())
    n = program.n_layers if args.layers is None else min(args.layers, program.n_layers)
    defects = () if args.no_defects else demo_defects(program)
    print(f"printing {demo_gcode().name} in the simulator: {n} of {program.n_layers} layers, "
          f"objects {', '.join(program.objects)}; {len(defects)} defects injected; each "
          f"layer scanned at 15 mm/s into {out}", file=sys.stderr)
    t0 = time.perf_counter()
    try:
        mode = viewer_mode(args.viewer, args.rrd)
        view = None if mode == ["off"] else (lambda store: open_job_view(store, mode))
        verdicts = run_simulated_print(
            out, defects=defects, layers=list(range(n)), seed=args.seed,
            config=demo_config(seed=args.seed), record=args.record,
            on_layer=lambda k, v, t: _print_verdict(k, v, t, n), view=view)
    except (JobError, ConfigError) as err:
        return fail(str(err))
    counts = {s: sum(v.verdict == s for v in verdicts) for s in ("pass", "warn", "fail",
                                                                 "unknown")}
    print(f"{len(verdicts)} layers in {time.perf_counter() - t0:.0f} s: "
          + ", ".join(f"{c} {s}" for s, c in counts.items())
          + f"; job folder {out} (sffscan.open_job)")
    return EXIT_OK


def cmd_show(args: argparse.Namespace) -> int:
    from sffscan.pipeline.printjob.jobstore import JobError, JobStore

    try:
        store = JobStore.open(args.job)
    except JobError as err:
        return fail(str(err))
    n = len(store.manifest.layer_z_mm)
    done = store.done_layers()
    print(f"job {store.manifest.job_id} ({store.manifest.printer or 'printer not named'}): "
          f"{len(done)} of {n} layers done")
    for k in done:
        _print_verdict(k, store.read_verdict(k), {}, n)
    return EXIT_OK


def _head(path: Path, size: int = 4096) -> bytes:
    """The first ``size`` bytes of a file (a report's title is in them)."""
    with open(path, "rb") as f:
        return f.read(size)


def cmd_report(args: argparse.Namespace) -> int:
    from sffscan.pipeline.config import ConfigError
    from sffscan.pipeline.printjob.jobstore import JobError
    from sffscan.pipeline.printjob.report import write_report
    from sffscan.pipeline.run import check_file_output

    try:
        if args.output is not None:  # never into a layer's recording or mosaic, nor over a
            check_file_output(args.output, "-o")  # file that is not a job report
            old = Path(args.output)
            if old.is_file() and b"<title>sffscan job " not in _head(old):
                raise ConfigError(f"-o {args.output}: exists and is not an sffscan job "
                                  "report; refusing to overwrite it, choose another path")
        out = write_report(args.job, args.output)
    except (JobError, ConfigError) as err:
        return fail(str(err))
    except OSError as err:  # the output cannot be written
        return fail(f"{args.output or args.job}: cannot write the report: {err}")
    print(f"report written to {out}")
    return EXIT_OK


def cmd_calibrate(args: argparse.Namespace) -> int:
    from sffscan.pipeline.printjob.jobstore import JobError
    from sffscan.pipeline.printjob.reprocess import calibrate_mapping

    try:
        c = calibrate_mapping(args.job, layer=args.layer, apply=args.apply)
    except JobError as err:
        return fail(str(err))
    (x, y), (dx, dy) = c.new.offset_um, c.change_um
    print(f"layer {c.layer}: printer -> mosaic offset ({x:.1f}, {y:.1f}) µm, rotation "
          f"{c.new.rotation_deg:g}° (kept); change from the manifest's mapping "
          f"({dx:+.1f}, {dy:+.1f}) µm")
    print("stored in the manifest: later layers use it ('sffscan job reprocess' redoes the "
          "done ones)" if c.applied else "not stored (--apply stores it in the manifest)")
    return EXIT_OK


def run_reprocess(job: str, *, layers: str | None = None,
                  processing: dict[str, object] | None = None) -> int:
    """Reprocess a job folder's layers and print the table (``job reprocess``, and
    ``batch JOB``); returns the exit code."""
    from sffscan.pipeline.printjob.jobstore import JobError, JobStore
    from sffscan.pipeline.printjob.reprocess import LayerRedo, parse_layers, reprocess_job

    try:
        store = JobStore.open(job)
        todo = parse_layers(layers, len(store.manifest.layer_z_mm))
    except JobError as err:
        return fail(str(err))

    def show(r: LayerRedo) -> None:
        new = r.new or ("(kept)" if r.status == "failed" else "-")
        extra = f"  {r.error}" if r.error else ""
        print(f"layer {r.layer:>4}  {r.status:<8} {r.old or '-':>7} -> {new:<8}"
              f"{r.seconds:6.1f} s{extra}", flush=True)

    print(f"{'layer':>10}  {'status':<8} {'old':>7} -> {'new':<8}  time")
    rows = reprocess_job(store, layers=todo, processing=dict(processing or {}) or None,
                         on_layer=show)
    failed = [r for r in rows if r.status == "failed"]
    n = {s: sum(r.status == s for r in rows) for s in ("done", "skipped", "failed")}
    print(", ".join(f"{c} {s}" for s, c in n.items()))
    for r in failed:
        print(f"sffscan: {store.path}: layer {r.layer}: reprocessing failed, its old "
              f"verdict kept: {r.error}", file=sys.stderr)
    return EXIT_FAILED if failed else EXIT_OK


def cmd_reprocess(args: argparse.Namespace) -> int:
    return run_reprocess(args.job, layers=args.layers,
                         processing={"depth_method": args.method} if args.method else None)


def add_printer_fit(subparsers: argparse._SubParsersAction, name: str) -> None:  # type: ignore[type-arg]
    """The printer-mapping fit as sub-command ``name`` (``job calibrate``, ``calibrate
    printer``: one command, two places a user looks for it)."""
    c = subparsers.add_parser(
        name, help="fit the printer -> mosaic mapping from a done layer's mosaic (--apply "
        "stores it in the manifest)",
        description="Fit the printer -> mosaic translation (phase correlation of the layer's "
        "mosaic with its expected map from the G-code, started from the manifest's mapping; "
        "the rotation is kept). Prints the offset and its change, µm. Exit 2 for a missing "
        "layer, a layer without a mosaic or a fit that fails. Also 'sffscan job calibrate' "
        "and 'sffscan calibrate printer'.")
    c.add_argument("job", help="job folder")
    c.add_argument("--layer", type=int, default=None,
                   help="layer to fit on, 0-based (default the first done layer)")
    c.add_argument("--apply", action="store_true",
                   help="store the fitted mapping in the job's manifest (later layers use it)")
    c.set_defaults(func=cmd_calibrate)


def register(sub: argparse._SubParsersAction) -> None:  # type: ignore[type-arg]
    p = sub.add_parser("job", help="print jobs: every layer scanned and compared with the "
                       "G-code (demo, show, report, calibrate, reprocess)",
                       description="Print jobs scanned layer by layer; see 'job demo'.")
    jsub = p.add_subparsers(dest="job_command", required=True)
    d = jsub.add_parser("demo", help="print the shipped plate in the simulator with injected "
                        "defects; scan and judge every layer",
                        description=__doc__)
    d.add_argument("-o", "--output", default="sffscan-job-demo",
                   help="job folder (default sffscan-job-demo; an existing job is resumed)")
    d.add_argument("--layers", type=int, default=None, help="print only the first N layers")
    d.add_argument("--no-defects", action="store_true", help="a defect-free print")
    d.add_argument("--seed", type=seed, default=0, help="texture, bead and noise seed")
    d.add_argument("--record", action="store_true",
                   help="keep each layer's raw recording in the job (larger, slower)")
    d.add_argument("--overwrite", action="store_true", help="replace an existing job folder")
    d.add_argument("--viewer", metavar="MODE", default=None,
                   help="watch it live in Rerun: each layer's scan, deviation and verdict "
                        "(spawn, serve, save with --rrd, auto, off; default off)")
    d.add_argument("--rrd", metavar="PATH", help="Rerun recording (.rrd) of the live view")
    d.set_defaults(func=cmd_demo)
    s = jsub.add_parser("show", help="verdicts of a job folder")
    s.add_argument("job", help="job folder")
    s.set_defaults(func=cmd_show)
    r = jsub.add_parser("report", help="a self-contained HTML report of a job folder "
                        "(tables and deviation maps per layer and object)")
    r.add_argument("job", help="job folder")
    r.add_argument("-o", "--output", default=None,
                   help="HTML file to write (default JOB/report.html)")
    r.set_defaults(func=cmd_report)
    add_printer_fit(jsub, "calibrate")
    rp = jsub.add_parser("reprocess", help="replay each done layer's raw recording into a "
                         "fresh mosaic, recompute its deviation and verdict",
                         description="Reprocess a job's layers from their recordings "
                         "('job demo --record'): replay, compare with the G-code under the "
                         "manifest's current mapping and tolerances, then replace the layer's "
                         "mosaic, deviation and verdict. A layer that fails keeps its old "
                         "results; layers without a recording are skipped. Exit 1 if any "
                         "layer failed, 2 for bad input.")
    rp.add_argument("job", help="job folder")
    rp.add_argument("--layers", metavar="A-B", default=None,
                    help="layers to redo, 0-based, inclusive: 'A-B', 'A' or 'A,B-C' "
                    "(default every done layer)")
    rp.add_argument("--method", choices=DEPTH_METHOD_CHOICES,
                    help="depth method of the replay (default the recorded one)")
    rp.set_defaults(func=cmd_reprocess)
