"""Speed-based shift: where each frame sits in world pixels before registration.

The commanded stage position of a frame, when the source gives one, is the world
position of the frame's first pixel. Without it, the position follows from the constant
stage speed and the frame's time stamp. Either way the result is a fractional position in
world pixels and its rounding to integers (frames are placed by whole pixels).
"""

from __future__ import annotations

from collections.abc import Callable, Iterator

from sffscan.stages.messages import Frame, FrameError, FrameHeader, PlacedFrame
from sffscan.stages.protocol import Stage


def position_from_speed_px(
    timestamp_ns: int,
    *,
    t0_ns: int,
    x0_um: float,
    speed_mm_s: float,
    direction: int,
    pixel_um: float,
) -> float:
    """World x position of a frame from the stage speed, px.

    Parameters
    ----------
    timestamp_ns : int
        Frame time stamp, ns.
    t0_ns : int
        Time stamp at which the stage was at ``x0_um``, ns.
    x0_um : float
        Stage position at ``t0_ns``, µm.
    speed_mm_s : float
        Stage speed, mm/s (> 0).
    direction : {+1, -1}
        Direction of travel along x.
    pixel_um : float
        Object-side pixel scale, µm/px.
    """
    if direction not in (1, -1):
        raise ValueError(f"direction must be +1 or -1, got {direction}")
    travel_um = speed_mm_s * 1000.0 * (timestamp_ns - t0_ns) * 1e-9
    return (x0_um + direction * travel_um) / pixel_um


def predicted_position_px(
    header: FrameHeader,
    *,
    pixel_um: float,
    speed_model: tuple[int, float, float, int] | None = None,
    y_default_um: float = 0.0,
) -> tuple[float, float]:
    """Fractional world (x, y) position of a frame's first pixel, px.

    ``speed_model`` = (t0_ns, x0_um, speed_mm_s, direction) is used when the header has no
    stage position; a header without either raises ``ValueError`` naming the frame.
    """
    if header.stage_x_um is not None:
        x = header.stage_x_um / pixel_um
    elif speed_model is not None:
        t0, x0, v, d = speed_model
        x = position_from_speed_px(header.timestamp_ns, t0_ns=t0, x0_um=x0, speed_mm_s=v,
                                   direction=d, pixel_um=pixel_um)
    else:
        raise ValueError(f"frame_id {header.frame_id}: no stage_x_um and no speed model")
    y_um = header.stage_y_um if header.stage_y_um is not None else y_default_um
    return x, y_um / pixel_um


class SpeedShiftStage(Stage):
    """Places each frame at the integer world position predicted from stage or speed.

    Frames that carry a commanded stage position are placed by it. Frames without one use
    the speed model of their pass: the pass is taken to start at its planned position
    (``pass_start``) at the time stamp of its first frame, and to move at constant speed in
    the pass's direction. Commanded positions that move against the pass's direction stop
    the scan with an error naming the frame (the configuration and the source disagree).

    Parameters
    ----------
    pixel_um : float
        Object-side pixel scale, µm/px.
    speed_mm_s : float
        Stage speed, mm/s.
    pass_start : callable
        Pass index -> (x px, y px, direction) of the pass's first frame.
    """

    name = "speed_shift"

    def __init__(self, *, pixel_um: float, speed_mm_s: float,
                 pass_start: Callable[[int], tuple[float, float, int]]) -> None:
        self.pixel_um = pixel_um
        self.speed_mm_s = speed_mm_s
        self.pass_start = pass_start
        self._pass: int | None = None
        self._t0 = 0
        self._last_x: float | None = None

    def process(self, item: Frame) -> Iterator[PlacedFrame]:
        h = item.header
        if h.pass_index != self._pass:
            self._pass, self._t0, self._last_x = h.pass_index, h.timestamp_ns, None
        x0, y0, direction = self.pass_start(h.pass_index)
        model = (self._t0, x0 * self.pixel_um, self.speed_mm_s, direction)
        x, y = predicted_position_px(h, pixel_um=self.pixel_um, speed_model=model,
                                     y_default_um=y0 * self.pixel_um)
        if self._last_x is not None and (x - self._last_x) * direction < -1e-6:
            raise FrameError(
                f"frame_id {h.frame_id}: stage_x_um moves {'-' if direction > 0 else '+'}x, "
                f"against the direction of pass {h.pass_index} in the configuration")
        self._last_x = x
        yield PlacedFrame(h, item.image, (x, y), (round(x), round(y)))
