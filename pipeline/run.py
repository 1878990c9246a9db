"""The one run path: every scan, replay, resume and batch task goes through :func:`execute`.

The command line (``sffscan demo | scan | replay``), the Python API (:func:`sffscan.scan`,
:func:`sffscan.replay`) and ``sffscan batch``'s tasks describe what to run as a :class:`Job`
and hand it here; the guarantees then hold whatever the entry point:

1. pre-flight (:func:`sffscan.pipeline.preflight.preflight`): configuration against the
   machine, paths, memory, a listening address that is free; before anything is created
   or deleted (``--overwrite`` included);
2. outputs that would destroy inputs are refused (:func:`check_clashes`): a mosaic equal
   to, inside or around the recording it is made from, a ``--record`` or ``--rrd`` path
   inside a Zarr store;
3. one writer at a time (:mod:`sffscan.pipeline.locks`): the mosaic, and the recording
   being written, are locked while written; a second writer is refused with the holder
   named; a replay of a recording still being written is refused (:class:`InputBusy`);
4. identity: a mosaic records which recording it is made from (:func:`recording_identity`,
   attribute ``recording.identity``); ``--resume`` refuses another recording, and ignores
   how a scan was run (:data:`RUN_ONLY`: threads or processes, queue sizes);
5. the completeness account (:mod:`sffscan.pipeline.completeness`) and the final status;
   SIGTERM in the main thread stops a run as Ctrl-C does (status ``failed``, resumable),
   raised as :class:`Terminated`.

Failures are raised, not printed: :class:`~sffscan.pipeline.config.ConfigError` (bad input,
nothing changed), :class:`~sffscan.pipeline.runtime.StageFailed`, ``KeyboardInterrupt``.
"""

from __future__ import annotations

import contextlib
import hashlib
import json
import logging
import signal
import threading
from collections.abc import Callable, Iterable, Iterator, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any

import zarr
from sffscan.pipeline import locks
from sffscan.pipeline.completeness import FrameAccount
from sffscan.pipeline.config import ConfigError, ScanConfig

if TYPE_CHECKING:
    from sffscan.pipeline.formats.recording_reader import Recording
    from sffscan.pipeline.wiring import ScanReport
    from sffscan.stages.messages import Frame
    from sffscan.stages.protocol import Sink

log = logging.getLogger(__name__)

#: configuration fields that say how a scan was run, not what it measures: a resume may
#: differ in them (the mosaics of threads and processes are bit for bit the same)
RUN_ONLY: tuple[tuple[str, str], ...] = (
    ("processing", "execution"), ("processing", "queue_capacity"), ("processing", "workers"),
    ("processing", "bands"),
    ("source", "idle_timeout_s"), ("source", "max_bad_messages"), ("source", "keys_dir"),
    ("source", "address"))


class ResumeRefused(ConfigError):
    """A mosaic that cannot be resumed with this job (another configuration or recording,
    unreadable); it is kept as it was."""


class InputBusy(ConfigError):
    """The recording to replay is still being written (its writer holds its lock)."""


class Terminated(KeyboardInterrupt):
    """SIGTERM received while a run was in progress (stopped as Ctrl-C stops it)."""


# --- identity ----------------------------------------------------------------------------


def recording_identity(path: str | Path) -> dict[str, Any]:
    """What identifies a recording: its ``recording_id`` attribute when it has one, and a
    digest of its stored configuration, creation time, status, frame count (attribute and
    entries of ``frames``) and resolved location, which changes when it is written on.

    Returns ``{"path", "id", "digest", "frames", "status"}`` (JSON-able).
    """
    p = Path(path).resolve()
    attrs: dict[str, Any] = {}
    entries: int | None = None
    with contextlib.suppress(Exception):  # an unreadable recording: refused elsewhere
        group = zarr.open_group(str(p), mode="r", use_consolidated=False)
        attrs = dict(group.attrs.asdict())
        frames = group.get("frames")
        if isinstance(frames, zarr.Array):
            entries = int(frames.shape[0])
    rid = attrs.get("recording_id")
    body = json.dumps({"config": attrs.get("scan_config"), "created": attrs.get("created"),
                       "status": attrs.get("status"), "frames": attrs.get("frames"),
                       "entries": entries, "path": str(p)}, sort_keys=True, default=str)
    return {"path": str(p), "id": str(rid) if rid is not None else None,
            "digest": hashlib.sha256(body.encode("utf-8")).hexdigest()[:32],
            "frames": entries, "status": attrs.get("status")}


def stored_identity(mosaic_attrs: dict[str, Any]) -> dict[str, Any] | None:
    """The identity of the recording a mosaic was made from (or recorded into, for a live
    scan with ``--record``), None for a mosaic that does not say (older versions)."""
    rec = mosaic_attrs.get("recording")
    ident = rec.get("identity") if isinstance(rec, dict) else None
    return ident if isinstance(ident, dict) else None


