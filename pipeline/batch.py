"""Reprocess many recordings on a Dask distributed cluster (``sffscan batch``).

One task per recording: the task replays the recording (:func:`sffscan.replay`) into its
own mosaic, on one worker, with the worker's numerical libraries capped to
``threads`` threads so that concurrent tasks do not fight over the cores. A recording that
cannot be processed (unreadable, corrupt, a stage failing) gives a ``failed`` row with the
cause; the other tasks go on.

Every task runs through the one run path (:func:`sffscan.pipeline.run.execute`): pre-flight,
clash checks, the mosaic's writer lock, the recording's identity. A recording still being
written (its writer holds its lock, :mod:`sffscan.pipeline.locks`) is not processed: its row
says ``recording`` and a rerun does it. The output folder may not be a recording's folder
(the mosaics would be taken for recordings on a rerun).

A rerun does only what is left. A mosaic that is final is kept when it was made from the
recording as it is now (:func:`~sffscan.pipeline.run.identity_mismatch`; one made from a
recording written on or replaced since is reprocessed): ``complete`` ones are skipped,
``incomplete`` ones (frames lost in the recording: a replay ends incomplete again) are kept
with their status. A mosaic left ``writing`` or ``failed`` (a worker killed, a
machine lost, a stage failing) is resumed as ``sffscan replay --resume`` does
(:meth:`~sffscan.pipeline.mosaic.writer.MosaicWriter.reopen`): the band writes already in it are
kept, torn tiles are rebuilt, and it ends equal to an uninterrupted run; a mosaic made with
another configuration or from another recording is not resumed but reported
(``overwrite=True`` replaces it). The choice is made by the task when it starts, so a task
that Dask retries after losing its worker resumes what that worker left. The accuracy of an
evaluated mosaic is stored in its attributes (``accuracy``), so that a skipped row still
shows it.

The cluster is a :class:`distributed.LocalCluster` of worker processes on this machine by
default, or any running Dask scheduler given by its address (``tcp://host:8786``): there,
every worker must see the recordings and the output folder at the same paths (a shared
file system) and have sffscan installed. Paths are made absolute before they are sent. The
workers of ``dask worker`` are daemonic processes, which may not start processes: there a
task runs the stages as threads (``processing.execution = "threads"``, the same mosaic).

Results travel back as plain dicts of numbers and strings; nothing of the pipeline crosses
the process boundary but paths.
"""

from __future__ import annotations

import asyncio
import csv
import sys
import time
from collections.abc import Callable, Iterator, Sequence
from contextlib import contextmanager
from dataclasses import asdict, fields
from pathlib import Path
from typing import TYPE_CHECKING, Any

import zarr
from sffscan.pipeline.batch_targets import (
    RESUMABLE,
    STATUSES,
    BatchError,
    BatchRow,
    _mosaic_status,
    mosaic_path,
    plan_targets,
)
from sffscan.pipeline.cover import plan_cover, planned_box_px
from sffscan.pipeline.metrology.evaluate import store_accuracy, stored_accuracy
from sffscan.pipeline.run import InputBusy, ResumeRefused, with_overrides

if TYPE_CHECKING:
    pass

__all__ = ["ResumeRefused", "format_table", "plan_cover", "planned_box_px", "process_recording",
           "run_batch", "store_accuracy", "stored_accuracy", "write_csv"]

#: seconds a local worker process is given to exit when the batch ends
CLOSE_TIMEOUT_S = 30.0
#: what a simulated recording's mosaic is scored against


