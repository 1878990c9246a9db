"""Process execution benchmark (issue 12): frames/s end to end, threads against processes.

One command, every configuration interleaved in one run (round-robin, ``--rounds`` times,
median reported)::

    python bench/bench_parallel.py            # about 4-5 min on the 2-core dev VM

1280 x 1024 uint16 frames (10-bit), N = 50, k = 9, GLVM, registration on, Zarr mosaic,
the depth method ``--method`` names (SPC unless told: the method of the runs before
2026-12-02; issue 28's bars name the default, ``--method default``). Each end-to-end run
is a fresh process, pinned with ``os.sched_setaffinity`` to 1 or 2 (or more, ``--cores``)
CPUs before anything starts; worker processes inherit it.
Cases:

- frames from memory (distinct simulated frames, read into memory first), threads and
  processes, on each core count;
- the same with the recorder on: every frame recorded, then the recording is read back
  and every frame compared with the one sent (outside the timing);
- ``replay`` of a full-size recording (reading and decoding included), threads and
  processes;
- the thesis-style torch conv2d GLVM on whole frames (the baseline), in the same run.

``--sources memory`` runs only the frames-from-memory cases (of ``memory, recorder,
replay``); ``--modes processes`` only that placement (of ``threads, processes``).
``--workers 1,2,auto`` runs every case with each number of band workers
(``processing.workers``; 'auto' resolved under the case's pinning), interleaved;
``--bands threads,processes`` with each kind of band worker (``processing.bands``; the
band processes' CPU counted in process mode).
``--one-thread on,off`` runs every processes case with each worker process's stages in
one thread (on) and in a thread each (off),
interleaved; by default the placement's own rule decides
(:func:`sffscan.pipeline.cores.one_thread_per_process`). ``--outputs DIR,DIR`` runs
every case once per folder given for what the run writes (the mosaic, and the recording
with the recorder on), interleaved: the file system's share. ``--recorder-io
unbuffered,page-cache`` runs every recorder case with the frames written past the page
cache (the default since 2026-12-04: :mod:`sffscan.pipeline.formats.unbuffered`) and
through it, interleaved; the table gives the recorder's own CPU per frame.
On the dev VM this matters: its root file system is ext4 without a journal, whose inode
allocator skips inodes deleted in the last seconds to minutes (the kernel's
``recently_deleted``, checked only without a journal), so after the benches' and the
tests' own deletions a new file costs up to ~1 ms of kernel CPU there (the mosaic writes
~2.4 new chunk files a frame, the recorder 2), against tens of µs on tmpfs or a journaled
file system. Default: the ``--cache`` folder, as before. Each run's outputs are kept
(in a ``runs-<pid>`` folder there) until the bench ends, so that no run pays for the
deletion of the runs before it, as a scan in the field does not; ``--delete-each`` deletes
them after each run, as the bench did before 2026-12-04 (a later bench, or test run, still
pays for this one's deletions for a minute or more).

frames/s = frames / wall time of streaming (process mode: from the moment every worker is
ready; the workers' start-up, mostly importing torch, is reported apart). CPU ms/frame
is the whole process tree's while streaming (every worker included, start-up excluded).
Writes ``--out`` (markdown) and the same figures as JSON beside it. The machine and its
load average (before and after) are named.

``--scaling ROUNDS`` measures only the core scaling of processes from memory: the lowest
and highest of ``--cores`` alternately (the order reversed every round), ROUNDS pairs, and
prints each pair's ratio and the ratio of the medians (nothing written)::

    python bench/bench_parallel.py --scaling 4
"""

from __future__ import annotations

import argparse
import contextlib
import json
import os
import resource
import shutil
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

import numpy as np
from sffscan.pipeline.config import ScanConfig

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "bench"))
# bench_pipeline (and torch with it) is imported inside the functions that use it: the
# worker processes start by importing this script again (multiprocessing's spawn), and
# their start-up is reported as the product's (which does not import torch)


