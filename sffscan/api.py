"""The functions of the public API (re-exported by :mod:`sffscan`).

Each one is what a command of the ``sffscan`` CLI does, without the printing: it returns
the same report object the CLI prints its summary from, and raises instead of choosing an
exit code. Heavy modules (torch, OpenCV, zarr) are imported by the call, not at import.
"""

from __future__ import annotations

from collections.abc import Iterable, Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from sffscan.pipeline.config import ScanConfig

if TYPE_CHECKING:
    import xarray

    from sffscan.pipeline.wiring import ScanReport
    from sffscan.stages.fields.stationary import FieldResult, StackSettings
    from sffscan.stages.messages import Frame
    from sffscan.stages.protocol import Sink


def scan(config: ScanConfig | str | Path, *, output: str | Path | None = None,
         overwrite: bool | None = None, frames: Iterable[Frame] | None = None,
         record: str | Path | None = None, processing: dict[str, Any] | None = None,
         evaluate: bool = False, progress: bool = False,
         sinks: Sequence[Sink] = ()) -> ScanReport:
    """Run a scan through the streaming pipeline into a Zarr mosaic.

    Parameters
    ----------
    config : ScanConfig or path-like
        The scan configuration, or a TOML file (:func:`sffscan.load_config`).
    output : path-like, keyword-only
        Mosaic path (a Zarr v3 group); default ``config.output.path``.
    overwrite : bool, keyword-only
        Replace an existing mosaic; default ``config.output.overwrite``.
    frames : iterable of Frame, keyword-only
        The frames to process; default the feed ``config.source`` names (the simulator,
        a GenICam camera or a zmq address).
    record : path-like, keyword-only
        Also record the raw stream into this Zarr group, for :func:`replay`.
    processing : dict, keyword-only
        Fields of ``[processing]`` to override (``{"depth_method": "gauss3"}``...).
    evaluate : bool, keyword-only
        Score the mosaic against the simulated true surface (``source.kind = "sim"`` only);
        fills ``report.accuracy``.
    progress : bool, keyword-only
        Show the progress display on stderr.
    sinks : sequence of Sink, keyword-only
        Extra side branches (a live viewer, ...).

    Returns
    -------
    ScanReport
        Frames, per-stage and per-queue statistics, accuracy if evaluated; the CLI prints
        its summary from it (:func:`sffscan.pipeline.wiring.format_summary`).

    Raises
    ------
    ConfigError
        Invalid configuration (the message names the field), or a check before anything
        is changed failed (:mod:`sffscan.pipeline.run`: pre-flight, an output that would
        destroy an input, another writer holding the mosaic's lock:
        :class:`~sffscan.pipeline.locks.LockHeld`). An existing output without
        ``overwrite`` is :class:`~sffscan.pipeline.preflight.OutputExists`, also a
        ``FileExistsError``.
    KeyboardInterrupt
        Ctrl-C, or SIGTERM (:class:`~sffscan.pipeline.run.Terminated`) when called from
        the main thread with SIGTERM's default action: the mosaic is ``failed``, resumable.
    StageFailed
        A stage failed; the message names it and the cause, and the mosaic holds what was
        completed (status ``failed``).
    """
    from sffscan.pipeline.config import load_config
    from sffscan.pipeline.run import Job, execute, with_overrides
    from sffscan.pipeline.wiring import evaluate_sim

    cfg = config if isinstance(config, ScanConfig) else load_config(config)
    cfg = with_overrides(cfg, origin="sffscan API", output=output, overwrite=overwrite,
                         processing=processing)
    if evaluate and (frames is not None or cfg.source.kind != "sim"):
        raise ValueError("evaluate=True needs the simulated source (source.kind = 'sim') "
                         "and frames=None")
    run = execute(Job(cfg, frames=frames, record=record, progress=progress,
                      sinks=list(sinks)))
    assert run is not None  # not check_only
    if evaluate:
        if run.world is None:
            raise ValueError("evaluate=True needs the simulated source (source.kind = 'sim') "
                             "and frames=None")
        evaluate_sim(run.report, run.world)
    return run.report