def _replay(recording: str, mosaic: str, *, processing: dict[str, Any], evaluate: bool,
            overwrite: bool, row: BatchRow, threads: int) -> None:
    """Replay ``recording`` into ``mosaic`` through the one run path
    (:func:`sffscan.pipeline.run.execute`), resuming it if it was interrupted (and not
    ``overwrite``); fills ``row``. Raises what the replay raises."""
    from sffscan.pipeline.formats.recording_reader import open_recording
    from sffscan.pipeline.preflight import needs_torch
    from sffscan.pipeline.run import Job, check_input_free, execute
    from sffscan.pipeline.wiring import evaluate_sim

    check_input_free(recording)  # before reading it: a recording being written is skipped
    rec = open_recording(recording)
    before = _mosaic_status(Path(mosaic))
    status = before.get("status") if before is not None else None
    resume = not overwrite and status in RESUMABLE
    # the same for a fresh run and a resume (which the writer's reopen checks)
    cfg = with_overrides(rec.config, origin="sffscan batch", output=mosaic,
                         overwrite=not resume, processing=processing)
    try:
        with _torch_threads(threads, needed=needs_torch(cfg)):
            run = execute(Job(cfg, recording=rec, resume=resume))
    except ResumeRefused as exc:
        raise ResumeRefused(f"{exc}; the mosaic (status {status}) is kept: --overwrite "
                            "replaces it") from None
    assert run is not None
    report = run.report
    if run.annotate_error:
        raise OSError(run.annotate_error)
    if run.resumed is not None:
        row.note = (f"resumed: {run.resumed[0]} band write(s) kept, {run.resumed[1]} torn "
                    "region(s) rebuilt")
    attrs = zarr.open_group(mosaic, mode="r", use_consolidated=False).attrs.asdict()
    row.status = str(attrs.get("status"))
    if resume and row.status == "complete":
        row.status = "resumed"
    row.frames = report.frames
    row.frames_lost = int(rec.report.as_dict().get("frames_lost", 0))
    valid = attrs.get("valid_pixels")
    row.valid_pixels = int(valid) if isinstance(valid, int) else None
    if evaluate and cfg.source.kind == "sim":
        from sffscan.pipeline.sim_source import make_world

        evaluate_sim(report, make_world(cfg))  # also stored in the mosaic's attributes
        group = zarr.open_group(str(mosaic), mode="r", use_consolidated=False)
        acc = stored_accuracy(group.attrs.asdict())
        if acc is not None:
            row.rmse_um, row.within_2sigma = acc.rmse_um, acc.within_2sigma
    row.coverage = plan_cover(mosaic)


def process_recording(recording: str, mosaic: str, *, processing: dict[str, Any],
                      evaluate: bool, threads: int, overwrite: bool = False) -> dict[str, Any]:
    """Replay one recording into ``mosaic``; the task a worker runs.

    A mosaic left ``writing`` or ``failed`` is resumed (one made with another configuration,
    or unreadable, is kept and the row fails, saying so), unless ``overwrite``; anything
    else at ``mosaic``
    is replaced. The accuracy of a simulated recording (``evaluate``) is stored in the
    mosaic. Never raises for a bad recording or a failing stage: the row says ``failed``
    and why. Returns a :class:`~sffscan.pipeline.batch_targets.BatchRow` as a dict.
    """
    import multiprocessing
    import socket

    from threadpoolctl import threadpool_limits

    row = BatchRow(recording=recording, mosaic=mosaic, status="failed",
                   worker=socket.gethostname())
    t0 = time.perf_counter()
    if multiprocessing.current_process().daemon:
        # a Dask worker is a daemonic process (dask worker, LocalCluster's default): it may
        # not start processes, so the stages run as threads (the same mosaic, bit for bit)
        processing = {**processing, "execution": "threads"}
    try:
        with threadpool_limits(limits=threads):
            _replay(recording, mosaic, processing=processing, evaluate=evaluate,
                    overwrite=overwrite, row=row, threads=threads)
    except Exception as exc:  # noqa: BLE001 - reported in the row; the batch goes on
        row.status = "failed"
        if isinstance(exc, InputBusy):  # not a failure: a rerun does it once it is complete
            row.status = "recording"
        text = str(exc) if isinstance(exc, (ResumeRefused, InputBusy)) \
            else f"{type(exc).__name__}: {exc}"
        row.error = " ".join(text.split())[:500]
    row.wall_s = round(time.perf_counter() - t0, 3)
    return asdict(row)


