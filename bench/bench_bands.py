"""Band workers (issue 28): CPU and wall time per frame of the focus measure and the depth
stage with K = 1, 2, 4 band workers, interleaved in one run, blocks compared bit for bit.

    python bench/bench_bands.py                  # 150 frames, 5 rounds, K = 1 2 4
    python bench/bench_bands.py --workers 1 2 4 8
    python bench/bench_bands.py --task-threads --serial --processes

The default configuration (1280 x 1024, N = 50, k = 9, GLVM, the default depth method),
over the distinct simulated frames of ``bench_pipeline.py``'s frame bank (read into memory
first), shifted and registered once; then in every round, for each K in turn (the order
reversed every other round), each frame's focus measure
(:class:`~sffscan.stages.focus_measure.FocusMeasureStage` with ``workers=K``) and depth
stage (:class:`~sffscan.stages.depth_stage.DepthStage` with ``workers=K``), as the focus
and depth worker runs them. Over the steady-state frames (from frame ``N + 10`` on):
CPU ms per frame (the process's CPU time, every thread's: the bands', OpenCV's; BLAS one
thread, OpenCV's threads as the scan's focus worker sets them) and wall ms per frame (the
two stages' throughput on this machine's cores); median of ``--rounds``. Every round
checks that each K's blocks are bit-identical to K = 1's.

``--serial`` adds, for every K > 1, the same K bands run one after another in the caller's
thread (``BandWorkers.run`` swapped for a loop, here only): what splitting the rows costs by
itself (the halos, each band's calls) against what running the bands in threads adds (the
hand-overs, the GIL between the bands' Python code): the share that band *processes*,
which share no interpreter, would not pay.
``--task-threads`` adds every K with the depth stage's bands as tasks in threads
(:class:`~sffscan.stages.bands.BandTaskThreads`, what a scan's band threads are with the
OpenCV backend), which measure the focus of the rows they accumulate; with ``--serial``
also each K > 1 of them one band after another.
``--processes`` adds every K with the depth stage's bands in processes
(:mod:`sffscan.pipeline.band_processes`), which measure the focus of the rows they
accumulate; their CPU is counted with this process's.
``--twin`` adds K = 1 run while a second process does the same work on its own copy of the
frames: the CPU a frame costs on this machine when both cores are busy, whatever shares
them (the reference a band placement's CPU on 2 cores should be read against).
Not a test: nothing here asserts; it writes ``bench/results/bands.json`` and ``.md``.
"""

from __future__ import annotations

import argparse
import json
import multiprocessing as mp
import os
import statistics
import sys
import tempfile
import time
from collections.abc import Callable, Iterator
from concurrent.futures import ThreadPoolExecutor
from contextlib import contextmanager, nullcontext
from pathlib import Path
from typing import Any, cast

sys.path.insert(0, str(Path(__file__).resolve().parent))
from bench_pipeline import bench_config, frame_bank, load_bank, machine, placed_frames  # noqa: E402
from sffscan.pipeline.band_processes import LazyBandProcesses  # noqa: E402
from sffscan.pipeline.heap import keep_freed_memory  # noqa: E402
from sffscan.pipeline.opencv_threads import opencv_thread_limit, opencv_threads  # noqa: E402
from sffscan.stages.bands import BandTaskThreads, BandWorkers  # noqa: E402
from sffscan.stages.depth_stage import DepthStage  # noqa: E402
from sffscan.stages.focus_measure import FocusMeasureStage  # noqa: E402
from sffscan.stages.shared_volume import SharedFocusVolume  # noqa: E402
from sffscan.stages.volume_tasks import run_task  # noqa: E402
from threadpoolctl import threadpool_limits  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]


