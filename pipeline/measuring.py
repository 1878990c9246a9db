"""The stages that measure: a scan configuration becomes the registration, focus measure and
depth stages (:func:`measure_stages`) and its focus heights (:func:`focus_heights_um`).

Their home apart from :mod:`sffscan.pipeline.wiring` (which builds the whole scan: source,
mosaic, Zarr), so that the worker processes that host these stages
(:mod:`sffscan.pipeline.scan_processes`) import neither the mosaic nor Zarr: 0.26-0.30 s
less CPU at each worker's start on the 2-core VM (``import sffscan.pipeline.wiring`` 0.59 s,
these modules 0.32 s, measured).
"""

from __future__ import annotations

from collections.abc import Callable, Collection
from typing import Any

import numpy as np
from sffscan.pipeline.band_processes import LazyBandProcesses
from sffscan.pipeline.config import ScanConfig
from sffscan.pipeline.plan import pass_direction
from sffscan.stages.bands import BandTaskThreads
from sffscan.stages.depth_stage import DepthStage
from sffscan.stages.focus_measure import FocusMeasureStage
from sffscan.stages.protocol import Stage
from sffscan.stages.registration import RegistrationStage
from sffscan.stages.shared_volume import SharedFocusVolume

__all__ = ["focus_heights_um", "measure_stages"]


def focus_heights_um(cfg: ScanConfig) -> list[float]:
    """Height in focus at each level, µm: from the calibration file's z response when
    ``processing.calibration`` is set, else the nominal optics table."""
    if cfg.processing.calibration:
        from sffscan.pipeline.metrology.calibration_model import (
            calibrated_focus_heights,
            load_calibration,
        )

        cal = load_calibration(cfg.processing.calibration)
        return [float(v) for v in calibrated_focus_heights(cal, cfg.optics.n_levels)]
    return cfg.optics.focus_heights_um()


TORCH_THREADS = 1
"""torch's intra-op threads where the torch backend's focus measure runs in a scan. The
stages already run in parallel (threads or processes), as for BLAS (limited to one thread
while a pipeline runs, :meth:`sffscan.pipeline.runtime.Pipeline.run`), and the pool's idle
threads spin after each call. Measured: on the 2-core VM with the CPU device (processes,
300 frames, 3 rounds interleaved, 2026-12-04) 60.7 -> 77.0 frames/s and 27.65 -> 18.92 ms
of CPU a frame (``OMP_NUM_THREADS=1`` in the workers: 73.2, 19.26); on a lent H200 with
the CUDA device the torch scan used 74.8 ms of CPU a frame, 25.0 with ``OMP_NUM_THREADS=1``
for the whole run (bench/results/gpu_cuda.md, gpu_cuda_omp1.md; this setting itself not
measured there)."""


def measure_stages(cfg: ScanConfig, *, only: Collection[str] | None = None) -> list[Stage]:
    """The stages from a placed frame to a depth block (registration when on, focus
    measure, depth), or only those named in ``only``: built alike for a thread and for
    the worker process that hosts them."""
    o, p, m = cfg.optics, cfg.processing, cfg.motion
    slack = int(2 * (m.wobble_along_px + m.wobble_across_px)) + 8
    directions = [pass_direction(cfg, i) for i in range(m.passes)]
    def depth_kw() -> dict[str, Any]:
        return dict(n_levels=o.n_levels, frame_shape=(o.height_px, o.width_px),
                    focus_heights_um=focus_heights_um(cfg), margin=p.focus_reach_px,
                    method=p.depth_method, median_size=p.median_size, spread_size=p.window,
                    block_columns=p.block_columns)

    wanted = {"focus_measure", "depth"} if only is None else set(only)
    bands: LazyBandProcesses | BandTaskThreads | None = None
    if p.bands_measure() and {"focus_measure", "depth"} <= wanted:
        # the depth stage's band workers, which measure the focus too (one band: none):
        # processes started where the stages run (sffscan.pipeline.band_processes), or
        # threads running the same tasks (sffscan.stages.bands.BandTaskThreads)
        layout = SharedFocusVolume.shared_layout(
            **depth_kw(), row_slack=slack, col_slack=slack, raw_dtype=np.dtype(o.dtype).str)
        bands = (LazyBandProcesses(p.band_workers(), layout, name="band")
                 if p.bands == "processes"
                 else BandTaskThreads(p.band_workers(), layout, name="depth-band"))
    build: dict[str, Callable[[], Stage]] = {
        "registration": lambda: RegistrationStage(n_levels=o.n_levels,
                                                  scale=p.registration_scale,
                                                  workers=p.band_workers()),
        "focus_measure": lambda: FocusMeasureStage(
            operator=p.focus_operator, window=p.window, backend=p.backend, device=p.device,
            max_value=o.max_value, margin=p.focus_reach_px, directions=directions,
            workers=p.band_workers(), bands_measure=bands is not None,
            torch_threads=TORCH_THREADS),
        "depth": lambda: DepthStage(
            directions=directions, slack_px=slack, workers=p.band_workers(),
            band_tasks=bands, **depth_kw()),
    }
    if not p.registration:
        del build["registration"]
    return [make() for name, make in build.items() if only is None or name in only]