def identity_mismatch(stored: dict[str, Any] | None, current: dict[str, Any], *,
                      unchanged: bool = False) -> str | None:
    """Why ``current`` is not the recording of ``stored`` (None when it is, or unknown).

    Recordings with a ``recording_id`` are compared by it, others by their digest. With
    ``unchanged``, a recording written on since (other frame count or status) is not it
    either (``sffscan batch`` keeps a final mosaic only of the recording as it is now)."""
    if stored is None:
        return None
    where = stored.get("path")
    if stored.get("live"):  # a live scan that recorded its frames: the recording's path
        return None if where == current.get("path") else \
            f"it was scanned live into the recording {where}"
    if stored.get("id") and current.get("id"):
        if stored["id"] != current["id"]:
            return f"it was made from the recording {where} (id {stored['id']})"
    elif stored.get("digest") != current.get("digest"):
        return (f"it was made from the recording {where}" if where != current.get("path")
                else f"it was made from {where} as it was then ({stored.get('frames')} "
                     f"entries, status {stored.get('status')}); the recording has changed since")
    if unchanged and (stored.get("frames"), stored.get("status")) != (current.get("frames"),
                                                                       current.get("status")):
        return (f"it was made from {where} as it was then ({stored.get('frames')} entries, "
                f"status {stored.get('status')}); the recording has changed since")
    return None


# --- outputs against inputs --------------------------------------------------------------


def with_overrides(cfg: ScanConfig, *, origin: str, output: str | Path | None = None,
                   overwrite: bool | None = None,
                   **tables: dict[str, Any] | None) -> ScanConfig:
    """``cfg`` with the given fields replaced, re-validated as a whole: the one place where
    the command line, the Python API and ``sffscan batch`` change a configuration.

    ``output`` and ``overwrite`` set ``output.path`` and ``output.overwrite`` (None: kept);
    every other keyword names a table (``processing``, ``motion``, ``source``, ...) and
    gives the fields to replace in it. A table or field the configuration does not have is
    a :class:`ValueError` naming it; an invalid value is the model's :class:`ConfigError`
    with ``origin`` (what asked for the change) in its message.
    """
    from sffscan.pipeline.config import config_from_dict

    data = cfg.model_dump()
    if output is not None:
        data["output"]["path"] = str(output)
    if overwrite is not None:
        data["output"]["overwrite"] = bool(overwrite)
    for table, fields in tables.items():
        if not fields:
            continue
        if not isinstance(data.get(table), dict):
            raise ValueError(f"{table}: not a table of the scan configuration")
        unknown = set(fields) - set(data[table])
        if unknown:
            raise ValueError(f"{table}: unknown field(s) {sorted(unknown)}")
        data[table].update(fields)
    return config_from_dict(data, origin=origin)


def _within(path: Path, other: Path) -> bool:
    """``path`` is ``other`` or lies inside it (both resolved)."""
    return path == other or other in path.parents


def zarr_store_of(path: str | Path) -> Path | None:
    """The Zarr store (a folder holding ``zarr.json``) that ``path`` lies inside, or None."""
    p = Path(path).resolve()
    for folder in p.parents:
        if (folder / "zarr.json").is_file():
            return folder
    return None


def check_file_output(path: str | Path, what: str, *, stores: Sequence[str | Path] = (),
                      overwrite: bool | None = None) -> None:
    """A file output (``--rrd``, ``--x3p``, ``--ply``...) that would write into a Zarr store
    (an existing one, or one of ``stores`` about to be written) is refused; with
    ``overwrite=False`` an existing file too (a mistyped name would replace an input: an
    image, a calibration), named with the option that allows it."""
    p = Path(path).resolve()
    inside = zarr_store_of(p)
    if inside is None:
        inside = next((Path(s).resolve() for s in stores if _within(p, Path(s).resolve())),
                      None)
    if inside is not None:
        raise ConfigError(f"{what} {path}: inside the Zarr store {inside}; writing there "
                          "would damage it, choose a path outside")
    if p.is_dir():
        raise ConfigError(f"{what} {path}: is a folder, expected a file path")
    if overwrite is False and p.exists():
        raise ConfigError(f"{what} {path}: exists; --overwrite replaces it, or choose another "
                          "path")


