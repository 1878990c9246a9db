"""The recordings of a batch and what a batch does with each: the recordings named by
paths, patterns or folders (:func:`find_recordings`), each one's mosaic
(:func:`mosaic_path`), the results row (:class:`BatchRow`) and its statuses, and which
mosaics a rerun keeps and which it processes (:func:`plan_targets`).

Running the batch on a Dask cluster and its results table are in
:mod:`sffscan.pipeline.batch`.
"""

from __future__ import annotations

import glob
import logging
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import zarr
from sffscan.pipeline import locks
from sffscan.pipeline.cover import plan_cover
from sffscan.pipeline.metrology.evaluate import stored_accuracy

log = logging.getLogger(__name__)

__all__ = ["BatchError", "BatchRow", "find_recordings", "mosaic_path", "plan_targets"]

#: statuses of a row: done now, resumed now (and complete), skipped (complete already),
#: failed, or incomplete (done now, or kept: frames lost in the recording)
#: or not started: the recording is still being written (a rerun does it)
STATUSES = ("complete", "resumed", "skipped", "failed", "incomplete", "recording")
#: mosaic statuses a rerun continues (an interrupted run) and keeps (final)
RESUMABLE = ("writing", "failed")
FINAL = ("complete", "incomplete")


class BatchError(ValueError):
    """Bad batch input (nothing found, two recordings mapping to one mosaic)."""


@dataclass
class BatchRow:
    """One recording's result (a row of the results table)."""

    recording: str
    mosaic: str
    status: str
    frames: int | None = None
    frames_lost: int | None = None
    valid_pixels: int | None = None
    rmse_um: float | None = None
    #: share of the scored pixels within 2 sigma of the truth (the uncertainty's calibration)
    within_2sigma: float | None = None
    #: valid pixels / pixels the scan's plan measures (:func:`plan_cover`)
    coverage: float | None = None
    wall_s: float | None = None
    worker: str = ""
    error: str = ""
    note: str = ""


def _is_recording(path: Path) -> bool:
    if not (path / "zarr.json").is_file():
        return False
    try:
        return zarr.open_group(str(path), mode="r").attrs.get("format") == "sffscan-recording"
    except Exception:  # noqa: BLE001 - unreadable: decided by the name below
        return False


def find_recordings(inputs: Sequence[str | Path]) -> list[Path]:
    """Recordings named by ``inputs``: recording paths, glob patterns, or folders (their
    children that are recordings or end in ``.zarr``), in order, each once.

    A path named explicitly (or matched by a pattern) is taken even if it does not read as
    a recording: it is then reported as a failed row, not left out silently.
    """
    out: list[Path] = []
    for item in inputs:
        text = str(item)
        if any(c in text for c in "*?["):
            matches = sorted(Path(m) for m in glob.glob(text))
            if not matches:
                raise BatchError(f"{text}: the pattern matches nothing")
            out += matches
            continue
        p = Path(text)
        if not p.exists():
            raise BatchError(f"{p}: no such recording or folder")
        if p.is_dir() and not (p / "zarr.json").exists():  # a folder of layers
            layers = sorted(c for c in p.iterdir()
                            if c.is_dir() and (c.suffix == ".zarr" or _is_recording(c))
                            and _mosaic_status(c) is None)  # a batch's own outputs
            if not layers:
                raise BatchError(f"{p}: a folder without recordings")
            out += layers
        else:
            out.append(p)
    seen: set[Path] = set()
    unique = []
    for p in out:
        if p.resolve() not in seen:
            seen.add(p.resolve())
            unique.append(p)
    return unique


def mosaic_path(recording: Path, out_dir: Path) -> Path:
    """``OUT/<name>.mosaic.zarr`` for a recording ``<name>.zarr`` (or ``<name>``)."""
    name = recording.name[:-5] if recording.name.endswith(".zarr") else recording.name
    return out_dir / f"{name}.mosaic.zarr"


def _mosaic_status(path: Path) -> dict[str, Any] | None:
    try:
        attrs = zarr.open_group(str(path), mode="r").attrs.asdict()
    except Exception:  # noqa: BLE001 - absent or not a group
        return None
    return attrs if attrs.get("format") == "sffscan-mosaic" else None


def _same_recording(recording: Path, attrs: dict[str, Any]) -> bool:
    """The final mosaic was made from the recording as it is now (a recording written on,
    or replaced, since is reprocessed; a mosaic that does not say is kept)."""
    from sffscan.pipeline.run import identity_mismatch, recording_identity, stored_identity

    why = identity_mismatch(stored_identity(attrs), recording_identity(recording),
                            unchanged=True)
    if why:
        log.info("%s: reprocessed: %s", recording, why)
    return why is None


def _kept(recording: Path, mosaic: Path, attrs: dict[str, Any]) -> BatchRow:
    """The row of a final mosaic left as it is: ``skipped`` (complete) or ``incomplete``."""
    rec = attrs.get("recording") or {}
    acc = stored_accuracy(attrs)
    row = BatchRow(recording=str(recording), mosaic=str(mosaic), status="skipped",
                   frames=rec.get("frames"), frames_lost=rec.get("frames_lost"),
                   valid_pixels=attrs.get("valid_pixels"),
                   rmse_um=acc.rmse_um if acc is not None else None,
                   within_2sigma=acc.within_2sigma if acc is not None else None,
                   coverage=plan_cover(mosaic))
    if attrs.get("status") == "incomplete":
        row.status = "incomplete"
        row.note = ("kept: frames lost in the recording, a replay ends incomplete again "
                    "(--rerun reprocesses it)")
    return row


def plan_targets(targets: Sequence[tuple[Path, Path]], *, rerun: bool = False
                 ) -> tuple[dict[int, BatchRow], list[int]]:
    """What a batch does with each (recording, mosaic): the rows decided now (a recording
    still being written; a final mosaic of the recording as it is now, kept unless
    ``rerun``) and the indexes left to process."""
    rows: dict[int, BatchRow] = {}
    todo: list[int] = []
    for i, (rec, mos) in enumerate(targets):
        attrs = _mosaic_status(mos)
        busy = locks.holder(rec)
        if busy is not None:
            rows[i] = BatchRow(recording=str(rec), mosaic=str(mos), status="recording",
                               note=f"still being written by {locks.describe_holder(busy)}; "
                                    "a rerun does it once it is complete")
        elif not rerun and attrs is not None and attrs.get("status") in FINAL \
                and _same_recording(rec, attrs):
            rows[i] = _kept(rec, mos, attrs)
        else:
            todo.append(i)
    return rows, todo
