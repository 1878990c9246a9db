"""One layer of a job: scan it into the job store, compare it, write its verdict.

:class:`LayerRunner` is what a job service calls per layer event::

    store = JobStore.create("job1", gcode="part.gcode", config=cfg, mapping=mapping)
    runner = LayerRunner(store)
    for layer, z in events:                       # from the printer
        runner.begin(layer, z)                    # order checked, partial layer cleared
        runner.scan(layer, config=cfg)            # only this holds the printer
        verdict = runner.analyse(layer)           # deviation + verdict, written to the store

A scan that raises, or a mosaic whose status is not ``complete``, gives an ``unknown``
verdict (never ``pass``) that says why; :meth:`LayerRunner.fail` records a timeout the same
way. The expected map of layers ``<= k - 1`` is kept, so each layer rasterises only its own
moves.
"""

from __future__ import annotations

import logging
import time
from collections.abc import Iterable, Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np
from sffscan.pipeline.printjob.deviation import (
    LayerVerdict,
    compare_layer,
    failed_layer_verdict,
)
from sffscan.pipeline.printjob.expected import (
    ExpectedMap,
    Grid,
    PrinterMapping,
    rasterise_expected,
)
from sffscan.pipeline.printjob.jobstore import JobError, JobStore

if TYPE_CHECKING:
    import xarray
    from sffscan.pipeline.config import ScanConfig
    from sffscan.pipeline.wiring import ScanReport
    from sffscan.stages.messages import Frame
    from sffscan.stages.protocol import Sink

__all__ = ["LayerRunner", "mosaic_grid", "open_job", "roi_grid"]

log = logging.getLogger(__name__)
ROI_MARGIN_UM = 2000.0


def mosaic_grid(cfg: ScanConfig) -> Grid:
    """The grid of the mosaic a scan with ``cfg`` writes, as :meth:`Grid.of_dataset` reads
    it from :func:`sffscan.open_mosaic` (the same float operations: the pixel is the
    difference of the first two coordinates)."""
    from sffscan.pipeline.plan import scan_extent_px

    x0, y0, x1, y1 = scan_extent_px(cfg)
    p = cfg.optics.pixel_um
    x = x0 * p + 0.0 + p * np.arange(2)
    return Grid((float(x[0]), float(y0 * p + 0.0)),
                float(x[1] - x[0]) if x1 - x0 > 1 else p, (y1 - y0, x1 - x0))


def roi_grid(store: JobStore, mosaic_grid: Grid) -> tuple[Grid, slice, slice]:
    """The compared region of a mosaic: the manifest's ``roi_um``, else the extrusion's
    extent (mapped) plus 2 mm; returns its grid and the row and column slices of the
    mosaic."""
    man = store.manifest
    if man.roi_um is not None:
        x0, y0, x1, y1 = man.roi_um
    else:
        e = store.program.extent_mm()
        corners = man.mapping.apply(np.array([[e[0], e[1]], [e[2], e[1]], [e[0], e[3]],
                                              [e[2], e[3]]]))
        x0, y0 = corners.min(0) - ROI_MARGIN_UM
        x1, y1 = corners.max(0) + ROI_MARGIN_UM
    p = mosaic_grid.pixel_um
    ox, oy = mosaic_grid.origin_um
    ny, nx = mosaic_grid.shape
    j0, j1 = max(0, int(np.floor((x0 - ox) / p))), min(nx, int(np.ceil((x1 - ox) / p)) + 1)
    i0, i1 = max(0, int(np.floor((y0 - oy) / p))), min(ny, int(np.ceil((y1 - oy) / p)) + 1)
    if j0 >= j1 or i0 >= i1:
        raise JobError(f"the mosaic ({ox:.0f}, {oy:.0f}) µm + {nx} x {ny} px does not overlap "
                       f"the job's region ({x0:.0f}, {y0:.0f}) - ({x1:.0f}, {y1:.0f}) µm: "
                       "check the printer mapping and the scanned area")
    grid = Grid((ox + j0 * p, oy + i0 * p), p, (i1 - i0, j1 - j0))
    return grid, slice(i0, i1), slice(j0, j1)


