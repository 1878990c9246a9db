"""CPU per frame of the depth stage's accumulation and block reduction, old against new
(issue 28).

    python bench/bench_accumulate.py                       # this tree only
    python bench/bench_accumulate.py --against /tmp/old    # and an older checkout, interleaved

The default configuration (1280 x 1024, N = 50, k = 9, GLVM, the default depth method
unless ``--method``), over the distinct simulated frames of ``bench_pipeline.py``'s frame
bank (read into memory first), registered once; then in every round, for each tree, each
frame's focus measure (this tree's :class:`~sffscan.stages.focus_measure.FocusMeasureStage`,
fresh output arrays per frame as in the scan) and the depth stage
(:class:`~sffscan.stages.depth_stage.DepthStage` of that tree). With ``--against`` the
other tree's depth modules (``stages/depth*.py``, ``focus_volume.py`` and, where it has them,
``accumulate.py``, ``volume_columns.py`` and ``volume_reduce.py``) are loaded under their
own names while its stage is built, so each tree runs its own code; trees alternate pass
by pass (old first in even rounds), so the machine's load hits both alike.

Reported per tree (process CPU time; OpenCV with the focus worker's threads, one on 2
cores; BLAS one thread; median of ``--rounds``), over the steady-state frames only (from
frame ``N + 10`` on: before, no column is complete and every frame is measured whole): the
focus measure's CPU per frame, the depth stage's, and the depth stage's split into the
accumulation (everything but the block reductions; deferred writes applied before a
reduction count here) and the block reduction. Every round checks that the trees' blocks
(those of the end of the pass too) are bit-identical. Not a test: nothing here asserts; it
writes ``bench/results/accumulate_results.json`` and ``.md``.
"""

from __future__ import annotations

import argparse
import json
import statistics
import sys
import tempfile
import time
from collections.abc import Callable
from pathlib import Path
from types import ModuleType
from typing import Any, cast

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from against import load_module  # noqa: E402
from bench_pipeline import bench_config, frame_bank, load_bank, machine, placed_frames  # noqa: E402
from sffscan.pipeline.heap import keep_freed_memory
from sffscan.pipeline.opencv_threads import opencv_thread_limit, opencv_threads  # noqa: E402
from sffscan.stages import depth_stage  # noqa: E402
from sffscan.stages.focus_measure import FocusMeasureStage  # noqa: E402
from threadpoolctl import threadpool_limits  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
#: the depth modules, in an order in which each one's imports come before it
MODULES = ("depth_levels", "depth_harmonics", "depth_peak", "depth_adaptive",
           "fitted_constants", "curve_shape", "depth_uncertainty", "depth_candidates",
           "depth_statistics", "depth_floor", "depth_spc", "depth_choice", "depth_warp",
           "depth_window", "depth_estimators", "depth", "accumulate", "block_depth",
           "volume_tasks", "volume_columns", "volume_reduce", "focus_volume", "depth_stage")
"""The depth modules loaded from the other tree, each after those it imports (until
2026-12-04 ``block_depth`` and ``volume_tasks`` were missing: the other tree's volume ran
this tree's block reduction; until 2026-12-05 ``depth_statistics``, so another tree's
choice ran on this tree's statistics; ``depth_floor``, ``depth_warp`` and ``depth_window``
since 2026-12-05 evening, before which another tree's ran this tree's; ``fitted_constants``
and ``depth_spc`` since they were split from ``depth_uncertainty`` and ``depth_choice``,
2026-12-06: a tree without them has them inside those; likewise ``volume_columns`` and
``volume_reduce``, split from ``focus_volume`` 2026-12-06, ``curve_shape``, split from
``depth_uncertainty`` 2026-12-06, ``depth_adaptive``, split from ``depth_peak``
2026-12-06, and ``depth_estimators``, split from ``depth`` 2026-12-06)."""