def case_config(case: dict[str, Any]) -> ScanConfig:
    from bench_pipeline import bench_config

    base = bench_config()
    data = base.model_dump()
    data["processing"].update(execution=case["mode"], depth_method=case.get("method", "spc"),
                              focus_operator="glvm", window=9, registration=True,
                              workers=case.get("workers", 1),
                              bands=case.get("bands", "threads"),
                              calibration=case.get("calibration") or None)
    return ScanConfig.model_validate(data)


def make_recording(cache: Path, bank: Path, frames: int) -> Path:
    """A full-size recording of the bank's first ``frames`` frames (made once, cached)."""
    from bench_pipeline import bench_config, load_bank, replay_frames
    from sffscan.pipeline.formats.recording_writer import RecordingWriter

    path = cache / f"rec-u16-{frames}.zarr"
    if path.is_dir() and (path / "zarr.json").is_file():
        return path
    cfg = bench_config()
    tmp = cache / f"rec-u16-{frames}.part.zarr"
    if tmp.exists():
        import shutil

        shutil.rmtree(tmp)
    w = RecordingWriter(tmp, cfg)
    for f in replay_frames(cfg, load_bank(cfg, bank, frames)):
        w.write(f)
    w.close(status="complete")
    tmp.rename(path)
    return path


def force_one_thread(on: bool) -> None:
    """Replace the process placement's rule (one thread a worker process, or a thread a
    stage) in this process: for a case run in a fresh process of its own."""
    import sffscan.pipeline.parallel as placement

    placement.one_thread_per_process = lambda processes: on  # type: ignore[assignment]


def run_case(case: dict[str, Any]) -> dict[str, Any]:
    """One end-to-end run, in a fresh process pinned to ``case['cores']`` CPUs, which keeps
    freed memory as the sffscan command's own process does."""
    cpus = sorted(os.sched_getaffinity(0))[:case["cores"]]
    os.sched_setaffinity(0, cpus)
    from sffscan.pipeline.heap import keep_freed_memory

    keep_freed_memory()  # as the sffscan command does in its own process (its workers too)
    if case.get("one_thread", "auto") != "auto":
        force_one_thread(case["one_thread"] == "on")
    from bench_pipeline import load_bank, replay_frames, scan_figures
    from sffscan.pipeline.formats.recorder_sink import recorder_sink
    from sffscan.pipeline.formats.recording_reader import open_recording
    from sffscan.pipeline.wiring import run_scan

    cfg = case_config(case)
    images = None
    if case["source"] == "memory":
        images = load_bank(cfg, Path(case["bank"]), case["frames"])
        frames = replay_frames(cfg, images)
    else:
        frames = open_recording(case["recording"]).frames()
    where = str(case.get("outputs") or case["tmp"])
    # "keep": the run's outputs stay until the bench ends (main removes that folder), so no
    # run pays for the deletion of the one before (see the module's docstring)
    with (contextlib.nullcontext(tempfile.mkdtemp(dir=Path(where) / case["keep"]))
          if case.get("keep") else tempfile.TemporaryDirectory(dir=where)) as tmp:
        sinks = [recorder_sink(cfg, str(Path(tmp) / "rec.zarr"),
                               page_cache=case.get("page_cache", False))
                 ] if case["record"] else []
        ru0 = (resource.getrusage(resource.RUSAGE_SELF),
               resource.getrusage(resource.RUSAGE_CHILDREN))
        t0 = time.perf_counter()
        rep = run_scan(cfg, frames=frames, output=Path(tmp) / "m.zarr", progress=False,
                       sinks=sinks)
        total_s = time.perf_counter() - t0
        ru1 = (resource.getrusage(resource.RUSAGE_SELF),
               resource.getrusage(resource.RUSAGE_CHILDREN))
        r = rep.result
        # process mode: CPU of every process while streaming (start-up excluded)
        out: dict[str, Any] = scan_figures(rep, sum(
            b.ru_utime + b.ru_stime - a.ru_utime - a.ru_stime
            for a, b in zip(ru0, ru1, strict=True)))
        out.update(wall_s=r.wall_s, total_s=total_s, fps_with_startup=rep.frames / total_s,
                   startup_s=r.extras.get("processes", {}).get("startup_s", 0.0))
        if case["record"]:
            got = open_recording(Path(tmp) / "rec.zarr")
            n = same = 0
            for f in got.frames():
                if images is not None:
                    same += int(np.array_equal(f.image, images[f.header.frame_id]))
                n += 1
            out["recorded"] = n
            out["recorded_equal"] = same
            out["recorder_waited_s"] = r.extras.get("recorder", {}).get("pipeline_waited_s")
    return out


