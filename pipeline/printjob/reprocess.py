"""Redo a job's done layers: refit the printer mapping, reprocess from the raw recordings.

:func:`calibrate_mapping` fits the printer -> mosaic translation from a done layer's mosaic
(:func:`~sffscan.pipeline.printjob.deviation.fit_printer_mapping`, phase correlation
with the expected map of that layer under the manifest's mapping) and, with
``apply=True``, stores it in the manifest (atomic write): later layers, and a
:func:`reprocess_job`, use it.

:func:`reprocess_job` replays each layer's ``recording.zarr`` into a fresh mosaic through
:func:`sffscan.api.replay` (the run path's guards apply), compares it with the G-code
under the manifest's current mapping and tolerances, and only then replaces the layer's
mosaic, deviation and verdict (the verdict last). A layer whose replay fails, or whose new
mosaic is not ``complete``, keeps everything it had and is reported as failed.
"""

from __future__ import annotations

import logging
import os
import shutil
import time
import uuid
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from sffscan.pipeline.printjob.deviation import LayerVerdict, compare_layer, fit_printer_mapping
from sffscan.pipeline.printjob.expected import Grid, PrinterMapping
from sffscan.pipeline.printjob.jobstore import JobError, JobStore

__all__ = ["Calibration", "LayerRedo", "calibrate_mapping", "parse_layers", "reprocess_job"]

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class Calibration:
    """A fitted printer mapping: ``old`` (the manifest's), ``new``, the layer it came from,
    and whether it was stored."""

    layer: int
    old: PrinterMapping
    new: PrinterMapping
    applied: bool

    @property
    def change_um(self) -> tuple[float, float]:
        """New minus old offset (x, y), µm."""
        return (self.new.offset_um[0] - self.old.offset_um[0],
                self.new.offset_um[1] - self.old.offset_um[1])


@dataclass(frozen=True)
class LayerRedo:
    """One layer of :func:`reprocess_job`: ``status`` is ``done``, ``skipped`` (no
    recording) or ``failed`` (the old results kept; ``error`` says why)."""

    layer: int
    status: str
    old: str | None
    new: str | None = None
    error: str = ""
    seconds: float = 0.0


def parse_layers(text: str | None, n_layers: int) -> list[int] | None:
    """``"A-B"``, ``"A"`` or ``"A,B,C-D"`` (0-based, inclusive) -> sorted layers; None for
    all. Raises :class:`JobError` for a malformed range or one outside ``0..n_layers-1``."""
    if text is None:
        return None
    out: set[int] = set()
    for part in text.split(","):
        a, sep, b = part.strip().partition("-")
        try:
            lo = int(a)
            hi = int(b) if sep else lo
        except ValueError:
            raise JobError(f"--layers {text!r}: {part!r} is not N or A-B") from None
        if not 0 <= lo <= hi < n_layers:
            raise JobError(f"--layers {text!r}: {part!r} is outside the job's layers "
                           f"0..{n_layers - 1}")
        out.update(range(lo, hi + 1))
    return sorted(out)


def _mosaic_maps(store: JobStore, layer: int, path: Path | None = None
                 ) -> tuple[Any, Grid, np.ndarray, np.ndarray, np.ndarray | None]:
    """A layer's mosaic cut to the job's compared region: (dataset, grid, height µm,
    confidence, uncertainty µm or None)."""
    from sffscan.pipeline.printjob.layer import roi_grid

    from sffscan.api import open_mosaic

    p = path or store.mosaic_path(layer)
    try:
        ds = open_mosaic(p)
    except (ValueError, FileNotFoundError, OSError) as err:
        raise JobError(f"{store.path}: layer {layer}: no readable mosaic at {p}: {err}") from None
    grid, rows, cols = roi_grid(store, Grid.of_dataset(ds))
    sub = ds.isel(y=rows, x=cols)
    height = np.asarray(sub["height"].values, dtype=np.float32)
    conf = np.asarray(sub["confidence"].values, dtype=np.float32)
    unc = (np.asarray(sub["uncertainty"].values, dtype=np.float32)
           if "uncertainty" in sub else None)
    return ds, grid, height, conf, unc