@contextmanager
def _torch_threads(threads: int, *, needed: bool) -> Iterator[None]:
    """torch's intra-op threads limited to ``threads`` for the block (restored after: a
    worker of a shared cluster runs other tasks) when the scan ``needed`` torch or torch is
    loaded already; nothing when torch is not installed (it is the optional extra
    ``sffscan[torch]``). Importing torch only to limit it cost a fresh Dask worker ~1.5 s
    of CPU for scans that never use it."""
    import importlib.util

    if not (needed or "torch" in sys.modules) or importlib.util.find_spec("torch") is None:
        yield
        return
    import torch

    before = torch.get_num_threads()
    torch.set_num_threads(threads)
    try:
        yield
    finally:
        torch.set_num_threads(before)


def _check_out_dir(recordings: Sequence[Path], out_dir: Path) -> None:
    """The output folder is not a recording's folder, nor inside a recording."""
    out = out_dir.resolve()
    for rec in recordings:
        r = rec.resolve()
        if out == r.parent:
            raise BatchError(f"-o {out_dir}: the folder of the recording {rec}; the mosaics "
                             "would be taken for recordings on a rerun, choose another folder")
        if out == r or r in out.parents:
            raise BatchError(f"-o {out_dir}: inside the recording {rec}; choose another folder")


