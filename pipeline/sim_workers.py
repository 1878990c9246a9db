"""The simulated scanner rendering in worker processes (the same frames, bit for bit).

Rendering a full-size frame takes about 25 ms of CPU (the simulator sets the pace of
``sffscan demo``); frames are independent except for the sensor noise, which one random
generator draws in frame order. Each frame draws a fixed number of values from it (its
``H x W`` noise indices, 16 bits each: ``H * W / 4`` steps of PCG64), so frame ``i``'s
generator is the scan's generator advanced by ``i`` times that: :func:`parallel_sim_frames`
checks this on frame 0 at start (else it renders in this process, as before), then ``K``
workers render frames ``k, k + K, ...`` into their slots of a shared-memory pool and the
frames are yielded in order, copied out of the slot (so a stage may hold them as long as
it likes). The renderer itself (:func:`sffscan.stages.sim.camera.render_frame`) is not
changed.
"""

from __future__ import annotations

import contextlib
import json
import logging
import os
import queue
import threading
import weakref
from collections.abc import Iterator
from typing import Any

import numpy as np
from sffscan.pipeline.config import ScanConfig
from sffscan.pipeline.shm_ring import PoolSpec, PoolStopped, SlotPool, new_spec
from sffscan.pipeline.spawn import (
    START_TIMEOUT_S,
    WAIT_S,
    StopPipes,
    helper_start,
    join_or_kill,
    spawn_context,
    watch_stop,
)
from sffscan.stages.messages import Frame, FrameHeader

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


def render_worker(cfg_json: dict[str, Any], k: int, workers: int, steps: int,
                  spec: dict[str, Any], sync: tuple[Any, Any], out: Any, control: Any,
                  parent: int) -> None:
    """Worker process: renders frames k, k + workers, ... into the pool, in order."""
    helper_start(parent)
    from sffscan.pipeline.plan import plan_frames
    from sffscan.pipeline.sim_source import make_world

    cfg = ScanConfig.model_validate(cfg_json)
    pool = SlotPool(PoolSpec.from_json(spec), sync, create=False)
    stop, done = threading.Event(), threading.Event()
    watch_stop(control, parent, stop.set, done)
    world = make_world(cfg)
    plan = list(plan_frames(cfg))
    rng = np.random.default_rng(cfg.source.seed + 1)
    _pcg(rng).advance(k * steps)
    try:
        for i in range(k, len(plan), workers):
            frame = _render_one(cfg, i, rng, world=world, plan=plan)
            _pcg(rng).advance((workers - 1) * steps)
            slot = pool.acquire(stop.is_set)
            view = pool.array(slot, offset=0, shape=frame.image.shape,
                              dtype=frame.image.dtype.str)
            np.copyto(view, frame.image)
            pool.incref(slot)  # the message's count; ``view`` releases ours
            msg = json.dumps({"i": i, "slot": slot, "h": frame.header.model_dump(mode="json"),
                              "dtype": frame.image.dtype.str,
                              "shape": list(frame.image.shape)})
            del view
            while True:
                if stop.is_set():
                    return
                try:
                    out.put(msg, timeout=WAIT_S)
                    break
                except queue.Full:
                    continue
        out.put(json.dumps({"end": True}))
    except PoolStopped:
        return
    except BaseException as exc:  # noqa: BLE001 - the consumer reports it
        with contextlib.suppress(Exception):
            out.put(json.dumps({"error": f"{type(exc).__name__}: {exc}"}), timeout=5)
    finally:
        done.set()
        if stop.is_set():
            out.cancel_join_thread()  # nobody reads what is left
        pool.close()


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
        spec = new_spec("render", slots=workers * (AHEAD + 2), slot_bytes=frame_bytes)
        sync = (ctx.Lock(), ctx.Semaphore(spec.slots))
        self.workers = workers
        self.pool = SlotPool(spec, sync, create=True)
        self.outs = [ctx.Queue(AHEAD) for _ in range(workers)]
        self.stops = StopPipes()
        self.procs = [ctx.Process(target=render_worker, name=f"sffscan-render-{k}",
                                  daemon=True,
                                  args=(cfg.model_dump(mode="json"), k, workers, steps,
                                        spec.to_json(), sync, self.outs[k],
                                        self.stops.pipe(ctx), os.getpid()))
                      for k in range(workers)]
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

    def frames(self) -> Iterator[Frame]:
        try:
            ended = 0
            i = 0
            while ended < self.workers:
                k = i % self.workers
                msg = _get(self.outs[k], self.procs[k], first=i < self.workers)
                if "error" in msg:
                    raise RuntimeError(f"simulated scanner, render worker {k}: "
                                       f"{msg['error']}")
                i += 1
                if "end" in msg:
                    ended += 1
                    continue
                if i == self.workers:
                    self.pool.unlink()  # every worker has attached: it rendered into it
                view = self.pool.array(msg["slot"], offset=0, shape=tuple(msg["shape"]),
                                       dtype=msg["dtype"])
                image = view.copy()
                del view
                yield Frame(FrameHeader.model_validate(msg["h"]), image)
        finally:
            self.stop()


class ParallelSimFrames:
    """Every frame of the simulated scan (as :func:`simulate_frames`), rendered by
    ``workers`` processes that start at once (while the pipeline's own workers start).

    An iterator with ``close()``; the workers also stop when it is garbage. Renders in
    this process when the noise cannot be split (:func:`noise_steps`).
    """

    def __init__(self, cfg: ScanConfig, *, workers: int, world: Any = None) -> None:
        from sffscan.pipeline.sim_source import simulate_frames

        steps = noise_steps(cfg, world=world)
        self._renderers: _Renderers | None = None
        if steps is None:
            log.info("simulated frames rendered in this process (the renderer's noise draws "
                     "cannot be split between workers)")
            self._it: Iterator[Frame] = simulate_frames(cfg, world=world)
            return
        self._renderers = _Renderers(cfg, workers, steps)
        self._finalizer = weakref.finalize(self, self._renderers.stop)
        self._it = self._renderers.frames()

    def __iter__(self) -> Iterator[Frame]:
        return self

    def __next__(self) -> Frame:
        return next(self._it)

    def close(self) -> None:
        close = getattr(self._it, "close", None)
        if close is not None:
            close()
        if self._renderers is not None:
            self._renderers.stop()


def parallel_sim_frames(cfg: ScanConfig, *, workers: int) -> Iterator[Frame]:
    """:class:`ParallelSimFrames` as a generator (workers start at the first frame)."""
    it = ParallelSimFrames(cfg, workers=workers)
    try:
        yield from it
    finally:
        it.close()


def _get(q: Any, proc: Any, *, first: bool) -> dict[str, Any]:
    waited = 0.0
    while True:
        try:
            return dict(json.loads(q.get(timeout=WAIT_S)))
        except queue.Empty:
            waited += WAIT_S
            if not proc.is_alive():
                raise RuntimeError(f"simulated scanner: render worker exited with code "
                                   f"{proc.exitcode}") from None
            if not first and waited > START_TIMEOUT_S:
                raise RuntimeError("simulated scanner: a render worker stopped answering "
                                   f"for {START_TIMEOUT_S:g} s") from None