def check_clashes(cfg: ScanConfig, *, inputs: Sequence[str | Path] = (),
                  record: str | Path | None = None, rrd: str | Path | None = None) -> None:
    """Outputs that would destroy inputs or each other are refused (:class:`ConfigError`)."""
    out = Path(cfg.output.path).resolve()
    for src in inputs:
        s = Path(src).resolve()
        if _within(out, s) or _within(s, out):
            how = "is" if out == s else ("lies inside" if _within(out, s) else "holds")
            raise ConfigError(f"output.path {cfg.output.path} {how} the input {src}; writing "
                              "the mosaic there would destroy it, choose another path")
    if record is not None:
        r = Path(record).resolve()
        if _within(r, out) or _within(out, r):
            raise ConfigError(f"--record {record}: overlaps output.path {cfg.output.path}")
        if zarr_store_of(r) is not None:
            raise ConfigError(f"--record {record}: inside the Zarr store {zarr_store_of(r)}")
    if rrd is not None:
        check_file_output(rrd, "--rrd", stores=[out, *inputs,
                                                *([record] if record is not None else [])])


# --- the run -----------------------------------------------------------------------------


@dataclass
class Job:
    """One run: a scan (frames from ``frames``, ``source`` or the configuration's source)
    or a replay of ``recording``; ``resume`` continues the mosaic at ``cfg.output.path``."""

    cfg: ScanConfig
    recording: Recording | None = None
    frames: Iterable[Frame] | None = None
    source: str | None = None
    record: str | Path | None = None
    rrd: str | Path | None = None
    resume: bool = False
    realtime: bool = False
    progress: bool = False
    check_only: bool = False
    #: the live view and other side branches, made once every check has passed
    sinks: Callable[[], list[Sink]] | Sequence[Sink] = ()
    account: FrameAccount | None = None


@dataclass
class Run:
    report: ScanReport
    world: Any | None
    account: FrameAccount | None
    resumed: tuple[int, int] | None = None  # (writes kept, torn regions rebuilt)
    sinks: list[Sink] = field(default_factory=list)
    annotate_error: str = ""


def _with_run_only(new: dict[str, Any], old: dict[str, Any]) -> dict[str, Any]:
    """``new`` with the :data:`RUN_ONLY` fields of ``old``: compared, they never differ."""
    out = {k: dict(v) if isinstance(v, dict) else v for k, v in new.items()}
    for table, name in RUN_ONLY:
        if isinstance(out.get(table), dict) and isinstance(old.get(table), dict) \
                and name in old[table]:
            out[table][name] = old[table][name]
    return out


def _reopen(cfg: ScanConfig, identity: dict[str, Any] | None) -> Any:
    from sffscan.pipeline.mosaic.writer import MosaicWriter

    path = Path(cfg.output.path)
    try:
        attrs = dict(zarr.open_group(str(path), mode="r", use_consolidated=False).attrs.asdict())
    except Exception as err:  # noqa: BLE001 - reopen names it below
        attrs = {}
        log.debug("%s: attributes unreadable (%s)", path, err)
    if identity is not None:
        why = identity_mismatch(stored_identity(attrs), identity)
        if why:
            raise ResumeRefused(f"{path}: cannot resume from the recording {identity['path']}: "
                                f"{why}")
    new = cfg.model_dump(mode="json")
    old = attrs.get("scan_config")
    compare = _with_run_only(new, old) if isinstance(old, dict) else new
    try:
        return MosaicWriter.reopen(path, scan_config=compare)
    except Exception as err:  # noqa: BLE001 - a corrupt zarr.json or chunk of the mosaic
        if type(err) is ValueError:  # the writer's own refusal, which names the mosaic
            where = "" if str(path) in str(err) else f"{path}: "
            raise ResumeRefused(f"{where}{err}") from None
        raise ResumeRefused(f"{path}: cannot resume ({type(err).__name__}: {err})") from err


def _mark_failed(writer: Any) -> None:
    """A mosaic interrupted before its pipeline ran (which marks it itself) is ``failed``."""
    if writer is None:
        return
    with contextlib.suppress(Exception):  # the interruption is what is reported
        # the group read afresh (the stages may have run elsewhere: a worker process); the
        # status alone changes, the journal stays as written for a resume
        group = zarr.open_group(str(writer.path), mode="r+", use_consolidated=False)
        if group.attrs.get("status") == "writing":
            group.update_attributes({"status": "failed"})


def _annotate(path: Path, rec: Recording, identity: dict[str, Any]) -> None:
    """Record in the mosaic which recording it was replayed from (its report and identity)."""
    from sffscan.pipeline.mosaic.attrs import MosaicAttrs

    group = zarr.open_group(str(path), mode="r+", use_consolidated=False)
    attrs = MosaicAttrs.model_validate({**group.attrs.asdict(), "recording": {
        **rec.report.as_dict(), "identity": identity}})
    group.update_attributes(attrs.model_dump(mode="json"))


