"""Command ``sffscan batch``: reprocess many recordings on a Dask cluster.

``sffscan batch REC... -o OUT`` replays every recording (paths, glob patterns, or folders of
layers) into ``OUT/<name>.mosaic.zarr``, one task per recording, on a local cluster of
worker processes (``--workers``) or on a running Dask scheduler (``--scheduler
tcp://host:8786``); prints the results table and writes it as CSV (``OUT/batch.csv``).
A rerun does what is left: complete mosaics are skipped, incomplete ones kept (both only
while the recording is as it was when they were made), interrupted ones (left ``writing``
or ``failed``) resumed (``--overwrite`` replaces them, ``--rerun`` redoes everything); a
recording still being written is left for a rerun (status ``recording``). ``-o`` may not
be the recordings' own folder. Exit 0 when every mosaic is complete, 1 when some failed, are
incomplete or still being recorded, 2 for bad input. See :mod:`sffscan.pipeline.batch`.
"""

from __future__ import annotations

import argparse
import logging
import os
import sys
from pathlib import Path

from sffscan.pipeline.cli.common import (
    EXIT_FAILED,
    EXIT_OK,
    fail,
    processing_choices,
)

log = logging.getLogger(__name__)


def _processing(args: argparse.Namespace) -> dict[str, object]:
    out: dict[str, object] = {}
    if args.no_registration:
        out["registration"] = False
    if args.method:
        out["depth_method"] = args.method
    if args.operator:
        out["focus_operator"] = args.operator
    if args.window is not None:
        out["window"] = args.window
    if args.calibration:
        out["calibration"] = str(Path(args.calibration).resolve())
    return out


def cmd_batch(args: argparse.Namespace) -> int:
    from sffscan.pipeline.batch import format_table, is_results_csv, run_batch, write_csv
    from sffscan.pipeline.batch_targets import BatchError, BatchRow, find_recordings, mosaic_path
    from sffscan.pipeline.config import ConfigError
    from sffscan.pipeline.run import check_file_output

    if len(args.recordings) == 1 and (Path(args.recordings[0]) / "manifest.json").is_file():
        # a print job's folder: its layers are reprocessed in place ('sffscan job reprocess')
        if args.output is not None or args.scheduler:
            return fail(f"{args.recordings[0]} is a job folder: its layers are reprocessed "
                  "in place, in this process (no -o, no --scheduler)")
        from sffscan.pipeline.cli.job import run_reprocess

        return run_reprocess(args.recordings[0], processing=_processing(args))
    if args.output is None:
        return fail("batch: -o/--output is required (the folder of the mosaics)")
    if args.workers < 1 or args.threads < 1:
        return fail("--workers and --threads must be >= 1")
    try:
        recordings = find_recordings(args.recordings)
    except BatchError as err:
        return fail(str(err))
    out = Path(args.output)
    csv_path = Path(args.csv) if args.csv else out / "batch.csv"
    try:  # never into a recording or a mosaic, never over another file
        check_file_output(csv_path, "--csv",
                          stores=[*recordings, *(mosaic_path(r, out) for r in recordings)])
        if csv_path.exists() and not is_results_csv(csv_path):
            raise ConfigError(f"--csv {csv_path}: exists and is not a batch's results table; "
                              "refusing to overwrite it, choose another path")
    except ValueError as err:
        return fail(str(err))
    where = args.scheduler or f"a local cluster of {args.workers} worker process(es)"
    log.info("batch: %d recording(s) -> %s on %s, %d thread(s) per task", len(recordings), out,
             where, args.threads)

    def progress(row: BatchRow, done: int, total: int) -> None:
        extra = f" ({row.error})" if row.error else ""
        log.info("[%d/%d] %s: %s%s", done, total, Path(row.recording).name, row.status, extra)

    try:
        rows = run_batch(recordings, out, scheduler=args.scheduler, workers=args.workers,
                         threads=args.threads, processing=_processing(args),
                         evaluate=not args.no_evaluate, rerun=args.rerun,
                         overwrite=args.overwrite,
                         on_row=None if args.quiet else progress)
    except BatchError as err:
        return fail(str(err))
    write_csv(rows, csv_path)
    print(format_table(rows))
    print(f"results: {csv_path}")
    bad = [r for r in rows if r.status not in ("complete", "resumed", "skipped")]
    for r in bad:
        print(f"sffscan: {r.recording}: {r.status}" + (f": {r.error}" if r.error else ""),
              file=sys.stderr)
    return EXIT_FAILED if bad else EXIT_OK


def register(sub: argparse._SubParsersAction) -> None:  # type: ignore[type-arg]
    p = sub.add_parser(
        "batch", help="reprocess many recordings on a Dask cluster",
        description="Replay many recordings ('sffscan scan --record') into one mosaic each, in "
                    "parallel on a Dask cluster: a local cluster of worker processes, or a "
                    "running scheduler (--scheduler). A bad recording is reported and the "
                    "others complete. A rerun skips complete mosaics, keeps incomplete ones "
                    "(frames lost in the recording) and resumes interrupted ones (left "
                    "'writing' or 'failed': a worker killed, a machine lost) as 'replay "
                    "--resume' does. A results table is printed and written as CSV; its "
                    "'cover' is the valid pixels as a fraction of the area the scan's plan "
                    "measures (its strip), whatever the truth. Exit 1 if any recording failed "
                    "or is incomplete. A print job's folder (sffscan job) as the only argument is "
                    "reprocessed in place, as 'sffscan job reprocess JOB'.",
        epilog="Several machines: start 'dask scheduler' on one (port 8786), 'dask worker "
               "tcp://HOST:8786 --nworkers 2 --nthreads 1' on each, with sffscan installed and "
               "the recordings and OUT on a shared file system at the same paths; then "
               "'sffscan batch layers/ -o OUT --scheduler tcp://HOST:8786'.")
    p.add_argument("recordings", nargs="+",
                   help="recordings (Zarr v3 groups), glob patterns ('layers/*.zarr') or "
                        "folders of recordings")
    p.add_argument("-o", "--output", default=None,
                   help="folder of the mosaics (OUT/<name>.mosaic.zarr) and of batch.csv "
                        "(required, except for a job folder)")
    p.add_argument("--scheduler", metavar="ADDRESS",
                   help="a running Dask scheduler (tcp://host:8786) instead of a local cluster")
    p.add_argument("--workers", type=int, default=max(1, (os.cpu_count() or 2) // 2),
                   help="worker processes of the local cluster (default: half the cores)")
    p.add_argument("--threads", type=int, default=1,
                   help="threads each task's numerical libraries (torch, BLAS) may use")
    p.add_argument("--csv", metavar="PATH", help="results table (default OUT/batch.csv)")
    p.add_argument("--rerun", action="store_true",
                   help="reprocess every recording from scratch, replacing its mosaic "
                        "(complete, incomplete or interrupted)")
    p.add_argument("--overwrite", action="store_true",
                   help="replace mosaics left 'writing' or 'failed' instead of resuming them "
                        "(needed when they were made with another configuration); complete "
                        "and incomplete ones are still kept")
    p.add_argument("--no-evaluate", action="store_true",
                   help="do not score simulated recordings against their true surface")
    processing_choices(p)
    p.set_defaults(func=cmd_batch)
