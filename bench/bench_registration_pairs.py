"""Registration's pairs farmed out (issue 28): CPU and wall time per frame of the
registration stage with its pairs in 1, 2, 3 threads, interleaved, and where a frame's
time goes (the part that stays in the stage's thread, each lag's pair).

    python bench/bench_registration_pairs.py --rounds 5

The stage runs alone over the frame bank of ``bench_pipeline.py`` (1280 x 1024 uint16,
N = 50, the default configuration's registration: quarter resolution, lags 1, 2 and N),
placed by the speed shift; BLAS and OpenCV on one thread each, as in the scan's
registration worker on 2 cores. With one worker the time of each pair (thread CPU inside
``_pair``) and of the downsampling are split from the rest (the new frame's shared
spectrum, the solve, the bookkeeping): the scaling model (``bench_scaling.py``) takes the
registration worker's time per frame, with its pairs in their own threads on cores of
their own, as the rest plus a band's downsampling plus its slowest pair. The results also
say whether every placed frame is the same for every number of workers (it must be). Not
a test: nothing here asserts.
"""

from __future__ import annotations

import argparse
import json
import statistics
import sys
import tempfile
import time
from collections import defaultdict
from pathlib import Path
from typing import Any

sys.path.insert(0, str(Path(__file__).resolve().parent))
from bench_pipeline import bench_config, frame_bank, load_bank, machine, placed_frames  # noqa: E402
from sffscan.pipeline.opencv_threads import opencv_thread_limit  # noqa: E402
from sffscan.stages.registration import RegistrationStage  # noqa: E402
from threadpoolctl import threadpool_limits  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]


