"""Frame feeds: where a scan's frames come from, chosen by configuration alone.

``source.kind`` picks the simulated scanner (default), a GenICam camera (harvesters) or
frames sent over zmq by ``sffscan grab``; ``--source tcp://...`` on the command line
overrides it. Replay of a recording has its own command (``sffscan replay``). Every feed
is a plain iterator of :class:`sffscan.stages.messages.Frame`; generators release their device
or socket when closed (the source stage closes them, on failure too).
"""

from __future__ import annotations

from collections.abc import Iterator
from dataclasses import dataclass, field
from typing import Any

from sffscan.pipeline.completeness import FrameAccount, planned_frames
from sffscan.pipeline.config import ConfigError, ScanConfig
from sffscan.stages.messages import Frame


@dataclass
class FrameFeed:
    """A scan's frames and what the summary needs to know about them."""

    frames: Iterator[Frame]
    description: str
    #: the simulated world (only for ``kind = "sim"``): lets the scan be scored
    world: Any | None = None
    #: frames expected and received: the mosaic is 'complete' only with all of them
    account: FrameAccount = field(default_factory=FrameAccount)


def open_feed(cfg: ScanConfig, *, source: str | None = None) -> FrameFeed:
    """The frame feed of ``cfg`` (``source``, a zmq address, overrides ``source.kind``)."""
    if source is not None:
        if not source.startswith(("tcp://", "ipc://")):
            raise ConfigError(f"--source {source!r}: expected a zmq address tcp://HOST:PORT or "
                              "ipc://PATH")
        return _tcp_feed(cfg, source)
    kind = cfg.source.kind
    if kind == "sim":
        from sffscan.pipeline.sim_source import make_world, simulate_frames
        from sffscan.pipeline.sim_workers import ParallelSimFrames, render_workers

        world = make_world(cfg)
        workers = render_workers(cfg)
        frames: Iterator[Frame] = (ParallelSimFrames(cfg, workers=workers, world=world)
                                   if workers else simulate_frames(cfg, world=world))
        return FrameFeed(frames, "simulated scanner" + (
            f" ({workers} render processes)" if workers else ""), world,
            FrameAccount(planned=planned_frames(cfg)))
    if kind == "camera":
        from sffscan.pipeline.hardware.camera_source import camera_frames

        return FrameFeed(camera_frames(cfg), "GenICam camera",
                         account=FrameAccount(planned=planned_frames(cfg)))
    return _tcp_feed(cfg, cfg.source.address)


def _tcp_feed(cfg: ScanConfig, address: str) -> FrameFeed:
    """Frames from 'sffscan grab': complete only with the count of the sender's end message
    and every frame of the receiver's plan (``camera.frames`` if set, else the scan plan's,
    as a camera would acquire): frame ids past it are not processed. The address is bound
    now: one in use is a ConfigError before anything is created."""
    from sffscan.pipeline.formats.transport_receiver import receive_frames

    planned = cfg.camera.frames if cfg.camera.frames is not None else planned_frames(cfg)
    account = FrameAccount(planned=planned, needs_sender=True)
    return FrameFeed(receive_frames(address, cfg, account=account), f"frames from {address}",
                     account=account)