@contextlib.contextmanager
def sigterm_interrupts() -> Iterator[None]:
    """While inside: SIGTERM raises :class:`Terminated` in the main thread (the pipeline
    stops as for Ctrl-C: the mosaic is marked ``failed`` and stays resumable). Only where
    SIGTERM has its default action and in the main thread; restored on leaving."""
    if threading.current_thread() is not threading.main_thread() \
            or signal.getsignal(signal.SIGTERM) is not signal.SIG_DFL:
        yield
        return

    def handler(signum: int, frame: Any) -> None:
        raise Terminated()

    signal.signal(signal.SIGTERM, handler)
    try:
        yield
    finally:
        signal.signal(signal.SIGTERM, signal.SIG_DFL)


def check_input_free(recording: str | Path) -> None:
    """A recording whose writer still holds its lock is refused (:class:`InputBusy`)."""
    holder = locks.holder(recording)
    if holder is not None:
        raise InputBusy(f"recording {recording}: still being written by "
                        f"{locks.describe_holder(holder)}; replay it when it is complete")


def execute(job: Job) -> Run | None:
    """Run ``job`` with every guarantee of this module (see the module notes).

    Returns None for ``check_only`` (every check passed, nothing created), else a
    :class:`Run`. Raises :class:`ConfigError` (its subclasses :class:`ResumeRefused`,
    :class:`InputBusy`, :class:`~sffscan.pipeline.locks.LockHeld`) before anything is
    changed, :class:`~sffscan.pipeline.runtime.StageFailed` or ``KeyboardInterrupt``
    (:class:`Terminated`) after.
    """
    from sffscan.pipeline.preflight import preflight

    cfg, rec = job.cfg, job.recording
    live = rec is None and job.frames is None
    preflight(cfg, record=job.record, resume=job.resume, source=job.source, live=live,
              simulated=live and job.source is None and cfg.source.kind == "sim")
    from sffscan.stages.fitted_constants import uncalibrated_focus_measure

    why = uncalibrated_focus_measure(cfg.processing.focus_operator, cfg.processing.window)
    if why is not None and not job.check_only:
        log.warning("%s", why)
    check_clashes(cfg, inputs=[rec.path] if rec is not None else [], record=job.record,
                  rrd=job.rrd)
    if rec is not None:
        check_input_free(rec.path)
    with contextlib.ExitStack() as held:
        held.enter_context(locks.acquire(cfg.output.path, what="mosaic"))
        if job.record is not None:
            held.enter_context(locks.acquire(job.record, what="recording"))
        if job.check_only:
            return None
        identity: dict[str, Any] | None = None
        if rec is not None:
            identity = recording_identity(rec.path)
        elif job.record is not None:
            identity = {"path": str(Path(job.record).resolve()), "live": True}
        return _run(job, identity)
    raise AssertionError("unreachable")  # pragma: no cover - the with block returns


def _run(job: Job, identity: dict[str, Any] | None) -> Run:
    from sffscan.pipeline.wiring import open_writer, run_scan

    cfg, rec = job.cfg, job.recording
    writer = None
    resumed = None
    if job.resume:
        writer = _reopen(cfg, identity if rec is not None else None)
        resumed = (writer.done, len(writer.rebuild))
        log.info("resuming %s: %d writes done, %d torn region(s) to rebuild", writer.path,
                 writer.done, len(writer.rebuild))
    world = None
    account = job.account
    if rec is not None:
        frames: Iterator[Frame] = rec.frames(realtime=job.realtime)
        account = rec.account()
    elif job.frames is not None:
        frames = iter(job.frames)
    else:
        from sffscan.pipeline.sources import open_feed

        feed = open_feed(cfg, source=job.source)
        frames, world, account = feed.frames, feed.world, feed.account
    sinks = list(job.sinks() if callable(job.sinks) else job.sinks)
    if job.record is not None:
        from sffscan.pipeline.formats.recorder_sink import recorder_sink

        sinks.append(recorder_sink(cfg, str(job.record), account=account))
    out = Run(report=None, world=world, account=account, resumed=resumed,  # type: ignore[arg-type]
              sinks=sinks)
    try:
        with sigterm_interrupts():
            if writer is None:
                writer = open_writer(cfg)
                if identity is not None:  # before any frame: an interrupted mosaic says it too
                    writer.update_attributes({"recording": {"path": identity["path"],
                                                            "identity": identity}})
            out.report = run_scan(cfg, frames=frames, progress=job.progress, sinks=sinks,
                                  writer=writer, account=account)
    except KeyboardInterrupt:  # Ctrl-C or SIGTERM, maybe before the pipeline's own handling
        _mark_failed(writer)
        raise
    finally:
        if rec is not None and identity is not None:
            try:
                _annotate(Path(cfg.output.path), rec, identity)
            except OSError as err:  # a full disk: the pipeline's failure, not the input's
                out.annotate_error = (f"{cfg.output.path}: cannot record which recording it "
                                      f"was replayed from: {err}")
                log.error("%s", out.annotate_error)
    return out