class LayerRunner:
    """Scans and judges the layers of one job (see the module docstring).

    Parameters
    ----------
    store : JobStore
        The job.
    """

    def __init__(self, store: JobStore, *, warm: bool = True) -> None:
        self.store = store
        self._expected: ExpectedMap | None = None
        self._grid: Grid | None = None
        self._mapping: PrinterMapping | None = None
        if warm:  # the service pays the imports at start, not after a layer's scan
            import dask.array  # noqa: F401 - open_mosaic's arrays
            import scipy.ndimage  # noqa: F401
            import xarray  # noqa: F401
            import zarr  # noqa: F401
            from dask.base import get_scheduler

            import sffscan.api  # noqa: F401

            get_scheduler()  # dask's first compute looks for a distributed client (1 s)

    def prepare(self, layer: int, *, config: ScanConfig | None = None) -> bool:
        """Rasterise the expected map of ``layer`` ahead (call it at the layer event, while
        the layer is scanned): the G-code says what it should be before it is measured.
        Uses the compared grid of the last done layer's mosaic (same configuration, same
        grid); before the first one, the grid the scan's configuration (``config``,
        default the manifest's) gives its mosaic (:func:`mosaic_grid`). Returns False when
        neither is known."""
        from sffscan.api import open_mosaic

        for k in reversed(self.store.done_layers()):
            try:
                ds = open_mosaic(self.store.mosaic_path(k))
            except (ValueError, FileNotFoundError, OSError):
                continue
            grid, _, _ = roi_grid(self.store, Grid.of_dataset(ds))
            self.expected(layer, grid)
            return True
        from sffscan.pipeline.config import ScanConfig

        try:
            cfg = config if config is not None else ScanConfig.model_validate(
                self.store.manifest.config)
            grid, _, _ = roi_grid(self.store, mosaic_grid(cfg))
        except (ValueError, JobError):  # no configuration, or it scans elsewhere
            return False
        self.expected(layer, grid)
        return True

    def begin(self, layer: int, z_mm: float | None = None) -> Path:
        """Check the layer event and prepare the layer's folder (:meth:`JobStore.begin_layer`)."""
        return self.store.begin_layer(layer, z_mm)

    def scan(self, layer: int, *, config: ScanConfig | None = None,
             frames: Iterable[Frame] | None = None, world: Any | None = None,
             record: bool = True, evaluate: bool = False,
             sinks: Sequence[Sink] = ()) -> ScanReport:
        """Scan the layer into the store (mosaic, and the raw recording when ``record``).

        Parameters
        ----------
        layer : int
            A begun layer.
        config : ScanConfig, keyword-only
            The scan; default the manifest's configuration.
        frames : iterable of Frame, keyword-only
            The frames (a camera, a replay); default the configuration's source, or the
            simulator over ``world``.
        world : PrintWorld or PlateWorld, keyword-only
            Simulated world to scan (``source.kind = "sim"``), e.g. a
            :class:`~sffscan.stages.sim.print_world.PrintWorld` at this layer.
        record : bool, keyword-only
            Record the raw frames to the layer's ``recording.zarr``.
        evaluate : bool, keyword-only
            Score the mosaic against ``world``'s truth (``report.accuracy``).
        sinks : sequence of Sink, keyword-only
            Side branches of the scan (a live view:
            :meth:`~.live_view.JobLiveView.scan_sink`).
        """
        from sffscan.pipeline.config import ScanConfig

        from sffscan.api import scan

        if not self.store.layer_dir(layer).is_dir():
            raise JobError(f"layer {layer} was not begun (LayerRunner.begin first)")
        cfg = config if config is not None else ScanConfig.model_validate(
            self.store.manifest.config)
        if frames is None and world is not None:
            from sffscan.pipeline.sim_source import simulate_frames

            frames = simulate_frames(cfg, world=world)
        report = scan(cfg, output=self.store.mosaic_path(layer), overwrite=True, frames=frames,
                      record=self.store.recording_path(layer) if record else None,
                      sinks=sinks)
        if evaluate and world is not None:
            from sffscan.pipeline.wiring import evaluate_sim

            evaluate_sim(report, world)
        return report

    def expected(self, layer: int, grid: Grid) -> ExpectedMap:
        """Expected map of layers ``<= layer`` on ``grid`` (incremental when possible)."""
        prog, mapping = self.store.program, self.store.manifest.mapping
        base = self._expected
        if (base is None or self._grid != grid or self._mapping != mapping
                or base.upto_layer > layer):
            base = None
        elif base.upto_layer == layer:
            return base
        exp = rasterise_expected(prog, grid, upto_layer=layer, mapping=mapping, base=base)
        self._expected, self._grid, self._mapping = exp, grid, mapping
        return exp

    def analyse(self, layer: int) -> LayerVerdict:
        """Compare the layer's mosaic with the G-code; write the deviation and the verdict.

        Returns
        -------
        LayerVerdict
            ``unknown`` (with the reason) when the mosaic is missing, unreadable or not
            ``complete``.
        """
        from sffscan.api import open_mosaic

        t0 = time.perf_counter()
        man = self.store.manifest
        z = man.layer_z_mm[layer]
        try:
            ds = open_mosaic(self.store.mosaic_path(layer))
        except (ValueError, FileNotFoundError, OSError) as err:
            return self.fail(layer, f"no readable mosaic: {err}")
        status = ds.attrs.get("status")
        if status != "complete":
            return self.fail(layer, f"the scan's mosaic is {status!r}, not 'complete'")
        grid, rows, cols = roi_grid(self.store, Grid.of_dataset(ds))
        sub = ds.isel(y=rows, x=cols)
        height = np.asarray(sub["height"].values, dtype=np.float32)
        conf = np.asarray(sub["confidence"].values, dtype=np.float32)
        unc = (np.asarray(sub["uncertainty"].values, dtype=np.float32)
               if "uncertainty" in sub else None)
        exp = self.expected(layer, grid)
        dev, verdict = compare_layer(height, exp, grid=grid, objects=man.objects, layer=layer,
                                     z_mm=z, confidence=conf, uncertainty_um=unc,
                                     tolerances=man.tolerances, mapping=man.mapping)
        self.store.write_deviation(layer, dev, grid)
        verdict = verdict.model_copy(update={"compute_s": time.perf_counter() - t0})
        self.store.finish_layer(layer, verdict)
        return verdict

    def recover(self) -> list[LayerVerdict]:
        """After a restart: finish every layer begun but not done below the last begun one
        (its analysis was interrupted): analysed when its mosaic is complete, else
        ``unknown``. The last begun layer is left to the next layer event (begun again, it
        is cleared and redone). Returns the verdicts written."""
        done = set(self.store.done_layers())
        begun = self.store.begun_layers()
        out = []
        for k in begun[:-1]:
            if k not in done:
                out.append(self.analyse(k))
        return out

    def fail(self, layer: int, reason: str) -> LayerVerdict:
        """Record the layer as ``unknown`` (scan failed, timed out...): never ``pass``."""
        man = self.store.manifest
        v = failed_layer_verdict(layer, man.layer_z_mm[layer], man.objects, reason=reason,
                                 tolerances=man.tolerances)
        if not self.store.layer_dir(layer).is_dir():
            self.store.begin_layer(layer)
        self.store.finish_layer(layer, v)
        log.warning("layer %d: unknown: %s", layer, reason)
        return v