def load_tree(root: Path) -> ModuleType:
    """The ``depth_stage`` module of another tree, with that tree's depth modules: each is
    loaded under its package name (so their imports of one another resolve to the same
    tree), then this tree's modules are put back."""
    import sffscan.stages as package

    names = [f"sffscan.stages.{m}" for m in MODULES]
    saved = {n: sys.modules.get(n) for n in names}
    # ``from sffscan.stages import block_depth`` takes the package's attribute first
    attrs = {m: getattr(package, m, None) for m in MODULES}
    loaded: dict[str, ModuleType] = {}
    try:
        for n, m in zip(names, MODULES, strict=True):
            path = root / "stages" / f"{m}.py"
            if path.exists():
                loaded[m] = load_module(n, path)
                setattr(package, m, loaded[m])
    finally:
        for n, mod in saved.items():
            if mod is None:
                sys.modules.pop(n, None)
            else:
                sys.modules[n] = mod
        for m, mod in attrs.items():
            if mod is None:
                if hasattr(package, m):
                    delattr(package, m)
            else:
                setattr(package, m, mod)
    return loaded["depth_stage"]


class Timer:
    """CPU seconds spent in wrapped methods, keyed by the call path of wrapped methods
    (``"reduce"``; ``"reduce/_apply_pending"`` for a call made inside ``reduce``)."""

    def __init__(self) -> None:
        self.seconds: dict[str, float] = {}
        self.active: list[str] = []

    def wrap(self, cls: type, name: str) -> None:
        if name not in vars(cls) or getattr(vars(cls)[name], "_timed", False):
            return
        fn: Callable[..., Any] = vars(cls)[name]
        timer = self

        def timed(*args: Any, **kwargs: Any) -> Any:
            key = "/".join([*timer.active, name])
            timer.active.append(name)
            c0 = time.process_time()
            try:
                return fn(*args, **kwargs)
            finally:
                timer.seconds[key] = timer.seconds.get(key, 0.0) + time.process_time() - c0
                timer.active.pop()

        timed._timed = True  # type: ignore[attr-defined]
        setattr(cls, name, timed)