def same(a: list[Any], b: list[Any]) -> bool:
    """Blocks equal bit for bit (headers and every array)."""
    def eq(u: Any, v: Any) -> bool:
        return (u is None and v is None) or (u is not None and v is not None
                                             and u.dtype == v.dtype and u.shape == v.shape
                                             and u.tobytes() == v.tobytes())
    return len(a) == len(b) and all(
        x.header == y.header and eq(x.height_um, y.height_um) and eq(x.texture, y.texture)
        and eq(x.confidence, y.confidence) and eq(x.uncertainty_um, y.uncertainty_um)
        for x, y in zip(a, b, strict=True))


def handoff_us(n: int = 2000) -> tuple[float, float]:
    """Wall and CPU µs of handing a no-op to a pool thread and waiting for it: what each
    band costs a call beyond its work (and about what each hand-over of the GIL between
    two busy threads costs)."""
    with ThreadPoolExecutor(1) as ex:
        ex.submit(int).result()
        c, w = time.process_time(), time.perf_counter()
        for _ in range(n):
            ex.submit(int).result()
        return 1e6 * (time.perf_counter() - w) / n, 1e6 * (time.process_time() - c) / n


@contextmanager
def bands_in_turn(on: bool) -> Iterator[None]:
    """With ``on``, every band of every call runs in the caller's thread, one after
    another (the stages' band workers keep their rows and halos, not their threads)."""
    if not on:
        yield
        return
    threaded, submit = BandWorkers.run, BandTaskThreads.submit_task

    def serial(self: BandWorkers, fn: Callable[[int, int], Any],
               bands: list[tuple[int, int]]) -> list[Any]:
        return [fn(a, b) for a, b in bands]

    def serial_tasks(self: BandTaskThreads, task: str, params: dict[str, Any],
                     bands: list[tuple[int, int]]) -> int:
        for rows in bands:
            run_task(self.arrays, task, params, rows)
        return 0

    BandWorkers.run = serial  # type: ignore[method-assign]
    BandTaskThreads.submit_task = serial_tasks  # type: ignore[method-assign]
    try:
        yield
    finally:
        BandWorkers.run = threaded  # type: ignore[method-assign]
        BandTaskThreads.submit_task = submit  # type: ignore[method-assign]


def run_stages(placed: list[Any], fm_ref: FocusMeasureStage, depth_ref: DepthStage, k: int,
               steady: int, go: Any = None, kind: str = "threads"
               ) -> tuple[float, float, list[Any]]:
    """The focus measure and depth stages with ``k`` band workers over ``placed``: CPU
    and wall ms per frame from frame ``steady`` on, and the blocks. ``go`` (an Event): stop
    at the first frame it is found cleared (the twin). ``kind``: ``"threads"``, or
    ``"processes"``: the depth stage's band processes (their CPU counted too), each
    measuring the focus of the rows it accumulates."""
    kw = dict(depth_ref.kwargs)
    kw["slack_px"] = kw.pop("row_slack")
    del kw["col_slack"]
    pool: LazyBandProcesses | BandTaskThreads | None = None
    if kind != "threads":
        layout = SharedFocusVolume.shared_layout(
            **depth_ref.kwargs, raw_dtype=placed[0].image.dtype.str)  # type: ignore[arg-type]
        pool = (LazyBandProcesses(k, layout) if kind == "processes"
                else BandTaskThreads(k, layout))
    fm = FocusMeasureStage(operator=fm_ref.operator, window=fm_ref.window,
                           max_value=fm_ref.max_value, margin=fm_ref.margin,
                           directions=fm_ref.directions, workers=k,
                           bands_measure=pool is not None)
    depth = DepthStage(directions=depth_ref.directions, workers=k, band_tasks=pool,
                       **kw)  # type: ignore[arg-type]
    depth.prepare()

    def cpu_s() -> float:  # this process's and the band processes'
        return time.process_time() + (0.0 if pool is None else pool.helpers_cpu_s())

    blocks: list[Any] = []
    c0 = w0 = 0.0
    try:
        for i, q in enumerate(placed):
            if go is not None and not go.is_set():
                break
            if i == steady:
                c0, w0 = cpu_s(), time.perf_counter()
            for f in fm.process(q):
                blocks += depth.process(f)
        c1, w1 = cpu_s(), time.perf_counter()
        blocks += depth.finish()
    finally:
        fm.close(failed=False)
        depth.close(failed=False)
    n = max(1, len(placed) - steady)
    return 1e3 * (c1 - c0) / n, 1e3 * (w1 - w0) / n, blocks


