"""CPU per frame of the registration and focus-measure stages alone, old against new.

    python bench/bench_stage_cpu.py                        # this tree only
    python bench/bench_stage_cpu.py --against /tmp/old     # and an older checkout, interleaved

Each stage runs alone in this process's one thread (BLAS limited to one thread, as the
pipeline does) over the same distinct simulated 1280 x 1024 uint16 frames (the frame bank
of ``bench_pipeline.py``, read into memory first), placed by the speed-shift stage of the
default configuration (N = 50, k = 9, GLVM, registration at quarter resolution). CPU time
is the process's (OpenCV's worker threads included), per frame, median of ``--rounds``
passes; with ``--against``, the other tree's ``stages/registration.py`` and
``stages/focus_measure.py`` run in the same process, alternating pass by pass with this
tree's, so the machine's load hits both alike. Also reported: whether the two give the same
results (registration: integer offsets and the largest difference of the corrections;
focus measure: bit for bit). Not a test: nothing here asserts.
"""

from __future__ import annotations

import argparse
import statistics
import sys
import tempfile
import time
from pathlib import Path
from types import ModuleType
from typing import Any, cast

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from against import load_module  # noqa: E402
from bench_pipeline import bench_config, frame_bank, load_bank, machine, placed_frames  # noqa: E402
from sffscan.pipeline.opencv_threads import opencv_thread_limit, opencv_threads  # noqa: E402
from sffscan.stages import focus_measure, registration  # noqa: E402
from sffscan.stages.focus_measure import FocusMeasureStage  # noqa: E402
from threadpoolctl import threadpool_limits  # noqa: E402


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--frames", type=int, default=300)
    ap.add_argument("--rounds", type=int, default=4)
    ap.add_argument("--against", type=Path, help="another source tree (its stages/ folder)")
    ap.add_argument("--cache", type=Path, default=Path(tempfile.gettempdir()) / "sffscan-bench")
    args = ap.parse_args(argv)
    cfg = bench_config()
    images = load_bank(cfg, frame_bank(args.cache, args.frames), args.frames)
    placed, built = placed_frames(cfg, images, register=False)
    fm_stage = cast(FocusMeasureStage, built["focus_measure"])
    o, p = cfg.optics, cfg.processing
    trees: dict[str, tuple[ModuleType, ModuleType]] = {"this tree": (registration, focus_measure)}
    if args.against is not None:
        trees[str(args.against)] = (
            load_module("_old_registration", args.against / "stages" / "registration.py"),
            load_module("_old_focus_measure", args.against / "stages" / "focus_measure.py"))

    def run(reg_mod: ModuleType, fm_mod: ModuleType) -> tuple[float, float, list[Any], Any]:
        reg = reg_mod.RegistrationStage(n_levels=o.n_levels, scale=p.registration_scale)
        fm = fm_mod.FocusMeasureStage(operator=p.focus_operator, window=p.window,
                                      max_value=o.max_value, margin=p.focus_reach_px,
                                      directions=fm_stage.directions)
        c0 = time.process_time()
        out = [y for q in placed for y in reg.process(q)] + list(reg.finish())
        c1 = time.process_time()
        first = None
        for q in out:
            for f in fm.process(q):
                first = first or (f.image01.copy(), f.focus.copy())
        c2 = time.process_time()
        n = len(placed)
        return 1e3 * (c1 - c0) / n, 1e3 * (c2 - c1) / n, out, first

    times: dict[str, dict[str, list[float]]] = {k: {"reg": [], "fm": []} for k in trees}
    outs: dict[str, Any] = {}
    # OpenCV's threads as in the scan's worker processes (one where the cores are no more
    # than the placement's three processes; before 2026-12-04 left at one per core)
    with threadpool_limits(limits=1, user_api="blas"), opencv_thread_limit(opencv_threads(3)):
        for _ in range(args.rounds):
            for k, (rm, fmm) in trees.items():
                r, f, out, first = run(rm, fmm)
                times[k]["reg"].append(r)
                times[k]["fm"].append(f)
                outs[k] = (out, first)
    print(f"machine: {machine()}; {args.frames} frames, {args.rounds} rounds (median)")
    print("| tree | registration CPU ms/frame | focus measure CPU ms/frame |")
    print("|---|---:|---:|")
    for k, t in times.items():
        print(f"| {k} | {statistics.median(t['reg']):.2f} | {statistics.median(t['fm']):.2f} |")
    if args.against is not None:
        (a, fa), (b, fb) = outs["this tree"], outs[str(args.against)]
        pairs = list(zip(a, b, strict=True))
        same = sum(x.offset_px == y.offset_px for x, y in pairs)
        diff = max(max(abs(x.correction_px[0] - y.correction_px[0]),
                       abs(x.correction_px[1] - y.correction_px[1])) for x, y in pairs)
        print(f"registration: {same}/{len(a)} integer offsets equal, corrections differ by "
              f"at most {diff:.2g} px; focus measure of the first frame bit-identical: "
              f"{bool(np.array_equal(fa[0], fb[0]) and np.array_equal(fa[1], fb[1]))}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