def run_batch(recordings: Sequence[Path], out_dir: Path, *, scheduler: str | None = None,
              workers: int = 2, threads: int = 1, processing: dict[str, Any] | None = None,
              evaluate: bool = True, rerun: bool = False, overwrite: bool = False,
              on_row: Callable[[BatchRow, int, int], None] | None = None) -> list[BatchRow]:
    """Reprocess ``recordings`` into ``out_dir`` on a Dask cluster.

    Parameters
    ----------
    recordings : sequence of Path
        From :func:`~sffscan.pipeline.batch_targets.find_recordings`.
    out_dir : Path
        Folder of the mosaics (``<name>.mosaic.zarr``), created if missing.
    scheduler : str, optional
        Address of a running Dask scheduler; by default a ``LocalCluster`` of ``workers``
        worker processes, one task at a time each, is started and closed here.
    workers, threads : int
        Local worker processes; threads each task's numerical libraries may use.
    processing : dict, optional
        ``processing`` fields overriding each recording's own (as ``sffscan replay``).
    evaluate : bool
        Score recordings of the simulator against its true surface (RMSE, CORR, PSNR,
        coverage), stored in the mosaic's attributes (``accuracy``).
    rerun : bool
        Reprocess every recording from scratch: final mosaics (complete, incomplete) are
        replaced instead of kept, interrupted ones instead of resumed.
    overwrite : bool
        Replace mosaics left ``writing`` or ``failed`` instead of resuming them (as a
        mosaic made with another configuration must be); final mosaics are still kept.
    on_row : callable, optional
        Called with (row, rows done, rows in all) as each recording finishes (progress).

    Returns
    -------
    list of BatchRow
        One per recording, in the order given.
    """
    from distributed import Client, LocalCluster, as_completed

    # the workers see paths, not this process's working folder (another one, or another
    # machine's with the same shared file system): every path goes absolute
    recordings = [Path(r).resolve() for r in recordings]
    out_dir = Path(out_dir).resolve()
    _check_out_dir(recordings, out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    targets = [(r, mosaic_path(r, out_dir)) for r in recordings]
    dupes = {str(m) for _, m in targets if sum(1 for _, n in targets if n == m) > 1}
    if dupes:
        raise BatchError(f"recordings with the same name would share a mosaic: {sorted(dupes)}")
    rows, todo = plan_targets(targets, rerun=rerun)
    total, done = len(targets), 0
    for i in sorted(rows):
        done += 1
        if on_row is not None:
            on_row(rows[i], done, total)
    if not todo:
        return [rows[i] for i in range(total)]
    import dask

    # worker processes that may start processes themselves (the pipeline's parallel stages)
    with dask.config.set({"distributed.worker.daemon": False}):
        cluster = (None if scheduler else
                   LocalCluster(n_workers=workers, threads_per_worker=1, processes=True,
                                # no fixed port: another cluster's 8787 is no conflict
                                dashboard_address="127.0.0.1:0", memory_limit=0))
        try:
            with Client(scheduler or cluster) as client:
                futures = {client.submit(process_recording, str(targets[i][0]),
                                         str(targets[i][1]), processing=processing or {},
                                         evaluate=evaluate, threads=threads,
                                         overwrite=overwrite or rerun, pure=False,
                                         key=f"sffscan-batch-{i}-{targets[i][0].name}"): i
                           for i in todo}
                for fut in as_completed(futures):
                    i = futures[fut]
                    try:
                        row = BatchRow(**fut.result())
                    except Exception as exc:  # noqa: BLE001 - a worker lost, not the batch
                        row = BatchRow(recording=str(targets[i][0]), mosaic=str(targets[i][1]),
                                       status="failed", error=f"{type(exc).__name__}: {exc}")
                    rows[i] = row
                    done += 1
                    if on_row is not None:
                        on_row(row, done, total)
        finally:
            if cluster is not None:
                # workers get time to exit by themselves (a worker that imported torch can
                # take more than the 4 s the default close waits, on a loaded machine)
                cluster.sync(_close_workers, cluster, CLOSE_TIMEOUT_S)
                cluster.close()
    return [rows[i] for i in range(total)]


async def _close_workers(cluster: Any, timeout: float) -> None:
    await asyncio.gather(*(w.close(timeout=timeout) for w in cluster.workers.values()))


def is_results_csv(path: Path) -> bool:
    """True when ``path`` holds a batch's results table (:func:`write_csv`'s header first):
    the only existing file a batch replaces with its own."""
    try:
        with open(path, encoding="utf-8", newline="") as f:
            first = f.readline().strip()
    except (OSError, UnicodeDecodeError):
        return False
    names = [f.name for f in fields(BatchRow)]
    # this version's header, or the one before ``within_2sigma`` (a folder of an older batch)
    return first in (",".join(names), ",".join(n for n in names if n != "within_2sigma"))


def write_csv(rows: Sequence[BatchRow], path: Path) -> None:
    """The results table as CSV (one row per recording, header first)."""
    names = [f.name for f in fields(BatchRow)]
    part = path.with_name(path.name + ".part")
    with open(part, "w", newline="", encoding="utf-8") as f:
        w = csv.DictWriter(f, fieldnames=names)
        w.writeheader()
        for r in rows:
            w.writerow({k: ("" if v is None else v) for k, v in asdict(r).items()})
    part.replace(path)


def format_table(rows: Sequence[BatchRow]) -> str:
    """The results table for a terminal."""
    lines = [f"{'recording':<28} {'status':<10} {'frames':>7} {'lost':>5} {'RMSE µm':>8} "
             f"{'in 2σ':>6} {'cover':>6} {'s':>7}  error / note"]

    def num(v: float | int | None, fmt: str) -> str:
        return "-" if v is None else format(v, fmt)

    for r in rows:
        lines.append(f"{Path(r.recording).name[:28]:<28} {r.status:<10} "
                     f"{num(r.frames, 'd'):>7} {num(r.frames_lost, 'd'):>5} "
                     f"{num(r.rmse_um, '.1f'):>8} {num(r.within_2sigma, '.3f'):>6} "
                     f"{num(r.coverage, '.3f'):>6} "
                     f"{num(r.wall_s, '.1f'):>7}  {'; '.join(t for t in (r.error, r.note) if t)}")
    counts = {s: sum(1 for r in rows if r.status == s) for s in STATUSES}
    lines.append(", ".join(f"{n} {s}" for s, n in counts.items() if n) or "nothing")
    return "\n".join(lines)