def spawn_case(case: dict[str, Any]) -> dict[str, Any]:
    env = {**os.environ, "PYTHONPATH": os.pathsep.join(
        [str(ROOT), os.environ.get("PYTHONPATH", "")]).rstrip(os.pathsep)}
    done = subprocess.run([sys.executable, str(Path(__file__).resolve()), "--case",
                           json.dumps(case)], capture_output=True, text=True, env=env,
                          check=False)
    if done.returncode != 0:
        raise RuntimeError(f"case {case} failed:\n{done.stderr[-3000:]}")
    return json.loads(done.stdout.strip().splitlines()[-1])


def baseline_fps(bank: Path, n: int) -> float:
    """The thesis-style torch conv2d GLVM on whole frames, frames/s (best of 3)."""
    import torch
    from bench_pipeline import bench_config, load_bank, rate
    from sffscan.stages.focus_torch import glvm_conv2d_baseline

    cfg = bench_config()
    tens = [torch.from_numpy(a.astype(np.float32) / 1023.0) for a in load_bank(cfg, bank, n)]
    with torch.inference_mode():
        return rate(lambda t: glvm_conv2d_baseline(t, window=9), tens)


def resolve_method(name: str) -> str:
    """A ``--method`` value: a depth method's name, or 'default' for the configuration's."""
    if name != "default":
        return name
    from sffscan.pipeline.config_groups import Method

    return str(Method.model_fields["depth_method"].default)


def file_system(path: str | Path) -> str:
    """The type of the file system ``path`` lies on, from /proc/mounts (the longest mount
    point above it); '?' where that cannot be read."""
    real = os.path.realpath(path)
    best, kind = "", "?"
    try:
        lines = Path("/proc/mounts").read_text(encoding="utf-8").splitlines()
    except OSError:
        return kind
    for line in lines:
        parts = line.split()
        if len(parts) >= 3 and (real == parts[1] or real.startswith(parts[1].rstrip("/") + "/")) \
                and len(parts[1]) > len(best):
            best, kind = parts[1], parts[2]
    return kind


def file_create_ms(folder: str | Path, n: int = 300) -> float:
    """CPU ms (this process, kernel included) to create a 64 kB file as the chunk writer
    does (a temporary name, written, renamed over the final one), median of 3 bursts of
    ``n`` files in a new sub-folder, each burst deleted after it (as the runs' outputs are)."""
    import shutil

    data = os.urandom(65536)
    costs = []
    for _ in range(3):
        d = Path(tempfile.mkdtemp(dir=folder))
        r0 = resource.getrusage(resource.RUSAGE_SELF)
        for i in range(n):
            tmp = d / f"{i}.partial"
            with open(tmp, "wb") as fh:
                fh.write(data)
            os.replace(tmp, d / str(i))
        r1 = resource.getrusage(resource.RUSAGE_SELF)
        costs.append(1e3 * (r1.ru_utime + r1.ru_stime - r0.ru_utime - r0.ru_stime) / n)
        shutil.rmtree(d)
    return statistics.median(costs)