def differences(a: list[Any], b: list[Any]) -> dict[str, tuple[int, int, float]] | None:
    """Per array of two trees' blocks: pixels that differ (NaN equal to NaN, one NaN
    against a number counts), pixels, the largest finite difference; None where the blocks
    themselves differ (count, position or a missing array)."""
    if len(a) != len(b) or any(x.header != y.header for x, y in zip(a, b, strict=True)):
        return None
    out: dict[str, tuple[int, int, float]] = {}
    for name in ("height_um", "texture", "confidence", "uncertainty_um"):
        n = total = 0
        big = 0.0
        for x, y in zip(a, b, strict=True):
            u, v = getattr(x, name), getattr(y, name)
            if u is None or v is None:
                if (u is None) != (v is None):
                    return None
                continue
            if u.dtype != v.dtype or u.shape != v.shape:
                return None
            same = (u == v) | (np.isnan(u) & np.isnan(v))
            n += int((~same).sum())
            total += u.size
            both = ~same & np.isfinite(u) & np.isfinite(v)
            if both.any():
                big = max(big, float(np.abs(u[both] - v[both]).max()))
        out[name] = (n, total, big)
    return out


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--frames", type=int, default=150)
    ap.add_argument("--rounds", type=int, default=5)
    ap.add_argument("--method", help="depth method (default: the configuration's)")
    ap.add_argument("--cache-bytes", type=int,
                    help="this tree's FocusVolume.cache_bytes (state kept in cache per strip)")
    ap.add_argument("--against", type=Path, help="another source tree (its stages/ folder)")
    ap.add_argument("--cache", type=Path, default=Path(tempfile.gettempdir()) / "sffscan-bench")
    ap.add_argument("--out", type=Path, default=ROOT / "bench" / "results" / "accumulate_results")
    args = ap.parse_args(argv)
    keep_freed_memory()  # the heap setting of the scan's focus worker (pipeline/heap.py)
    cfg = bench_config()
    # the configuration's default method (bench_config's is SPC), unless told
    cfg.processing.depth_method = args.method or type(
        cfg.processing).model_fields["depth_method"].default
    images = load_bank(cfg, frame_bank(args.cache, args.frames), args.frames)
    placed, built = placed_frames(cfg, images)
    fm_stage = cast(FocusMeasureStage, built["focus_measure"])
    del images
    depth = cast(depth_stage.DepthStage, built["depth"])
    kwargs = dict(depth.kwargs, directions=depth.directions)
    kwargs["slack_px"] = kwargs.pop("row_slack")
    del kwargs["col_slack"]
    n_levels = cfg.optics.n_levels
    steady = n_levels + 10
    trees: dict[str, ModuleType] = {"this tree": depth_stage}
    if args.cache_bytes:
        depth_stage.FocusVolume.cache_bytes = args.cache_bytes
    if args.against is not None:
        trees[str(args.against)] = load_tree(args.against)
    timers = {k: Timer() for k in trees}
    for k, mod in trees.items():
        fv_cls = mod.FocusVolume  # type: ignore[attr-defined]
        for name in ("reduce", "_apply_pending"):
            timers[k].wrap(fv_cls, name)

    def run(key: str) -> tuple[dict[str, float], list[Any]]:
        mod = trees[key]
        stage = mod.DepthStage(**kwargs)  # type: ignore[attr-defined]
        stage.prepare()
        fm_stage._pass = None
        fm_stage._prev_x = {}
        t = timers[key]
        t.seconds = {}
        cpu_fm = cpu_depth = 0.0
        blocks: list[Any] = []
        for i, q in enumerate(placed):
            if i == steady:
                t.seconds = {}
            c0 = time.process_time()
            ff = list(fm_stage.process(q))
            c1 = time.process_time()
            for f in ff:
                blocks += stage.process(f)
            c2 = time.process_time()
            if i >= steady:
                cpu_fm += c1 - c0
                cpu_depth += c2 - c1
        # deferred writes applied inside a reduction count as accumulation (those applied
        # when the deferral is full are outside it already)
        reduce_s = t.seconds.get("reduce", 0.0) - t.seconds.get("reduce/_apply_pending", 0.0)
        blocks += stage.finish()
        n = len(placed) - steady
        ms = {"focus measure": 1e3 * cpu_fm / n, "depth": 1e3 * cpu_depth / n,
              "accumulation": 1e3 * (cpu_depth - reduce_s) / n,
              "reduction": 1e3 * reduce_s / n}
        return ms, blocks

    times: dict[str, dict[str, list[float]]] = {k: {} for k in trees}
    identical: list[bool] = []
    differ: dict[str, tuple[int, int, float]] = {}
    # OpenCV's own threads as the scan's focus worker has them (one where the cores are no
    # more than the process placement's three processes; before 2026-12-04 this benchmark
    # left OpenCV's default, a thread per core, which the worker does not run with)
    with threadpool_limits(limits=1, user_api="blas"), opencv_thread_limit(opencv_threads(3)):
        for r in range(args.rounds):
            order = list(trees) if r % 2 == 0 else list(trees)[::-1]
            outs = {}
            for k in order:
                ms, blocks = run(k)
                outs[k] = blocks
                for name, v in ms.items():
                    times[k].setdefault(name, []).append(v)
            if args.against is not None:
                a, b = outs.values()
                diff = differences(a, b)
                identical.append(diff is not None and not any(n for n, _, _ in diff.values()))
                if diff is not None:
                    differ = diff
    method = kwargs["method"]
    command = "python bench/bench_accumulate.py " + " ".join(sys.argv[1:] if argv is None
                                                             else argv)
    head = (f"`{command}`\n\nmachine: {machine()}; depth method {method}, {len(placed)} frames "
            f"(steady state: the last {len(placed) - steady}), {args.rounds} rounds; "
            "CPU ms per frame, median (min-max)")
    cols = list(next(iter(times.values())))
    lines = [head, "", "| tree | " + " | ".join(cols) + " |",
             "|---|" + "---:|" * len(cols)]
    for k, t in times.items():
        cells = [f"{statistics.median(v):.2f} ({min(v):.2f}-{max(v):.2f})"
                 for v in t.values()]
        lines.append(f"| {k} | " + " | ".join(cells) + " |")
    if identical:
        lines += ["", f"blocks bit-identical to the other tree in {sum(identical)} of "
                  f"{len(identical)} rounds"]
        if differ and not all(identical):
            lines += ["", "where they differ (the last round; the same frames every round): "
                      + "; ".join(f"{name} {n} of {total} px (largest difference {big:.4g})"
                                  for name, (n, total, big) in differ.items())]
    text = "\n".join(lines)
    print(text)
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.with_suffix(".md").write_text(text + "\n")
    args.out.with_suffix(".json").write_text(json.dumps(
        {"command": command, "machine": machine(), "method": method, "frames": len(placed),
         "steady_from": steady, "rounds": args.rounds, "cpu_ms_per_frame": times,
         "identical_rounds": identical},
        indent=1) + "\n")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
