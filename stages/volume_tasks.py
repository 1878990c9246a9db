"""The focus volume's band work as tasks on named arrays.

A task is a name and JSON-able parameters; :func:`run_task` runs one on rows [r0, r1) of
a volume's arrays. The volume reduces its blocks with them, each band in its own thread
where there are band threads (:class:`sffscan.stages.bands.BandWorkers`). A band
*process* shares no interpreter with the volume: it maps the same arrays (one
shared-memory segment, :mod:`sffscan.pipeline.band_processes`) and receives the tasks
down a pipe, the frames' writes too (:class:`sffscan.stages.shared_volume.SharedFocusVolume`);
the volume's own process runs the first band the same way.
Each task calls the functions the threads call (:func:`~sffscan.stages.accumulate.apply_writes`,
:func:`~sffscan.stages.block_depth.depth_rows`,
:func:`~sffscan.stages.block_depth.block_uncertainty`) on the same values, so the blocks
are bit-identical for any number of bands and either kind of band worker (tested in
``tests/pipeline/test_band_processes.py``).

The arrays (:func:`volume_layout`): the volume's per-pixel state (``best``, ``argmax``,
``tex``, ``sums``, ``low``, ``fv``, ``level_buf``, the sums' weights ``coef`` and the
levels' heights ``heights``), the frame being added (``focus``, ``image01``, written by
the volume before its writes are applied), and a block's scratch (``b_*``, flat, cut to
the block's shape by :func:`scratch`).
"""

from __future__ import annotations

import math
from collections.abc import Callable, Iterator
from typing import Any

import numpy as np
from sffscan.stages import block_depth as blocks
from sffscan.stages.accumulate import AccumulatorState, Write, apply_writes
from sffscan.stages.depth_choice import DEPARTURE_METHODS
from sffscan.stages.depth_floor import GuardFloor
from sffscan.stages.depth_statistics import SHAPE_SAMPLE_STEP

__all__ = ["RAW_SLOTS", "TASKS", "gather", "grid_rows", "keeps_grid", "pieces", "run_task",
           "scratch", "scratch_arrays", "volume_layout"]

Layout = dict[str, tuple[tuple[int, ...], str]]
"""Array name -> (shape, dtype string)."""


def volume_layout(*, n_levels: int, rows: int, ring: int, frame_shape: tuple[int, int],
                  block_columns: int, n_sums: int, levels: bool, low: bool,
                  grid: bool = False, raw_dtype: str = "<u2") -> Layout:
    """The arrays a focus volume with band processes keeps in shared memory.

    Parameters
    ----------
    n_levels, rows, ring : int, keyword-only
        N, the state's rows (frame height + wobble slack) and ring columns.
    frame_shape : (int, int), keyword-only
        Frame (height, width), px: the largest focus measure a frame adds.
    block_columns : int, keyword-only
        Columns of a block (the scratch's width).
    n_sums : int, keyword-only
        Planes of running sums (0 for the methods that store every level).
    levels, low : bool, keyword-only
        Whether the N-level ring is kept; whether a running minimum is.
    grid : bool, keyword-only
        Whether every level of every :data:`~sffscan.stages.depth_statistics.
        SHAPE_SAMPLE_STEP`-th row is kept (``grid``: the curves a block's departure bias is
        judged on, for the accumulating methods that have one).
    raw_dtype : str, keyword-only
        The raw frames' dtype (``raw``: :data:`RAW_SLOTS` slots of the columns a frame's
        focus measure reads).
    """
    amax = "|u1" if n_levels <= 256 else "<u2"
    plane = (rows, ring)
    out: Layout = {
        "best": (plane, "<f4"), "argmax": (plane, amax), "tex": (plane, "<f4"),
        "sums": ((n_sums, *plane), "<f4"), "low": (plane if low else (0, 0), "<f4"),
        "level_buf": ((rows, frame_shape[1]), amax),
        "coef": ((max(n_sums, 1), n_levels), "<f8"), "heights": ((n_levels,), "<f8"),
        "focus": (frame_shape, "<f4"), "image01": (frame_shape, "<f4"),
        "raw": ((RAW_SLOTS, *frame_shape), np.dtype(raw_dtype).str),
    }
    if levels:
        out["fv"] = ((n_levels, *plane), "<f4")
    if grid:
        out["grid"] = ((n_levels, grid_rows(rows), ring), "<f4")
    out.update({name: ((planes * rows * block_columns,), "<f4") for name, planes in _SCRATCH})
    return out