def label(c: dict[str, Any]) -> str:
    src = "replay of a recording" if c["source"] == "replay" else "from memory"
    rec = ((", recorder on (frames through the page cache)" if c.get("page_cache") else
            ", recorder on") if c["record"] else "")
    where = (f", outputs on {file_system(c['outputs'])} ({c['outputs']})"
             if c.get("outputs") else "")
    k = c.get("workers", 1)
    n = band_workers(c)
    bands = f", {'auto = ' if k == 'auto' else ''}{n} band workers" if k != 1 else ""
    if c.get("bands", "threads") == "processes" and n > 1:
        bands += " in band processes"
    one = {"on": ", one thread a worker", "off": ", a thread a stage"}.get(
        c.get("one_thread", "auto"), "")
    return (f"{src}{rec}, {c['mode']}, {c['cores']} core{'s' if c['cores'] > 1 else ''}"
            f"{bands}{one}{where}")


def band_workers(case: dict[str, Any]) -> int:
    """The case's band workers, 'auto' resolved as ``ProcessingConfig.band_workers`` does
    under the case's pinning."""
    from sffscan.pipeline.cores import auto_band_workers

    k = case.get("workers", 1)
    return auto_band_workers(case["cores"]) if k == "auto" else int(k)


def unique_cases(cases: list[dict[str, Any]]) -> list[dict[str, Any]]:
    """``cases`` without repeats, in order: with one band worker the kind of band workers
    makes no difference (it is set to threads), and 'auto' that resolves to a number also
    given is that number's case."""
    out, seen = [], set()
    for c in cases:
        n = band_workers(c)
        c = {**c, "bands": c.get("bands", "threads") if n > 1 else "threads"}
        key = json.dumps({**c, "workers": n}, sort_keys=True)
        if key not in seen:
            seen.add(key)
            out.append(c)
    return out


def busiest(runs: list[dict[str, Any]]) -> str:
    """The stage with the most wall time per frame (median over ``runs``), that time and
    its share of the frame period; empty for runs from before the figure was kept."""
    if not all("busy" in x for x in runs):
        return ""
    busy = {name: statistics.median(x["busy"][name] for x in runs) for name in runs[0]["busy"]}
    name = max(busy, key=busy.__getitem__)
    period = 1e3 / statistics.median(x["fps"] for x in runs)
    return f"{name} {busy[name]:.2f} / {period:.2f} ms"


