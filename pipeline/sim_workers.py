"""The simulated scanner rendering in worker processes (the same frames, bit for bit).

Rendering a full-size frame takes about 25 ms of CPU (the simulator sets the pace of
``sffscan demo``); frames are independent except for the sensor noise, which one random
generator draws in frame order. Each frame draws a fixed number of values from it (its
``H x W`` noise indices, 16 bits each: ``H * W / 4`` steps of PCG64), so frame ``i``'s
generator is the scan's generator advanced by ``i`` times that: :func:`parallel_sim_frames`
checks this on frame 0 at start (else it renders in this process, as before), then ``K``
workers render frames ``k, k + K, ...`` and the frames are yielded in order, copied out of
their shared-memory slot (so a stage may hold them as long as it likes). The workers are
the process runtime's (:func:`~sffscan.pipeline.worker.worker_main`, like the recorder's
and the stage groups'): a :class:`RenderSource` chain sending into a channel, the same
start, stop order, failure report and death with the main process. The renderer itself
(:func:`sffscan.stages.sim.camera.render_frame`) is not changed.
"""

from __future__ import annotations

import json
import logging
import os
import queue
import time
import weakref
from collections.abc import Iterator
from typing import Any

import numpy as np
from sffscan.pipeline.config import ScanConfig
from sffscan.pipeline.shm_ring import SlotPool, new_spec
from sffscan.pipeline.spawn import (
    START_TIMEOUT_S,
    WAIT_S,
    StopPipes,
    join_or_kill,
    spawn_context,
)
from sffscan.pipeline.wire import decode
from sffscan.pipeline.worker import rebuild_exception, worker_main
from sffscan.stages.frame_source import FrameBuffers, SourceFrames
from sffscan.stages.messages import Frame
from sffscan.stages.protocol import END_OF_STREAM, Stage

log = logging.getLogger(__name__)

#: frames each worker may have rendered ahead of the consumer
AHEAD = 2