def prepared(cache: Path, frames: int) -> tuple[list[Any], FocusMeasureStage, DepthStage, int]:
    """The bench's placed frames and the reference stages (their settings)."""
    cfg = bench_config()
    cfg.processing.depth_method = type(cfg.processing).model_fields["depth_method"].default
    images = load_bank(cfg, frame_bank(cache, frames), frames)
    placed, built = placed_frames(cfg, images)
    return (placed, cast(FocusMeasureStage, built["focus_measure"]),
            cast(DepthStage, built["depth"]), cfg.optics.n_levels + 10)


def twin_main(cache: str, frames: int, cv_threads: int | None, go: Any, busy: Any,
              idle: Any, ready: Any, stop: Any) -> None:
    """The twin process: the same K = 1 work over its own copy of the frames, pass after
    pass while ``go`` is set (``busy`` set meanwhile, ``idle`` cleared); otherwise blocked
    on ``go``."""
    keep_freed_memory()  # as the scan's focus worker
    placed, fm_ref, depth_ref, steady = prepared(Path(cache), frames)
    idle.set()
    ready.set()
    with threadpool_limits(limits=1, user_api="blas"), opencv_thread_limit(cv_threads):
        while not stop.is_set():
            if not go.wait(0.2):
                continue
            idle.clear()
            busy.set()
            while go.is_set():
                run_stages(placed, fm_ref, depth_ref, 1, steady, go)
            busy.clear()
            idle.set()


class Twin:
    """Another process doing the same K = 1 work (:func:`twin_main`), on while
    :meth:`beside` runs something."""

    def __init__(self, cache: Path, frames: int, cv_threads: int | None) -> None:
        ctx = mp.get_context("spawn")
        self.go, self.busy, self.idle, self.stop = (ctx.Event() for _ in range(4))
        ready = ctx.Event()
        self.proc = ctx.Process(target=twin_main, args=(str(cache), frames, cv_threads,
                                                        self.go, self.busy, self.idle, ready,
                                                        self.stop), daemon=True)
        self.proc.start()
        while not ready.wait(1.0):
            if not self.proc.is_alive():
                raise RuntimeError(f"the twin process exited ({self.proc.exitcode})")

    @contextmanager
    def beside(self) -> Iterator[None]:
        self.go.set()
        if not self.busy.wait(60.0):
            raise RuntimeError("the twin did not start within 60 s")
        try:
            yield
        finally:
            self.go.clear()
            if not self.idle.wait(60.0):  # the twin leaves at its next frame (a few ms)
                raise RuntimeError("the twin did not stop within 60 s")

    def close(self) -> None:
        self.stop.set()
        self.go.clear()
        self.proc.join(10.0)
        if self.proc.is_alive():
            self.proc.kill()


