"""Complete means complete: the frames a scan should have against those it processed.

A mosaic's status is ``complete`` only when every expected frame was received and
processed; a clean end of stream with fewer is ``incomplete`` (exit code
:data:`sffscan.pipeline.cli.common.EXIT_INCOMPLETE`), with both counts in the mosaic's
attributes (``frames_expected``, ``frames_received``), the summary, ``sffscan info`` and
``replay --resume``.

The expected count is, in this order:

- the count the sender's end message gives (``sffscan scan --source``: the sender knows what
  it acquired); a stream that ends without an end message (the sender went silent) has no
  count and is ``incomplete``;
- for a replay, the recording's ``frames_planned`` attribute (what the live scan expected),
  else the plan of its configuration;
- otherwise ``camera.frames`` for a camera, else the scan plan's frame count.
"""

from __future__ import annotations

from collections.abc import Iterator
from dataclasses import dataclass
from typing import Any

from sffscan.pipeline.config import ScanConfig
from sffscan.stages.messages import Frame


def planned_frames(cfg: ScanConfig) -> int:
    """Frames the configuration plans: ``camera.frames`` for a camera, else the plan's."""
    from sffscan.pipeline.plan import frame_count

    if cfg.source.kind == "camera" and cfg.camera.frames is not None:
        return cfg.camera.frames
    return frame_count(cfg)


@dataclass
class FrameAccount:
    """Frames expected and received by one scan.

    ``planned`` is the configuration's (or the recording's) count; ``sent`` the sender's
    count from its end message; ``needs_sender`` says that only the sender's count can
    make the scan complete (a transport source).
    """

    planned: int | None = None
    sent: int | None = None
    needs_sender: bool = False
    received: int = 0

    @property
    def expected(self) -> int | None:
        if self.sent is not None:
            return self.sent
        return None if self.needs_sender else self.planned

    @property
    def complete(self) -> bool:
        exp = self.expected
        return exp is not None and self.received >= exp

    def counts(self) -> dict[str, Any]:
        exp = self.expected
        return {"frames_expected": exp if exp is not None else self.planned,
                "frames_received": self.received}

    def status(self) -> tuple[str, dict[str, Any]]:
        """``("complete" | "incomplete", counts)``: the mosaic writer's account hook."""
        return ("complete" if self.complete else "incomplete"), self.counts()

    def describe(self) -> str:
        exp = self.expected
        if exp is None:
            extra = f" (the plan has {self.planned})" if self.planned is not None else ""
            return (f"{self.received} frames received; the sender gave no count (no end "
                    f"message){extra}")
        missing = max(exp - self.received, 0)
        return f"{self.received} of {exp} expected frames received and processed" + (
            f", {missing} missing" if missing else "")

    def count(self, frames: Iterator[Frame]) -> Iterator[Frame]:
        """``frames``, counting each one that is taken; closing it closes ``frames``."""
        try:
            for frame in frames:
                self.received += 1
                yield frame
        finally:
            close = getattr(frames, "close", None)
            if close is not None:
                close()
