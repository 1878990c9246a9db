"""Band processes (issue 28): the focus volume's rows split among K processes sharing its
state; blocks bit-identical to one band, failures named, nothing left behind."""

from __future__ import annotations

import os
import signal
from pathlib import Path

import numpy as np
import pytest
from sffscan.pipeline.band_processes import BandProcesses, BandProcessFailed
from sffscan.stages.focus_volume import FocusVolume

from tests.stages.test_focus_volume import HEIGHTS, H, N, W, _frame, _wobbly_scan

# what _wobbly_scan builds its volume with
VOLUME = dict(n_levels=N, frame_shape=(H, W), focus_heights_um=HEIGHTS, margin=3,
              median_size=3, block_columns=16, row_slack=3, spread_size=3)


def _segments() -> set[str]:
    shm = Path("/dev/shm")
    return {p.name for p in shm.iterdir() if p.name.startswith(f"sffscan-{os.getpid()}-")} \
        if shm.is_dir() else set()


def _passes(method: str, direction: int, workers: BandProcesses | None) -> list:
    """The blocks of two passes of _wobbly_scan's frames, the second volume taking over the
    first's ring (as the depth stage does), the first pass from a new volume."""
    out, vol = [], None
    for _ in range(2):
        vol = FocusVolume(direction=direction, method=method, reuse=vol, workers=workers,
                          **VOLUME)  # type: ignore[arg-type]
        for k in range(70):
            if k == 25:
                continue
            x, y = 100 + direction * 4 * k, 10 + (k * 7) % 5 - 2
            fm, img = _frame(x, y, k % N)
            fm = (np.round(fm * 4) / 4).astype(np.float32)
            c0 = 3 + (k % 3) * 10
            out += vol.add(fm[:, c0:], img[:, c0:], x=x, y=y, level=k % N, col0=c0)
        out += vol.finish()
    return out


def _same(a: list, b: list) -> None:
    assert len(a) == len(b)
    for u, v in zip(a, b, strict=True):
        assert (u.x0, u.y0, u.complete) == (v.x0, v.y0, v.complete)
        for p, q in zip(u[2:5] + (u.uncertainty_um,), v[2:5] + (v.uncertainty_um,),
                        strict=True):
            assert p.dtype == q.dtype and p.shape == q.shape
            assert p.tobytes() == q.tobytes()


@pytest.mark.parametrize(("method", "direction"), [
    ("shape_select", 1), ("shape_select", -1), ("spc", 1), ("centroid", -1),
    ("wcentroid", 1), ("gauss3", 1)])
def test_blocks_are_bit_identical_in_band_processes(method: str, direction: int) -> None:
    """Three bands (two helper processes) and one band in the shared arrays give every
    block bit for bit as the volume alone: wobble, ties, partial columns, a dropped frame,
    the ring wrapping, both directions, a second pass that takes over the first's ring;
    the streaming sums and the N-level ring."""
    alone = _passes(method, direction, None)
    assert sum(b.complete for b in alone) > 200
    layout = FocusVolume.shared_layout(method=method, **VOLUME)
    with BandProcesses(3, layout, name="test-band") as pool:
        _same(alone, _passes(method, direction, pool))
        assert pool.helpers_cpu_s() > 0
        _same(alone, _passes(method, direction, pool))  # the arrays used before
    with BandProcesses(1, layout) as one:
        _same(alone, _passes(method, direction, one))
    assert not _segments()


def test_a_failing_band_process_names_itself_and_the_rows() -> None:
    layout = FocusVolume.shared_layout(method="spc", **VOLUME)
    with BandProcesses(2, layout, name="test-fail") as pool:
        assert not _segments()  # unlinked once the helper mapped it
        # level 99 of 12: only the helper's band has rows to write
        bad = {"writes": [[99, 0, 0, 0, 10, 0, 4]], "shape": [10, 4], "cache_bytes": 1 << 19,
               "low": False}
        with pytest.raises(BandProcessFailed, match=r"sffscan-test-fail-1 \(accumulate, rows "
                           r"5\.\.10\): IndexError: index 99 is out of bounds"):
            pool.run_task("accumulate", bad, [(0, 0), (5, 10)])
        with pytest.raises(ValueError, match="unknown band task 'nonsense'"):
            pool.run_task("nonsense", {}, [(0, 5), (5, 10)])  # the caller's own band first
        # still answers after an error
        _same(_wobbly_scan("spc", 1), _wobbly_scan("spc", 1, workers=pool))
        os.kill(pool._procs[0].pid, signal.SIGKILL)
        pool._procs[0].join(10)
        with pytest.raises(BandProcessFailed, match="sffscan-test-fail-1 .* died"):
            _wobbly_scan("spc", 1, workers=pool)
    pool.close()  # idempotent
    assert not pool._procs


def test_a_volume_refuses_arrays_laid_out_for_another() -> None:
    layout = FocusVolume.shared_layout(method="spc", **VOLUME)
    with BandProcesses(1, layout) as pool, pytest.raises(ValueError, match="laid out for"):
        FocusVolume(method="gauss3", workers=pool, **VOLUME)  # type: ignore[arg-type]
    assert np.prod(layout["fv"][0]) if "fv" in layout else True
