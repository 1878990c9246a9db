r"""The scan pipeline in processes: which stages run where, and the shared-memory rings.

    main:    source -> speed_shift --ch--> [registration] --ch--> [focus_measure -> depth]
                    \-> recorder (own process, reads the same frame slots)  |     |     |
    main:    mosaic <-------------------------------------------------------+-----+--ch-/
    main:    viewer <--relay channel-- placed frames, focus frames (1 in frame_step), blocks

The live viewer runs in the main process (a relayed sink): the Rerun recording stream it
logs to is created there by ``--viewer`` before the scan (spawn, serve, connect, save) and
a served view stays up there after the scan until Enter, which a worker process could not
do without outliving the pipeline; the viewer's own work is small (it logs one frame in
``frame_step`` and reduced blocks: bench/bench_viz.py), so the main process's GIL is not
the price. Its placed frames come by reference (the frame slots the recorder reads, no
copy), the focus frames it logs are copied into a small pool of their own, the depth
blocks into the block ring.

The split follows the measured CPU per frame of the stages (bench/results.md: registration
4.2 ms, focus measure 2.4 ms, depth 3.4 ms, mosaic 0.5 ms, source + speed shift 0.2 ms on
the 2-core dev VM): registration, and focus measure with depth, are the two heavy halves,
each in its own worker; the source and the mosaic writer stay in the main process (the
writer may be a mosaic reopened to resume). The focus measure and depth share a worker
because the focus frames are 2 float32 planes of every new column (5 MB a frame at full
size): moving them between processes would cost more than it saves on 2 cores.

Ring sizes (:func:`ring_plan`) — the bound on shared memory, whatever the scan length:

- frame ring: ``N + 40 + 2 * C + R`` slots of ``H * W * bytes_per_pixel`` (N focus
  levels; C the channel capacity, ``processing.queue_capacity``; ``R = 2 * Cr + 8`` with
  a recorder of channel capacity ``Cr = min(its queue, 32)``, else 0): the registration
  holds N + 2 frames (its sliding window), every queue and channel on the way holds its
  capacity, and each stage one in hand;
- block ring: ``2 * C + 8`` slots of ``4 * (H + 2 * slack) * block_columns * 4`` bytes
  (depth blocks: height, texture, confidence, uncertainty, float32).

A relayed sink (the viewer, channel and queue capacity ``Cv = min(its capacity, 16)``)
holds at most ``V = 3 * (4 + 1) + 2 * Cv + P + 2`` items (:func:`relay_holdings`; ``P``
= 16, the channel's reserve for the sink's precious items, 0 without them): ``V`` more
frame slots, ``V`` more block slots when it taps the depth blocks, and a pool of 8 slots
of ``2 * H * W * 4`` bytes for the focus frames it logs.

At the default optics (1280 x 1024, 10-bit, N = 50, C = 8) that is 106 frame slots
(278 MB), 178 (467 MB) with the recorder, plus 24 block slots (51 MB); the viewer adds 65
frame slots (170 MB), 65 block slots (138 MB) and 84 MB of focus slots.
"""

from __future__ import annotations

import logging
import os
from typing import Any

import numpy as np
from sffscan.pipeline.config import ScanConfig
from sffscan.pipeline.parallel import ProcessPlacement
from sffscan.pipeline.plan import frame_count
from sffscan.pipeline.relays import RELAY_LOCAL_CAPACITY, Relay, relay_of, relayed_sinks
from sffscan.pipeline.worker import HostedSink, WorkerGroup
from sffscan.stages.protocol import Sink, Stage

log = logging.getLogger(__name__)

#: ``execution = "auto"`` runs processes for scans of at least this many pixels
AUTO_MIN_PIXELS = 2e8
#: a hosted sink's channel holds at most this many frames
HOSTED_SINK_CAPACITY = 32


def _cfg(cfg: dict[str, Any]) -> ScanConfig:
    return ScanConfig.model_validate(cfg)


def registration_group(cfg: dict[str, Any]) -> list[Stage]:
    """Worker factory: the registration stage."""
    from sffscan.pipeline.measuring import measure_stages

    return measure_stages(_cfg(cfg), only=("registration",))


def focus_group(cfg: dict[str, Any]) -> list[Stage]:
    """Worker factory: the focus measure and depth stages."""
    from sffscan.pipeline.measuring import measure_stages

    return measure_stages(_cfg(cfg), only=("focus_measure", "depth"))


def hosted_recorder(cfg: dict[str, Any], path: str, codec: str, page_cache: bool = False
                    ) -> Sink:
    """Worker factory: the raw-stream recorder, in its own process."""
    from sffscan.pipeline.formats.recorder_sink import recorder_sink

    return recorder_sink(_cfg(cfg), path, codec=codec, page_cache=page_cache)