def write_report(out: Path, meta: dict[str, Any], rows: list[dict[str, Any]]) -> None:
    base = meta["baseline_fps"]
    lines = [f"# sffscan process-execution benchmark ({time.strftime('%Y-%m-%d %H:%M')})", "",
             f"Machine: {meta['machine']}", "",
             f"Load average before / after: {meta['load_before']} / {meta['load_after']} "
             "(other work on the machine lowers every figure)", "",
             f"Command: `{meta['command']}` ({meta['frames']} frames per run, "
             f"{meta['rounds']} rounds interleaved, median; whole run {meta['run_s']:.0f} s)."
             f" 1280 x 1024 uint16, N = 50, k = 9, GLVM, {meta['method']}, registration on.",
             "",
             "| case | frames/s (median) | runs | vs baseline | with start-up | start-up s |"
             " CPU ms/frame (all processes) | busiest stage: wall ms/frame / frame period |"
             " recorded and equal |",
             "|---|---:|---|---:|---:|---:|---:|---|---|"]
    for r in rows:
        fps = [x["fps"] for x in r["runs"]]
        med = statistics.median(fps)
        rec = ""
        if r["case"]["record"]:
            rec = "; ".join(f"{x['recorded_equal']}/{x['frames']}" for x in r["runs"])
            own = statistics.median(x["stages"]["recorder"] for x in r["runs"])
            rec += f" (the recorder's own CPU {own:.2f} ms/frame)"
        lines.append(
            f"| {label(r['case'])} | {med:.1f} | {', '.join(f'{v:.0f}' for v in fps)} | "
            f"{med / base:.1f}x | "
            f"{statistics.median(x['fps_with_startup'] for x in r['runs']):.1f} | "
            f"{statistics.median(x['startup_s'] for x in r['runs']):.1f} | "
            f"{statistics.median(x['cpu_ms_per_frame'] for x in r['runs']):.2f} | "
            f"{busiest(r['runs'])} | {rec} |")
    lines += ["", "Busiest stage: the stage with the most wall time inside its own code per "
              "frame (median over the runs; a stage that waits for its band processes counts "
              "the wait), against the frame period (1000 / frames/s): near 1, that stage sets "
              "the pace.", "",
              f"Baseline (thesis-style torch conv2d GLVM, whole frames, best of 3): "
              f"{base:.1f} frames/s.", "",
              f"- Each run's outputs (mosaic, recording) deleted "
              f"{meta.get('outputs_deleted', 'after each run')}."]
    for d, times in meta.get("file_create_ms", {}).items():
        after = f", {times[1]:.3f} after" if len(times) > 1 else ""  # none: cut short
        lines.append(f"- Creating a 64 kB file as the chunk writer does, in {d} "
                     f"({file_system(d)}): {times[0]:.3f} ms of CPU before the runs{after} "
                     "(median of 3 bursts of 300, each deleted after).")
    by = {label(r["case"]): statistics.median(x["fps"] for x in r["runs"]) for r in rows}
    for mode in ("threads", "processes"):
        one, two = (by.get(f"from memory, {mode}, 1 core"),
                    by.get(f"from memory, {mode}, 2 cores"))
        if one and two:
            lines.append(f"- {mode}: 2 cores / 1 core = {two / one:.2f}x")
    lines.append("")
    out.write_text("\n".join(lines), encoding="utf-8")
    out.with_suffix(".json").write_text(json.dumps({"meta": meta, "rows": rows}, indent=1),
                                        encoding="utf-8")


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--frames", type=int, default=600, help="frames per end-to-end run")
    ap.add_argument("--rounds", type=int, default=2, help="interleaved rounds (median)")
    ap.add_argument("--cores", default="1,2", help="core counts to pin to, e.g. 1,2,4,8,16")
    ap.add_argument("--cache", type=Path, default=Path(tempfile.gettempdir()) / "sffscan-bench",
                    help="where the rendered frames and the recording are kept")
    ap.add_argument("--out", type=Path, default=ROOT / "bench" / "parallel_results.md")
    ap.add_argument("--quick", action="store_true",
                    help="from memory only, processes and threads on the largest core count")
    ap.add_argument("--method", default="spc",
                    help="depth method of the runs (default spc; 'default': the "
                         "configuration's default)")
    ap.add_argument("--outputs", default="",
                    help="comma-separated folders for what the runs write (mosaic, "
                         "recording): every case runs once per folder, interleaved; default "
                         "the --cache folder")
    ap.add_argument("--workers", default="1",
                    help="comma-separated processing.workers (band threads of the focus "
                         "measure and depth; a number or 'auto') to run every case with, "
                         "interleaved; default 1")
    ap.add_argument("--sources", default="memory,recorder,replay",
                    help="comma-separated cases to run: frames from memory on each core "
                         "count, the recorder on and the replay of a recording on the "
                         "largest (default all three)")
    ap.add_argument("--modes", default="threads,processes",
                    help="comma-separated processing.execution placements of the cases "
                         "(threads, processes; default both)")
    ap.add_argument("--bands", default="threads",
                    help="comma-separated processing.bands (threads, processes: the band "
                         "workers' kind), each case run with each")
    ap.add_argument("--recorder-io", default="unbuffered",
                    help="comma-separated unbuffered/page-cache: how the recorder writes its "
                         "frames (past the page cache, the default, or through it), every "
                         "recorder case with each, interleaved")
    ap.add_argument("--one-thread", default="auto",
                    help="comma-separated on/off: each worker process's stages in one thread "
                         "or a thread each, every processes case with each, interleaved; "
                         "default auto (the placement's rule)")
    ap.add_argument("--delete-each", action="store_true",
                    help="delete each run's outputs right after it (before 2026-12-04 the "
                         "only way); default: keep them until the bench ends")
    ap.add_argument("--case", help=argparse.SUPPRESS)
    ap.add_argument("--scaling", type=int, metavar="ROUNDS",
                    help="only the core scaling of processes from memory, ROUNDS pairs")
    args = ap.parse_args(argv)
    from bench_pipeline import frame_bank

    if args.case:
        print(json.dumps(run_case(json.loads(args.case))))
        return 0
    t_run = time.perf_counter()
    load_before = " ".join(f"{v:.2f}" for v in os.getloadavg())
    bank = frame_bank(args.cache, args.frames)
    cores = [c for c in (int(v) for v in args.cores.split(",")) if c <= len(
        os.sched_getaffinity(0))]
    method = resolve_method(args.method)
    common = {"frames": args.frames, "bank": str(bank), "tmp": str(args.cache),
              "method": method}
    if args.scaling:
        return scaling(common, min(cores), max(cores), args.scaling)
    modes = [v for v in args.modes.split(",") if v]
    if not modes or any(v not in ("threads", "processes") for v in modes):
        ap.error(f"--modes takes threads, processes; got {args.modes!r}")
    cases = [{**common, "source": "memory", "mode": m, "record": False, "cores": c}
             for c in cores for m in modes]
    sources = [v for v in args.sources.split(",") if v]
    if not sources or any(v not in ("memory", "recorder", "replay") for v in sources):
        ap.error(f"--sources takes memory, recorder, replay; got {args.sources!r}")
    if "memory" not in sources:
        cases = []
    if not args.quick:
        top = max(cores)
        if "recorder" in sources:
            cases += [{**common, "source": "memory", "mode": m, "record": True, "cores": top}
                      for m in modes]
        if "replay" in sources:
            rec = make_recording(args.cache, bank, args.frames)
            cases += [{**common, "source": "replay", "mode": m, "record": False,
                       "cores": top, "recording": str(rec)} for m in modes]
    else:
        top = max(cores)
        cases = [c for c in cases if c["cores"] == top]
    outputs = [d for d in args.outputs.split(",") if d]
    for d in outputs:
        Path(d).mkdir(parents=True, exist_ok=True)
    if outputs:
        cases = [{**c, "outputs": d} for c in cases for d in outputs]
    ks = [v for v in args.workers.split(",") if v]
    if not ks or any(v != "auto" and not v.isdigit() for v in ks):
        ap.error(f"--workers takes numbers or auto; got {args.workers!r}")
    cases = [{**c, "workers": k if k == "auto" else int(k)} for c in cases for k in ks]
    kinds = [v for v in args.bands.split(",") if v]
    if not kinds or any(v not in ("threads", "processes") for v in kinds):
        ap.error(f"--bands takes threads, processes; got {args.bands!r}")
    cases = unique_cases([{**c, "bands": v} for c in cases for v in kinds])
    ios = [v for v in args.recorder_io.split(",") if v]
    if not ios or any(v not in ("unbuffered", "page-cache") for v in ios):
        ap.error(f"--recorder-io takes unbuffered, page-cache; got {args.recorder_io!r}")
    cases = [{**c, "page_cache": v == "page-cache"} for c in cases
             for v in (ios if c["record"] else ["unbuffered"])]
    ones = [v for v in args.one_thread.split(",") if v]
    if any(v not in ("auto", "on", "off") for v in ones):
        ap.error(f"--one-thread takes auto, on, off; got {args.one_thread!r}")
    cases = [{**c, "one_thread": v} for c in cases
             for v in (ones if c["mode"] == "processes" else ["auto"])]
    keep = "" if args.delete_each else f"runs-{os.getpid()}"
    kept = [Path(d) / keep for d in sorted({c.get("outputs") or c["tmp"] for c in cases})
            ] if keep else []
    for d in kept:
        d.mkdir(parents=True, exist_ok=True)
    cases = [{**c, "keep": keep} for c in cases]
    try:
        return run_rounds(args, argv, cases, outputs, bank, method, t_run, load_before)
    finally:
        for d in kept:
            shutil.rmtree(d, ignore_errors=True)