class TimedStage(RegistrationStage):
    """The stage, each pair's thread CPU summed by lag (the frames apart)."""

    def __init__(self, **kw: Any) -> None:
        super().__init__(**kw)
        self.pair_s: dict[int, float] = defaultdict(float)
        self.pairs: dict[int, int] = defaultdict(int)

    def _reduce(self, image: Any) -> Any:
        t = time.thread_time()
        try:
            return super()._reduce(image)
        finally:
            self.pair_s[0] += time.thread_time() - t  # 0: the downsampling

    def _pair(self, old: Any, new: Any, pred: Any, crop: Any, fixed: Any) -> Any:
        t = time.thread_time()
        try:
            return super()._pair(old, new, pred, crop, fixed)
        finally:
            lag = new.index - old.index
            self.pair_s[lag] += time.thread_time() - t
            self.pairs[lag] += 1


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--frames", type=int, default=300)
    ap.add_argument("--rounds", type=int, default=5)
    ap.add_argument("--workers", type=int, nargs="+", default=[1, 2, 3])
    ap.add_argument("--cache", type=Path, default=Path(tempfile.gettempdir()) / "sffscan-bench")
    ap.add_argument("--out", type=Path,
                    default=ROOT / "bench" / "results" / "registration_pairs")
    args = ap.parse_args(argv)
    cfg = bench_config()
    images = load_bank(cfg, frame_bank(args.cache, args.frames), args.frames)
    placed, _ = placed_frames(cfg, images, register=False)
    del images
    o, p = cfg.optics, cfg.processing
    cpu: dict[int, list[float]] = {k: [] for k in args.workers}
    wall: dict[int, list[float]] = {k: [] for k in args.workers}
    split: dict[str, list[float]] = defaultdict(list)
    outs: dict[int, list[Any]] = {}
    n = len(placed)
    with threadpool_limits(limits=1, user_api="blas"), opencv_thread_limit(1):
        for r in range(args.rounds):
            order = args.workers if r % 2 == 0 else args.workers[::-1]
            for k in order:
                stage = TimedStage(n_levels=o.n_levels, scale=p.registration_scale, workers=k)
                c0, w0, t0 = time.process_time(), time.perf_counter(), time.thread_time()
                out = [y for q in placed for y in stage.process(q)] + list(stage.finish())
                c1, w1, t1 = time.process_time(), time.perf_counter(), time.thread_time()
                stage.close(failed=False)
                cpu[k].append(1e3 * (c1 - c0) / n)
                wall[k].append(1e3 * (w1 - w0) / n)
                outs[k] = [(q.header.frame_id, q.offset_px, q.correction_px) for q in out]
                if k == 1:
                    pairs_ms = {lag: 1e3 * s / n for lag, s in stage.pair_s.items() if lag}
                    down = 1e3 * stage.pair_s[0] / n
                    split["downsampling"].append(down)
                    split["rest"].append(1e3 * (t1 - t0) / n - sum(pairs_ms.values()) - down)
                    for lag, v in pairs_ms.items():
                        split[f"lag {lag}"].append(v)
                        split[f"lag {lag} pairs a frame"].append(stage.pairs[lag] / n)
    ref = outs[args.workers[0]]
    same = {k: outs[k] == ref for k in args.workers}
    med = {k: statistics.median(v) for k, v in split.items()}
    lags = sorted(int(k.split()[1]) for k in med if k.startswith("lag") and "pairs" not in k)
    pair_ms = {lag: med[f"lag {lag}"] for lag in lags}
    # a thread a pair; the downsampling in as many bands of rows
    critical = med["rest"] + med["downsampling"] / len(lags) + max(pair_ms.values())
    one = med["rest"] + med["downsampling"] + sum(pair_ms.values())
    command = "python bench/bench_registration_pairs.py " + " ".join(
        sys.argv[1:] if argv is None else argv)
    lines = [f"`{command}`", "",
             f"machine: {machine()}; {n} frames, {args.rounds} rounds interleaved, median "
             "(min-max); the registration stage alone, OpenCV and BLAS on one thread", "",
             "| pair workers | CPU ms/frame | wall ms/frame | frames the same as with "
             f"{args.workers[0]} |", "|---:|---:|---:|---|"]
    for k in args.workers:
        lines.append(f"| {k} | {statistics.median(cpu[k]):.2f} ({min(cpu[k]):.2f}-"
                     f"{max(cpu[k]):.2f}) | {statistics.median(wall[k]):.2f} "
                     f"({min(wall[k]):.2f}-{max(wall[k]):.2f}) | {same[k]} |")
    lines += ["", "Where a frame's time goes with one worker (thread CPU, ms a frame; a pair's "
              "time per frame that has it):", "",
              "| part | ms a frame | pairs a frame |", "|---|---:|---:|",
              f"| downsampling (in bands of rows with pair workers) | "
              f"{med['downsampling']:.2f} | |",
              f"| the rest of the stage's thread: shared spectrum, solve, bookkeeping | "
              f"{med['rest']:.2f} | |"]
    for lag in lags:
        lines.append(f"| pair at lag {lag} | {pair_ms[lag]:.2f} | "
                     f"{med[f'lag {lag} pairs a frame']:.2f} |")
    lines += ["", f"With each pair in a thread on a core of its own (and the downsampling in "
              f"{len(lags)} bands) the stage takes the rest, a band's downsampling and its "
              f"slowest pair: **{critical:.2f} ms a frame** ({med['rest']:.2f} + "
              f"{med['downsampling'] / len(lags):.2f} + {max(pair_ms.values()):.2f}), against "
              f"{one:.2f} in one thread ({critical / one:.3f}x)."]
    text = "\n".join(lines)
    print(text)
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.with_suffix(".md").write_text(text + "\n")
    args.out.with_suffix(".json").write_text(json.dumps({
        "command": command, "machine": machine(), "frames": n, "rounds": args.rounds,
        "cpu_ms_per_frame": cpu, "wall_ms_per_frame": wall, "same_frames": same,
        "split_ms_per_frame": med, "rest_ms": med["rest"],
        "downsampling_ms": med["downsampling"], "pair_ms": pair_ms, "one_thread_ms": one,
        "critical_ms": critical}, indent=1) + "\n")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
