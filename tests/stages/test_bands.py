"""Band workers (issue 28): a frame's rows split among K threads, bit-identical for every K."""

from __future__ import annotations

import threading

import numpy as np
import pytest
from sffscan.stages.bands import BandWorkers, row_bands
from sffscan.stages.focus_measure import FocusMeasureStage
from sffscan.stages.messages import FrameHeader, PlacedFrame

from tests.stages.test_focus_volume import _wobbly_scan, assert_same_blocks


def test_row_bands_cover_the_rows_once_in_order() -> None:
    assert row_bands(0, 10, 3) == [(0, 3), (3, 6), (6, 10)]
    assert row_bands(5, 7, 4) == [(5, 6), (6, 7)]  # fewer rows than bands
    assert row_bands(3, 3, 2) == []
    for n, k in [(1040, 1), (1040, 2), (1040, 4), (1041, 7)]:
        bands = row_bands(0, n, k)
        assert len(bands) == k and bands[0][0] == 0 and bands[-1][1] == n
        assert all(b[1] == c[0] for b, c in zip(bands, bands[1:], strict=False))
        assert max(b - a for a, b in bands) - min(b - a for a, b in bands) <= 1
    with pytest.raises(ValueError, match="must be >= 1, got 0"):
        row_bands(0, 10, 0)


def test_band_workers_run_the_bands_at_once_and_keep_the_order() -> None:
    barrier = threading.Barrier(3, timeout=10)  # passes only if 3 bands run at once
    seen: list[str] = []
    lock = threading.Lock()

    def work(a: int, b: int) -> int:
        with lock:
            seen.append(threading.current_thread().name)
        barrier.wait()
        return a * 100 + b

    with BandWorkers(3) as pool:
        assert pool.run(work, row_bands(0, 9, 3)) == [3, 306, 609]
    assert threading.current_thread().name in seen  # the caller takes the first band
    assert len(set(seen)) == 3
    with BandWorkers(1) as one:  # no threads at all
        assert one.run(lambda a, b: a * 100 + b, [(0, 1), (1, 2)]) == [1, 102]


def test_a_failing_band_fails_the_call_with_its_cause() -> None:
    def work(a: int, b: int) -> int:
        if a == 4:
            raise ValueError("band 4..8 broke")
        return a

    with BandWorkers(2) as pool, pytest.raises(ValueError, match="band 4..8 broke"):
        pool.run(work, [(0, 4), (4, 8)])


@pytest.mark.parametrize("method", ["spc", "centroid", "adaptive", "gauss3", "wcentroid",
                                    "shape_select", "adaptive_centroid"])
@pytest.mark.parametrize("k", [2, 3, 4, 9])
def test_focus_volume_blocks_are_bit_identical_for_any_number_of_bands(method: str,
                                                                       k: int) -> None:
    """Accumulation and reduction by bands of rows (wobble, ties, partial columns, a drop;
    9 bands of ~5 rows are narrower than the filters' reach) give every block bit for bit
    as one band."""
    one = _wobbly_scan(method, 1)
    with BandWorkers(k) as pool:
        banded = _wobbly_scan(method, 1, workers=pool)
    assert sum(b.complete for b in one) > 100
    assert_same_blocks(one, banded)


def _placed(k: int, image: np.ndarray) -> PlacedFrame:
    hdr = FrameHeader(frame_id=k, timestamp_ns=k, focus_index=k % 5, pass_index=0)
    return PlacedFrame(hdr, image, (3.0 * k, 0.0), (3 * k, 0))


@pytest.mark.parametrize("operator", ["glvm", "tenv"])
def test_focus_measure_by_bands_is_bit_identical(operator: str) -> None:
    rng = np.random.default_rng(3)
    frames = [rng.integers(0, 1024, (70, 90), dtype=np.uint16) for _ in range(8)]
    outs = []
    for k in (1, 2, 4, 7):
        stage = FocusMeasureStage(operator=operator, window=5, max_value=1023.0, margin=3,
                                  workers=k)
        try:
            outs.append([f for i, img in enumerate(frames)
                         for f in stage.process(_placed(i, img))])
        finally:
            stage.close(failed=False)
    for other in outs[1:]:
        for a, b in zip(outs[0], other, strict=True):
            assert a.col0 == b.col0
            assert a.focus.tobytes() == b.focus.tobytes()
            assert a.image01.tobytes() == b.image01.tobytes()
