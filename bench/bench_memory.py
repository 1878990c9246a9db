"""Peak memory against scan length (issue 28: "memory flat in scan length").

    python bench/bench_memory.py                      # 300, 1200, 2400 frames; ~1 min

The default scan (``bench_scaling.py``'s: 1280 x 1024 uint16, N = 50, GLVM k = 9, the
default depth method, registration on), frames from memory (the bench's 600-frame bank,
cycled for longer scans), mosaic on ``--outputs`` (tmpfs by default: the disk is not what
is measured), in processes and in threads. Each scan runs in a fresh process; every
process of it (main and workers) writes its peak resident set (``VmHWM`` of
/proc/self/status, which, unlike ``ru_maxrss``, does not carry the parent's peak over a
spawn's fork and exec) when it exits. The main process's figure includes the frame bank
held in memory (about 1.5 GB; the same in every run). Writes
``bench/results/memory.md``. Not a test: nothing here asserts.
"""

from __future__ import annotations

import argparse
import atexit
import json
import os
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE))


def _write_peak() -> None:
    """At exit, this process's peak resident set (kB) into ``$SFFSCAN_BENCH_HWM/<pid>``
    (every process of a scan: the spawned workers import this module too)."""
    folder = os.environ.get("SFFSCAN_BENCH_HWM")
    if folder:
        with open("/proc/self/status", encoding="ascii") as fh:
            kb = next(line.split()[1] for line in fh if line.startswith("VmHWM"))
        Path(folder, str(os.getpid())).write_text(kb)


atexit.register(_write_peak)


def run(frames: int, mode: str, bank: Path, outputs: Path) -> dict[str, object]:
    """One scan of ``frames`` frames in this process (a fresh one)."""
    os.sched_setaffinity(0, sorted(os.sched_getaffinity(0))[:2])
    from bench_pipeline import load_bank, replay_frames
    from bench_scaling import scan_config
    from sffscan.pipeline.wiring import run_scan

    cfg = scan_config(mode)
    images = load_bank(cfg, bank, 600)
    with tempfile.TemporaryDirectory(dir=outputs) as tmp:
        rep = run_scan(cfg, frames=replay_frames(cfg, [images[i % len(images)]
                                                       for i in range(frames)]),
                       output=Path(tmp) / "m.zarr", progress=False)
    return {"frames": rep.frames, "method": cfg.processing.depth_method}


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--lengths", default="300,1200,2400", help="scan lengths, frames")
    ap.add_argument("--outputs", type=Path, default=Path("/dev/shm/sffscan-bench-memory"),
                    help="folder the mosaics are written in (removed after)")
    ap.add_argument("--cache", type=Path, default=Path(tempfile.gettempdir()) / "sffscan-bench",
                    help="where the rendered frame bank is kept")
    ap.add_argument("--out", type=Path, default=HERE / "results" / "memory.md")
    ap.add_argument("--case", help=argparse.SUPPRESS)
    args = ap.parse_args(argv)
    if args.case:
        c = json.loads(args.case)
        print(json.dumps(run(c["frames"], c["mode"], Path(c["bank"]), Path(c["outputs"]))))
        return 0
    from bench_pipeline import frame_bank, machine

    t0 = time.perf_counter()
    bank = frame_bank(args.cache, 600)
    args.outputs.mkdir(parents=True, exist_ok=True)
    rows = []
    try:
        for mode in ("processes", "threads"):
            for n in (int(v) for v in args.lengths.split(",")):
                peaks = Path(tempfile.mkdtemp())
                case = {"frames": n, "mode": mode, "bank": str(bank),
                        "outputs": str(args.outputs)}
                done = subprocess.run([sys.executable, __file__, "--case", json.dumps(case)],
                                      capture_output=True, text=True, check=False,
                                      env={**os.environ, "SFFSCAN_BENCH_HWM": str(peaks)})
                if done.returncode != 0:
                    raise SystemExit(f"{mode}, {n} frames failed:\n{done.stderr[-3000:]}")
                got = json.loads(done.stdout.strip().splitlines()[-1])
                mb = sorted((int(p.read_text()) // 1024 for p in peaks.iterdir()),
                            reverse=True)
                shutil.rmtree(peaks)
                rows.append((mode, got["frames"], got["method"], mb))
                print(f"{mode}, {got['frames']} frames: peak MB {mb}", file=sys.stderr,
                      flush=True)
    finally:
        shutil.rmtree(args.outputs, ignore_errors=True)
    lines = [f"# Peak memory against scan length ({time.strftime('%Y-%m-%d %H:%M')})", "",
             f"Machine: {machine()}.", "",
             f"Command: `{' '.join(['python bench/bench_memory.py', *(argv or sys.argv[1:])])}` "
             f"(whole run {time.perf_counter() - t0:.0f} s). Default scan, frames from "
             "memory (600 distinct, cycled), mosaic on "
             f"{args.outputs}; peak resident set (VmHWM) of every process of the scan, MB, "
             "largest first (the main process's includes the 1.5 GB frame bank).", "",
             "| placement | frames | depth method | peak MB per process |",
             "|---|---:|---|---|"]
    lines += [f"| {m} | {n} | {meth} | {', '.join(str(v) for v in mb)} |"
              for m, n, meth, mb in rows]
    lines.append("")
    args.out.write_text("\n".join(lines), encoding="utf-8")
    print(args.out.read_text(encoding="utf-8"))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