def _hostable(sink: Sink) -> HostedSink | None:
    """The recorder as a sink for its own process (its writer creates the recording at
    the first frame, so the one built here is never opened); None for other sinks."""
    from sffscan.pipeline.formats.recorder_sink import RecorderSink

    if isinstance(sink, RecorderSink) and sink.writer.group is None:
        w = sink.writer
        return HostedSink(sink.name, tuple(sink.taps), min(sink.capacity, HOSTED_SINK_CAPACITY),
                          sink.policy, hosted_recorder,
                          {"path": str(w.path), "codec": w.codec,
                           "page_cache": w.page_cache})
    return None


#: slots of the pool for the focus frames a relayed sink (the viewer) gets: a forwarder
#: that finds them all held drops its focus frame (counted), the pipeline goes on
RELAY_FOCUS_SLOTS = 8


def relay_holdings(relay: Relay) -> int:
    """Items a relayed sink holds at most (each in at most one slot of a pool): the queue
    and the one in hand of its forwarder in each of 3 processes (head, registration,
    focus), its channel (and its reserve), the one the receiver has in hand, its queue and
    the one in the sink's hand."""
    return 3 * (RELAY_LOCAL_CAPACITY + 1) + 2 * relay.capacity + relay.reserve + 2


def ring_plan(cfg: ScanConfig, hosted: list[HostedSink], relays: list[Relay] | None = None,
              ) -> list[tuple[str, int, int, tuple[str, ...]]]:
    """(label, slots, slot_bytes, message kinds) of the pools (module docstring)."""
    o, p, m = cfg.optics, cfg.processing, cfg.motion
    c = p.queue_capacity
    relays = relays or []
    frame_bytes = o.height_px * o.width_px * np.dtype(o.dtype).itemsize
    frames = (o.n_levels + 40 + 2 * c + sum(2 * k.capacity + 8 for k in hosted)
              + sum(relay_holdings(r) for r in relays))
    slack = int(2 * (m.wobble_along_px + m.wobble_across_px)) + 8
    block_bytes = 4 * (o.height_px + 2 * slack) * p.block_columns * 4 + 4 * 64
    blocks = 2 * c + 8 + sum(relay_holdings(r) for r in relays if "depth" in r.taps)
    plan = [("frames", frames, frame_bytes, ("frame", "placed")),
            ("blocks", blocks, block_bytes, ("block",))]
    if any("focus_measure" in r.taps for r in relays):
        # a focus frame's unit-scaled image and focus measure, (H, w <= W) float32 each
        plan.append(("focus", RELAY_FOCUS_SLOTS, 2 * (o.height_px * o.width_px * 4 + 64),
                     ("focus",)))
    return plan


def use_processes(cfg: ScanConfig, sinks: list[Sink]) -> bool:
    """Whether ``processing.execution`` (``auto`` resolved) asks for processes."""
    mode = cfg.processing.execution
    if mode == "threads":
        return False
    if mode == "auto":  # any sink runs in process mode (the viewer relayed, issue 12)
        o = cfg.optics
        big = frame_count(cfg) * o.width_px * o.height_px >= AUTO_MIN_PIXELS
        return big and (os.cpu_count() or 1) >= 2
    return True


def process_placement(cfg: ScanConfig, stages: list[Stage], *,
                      sinks: list[Sink]) -> ProcessPlacement:
    """Where the scan's stages (:func:`sffscan.pipeline.wiring.build_stages`) run in
    processes: the registration in a worker, the focus measure and depth in another
    (built there from ``cfg``); the stages up to the speed shift (the optics corrections of
    the frames included) and after the depth stage (the corrections of the blocks, the
    mosaic) in the main process. The recorder runs in its own process; other sinks (the
    live viewer) run in the main process, fed by the processes that run their taps
    (relayed, :class:`~sffscan.pipeline.relays.Relay`).
    """
    names = [s.name for s in stages]
    head = names[:names.index("speed_shift") + 1]
    tail = names[names.index("depth") + 1:]
    cj = cfg.model_dump(mode="json")
    groups = []
    if "registration" in names:
        groups.append(WorkerGroup("registration", registration_group, {"cfg": cj},
                                  ("registration",)))
    groups.append(WorkerGroup("focus", focus_group, {"cfg": cj}, ("focus_measure", "depth"),
                              spawns=cfg.processing.bands == "processes"
                              and cfg.processing.band_workers() > 1))
    hosted: list[HostedSink] = []
    local: list[Sink] = []
    for k in sinks:
        h = _hostable(k)
        if h is not None:
            hosted.append(HostedSink(h.name, h.taps, h.capacity, h.policy, h.factory,
                                     {**h.kwargs, "cfg": cj}))
        else:
            local.append(k)
    relays = [relay_of(k) for k in relayed_sinks(local, head, tail)]
    return ProcessPlacement(groups, ring_plan(cfg, hosted, relays), hosted)