def calibrate_mapping(job: str | Path | JobStore, *, layer: int | None = None,
                      apply: bool = False) -> Calibration:
    """Fit the printer -> mosaic mapping from a done layer's mosaic.

    Parameters
    ----------
    job : path-like or JobStore
        The job folder.
    layer : int, keyword-only
        The layer to fit on (0-based); default the first done layer with a mosaic.
    apply : bool, keyword-only
        Store the fitted mapping in the manifest (atomic write).

    Returns
    -------
    Calibration

    Raises
    ------
    JobError
        Not a job, the layer is not in the G-code, not done, has no mosaic, or the fit
        fails (no valid pixel, the mosaic does not overlap the job's region); the message
        names the job and the layer.
    """
    store = job if isinstance(job, JobStore) else JobStore.open(job)
    n = len(store.manifest.layer_z_mm)
    done = store.done_layers()
    if layer is None:
        with_mosaic = [k for k in done if store.mosaic_path(k).is_dir()]
        if not with_mosaic:
            raise JobError(f"{store.path}: no done layer has a mosaic to calibrate from")
        layer = with_mosaic[0]
    if not 0 <= layer < n:
        raise JobError(f"{store.path}: layer {layer}: the G-code has layers 0..{n - 1}")
    if layer not in done:
        raise JobError(f"{store.path}: layer {layer} is not done (no verdict)")
    if not store.mosaic_path(layer).is_dir():
        raise JobError(f"{store.path}: layer {layer} has no mosaic "
                       f"({store.mosaic_path(layer)})")
    old = store.manifest.mapping
    _, grid, height, conf, _ = _mosaic_maps(store, layer)
    try:
        new = fit_printer_mapping(height, store.program, grid, layer=layer, initial=old,
                                  confidence=conf)
    except ValueError as err:
        raise JobError(f"{store.path}: layer {layer}: the mapping fit failed: {err}") from None
    if not all(np.isfinite(new.offset_um)):
        raise JobError(f"{store.path}: layer {layer}: the mapping fit failed (offset "
                       f"{new.offset_um})")
    if apply:
        store.update_manifest(mapping=new)
    return Calibration(layer=layer, old=old, new=new, applied=apply)


def _replace_dir(new: Path, final: Path) -> None:
    """Put folder ``new`` at ``final``; the old one is moved aside first and removed only
    after the rename."""
    old = final.with_name(f".{final.name}.{uuid.uuid4().hex}.old")
    if final.exists():
        os.replace(final, old)
    os.replace(new, final)
    shutil.rmtree(old, ignore_errors=True)


def _redo_layer(store: JobStore, runner: Any, layer: int,
                processing: dict[str, Any] | None) -> LayerVerdict:
    """Replay, compare, then swap in; raises on any failure with the old results intact."""
    from sffscan.api import replay

    d = store.layer_dir(layer)
    tmp = d / f".mosaic.{uuid.uuid4().hex}.tmp.zarr"
    try:
        t0 = time.perf_counter()
        replay(store.recording_path(layer), output=tmp, processing=processing)
        ds, grid, height, conf, unc = _mosaic_maps(store, layer, tmp)
        status = ds.attrs.get("status")
        if status != "complete":
            raise JobError(f"the replayed mosaic is {status!r}, not 'complete'")
        man = store.manifest
        exp = runner.expected(layer, grid)
        dev, verdict = compare_layer(height, exp, grid=grid, objects=man.objects,
                                     layer=layer, z_mm=man.layer_z_mm[layer], confidence=conf,
                                     uncertainty_um=unc, tolerances=man.tolerances,
                                     mapping=man.mapping)
        verdict = verdict.model_copy(update={"compute_s": time.perf_counter() - t0})
        del ds
        _replace_dir(tmp, store.mosaic_path(layer))
    finally:
        if tmp.exists():
            shutil.rmtree(tmp, ignore_errors=True)
    store.write_deviation(layer, dev, grid)
    store.finish_layer(layer, verdict)  # last: the layer is done with its new verdict
    return verdict


def reprocess_job(job: str | Path | JobStore, *, layers: list[int] | None = None,
                  processing: dict[str, Any] | None = None,
                  on_layer: Any | None = None) -> list[LayerRedo]:
    """Reprocess a job's done layers from their raw recordings.

    Parameters
    ----------
    job : path-like or JobStore
        The job folder.
    layers : list of int, keyword-only
        Layers to redo (0-based); default every done layer. A layer not done is skipped.
    processing : dict, keyword-only
        ``[processing]`` fields to override in the replay (``{"depth_method": "gauss3"}``).
    on_layer : callable(LayerRedo), keyword-only
        Called after each layer.

    Returns
    -------
    list of LayerRedo
        One per layer asked for (or done), increasing.
    """
    from sffscan.pipeline.printjob.layer import LayerRunner

    store = job if isinstance(job, JobStore) else JobStore.open(job)
    done = store.done_layers()
    todo = done if layers is None else layers
    runner = LayerRunner(store, warm=False)
    out = []
    for k in todo:
        t0 = time.perf_counter()
        if k not in done:
            row = LayerRedo(k, "skipped", None, error="not done (no verdict)")
        else:
            old = store.read_verdict(k).verdict
            if not store.recording_path(k).is_dir():
                row = LayerRedo(k, "skipped", old, error="no recording.zarr")
            else:
                try:
                    v = _redo_layer(store, runner, k, processing)
                    row = LayerRedo(k, "done", old, v.verdict,
                                    seconds=time.perf_counter() - t0)
                except Exception as err:  # noqa: BLE001 - reported per layer, old results kept
                    log.warning("layer %d: reprocessing failed: %s", k, err)
                    row = LayerRedo(k, "failed", old, error=f"{type(err).__name__}: {err}",
                                    seconds=time.perf_counter() - t0)
        out.append(row)
        if on_layer is not None:
            on_layer(row)
    return out