def keeps_grid(method: str, *, streaming: bool, uncertainty: bool) -> bool:
    """Whether a volume keeps the judged rows' curves (``grid``): a method that accumulates
    sums (``streaming``) but whose uncertainty's bias is its departure from the curves'
    peaks (:data:`sffscan.stages.depth_choice.DEPARTURE_METHODS`), when it computes one."""
    return uncertainty and streaming and method in DEPARTURE_METHODS


def grid_rows(rows: int) -> int:
    """Rows of a volume's ``grid``: every ``SHAPE_SAMPLE_STEP[0]``-th of ``rows``, from the
    first."""
    return -(-rows // SHAPE_SAMPLE_STEP[0])


RAW_SLOTS = 3
"""Slots of raw columns in the shared arrays: the band processes may measure a frame while
the next ones are copied in (:meth:`sffscan.stages.shared_volume.SharedFocusVolume.add_raw`:
the helpers lag the caller by up to this many frames less one)."""

_SCRATCH = (("b_sums", 3), ("b_low", 1), ("b_depth", 1), ("b_conf", 1), ("b_filled", 1),
            ("b_valid", 1), ("b_unc", 1), ("b_peak", 1), ("b_window", 1))
"""A block's scratch arrays and their planes (flat float32)."""


def scratch_arrays(rows: int, block_columns: int) -> dict[str, np.ndarray]:
    """A block's scratch arrays (``b_*``, flat float32; :func:`scratch` cuts them to a
    block's shape) for a volume of ``rows`` rows and blocks of ``block_columns``."""
    return {name: np.empty(planes * rows * block_columns, np.float32)
            for name, planes in _SCRATCH}


def scratch(arrays: dict[str, np.ndarray], name: str, shape: tuple[int, ...]) -> np.ndarray:
    """The flat scratch array ``name`` cut to a contiguous ``shape`` (a block's)."""
    n = int(np.prod(shape))
    return arrays[name][:n].reshape(shape)


def pieces(u0: int, u1: int, ring: int) -> Iterator[tuple[int, int, int]]:
    """Internal columns [u0, u1) as (v0, v1, first slot) runs contiguous in a ring of
    ``ring`` slots."""
    while u0 < u1:
        s0 = u0 % ring
        v1 = min(u1, u0 + ring - s0)
        yield u0, v1, s0
        u0 = v1


def gather(arr: np.ndarray, u0: int, u1: int, ring: int) -> np.ndarray:
    """``arr[..., columns u0..u1)`` from a ring: a view unless it wraps."""
    parts = [arr[..., s0:s0 + (v1 - v0)] for v0, v1, s0 in pieces(u0, u1, ring)]
    return parts[0] if len(parts) == 1 else np.concatenate(parts, axis=-1)


def _state(arrays: dict[str, np.ndarray], p: dict[str, Any]) -> AccumulatorState:
    return AccumulatorState(arrays["best"], arrays["argmax"], arrays["tex"], arrays["sums"],
                            arrays["coef"], arrays["low"] if p["low"] else None,
                            arrays.get("fv"), arrays["level_buf"], arrays.get("grid"),
                            SHAPE_SAMPLE_STEP[0])


def _band_of_frame(p: dict[str, Any], rows: tuple[int, int]) -> tuple[int, int, int] | None:
    """The state rows [s0, s1) of ``rows`` that the frame's writes cover, and the focus
    measure's row of s0; None where they cover none."""
    if not p["writes"]:
        return None
    _, fr0, _, r0, r1, _, _ = p["writes"][0]  # one frame: every write covers the same rows
    s0, s1 = max(rows[0], r0), min(rows[1], r1)
    return None if s1 <= s0 else (s0, s1, fr0 + s0 - r0)


def _apply_frame(arrays: dict[str, np.ndarray], p: dict[str, Any], focus: np.ndarray,
                 image01: np.ndarray, s0: int, s1: int, rows: tuple[int, int]) -> None:
    """The frame's writes from ``focus`` and ``image01`` (state rows [s0, s1), the frame's
    columns), each on its own (strips sized for one frame's values: see
    :func:`~sffscan.stages.accumulate.apply_writes`), as the volume without band
    processes applies them."""
    state = _state(arrays, p)
    for level, _, fc0, _, _, cs0, cs1 in p["writes"]:
        n = cs1 - cs0
        apply_writes(state, [Write(level, focus[:, fc0:fc0 + n], image01[:, fc0:fc0 + n],
                                   s0, s1, slice(cs0, cs1))],
                     cache_bytes=p["cache_bytes"], rows=rows)


def accumulate(arrays: dict[str, np.ndarray], p: dict[str, Any], rows: tuple[int, int]
               ) -> None:
    """The frame's writes (``p["writes"]``: level, the focus measure's first row and
    column, rows r0, r1 and ring slots s0, s1 of the state) applied to ``rows``, the
    frame's focus measure of shape ``p["shape"]`` in ``arrays["focus"]``."""
    band = _band_of_frame(p, rows)
    if band is None:
        return
    s0, s1, f0 = band
    w = p["shape"][1]
    _apply_frame(arrays, p, arrays["focus"][f0:f0 + s1 - s0, :w],
                 arrays["image01"][f0:f0 + s1 - s0, :w], s0, s1, rows)


def measure_accumulate(arrays: dict[str, np.ndarray], p: dict[str, Any],
                       rows: tuple[int, int]) -> None:
    """The focus measure of the frame's raw columns (``raw`` slot ``p["slot"]``, shape
    ``p["shape"]``) on the
    focus rows the writes map to ``rows`` (with the operator's reach: bit-identical to the
    whole frame's for GLVM and TENV), its columns ``p["cols"]`` (mirrored where
    ``p["flip"]``), then :func:`accumulate`'s writes from it. Nothing is gathered: each
    band measures what it writes."""
    from sffscan.stages.focus_measure import focus_measure_raw  # it imports the volume

    band = _band_of_frame(p, rows)
    if band is None:
        return
    s0, s1, f0 = band
    h, w = p["shape"]
    c0, c1 = p["cols"]
    image01, fm = focus_measure_raw(arrays["raw"][p["slot"], :h, :w], max_value=p["max_value"],
                                    operator=p["operator"], window=p["window"],
                                    rows=(f0, f0 + s1 - s0))
    image01, fm = image01[:, c0:c1], fm[:, c0:c1]
    if p["flip"]:  # OpenCV takes positive strides only
        image01 = np.ascontiguousarray(image01[:, ::-1])
        fm = np.ascontiguousarray(fm[:, ::-1])
    _apply_frame(arrays, p, fm, image01, s0, s1, rows)


def depth(arrays: dict[str, np.ndarray], p: dict[str, Any], rows: tuple[int, int]) -> None:
    """A block's depth and confidence (``b_depth``, ``b_conf``), its curves' sums and
    minima (``b_sums``, ``b_low``) and, with ``wide_test``, the peak estimator's depth where
    the wide centroid was taken (``b_peak``), with ``window_test`` the 9-level centroid
    (``b_window``), rows [r0, r1)
    (:func:`sffscan.stages.volume_reduce.reduce_block`)."""
    r0, r1 = rows
    u0, u1, a0, a1, ring = p["u0"], p["u1"], p["a0"], p["a1"], p["ring"]
    n_rows, width, halo = p["rows"], u1 - u0, p["halo"]
    streaming = "fv" not in arrays
    # only the band's rows and their halo are read: gathered from the whole state, a
    # block that wraps the ring was copied whole by every band (all N levels of every
    # row with the default method), K times the copy with K bands
    ra0, ra1 = max(r0 - halo, 0), min(r1 + halo, n_rows)
    band = slice(ra0, ra1)
    if streaming:
        src = gather(arrays["sums"][:, band], a0, a1, ring)
        low_src = gather(arrays["low"][band], u0, u1, ring) if p["uncertainty"] else None
    else:
        src = gather(arrays["fv"][:, band], u0 if p["own"] else a0,
                     u1 if p["own"] else a1, ring)
        low_src = None
    argmax = gather(arrays["argmax"][band], a0, a1, ring)
    sums = scratch(arrays, "b_sums", (3, n_rows, width))
    low = scratch(arrays, "b_low", (n_rows, width))
    d, c = blocks.depth_rows(src, argmax, low_src, (r0 - ra0, r1 - ra0),
                             slice(r0 - ra0, r1 - ra0),
                             slice(u0 - a0, u1 - a0), sums[:, r0:r1], low[r0:r1],
                             method=p["method"], n_levels=p["n_levels"],
                             median_size=p["median_size"], spread_size=p["spread_size"],
                             streaming=streaming, keep_low=p["uncertainty"],
                             wide_peak=scratch(arrays, "b_peak", (n_rows, width))[r0:r1]
                             if p["wide_test"] else None,
                             window_out=scratch(arrays, "b_window", (n_rows, width))[r0:r1]
                             if p["window_test"] else None,
                             floor=None if p.get("floor") is None
                             else GuardFloor(*(math.nan if v is None else float(v)
                                               for v in p["floor"])),
                             spc_weight=float(p.get("spc_weight", 1.0)))
    scratch(arrays, "b_depth", (n_rows, width))[r0:r1] = d
    scratch(arrays, "b_conf", (n_rows, width))[r0:r1] = c


def uncertainty(arrays: dict[str, np.ndarray], p: dict[str, Any], rows: tuple[int, int]
                ) -> None:
    """A block's height uncertainty (``b_unc``), rows [r0, r1), from its filled depth
    (``b_filled``), sums and minima of its valid pixels (``b_valid``, 1.0 or 0.0)
    (:func:`sffscan.stages.block_depth.block_uncertainty`)."""
    r0, r1 = rows
    shape = (p["rows"], p["width"])
    u = blocks.block_uncertainty(scratch(arrays, "b_filled", shape),
                                 scratch(arrays, "b_sums", (3, *shape)),
                                 scratch(arrays, "b_low", shape), (r0, r1),
                                 method=p["method"], n_levels=p["n_levels"],
                                 focus_heights_um=arrays["heights"],
                                 window=p["window"], bias_levels=p["bias"],
                                 locking_levels=p["locking"],
                                 valid=scratch(arrays, "b_valid", shape) > 0.5)
    scratch(arrays, "b_unc", shape)[r0:r1] = u


TASKS: dict[str, Callable[[dict[str, np.ndarray], dict[str, Any], tuple[int, int]], None]] = {
    "accumulate": accumulate, "measure_accumulate": measure_accumulate, "depth": depth,
    "uncertainty": uncertainty}
"""The tasks a band process runs, by name."""


def run_task(arrays: dict[str, np.ndarray], task: str, params: dict[str, Any],
             rows: tuple[int, int]) -> None:
    """Run task ``task`` (a :data:`TASKS` name) with ``params`` on rows [r0, r1)."""
    try:
        fn = TASKS[task]
    except KeyError:
        raise ValueError(f"unknown band task {task!r}; known: {sorted(TASKS)}") from None
    fn(arrays, params, rows)