def replay(recording: str | Path, *, output: str | Path | None = None,
           overwrite: bool | None = None, processing: dict[str, Any] | None = None,
           evaluate: bool = False, progress: bool = False) -> ScanReport:
    """Re-process a recorded raw stream (``sffscan scan --record``) into a mosaic.

    Parameters
    ----------
    recording : path-like
        The recording, a Zarr v3 group.
    output, overwrite, processing, evaluate, progress
        As in :func:`scan`; the configuration is the recorded one.

    Returns
    -------
    ScanReport
        As :func:`scan`; ``report.extras["recording"]`` holds the recording's report
        (frames, gaps, defects, corrupt chunks left out).

    Raises
    ------
    RecordingError
        The path is not a usable recording (the message names the file and the field).
    ConfigError
        As in :func:`scan`; also a recording still being written. ``overwrite`` defaults
        to False whatever the recorded configuration says.
    StageFailed
        As in :func:`scan`.
    """
    from sffscan.pipeline.formats.recording_reader import open_recording
    from sffscan.pipeline.run import Job, execute, with_overrides
    from sffscan.pipeline.wiring import evaluate_sim

    rec = open_recording(recording)
    # the recorded [output] overwrite is the recording's, never the caller's
    cfg = with_overrides(rec.config, origin="sffscan API", output=output,
                         overwrite=bool(overwrite), processing=processing)
    run = execute(Job(cfg, recording=rec, progress=progress))
    assert run is not None  # not check_only
    report = run.report
    if run.annotate_error:
        raise OSError(run.annotate_error)
    report.extras["recording"] = rec.report.as_dict()
    if evaluate:
        if cfg.source.kind != "sim":
            raise ValueError("evaluate=True needs a recording of the simulator")
        from sffscan.pipeline.sim_source import make_world

        evaluate_sim(report, make_world(cfg))
    return report


def reconstruct_stack(stack: np.ndarray, focus_um: Sequence[float] | np.ndarray, *,
                      settings: StackSettings | None = None, max_value: float | None = None,
                      **options: Any) -> FieldResult:
    """Height map of one field from its focus stack (the camera standing still).

    Parameters
    ----------
    stack : (N, H, W) ndarray of uint8, uint16 or float
        One grey image per focus level, N >= 3.
    focus_um : (N,) array_like of float
        Height in focus of each image, µm, strictly monotonic.
    settings : StackSettings, keyword-only
        Operator, window, depth method, post-filter; default ``StackSettings(**options)``.
    max_value : float, keyword-only
        Full scale of the images (1023 for 10-bit data in uint16); default from the dtype.
    **options
        Fields of :class:`~sffscan.stages.fields.stationary.StackSettings` (``operator``,
        ``window``, ``method``, ``filter_size``...), when ``settings`` is not given.

    Returns
    -------
    FieldResult
        ``height_um``, ``raw_height_um``, ``levels``, ``texture``, ``confidence``, all
        (H, W) float32.
    """
    from sffscan.stages.fields.stationary import StackSettings, reconstruct_field

    if settings is not None and options:
        raise TypeError("give either settings or StackSettings fields, not both")
    settings = settings if settings is not None else StackSettings(**options)
    return reconstruct_field(stack, focus_heights_um=focus_um, settings=settings,
                             max_value=max_value)


def focus_measure(image: np.ndarray, *, operator: str = "glvm", window: int = 9,
                  backend: str = "opencv", device: str = "cpu") -> np.ndarray:
    """Focus measure of an image (or a batch) scaled to 0..1.

    Parameters
    ----------
    image : (H, W) or (B, H, W) ndarray of float
        Grey image(s), 0..1.
    operator : str, keyword-only
        Focus measure operator: an acronym of Pertuz's toolbox, any case (``"LAPM"``,
        ``"glvm"``, ``"TENV"``...), see ``sffscan.stages.operators.FOCUS_OPERATORS``.
    window : int, keyword-only
        Odd window size k >= 3, px.
    backend : {"opencv", "torch"}, keyword-only
        CPU fast path or torch (on ``device``).
    device : str, keyword-only
        Torch device for the torch backend.

    Returns
    -------
    ndarray of float32, the shape of ``image``
    """
    from sffscan.stages.focus_measure import focus_measure as _focus_measure

    return _focus_measure(image, operator=operator, window=window, backend=backend,
                          device=device)


def open_mosaic(path: str | Path, *, level: int = 0) -> xarray.Dataset:
    """Open a mosaic lazily as an xarray Dataset with coordinates in µm.

    Parameters
    ----------
    path : path-like
        A mosaic (Zarr v3 group written by a scan, replay or stop-and-go).
    level : int, keyword-only
        Level of the resolution pyramid: 0 is the full resolution; level k is the
        2^k x 2^k reduction (NaN-aware mean of height and texture, mean confidence, summed
        weight). Version-1 mosaics have level 0 only.

    Returns
    -------
    xarray.Dataset
        Variables ``height`` (µm), ``texture`` (0..1), ``confidence`` (0..1) and ``weight``
        (and any other array the mosaic was written with; the same as
        ``xarray.open_zarr`` gives from format version 3 on), each (y, x) float32 backed by
        dask with the mosaic's chunks (nothing is read until
        computed); coordinates ``y`` and ``x`` are the pixel centres in µm (for level k the
        centres of the 2^k x 2^k blocks); ``attrs`` are the mosaic's attributes plus
        ``level`` and ``pixel_um_level`` (the level's pixel size, µm).

    Raises
    ------
    ValueError
        The path is not a valid mosaic (the message names the file and the attribute), or
        it has no such level.
    """
    from sffscan.pipeline.mosaic.reader import open_dataset

    return open_dataset(path, level=level)