def run_rounds(args: argparse.Namespace, argv: list[str] | None,
               cases: list[dict[str, Any]], outputs: list[str], bank: Path, method: str,
               t_run: float, load_before: str) -> int:
    """Every case ``args.rounds`` times, interleaved; writes the report."""
    from bench_pipeline import machine

    rows: list[dict[str, Any]] = [{"case": c, "runs": []} for c in cases]
    creates = {d: [file_create_ms(d)] for d in outputs}
    base = baseline_fps(bank, 12)
    meta = {"machine": machine(), "load_before": load_before, "file_create_ms": creates,
            "command": "python bench/bench_parallel.py " + " ".join(argv or sys.argv[1:]),
            "frames": args.frames, "rounds": args.rounds, "baseline_fps": base,
            "method": method, "outputs_deleted": "after each run" if args.delete_each
            else "at the end of the bench"}
    for r in range(args.rounds):
        for row in rows:
            got = spawn_case(row["case"])
            row["runs"].append(got)
            print(f"round {r + 1}: {label(row['case'])}: {got['fps']:.1f} frames/s "
                  f"(start-up {got['startup_s']:.1f} s, {got['cpu_ms_per_frame']:.2f} CPU "
                  f"ms/frame)", file=sys.stderr, flush=True)
        if r + 1 < args.rounds:  # a bench cut short keeps the rounds it finished
            write_report(args.out, {**meta, "rounds": r + 1, "load_after": "(cut short)",
                                    "run_s": time.perf_counter() - t_run}, [
                {**row, "runs": row["runs"][:r + 1]} for row in rows])
    for d in outputs:
        creates[d].append(file_create_ms(d))
    meta.update(load_after=" ".join(f"{v:.2f}" for v in os.getloadavg()),
                run_s=time.perf_counter() - t_run)
    write_report(args.out, meta, rows)
    print(args.out.read_text(encoding="utf-8"))
    return 0


