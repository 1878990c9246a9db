"""The job store: one folder per print job, restart-safe.

Layout::

    JOB/
      manifest.json            JobManifest (printer, hashes, layer z, configuration, ...)
      job.gcode                a copy of the print's G-code (hash in the manifest)
      models/NAME              copies of the models (STL/3MF), if any
      layers/0007/
        mosaic.zarr            the layer's height mosaic (OME-Zarr, as 'sffscan scan')
        recording.zarr         the raw recording of the layer's scan (for 'sffscan replay')
        deviation.zarr         measured - expected, µm (Zarr v3 array, float32; attributes
                               origin_um, pixel_um)
        verdict.json           LayerVerdict; written last: its presence marks the layer done

Every JSON file is written to a temporary name and renamed (atomic on POSIX), the
deviation array into a temporary folder that is renamed, so a crash leaves either the old
state or the new one. A layer without ``verdict.json`` is not done: :meth:`JobStore.begin_layer`
clears and redoes it. Layer events must come in increasing layer order; a layer already
done, or one below the last begun, is refused with :class:`LayerOrderError` (nothing is
changed). Layers may be skipped (scanning every n-th layer).
"""

from __future__ import annotations

import datetime as _dt
import hashlib
import json
import os
import shutil
import uuid
from pathlib import Path
from typing import Any

import numpy as np
from pydantic import BaseModel, ConfigDict, Field, ValidationError
from sffscan.pipeline.printjob.deviation import LayerVerdict, Tolerances
from sffscan.pipeline.printjob.expected import Grid, PrinterMapping
from sffscan.pipeline.printjob.gcode import GcodeProgram, read_gcode

__all__ = ["JobError", "JobManifest", "JobStore", "LayerOrderError", "sha256_file"]

MANIFEST = "manifest.json"
Z_MATCH_MM = 0.0015  # a layer event's z must match the G-code's within this, mm


class JobError(ValueError):
    """A job folder that cannot be used; the message names the file and the field."""


class LayerOrderError(JobError):
    """A layer event out of order, repeated, or at a z the G-code does not have."""


class JobManifest(BaseModel):
    """What a job is: stored as ``manifest.json``."""

    model_config = ConfigDict(extra="forbid", allow_inf_nan=False)
    version: int = Field(1, description="Job store format version")
    job_id: str = Field(description="Random identifier of the job")
    created_utc: str = Field(description="Creation time, ISO 8601 UTC")
    printer: str = Field("", description="Printer name or link ('octoprint', 'moonraker', "
                         "'sim', ...)")
    gcode_file: str = Field("job.gcode", description="The G-code's copy inside the job")
    gcode_sha256: str
    models: dict[str, str] = Field(default_factory=dict,
                                   description="Model copy (under models/) -> sha256")
    objects: list[str] = Field(default_factory=list, description="Object names of the G-code")
    layer_z_mm: list[float] = Field(description="Layer heights of the G-code, mm")
    config: dict[str, Any] = Field(default_factory=dict,
                                   description="The scan configuration (ScanConfig as JSON)")
    calibration: dict[str, Any] | None = Field(None, description="The calibration used")
    mapping: PrinterMapping = Field(default_factory=PrinterMapping,
                                    description="Printer mm -> mosaic µm")
    roi_um: tuple[float, float, float, float] | None = Field(
        None, description="Region compared (x0, y0, x1, y1), mosaic µm; default the "
        "extrusion's extent plus 2 mm")
    tolerances: Tolerances = Field(default_factory=Tolerances)


def sha256_file(path: str | Path) -> str:
    """Hex SHA-256 of a file's bytes."""
    h = hashlib.sha256()
    with open(path, "rb") as f:
        for chunk in iter(lambda: f.read(1 << 20), b""):
            h.update(chunk)
    return h.hexdigest()


def _write_json_atomic(path: Path, text: str) -> None:
    tmp = path.with_name(f".{path.name}.{uuid.uuid4().hex}.tmp")
    with open(tmp, "w", encoding="utf-8") as f:
        f.write(text)
        f.flush()
        os.fsync(f.fileno())
    os.replace(tmp, path)


