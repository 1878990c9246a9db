"""The job service's messages and its state file (pydantic models, the single source of
truth of the HTTP bodies), the :class:`LayerHandler` protocol, and the state file's atomic
write and read."""

from __future__ import annotations

import os
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Literal, Protocol

from pydantic import BaseModel, ConfigDict, Field, model_validator

Verdict = Literal["pass", "warn", "fail", "unknown", "pending"]
ScanState = Literal["running", "done", "failed", "timeout", "skipped"]
STATE_FILE = "service_state.json"


class _Model(BaseModel):
    model_config = ConfigDict(extra="forbid", allow_inf_nan=False)


class ObjectOutline(_Model):
    """One object of the print in this layer, as the printer knows it."""

    name: str = Field(min_length=1, max_length=200, description="Object name (slicer's label)")
    polygon_mm: list[tuple[float, float]] = Field(
        min_length=3, max_length=10000, description="Outline in printer coordinates (x, y), mm")


class JobStart(_Model):
    """``POST /jobs``: a print starts (or resumes after a restart of the service)."""

    job_id: str = Field(pattern=r"^[A-Za-z0-9][A-Za-z0-9._-]{0,99}$",
                        description="Job name, also its folder in the store")
    printer: str = Field("", max_length=200, description="Printer name, for the record")
    gcode_name: str = Field("", max_length=500, description="G-code file name, for the record")
    strict: bool | None = Field(None, description="Wait for each verdict before releasing the "
                                                  "print (null: the service's default)")


class LayerEvent(_Model):
    """``POST /jobs/{job_id}/layers``: layer ``layer`` is printed at height ``z_mm``."""

    layer: int = Field(ge=0, le=1_000_000, description="Layer number, from 0")
    z_mm: float = Field(ge=-1000, le=10000, description="Nozzle height of the layer, mm")
    region_mm: tuple[float, float, float, float] | None = Field(
        None, description="Region to scan (x0, y0, x1, y1) in printer coordinates, mm; null: "
                          "the handler's configured region")
    objects: list[ObjectOutline] = Field(default_factory=list, max_length=1000,
                                         description="Objects printed in this layer")

    @model_validator(mode="after")
    def _region_order(self) -> LayerEvent:
        r = self.region_mm
        if r is not None and not (r[2] > r[0] and r[3] > r[1]):
            raise ValueError(f"region_mm: need x1 > x0 and y1 > y0, got {r}")
        return self


class JobEnd(_Model):
    """``POST /jobs/{job_id}/end``."""

    outcome: Literal["completed", "cancelled", "failed", "disconnected"] = "completed"
    reason: str = Field("", max_length=2000)


class LayerRecord(_Model):
    """What the service knows of one layer."""

    layer: int
    z_mm: float
    scan: ScanState
    verdict: Verdict
    reason: str = ""
    late: bool = Field(False, description="The verdict arrived after the hold was released "
                                          "with 'unknown' (strict timeout)")
    objects: dict[str, Verdict] = Field(default_factory=dict, description="Verdict per object")
    scan_s: float | None = Field(None, description="Duration of the scan, s")
    analysis_s: float | None = Field(None, description="Duration of the analysis, s")
    output: str | None = Field(None, description="The scan's output, relative to the job folder")


class JobState(_Model):
    """``service_state.json``: the job's record, rewritten after every change."""

    version: Literal[1] = 1
    job: JobStart
    status: Literal["open", "ended"] = "open"
    end: JobEnd | None = None
    layers: dict[int, LayerRecord] = Field(default_factory=dict)


class LayerReply(_Model):
    """The answer to a layer event."""

    job_id: str
    record: LayerRecord
    repeated: bool = Field(False, description="The layer was already done; nothing was scanned")
    alerts: list[LayerRecord] = Field(
        default_factory=list, description="Every layer of the job whose verdict is warn or fail")


class JobStatus(_Model):
    job_id: str
    status: Literal["open", "ended"]
    resumed: bool = False
    strict: bool
    layers_done: list[int] = Field(default_factory=list)
    pending: list[int] = Field(default_factory=list, description="Layers awaiting a verdict")
    counts: dict[str, int] = Field(default_factory=dict, description="Layers per verdict")


class Analysis(_Model):
    """A handler's verdict on one layer."""

    verdict: Literal["pass", "warn", "fail", "unknown"]
    reason: str = ""
    objects: dict[str, Literal["pass", "warn", "fail", "unknown"]] = Field(default_factory=dict)


@dataclass
class ScanResult:
    """A handler's scan of one layer: its output (inside the job folder) and free notes."""

    output: Path | None = None
    info: dict[str, Any] = field(default_factory=dict)


class LayerHandler(Protocol):
    """Scan and analyse one layer. ``scan`` runs while the print is held; ``analyse`` runs
    in the background and may read what ``scan`` wrote into ``folder``. Both may raise: the
    layer is then recorded ``unknown`` with the error as the reason."""

    def scan(self, job: JobStart, event: LayerEvent, folder: Path) -> ScanResult: ...

    def analyse(self, job: JobStart, event: LayerEvent, scan: ScanResult,
                folder: Path) -> Analysis: ...


class ServiceError(Exception):
    """A request the service refuses: ``status`` is the HTTP status, the message says why."""

    def __init__(self, status: int, message: str) -> None:
        super().__init__(message)
        self.status = status


def write_state(path: Path, state: JobState) -> None:
    """Write atomically: a reader (or a restart) sees the old or the new file, never half."""
    tmp = path.with_name(path.name + ".tmp")
    tmp.write_text(state.model_dump_json(indent=1), encoding="utf-8")
    os.replace(tmp, path)


def read_state(path: Path) -> JobState:
    try:
        return JobState.model_validate_json(path.read_bytes())
    except ValueError as err:
        raise ServiceError(500, f"{path}: unreadable job state ({err})") from None
