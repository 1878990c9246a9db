"""Speed-based shift: world position of a frame from stage position or speed."""

from __future__ import annotations

import pytest
from sffscan.stages.messages import Frame, FrameError, FrameHeader
from sffscan.stages.speed_shift import (
    SpeedShiftStage,
    position_from_speed_px,
    predicted_position_px,
)


def test_position_from_speed_matches_the_thesis_figure() -> None:
    # 15 mm/s at 150 fps, 8.5 µm/px: 100 µm per frame, 11.76 px (thesis: ~11.6 px)
    one_frame_ns = round(1e9 / 150)
    x = position_from_speed_px(one_frame_ns, t0_ns=0, x0_um=0.0, speed_mm_s=15.0,
                               direction=1, pixel_um=8.5)
    assert x == pytest.approx(100.0 / 8.5, rel=1e-6)
    back = position_from_speed_px(one_frame_ns, t0_ns=0, x0_um=850.0, speed_mm_s=15.0,
                                  direction=-1, pixel_um=8.5)
    assert back == pytest.approx(100.0 - 100.0 / 8.5, rel=1e-6)
    with pytest.raises(ValueError, match="direction"):
        position_from_speed_px(0, t0_ns=0, x0_um=0, speed_mm_s=1, direction=0, pixel_um=1)


def test_stage_position_wins_over_speed_and_is_rounded() -> None:
    hdr = FrameHeader(frame_id=3, timestamp_ns=10**9, focus_index=3, stage_x_um=1000.0,
                      stage_y_um=-17.0)
    assert predicted_position_px(hdr, pixel_um=8.5) == pytest.approx((1000 / 8.5, -2.0))
    stage = SpeedShiftStage(pixel_um=8.5, speed_mm_s=15.0, pass_start=lambda p: (0.0, 0.0, 1))
    (placed,) = stage.process(Frame(hdr, None))  # type: ignore[arg-type]
    assert placed.offset_px == (118, -2)
    # a commanded position that goes back against the pass direction is refused
    back = hdr.model_copy(update={"frame_id": 4, "stage_x_um": 900.0})
    with pytest.raises(FrameError, match="frame_id 4.*against the direction"):
        list(stage.process(Frame(back, None)))  # type: ignore[arg-type]


def test_headers_without_position_use_the_speed_model_of_their_pass() -> None:
    starts = {0: (50.0, 0.0, 1), 1: (300.0, 80.0, -1)}
    stage = SpeedShiftStage(pixel_um=10.0, speed_mm_s=10.0, pass_start=starts.__getitem__)
    out = []
    for k in range(6):
        p = k // 3
        t = 5_000 + k * 10_000_000 + p * 500_000_000  # half a second between passes
        hdr = FrameHeader(frame_id=k, timestamp_ns=t, focus_index=k, pass_index=p)
        out += list(stage.process(Frame(hdr, None)))  # type: ignore[arg-type]
    # 10 mm/s for 10 ms = 100 µm = 10 px per frame; each pass from its own start and way
    assert [p.predicted_px[0] for p in out] == pytest.approx([50, 60, 70, 300, 290, 280])
    assert [p.predicted_px[1] for p in out] == pytest.approx([0, 0, 0, 80, 80, 80])
    with pytest.raises(ValueError, match="frame_id 7"):
        predicted_position_px(FrameHeader(frame_id=7, timestamp_ns=0, focus_index=0),
                              pixel_um=1.0)