class JobStore:
    """A print job's folder (create with :meth:`create`, reopen with :meth:`open`)."""

    def __init__(self, path: Path, manifest: JobManifest) -> None:
        self.path = path
        self.manifest = manifest
        self._program: GcodeProgram | None = None

    # ------------------------------------------------------------------ creation
    @classmethod
    def create(cls, path: str | Path, *, gcode: str | Path, models: tuple[str | Path, ...] = (),
               printer: str = "", config: Any | None = None,
               calibration: dict[str, Any] | None = None,
               mapping: PrinterMapping | None = None, tolerances: Tolerances | None = None,
               roi_um: tuple[float, float, float, float] | None = None) -> JobStore:
        """Create a job folder for a G-code file (parsed first: a bad file creates nothing).

        Parameters
        ----------
        path : path-like
            The job folder; must not exist or be empty.
        gcode : path-like, keyword-only
            The print's G-code (copied into the job).
        models : sequence of path-like, keyword-only
            STL/3MF models (copied, hashed).
        printer : str, keyword-only
            Printer name or link.
        config : ScanConfig or dict, keyword-only
            The scan configuration (stored as JSON).
        calibration : dict, keyword-only
            The calibration (stored as given).
        mapping : PrinterMapping, keyword-only
            Printer -> mosaic coordinates.
        tolerances : Tolerances, keyword-only
            Verdict tolerances.
        roi_um : (x0, y0, x1, y1), keyword-only
            Region compared, mosaic µm.

        Raises
        ------
        GcodeError
            The G-code does not parse (its line is named).
        JobError
            The folder exists and is not empty, or a model is missing.
        """
        p = Path(path)
        if p.exists() and any(p.iterdir()):
            raise JobError(f"{p}: the job folder exists and is not empty (open it with "
                           "JobStore.open to resume)")
        program = read_gcode(gcode)
        for mdl in models:
            if not Path(mdl).is_file():
                raise JobError(f"{mdl}: model file not found")
        if config is not None and hasattr(config, "model_dump"):
            config = config.model_dump(mode="json")
        p.mkdir(parents=True, exist_ok=True)
        (p / "layers").mkdir(exist_ok=True)
        shutil.copyfile(gcode, p / "job.gcode")
        hashes = {}
        if models:
            (p / "models").mkdir(exist_ok=True)
            for mdl in models:
                dst = p / "models" / Path(mdl).name
                shutil.copyfile(mdl, dst)
                hashes[dst.name] = sha256_file(dst)
        man = JobManifest(
            job_id=uuid.uuid4().hex,
            created_utc=_dt.datetime.now(_dt.UTC).isoformat(timespec="seconds"),
            printer=printer, gcode_sha256=sha256_file(p / "job.gcode"), models=hashes,
            objects=list(program.objects), layer_z_mm=[float(z) for z in program.layer_z_mm],
            config=dict(config or {}), calibration=calibration,
            mapping=mapping or PrinterMapping(), tolerances=tolerances or Tolerances(),
            roi_um=roi_um)
        _write_json_atomic(p / MANIFEST, man.model_dump_json(indent=2))
        store = cls(p, man)
        store._program = program
        return store

    @classmethod
    def open(cls, path: str | Path) -> JobStore:
        """Open an existing job folder (to resume or read it).

        Raises
        ------
        JobError
            No manifest, an invalid one (the field is named), or a G-code copy whose hash
            differs from the manifest's.
        """
        p = Path(path)
        f = p / MANIFEST
        try:
            man = JobManifest.model_validate_json(f.read_text(encoding="utf-8"))
        except FileNotFoundError:
            raise JobError(f"{p}: not a job folder (no {MANIFEST})") from None
        except ValidationError as err:
            e = err.errors()[0]
            loc = ".".join(str(x) for x in e["loc"])
            raise JobError(f"{f}: {loc}: {e['msg']}") from None
        store = cls(p, man)
        digest = sha256_file(p / man.gcode_file)
        if digest != man.gcode_sha256:
            raise JobError(f"{p / man.gcode_file}: sha256 {digest[:12]}... differs from the "
                           f"manifest's gcode_sha256 {man.gcode_sha256[:12]}...")
        return store

    def update_manifest(self, **fields: Any) -> JobManifest:
        """Change manifest fields (e.g. a fitted ``mapping``), written atomically."""
        man = JobManifest.model_validate({**self.manifest.model_dump(), **fields})
        _write_json_atomic(self.path / MANIFEST, man.model_dump_json(indent=2))
        self.manifest = man
        return man

    # ------------------------------------------------------------------ reading
    @property
    def program(self) -> GcodeProgram:
        """The job's parsed G-code (cached)."""
        if self._program is None:
            self._program = read_gcode(self.path / self.manifest.gcode_file)
        return self._program

    def layer_dir(self, layer: int) -> Path:
        return self.path / "layers" / f"{layer:04d}"

    def mosaic_path(self, layer: int) -> Path:
        return self.layer_dir(layer) / "mosaic.zarr"

    def recording_path(self, layer: int) -> Path:
        return self.layer_dir(layer) / "recording.zarr"

    def deviation_path(self, layer: int) -> Path:
        return self.layer_dir(layer) / "deviation.zarr"

    def verdict_path(self, layer: int) -> Path:
        return self.layer_dir(layer) / "verdict.json"

    def done_layers(self) -> list[int]:
        """Layers whose verdict is written, increasing."""
        root = self.path / "layers"
        if not root.is_dir():
            return []
        return sorted(int(d.name) for d in root.iterdir()
                      if d.name.isdigit() and (d / "verdict.json").is_file())

    def begun_layers(self) -> list[int]:
        """Layers with a folder (done or not), increasing."""
        root = self.path / "layers"
        return sorted(int(d.name) for d in root.iterdir() if d.name.isdigit())

    def read_verdict(self, layer: int) -> LayerVerdict:
        f = self.verdict_path(layer)
        try:
            return LayerVerdict.model_validate_json(f.read_text(encoding="utf-8"))
        except FileNotFoundError:
            raise JobError(f"{f}: layer {layer} is not done (no verdict)") from None

    # ------------------------------------------------------------------ writing
    def check_layer_event(self, layer: int, z_mm: float | None = None) -> None:
        """Raise :class:`LayerOrderError` unless ``layer`` may be begun now."""
        zs = self.manifest.layer_z_mm
        if not 0 <= layer < len(zs):
            raise LayerOrderError(f"layer event {layer}: the G-code has layers 0..{len(zs) - 1}")
        if z_mm is not None and abs(z_mm - zs[layer]) > Z_MATCH_MM:
            raise LayerOrderError(f"layer event {layer} at z = {z_mm:g} mm: the G-code's "
                                  f"layer {layer} is at z = {zs[layer]:g} mm")
        done = self.done_layers()
        if layer in done:
            raise LayerOrderError(f"layer event {layer}: repeated (layer {layer} is already "
                                  f"done; its verdict is {self.verdict_path(layer)})")
        begun = self.begun_layers()
        if begun and layer < max(begun):
            raise LayerOrderError(f"layer event {layer}: out of order (layer {max(begun)} "
                                  "was already begun; layers must increase)")

    def begin_layer(self, layer: int, z_mm: float | None = None) -> Path:
        """Start (or restart, after a crash) a layer: checks the order, clears a partial
        folder, returns the layer's folder."""
        self.check_layer_event(layer, z_mm)
        d = self.layer_dir(layer)
        if d.exists():  # begun before a crash, not done: redo it
            shutil.rmtree(d)
        d.mkdir(parents=True)
        return d

    def write_deviation(self, layer: int, deviation_um: np.ndarray, grid: Grid) -> Path:
        """Store a layer's deviation map (Zarr v3 array, atomically renamed into place)."""
        import zarr

        final = self.deviation_path(layer)
        tmp = final.with_name(f".deviation.{uuid.uuid4().hex}.tmp.zarr")
        dev = np.asarray(deviation_um, dtype=np.float32)
        arr = zarr.create_array(str(tmp), shape=dev.shape, dtype="float32",
                                chunks=(min(512, dev.shape[0]), min(512, dev.shape[1])),
                                fill_value=float("nan"),
                                attributes={"origin_um": list(grid.origin_um),
                                            "pixel_um": grid.pixel_um, "units": "µm",
                                            "what": "measured - expected height"})
        arr[...] = dev
        if final.exists():
            shutil.rmtree(final)
        os.replace(tmp, final)
        return final

    def finish_layer(self, layer: int, verdict: LayerVerdict) -> Path:
        """Write the layer's verdict (atomically): the layer is done."""
        if verdict.layer != layer:
            raise JobError(f"verdict of layer {verdict.layer} given for layer {layer}")
        d = self.layer_dir(layer)
        if not d.is_dir():
            raise LayerOrderError(f"layer {layer} was not begun (begin_layer first)")
        f = self.verdict_path(layer)
        _write_json_atomic(f, verdict.model_dump_json(indent=2))
        return f

    def summary(self) -> list[dict[str, Any]]:
        """One row per done layer: layer, z, verdict, objects' verdicts."""
        rows = []
        for k in self.done_layers():
            v = self.read_verdict(k)
            rows.append({"layer": k, "z_mm": v.z_mm, "verdict": v.verdict,
                         "objects": {o.name: o.verdict for o in v.objects},
                         "reason": v.reason})
        return rows


def manifest_json(path: str | Path) -> dict[str, Any]:
    """The raw manifest of a job folder (for tools that do not need the models)."""
    return json.loads((Path(path) / MANIFEST).read_text(encoding="utf-8"))