def open_job(path: str | Path) -> xarray.Dataset:
    """Open a print job lazily as one xarray Dataset with a ``layer`` dimension.

    Parameters
    ----------
    path : path-like
        A job folder (:class:`~sffscan.pipeline.printjob.jobstore.JobStore`).

    Returns
    -------
    xarray.Dataset
        Dimensions ``layer`` (the done layers), ``y``, ``x`` (µm, the union of the layers'
        grids). Variables: ``height``, ``confidence`` (from each layer's mosaic) and
        ``deviation`` (measured - expected, µm, over the compared region), all float32
        backed by dask (NaN where a layer has no data); ``verdict`` (layer,) str. Coordinate
        ``z_mm`` (layer,). ``attrs["manifest"]`` is the manifest as a dict.

    Raises
    ------
    JobError
        Not a job folder, or no layer is done yet.
    """
    import dask.array as da
    import xarray as xr
    import zarr

    from sffscan.api import open_mosaic

    store = JobStore.open(path)
    layers = store.done_layers()
    if not layers:
        raise JobError(f"{path}: no layer is done yet")
    parts = []
    for k in layers:
        v = store.read_verdict(k)
        vars_: dict[str, Any] = {}
        coords: dict[str, Any] = {}
        mp = store.mosaic_path(k)
        if mp.exists():
            try:
                ds = open_mosaic(mp)
                ds = ds.assign_coords(x=np.round(ds["x"].values, 6),
                                      y=np.round(ds["y"].values, 6))
                vars_["height"] = ds["height"]
                vars_["confidence"] = ds["confidence"]
            except ValueError as err:
                log.warning("layer %d: mosaic not readable: %s", k, err)
        dp = store.deviation_path(k)
        if dp.exists():
            arr = zarr.open_array(str(dp), mode="r")
            origin = arr.attrs["origin_um"]
            assert isinstance(origin, list)
            ox, oy = float(origin[0]), float(origin[1])  # type: ignore[arg-type]
            p = float(arr.attrs["pixel_um"])  # type: ignore[arg-type]
            ny, nx = arr.shape
            dv = xr.DataArray(da.from_array(arr, chunks=arr.chunks), dims=("y", "x"),
                              coords={"y": np.round(oy + p * np.arange(ny), 6),
                                      "x": np.round(ox + p * np.arange(nx), 6)},
                              attrs={"units": "µm"})
            vars_["deviation"] = dv
        part = xr.Dataset(vars_, coords=coords)
        part = part.expand_dims(layer=[k])
        part["verdict"] = ("layer", [v.verdict])
        part = part.assign_coords(z_mm=("layer", [v.z_mm]))
        parts.append(part)
    out = xr.concat(parts, dim="layer", join="outer", data_vars="all", coords="different",
                    compat="equals")
    out.attrs = {"manifest": store.manifest.model_dump(mode="json"), "path": str(path)}
    return out