def scaling(common: dict[str, Any], low: int, high: int, rounds: int) -> int:
    """Pairs of runs, processes from memory, on ``low`` and ``high`` cores (order reversed
    every round); prints the frames/s, each pair's ratio and the ratio of the medians."""
    from bench_pipeline import machine

    fps: dict[int, list[float]] = {low: [], high: []}
    for r in range(rounds):
        for c in (low, high) if r % 2 == 0 else (high, low):
            got = spawn_case({**common, "source": "memory", "mode": "processes",
                              "record": False, "cores": c})
            fps[c].append(got["fps"])
            print(f"round {r + 1}: {c} core(s): {got['fps']:.1f} frames/s (load "
                  f"{os.getloadavg()[0]:.2f})", file=sys.stderr, flush=True)
    pairs = [b / a for a, b in zip(fps[low], fps[high], strict=True)]
    ratio = statistics.median(fps[high]) / statistics.median(fps[low])
    print(f"{machine()}; processes from memory, {common['frames']} frames per run")
    print(f"{low} core(s): " + ", ".join(f"{v:.1f}" for v in fps[low]) + " frames/s")
    print(f"{high} core(s): " + ", ".join(f"{v:.1f}" for v in fps[high]) + " frames/s")
    print(f"{high}/{low} cores: ratio of the medians {ratio:.2f}x (pairs "
          + ", ".join(f"{v:.2f}" for v in pairs) + ")")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