def rounds(n: int, configs: list[str],
           run: Callable[[int, str], tuple[float, float, list[Any]]],
           twin: Twin | None, cpu: dict[str, list[float]], wall: dict[str, list[float]],
           identical: dict[str, list[bool]], ref: str) -> None:
    """``n`` rounds over ``configs``, the order reversed every other round."""
    for r in range(n):
        order = configs if r % 2 == 0 else configs[::-1]
        outs = {}
        for name in order:
            with bands_in_turn(name.endswith("in turn")), \
                    (twin.beside() if twin is not None and name.endswith("twin")
                     else nullcontext()):
                kind = ("processes" if "processes" in name else "task threads"
                        if "task threads" in name else "threads")
                c, w, outs[name] = run(int(name.split()[0]), kind)
            cpu[name].append(c)
            wall[name].append(w)
            print(f"round {r + 1}: K = {name}: {c:.2f} CPU ms/frame, {w:.2f} wall ms/frame",
                  file=sys.stderr, flush=True)
        for name in configs[1:]:
            identical[name].append(same(outs[ref], outs[name]))


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--frames", type=int, default=150, help="frames per run")
    ap.add_argument("--rounds", type=int, default=5, help="interleaved rounds (median)")
    ap.add_argument("--workers", type=int, nargs="+", default=[1, 2, 4],
                    help="band workers K to compare (the first is the reference)")
    ap.add_argument("--cache", type=Path, default=Path(tempfile.gettempdir()) / "sffscan-bench",
                    help="where the rendered frames are kept")
    ap.add_argument("--out", type=Path, default=ROOT / "bench" / "results" / "bands",
                    help="results, without suffix (.md and .json are written)")
    ap.add_argument("--serial", action="store_true",
                    help="also each K > 1 with its bands in turn in one thread")
    ap.add_argument("--processes", action="store_true",
                    help="also each K with the focus measure's and depth stage's bands in "
                         "processes (sffscan.pipeline.band_processes)")
    ap.add_argument("--task-threads", action="store_true",
                    help="also each K with the depth stage's bands as tasks in threads "
                         "(sffscan.stages.bands.BandTaskThreads), each measuring the focus "
                         "of the rows it accumulates")
    ap.add_argument("--twin", action="store_true",
                    help="also K = 1 while another process does the same work (every core "
                         "busy: what this machine's shared caches and memory cost)")
    args = ap.parse_args(argv)
    keep_freed_memory()  # the heap setting of the scan's focus worker
    placed, fm_ref, depth_ref, steady = prepared(args.cache, args.frames)

    def run(k: int, kind: str) -> tuple[float, float, list[Any]]:
        return run_stages(placed, fm_ref, depth_ref, k, steady, kind=kind)

    # configurations: "K" (K band threads) and, with --serial, "K in turn"
    configs = [str(k) for k in args.workers] + (
        [f"{k} in turn" for k in args.workers if k > 1] if args.serial else []) + (
        [f"{k} processes" for k in args.workers] if args.processes else []) + (
        [f"{k} task threads" for k in args.workers] if args.task_threads else []) + (
        [f"{k} task threads in turn" for k in args.workers if k > 1]
        if args.task_threads and args.serial else []) + (
        ["1 beside a twin"] if args.twin else [])
    ref = configs[0]
    cpu: dict[str, list[float]] = {c: [] for c in configs}
    wall: dict[str, list[float]] = {c: [] for c in configs}
    identical: dict[str, list[bool]] = {c: [] for c in configs[1:]}
    load0 = " ".join(f"{v:.1f}" for v in os.getloadavg())
    # OpenCV's own threads as the scan's focus worker has them (one where the cores are no
    # more than the process placement's three processes)
    cv_threads = opencv_threads(3)
    twin = Twin(args.cache, args.frames, cv_threads) if args.twin else None
    try:
        with threadpool_limits(limits=1, user_api="blas"), opencv_thread_limit(cv_threads):
            rounds(args.rounds, configs, run, twin, cpu, wall, identical, ref)
    finally:
        if twin is not None:
            twin.close()
    load1 = " ".join(f"{v:.1f}" for v in os.getloadavg())
    hand_wall, hand_cpu = handoff_us()
    command = "python bench/bench_bands.py " + " ".join(sys.argv[1:] if argv is None else argv)
    c_ref = statistics.median(cpu[ref])
    w_ref = statistics.median(wall[ref])
    ks = ", ".join(map(str, args.workers))
    lines = [f"# Band workers: focus measure + depth stage, K = {ks}",
             "", f"`{command}`", "",
             f"Machine: {machine()}; cores available {len(os.sched_getaffinity(0))}; load "
             f"before / after {load0} / {load1}. Depth method "
             f"{depth_ref.kwargs['method']}, {len(placed)} frames (steady state: the last "
             f"{len(placed) - steady}), {args.rounds} rounds interleaved; median (min-max); "
             f"OpenCV's threads {cv_threads or 'its default'} and the heap setting "
             "(`sffscan.pipeline.heap`) as in the scan's focus worker here.",
             "", f"A no-op handed to a pool thread and waited for: {hand_wall:.0f} µs wall, "
             f"{hand_cpu:.0f} µs CPU (per band and call; each hand-over of the GIL between "
             "two busy threads costs about as much)."]
    if args.serial:
        lines += ["", "`K in turn`: the same K bands, one after another in one thread (the "
                  "split's own cost: halos, each band's calls); K against `K in turn`: what "
                  "the threads add (hand-overs, the GIL shared by the bands' Python code)."]
    lines += ["", "`K`: the focus measure stage's and the focus volume's own band threads "
              "(`BandWorkers`; the focus measure joined from its bands, then split again "
              "for the accumulation): a scan's band threads before 2026-12-04 night, and "
              "still with the torch backend."]
    if args.task_threads:
        lines += ["", "`K task threads`: K bands as tasks in threads "
                  "(`sffscan.stages.bands.BandTaskThreads`), the same tasks on the same "
                  "arrays as band processes, each band measuring the focus of the rows it "
                  "accumulates (one task a frame): a scan's `processing.bands = \"threads\"` "
                  "with the OpenCV backend since 2026-12-04 night."
                  + (" `K task threads in turn`: the same tasks one band after another in "
                     "the caller's thread." if args.serial else "")]
    if args.processes:
        lines += ["", "`K processes`: K bands in K processes sharing the depth stage's "
                  "state (`sffscan.pipeline.band_processes`: the caller's and K - 1 "
                  "helpers, their CPU counted), each band measuring the focus of the rows "
                  "it accumulates (one task a frame, the frame's columns copied once)."]
    if args.twin:
        lines += ["", "`1 beside a twin`: K = 1 while another process does the same work on "
                  "its own copy of the frames (started before, stopped after): both cores "
                  "busy, nothing shared but the machine (its caches, memory bandwidth, the "
                  "hypervisor's scheduling). Its CPU / K=1 is what any placement that keeps "
                  "two cores busy pays here, band threads or band processes alike."]
    lines += ["", "Round by round: the median over rounds of each round's CPU against K=" + ref
              + "'s in the same round (the machine's speed drifts between rounds)."]
    lines += ["", "| K | CPU ms/frame | CPU / K=" + ref + " | round by round (median) | "
              "wall ms/frame | frames/s (these two stages) | speed-up | blocks bit-identical "
              "to K=" + ref + " |",
              "|---|---:|---:|---:|---:|---:|---:|---|"]
    for name in configs:
        c, w = statistics.median(cpu[name]), statistics.median(wall[name])
        ident = ("reference" if name == ref else
                 f"{sum(identical[name])} of {len(identical[name])} rounds")
        paired = statistics.median(a / b for a, b in zip(cpu[name], cpu[ref], strict=True))
        lines.append(f"| {name} | {c:.2f} ({min(cpu[name]):.2f}-{max(cpu[name]):.2f}) | "
                     f"{c / c_ref:.3f} | {paired:.3f} | "
                     f"{w:.2f} ({min(wall[name]):.2f}-{max(wall[name]):.2f})"
                     f" | {1e3 / w:.0f} | {w_ref / w:.2f} | {ident} |")
    text = "\n".join(lines)
    print(text)
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.with_suffix(".md").write_text(text + "\n")
    args.out.with_suffix(".json").write_text(json.dumps(
        {"command": command, "machine": machine(), "frames": len(placed),
         "steady_from": steady, "rounds": args.rounds, "cpu_ms_per_frame": cpu,
         "wall_ms_per_frame": wall, "identical": identical,
         "handoff_us": {"wall": hand_wall, "cpu": hand_cpu}}, indent=1) + "\n")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