def noise_steps(cfg: ScanConfig, *, world: Any = None) -> int | None:
    """PCG64 steps the renderer's noise draws per frame, checked on frame 0; None when
    the renderer draws otherwise (then frames must be rendered in order)."""
    from sffscan.pipeline.sim_source import simulate_frames

    o = cfg.optics
    n = o.height_px * o.width_px
    rng = np.random.default_rng(cfg.source.seed + 1)
    used = _render_one(cfg, 0, rng, world=world, plan=None)
    ref = next(simulate_frames(cfg, world=world))
    if not np.array_equal(used.image, ref.image):
        return None
    state = rng.bit_generator.state
    for steps in ((n + 3) // 4, 0):
        probe = np.random.default_rng(cfg.source.seed + 1)
        _pcg(probe).advance(steps)
        if (probe.bit_generator.state["state"] == state["state"]
                and not state["has_uint32"]):
            return steps
    return None


def _pcg(rng: np.random.Generator) -> np.random.PCG64:
    bg = rng.bit_generator
    if not isinstance(bg, np.random.PCG64):
        raise TypeError(f"expected a PCG64 generator, got {type(bg).__name__}")
    return bg


def _render_one(cfg: ScanConfig, i: int, rng: np.random.Generator, *, world: Any,
                plan: list[Any] | None) -> Frame:
    from sffscan.pipeline.plan import plan_frames
    from sffscan.pipeline.sim_source import header_of, make_optics, make_world, wobble_px
    from sffscan.stages.sim.camera import render_frame

    world = world if world is not None else make_world(cfg)
    pf = plan[i] if plan is not None else next(p for k, p in enumerate(plan_frames(cfg))
                                                 if k == i)
    wx, wy = wobble_px(cfg, pf.travel_px)
    heights = cfg.optics.focus_heights_um()
    image = render_frame(world, x0=pf.x_px + wx, y0=pf.y_px + wy,
                         focus_um=heights[pf.focus_index], optics=make_optics(cfg), rng=rng)
    return Frame(header_of(cfg, pf), image)


class RenderSource(Stage):
    """Source of a render worker: frames ``k, k + workers, ...`` of the scan, each rendered
    with the scan's noise generator advanced to it (``steps`` per frame)."""

    name = "render"

    def __init__(self, cfg: ScanConfig, k: int, workers: int, steps: int) -> None:
        self.cfg, self.k, self.workers, self.steps = cfg, k, workers, steps
        self.world: Any = None
        self.plan: list[Any] = []

    def prepare(self) -> None:
        from sffscan.pipeline.plan import plan_frames
        from sffscan.pipeline.sim_source import make_world

        self.world = make_world(self.cfg)
        self.plan = list(plan_frames(self.cfg))

    def produce(self) -> Iterator[Frame]:
        rng = np.random.default_rng(self.cfg.source.seed + 1)
        _pcg(rng).advance(self.k * self.steps)
        for i in range(self.k, len(self.plan), self.workers):
            frame = _render_one(self.cfg, i, rng, world=self.world, plan=self.plan)
            _pcg(rng).advance((self.workers - 1) * self.steps)
            yield frame


def render_group(cfg: dict[str, Any], k: int, workers: int, steps: int) -> list[Stage]:
    """Worker factory: the render worker ``k`` of ``workers``."""
    return [RenderSource(ScanConfig.model_validate(cfg), k, workers, steps)]


def render_workers(cfg: ScanConfig) -> int:
    """Render workers for a scan: 0 (render here) for small scans or ``execution =
    "threads"``, else one per core but one (2 at least, 8 at most)."""
    from sffscan.pipeline.plan import frame_count
    from sffscan.pipeline.scan_processes import AUTO_MIN_PIXELS

    o, cores = cfg.optics, os.cpu_count() or 1
    if cfg.processing.execution == "threads" or cores < 2:
        return 0
    if (cfg.processing.execution == "auto"
            and frame_count(cfg) * o.width_px * o.height_px < AUTO_MIN_PIXELS):
        return 0
    return max(2, min(cores - 1, 8))


class _Renderers:
    """The render workers, their pool and pipes; :meth:`stop` ends them (idempotent)."""

    def __init__(self, cfg: ScanConfig, workers: int, steps: int) -> None:
        ctx = spawn_context()
        o = cfg.optics
        frame_bytes = o.height_px * o.width_px * np.dtype(o.dtype).itemsize
        spec = new_spec("render", slots=workers * (AHEAD + 2), slot_bytes=frame_bytes,
                         kinds=("frame",))
        sync = (ctx.Lock(), ctx.Semaphore(spec.slots))
        self.workers = workers
        self.pool = SlotPool(spec, sync, create=True)
        self.outs = [ctx.Queue(AHEAD) for _ in range(workers)]
        self.results = ctx.Queue()
        self.stops = StopPipes()
        cj = cfg.model_dump(mode="json")
        self.procs = [ctx.Process(
            target=worker_main, name=f"sffscan-render-{k}", daemon=True,
            args=({"label": f"render-{k}", "factory": render_group, "capacity": AHEAD,
                   "kwargs": {"cfg": cj, "k": k, "workers": workers, "steps": steps}},
                  "stages", [spec.to_json()], [sync], None, self.outs[k], self.results,
                  self.stops.pipe(ctx), os.getpid())) for k in range(workers)]
        self.stopped = False
        try:
            for p in self.procs:
                p.start()
        finally:
            self.stops.started()

    def stop(self) -> None:
        if self.stopped:
            return
        self.stopped = True
        self.stops.set()
        join_or_kill((p.name, p) for p in self.procs)
        self.stops.close()
        self.pool.close()

    def frames(self, buffers: FrameBuffers) -> Iterator[Frame]:
        """The frames in order, each copied out of its render slot into an array of
        ``buffers`` (the frame ring's slot in the process placement: the only copy)."""
        try:
            ended = 0
            i = 0
            while ended < self.workers:
                k = i % self.workers
                item = self._get(k)
                i += 1
                if i == self.workers:
                    self.pool.unlink()  # every worker has attached: it sent through it
                if item is END_OF_STREAM:
                    ended += 1
                    continue
                # a copy: a stage may hold its frames as long as it likes, the slot is free
                image = buffers.empty(item.image.shape, item.image.dtype)
                np.copyto(image, item.image)
                frame = Frame(item.header, image)
                del item
                yield frame
        finally:
            self.stop()

    def _get(self, k: int) -> Any:
        """Worker ``k``'s next item; a failure there raises, naming it."""
        t0 = time.monotonic()
        while True:
            try:
                return decode(self.outs[k].get(timeout=WAIT_S), [self.pool])[0]
            except queue.Empty:
                pass
            while True:
                try:
                    msg = json.loads(self.results.get_nowait())
                except queue.Empty:
                    break
                if msg["kind"] == "error":
                    exc = rebuild_exception(msg)
                    worker = msg["label"].rsplit("-", 1)[-1]
                    raise RuntimeError(f"simulated scanner, render worker {worker}: "
                                       f"{msg['type']}: {msg['message']}") from exc
            proc = self.procs[k]
            if not proc.is_alive():
                raise RuntimeError(f"simulated scanner: render worker {k} exited with code "
                                   f"{proc.exitcode}")
            if time.monotonic() - t0 > START_TIMEOUT_S:
                raise RuntimeError(f"simulated scanner: render worker {k} sent nothing for "
                                   f"{START_TIMEOUT_S:g} s")


class ParallelSimFrames(SourceFrames):
    """Every frame of the simulated scan (as :func:`simulate_frames`), rendered by
    ``workers`` processes that start at once (while the pipeline's own workers start).

    An iterator with ``close()``; the workers also stop when it is garbage. Renders in
    this process when the noise cannot be split (:func:`noise_steps`). The workers' frames
    are copied into arrays of :attr:`buffers` (the process placement binds its frame ring:
    :class:`~sffscan.stages.frame_source.FrameBuffers`).
    """

    def __init__(self, cfg: ScanConfig, *, workers: int, world: Any = None) -> None:
        from sffscan.pipeline.sim_source import simulate_frames

        steps = noise_steps(cfg, world=world)
        buffers = FrameBuffers()
        self._renderers: _Renderers | None = None
        if steps is None:
            log.info("simulated frames rendered in this process (the renderer's noise draws "
                     "cannot be split between workers)")
            super().__init__(simulate_frames(cfg, world=world), buffers)
            return
        self._renderers = _Renderers(cfg, workers, steps)
        self._finalizer = weakref.finalize(self, self._renderers.stop)
        super().__init__(self._renderers.frames(buffers), buffers)

    def close(self) -> None:
        super().close()
        if self._renderers is not None:
            self._renderers.stop()


def parallel_sim_frames(cfg: ScanConfig, *, workers: int) -> Iterator[Frame]:
    """:class:`ParallelSimFrames` as a generator (workers start at the first frame)."""
    it = ParallelSimFrames(cfg, workers=workers)
    try:
        yield from it
    finally:
        it.close()
