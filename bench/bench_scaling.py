"""Scaling model (issue 28, item 3): CPU per frame of each stage and of the transport,
measured; frames/s predicted for 2, 4, 8, 16 cores; the prediction for 2 cores checked
against a measured run in processes.

    nice -n 10 python bench/bench_scaling.py            # about 3-5 min on the 2-core VM

The scan is the default one from memory: the demo optics (1280 x 1024 uint16, 10-bit),
N = 50, GLVM k = 9, the default depth method (``processing.depth_method``'s default),
registration on, Zarr mosaic; distinct simulated frames (the frame bank of
``bench_pipeline.py``) read into memory first. Every end-to-end run is a fresh process
pinned to ``--cores`` CPUs; the thread placement, the process placement and the process
placement with a thread a stage (the rule of more cores forced) in turn, ``--rounds`` times;
medians.

Measured:

1. **Per-stage CPU per frame**, in the process placement (what the model takes) and in the
   thread placement: each stage's ``StageStats.cpu_s`` (its thread's CPU inside its own
   code) / frames of the scan. **Transport**, process placement: the CPU of every process
   while streaming (``extras["processes"]["cpu_s"]``) minus the sum of its stages'
   ``cpu_s``, per frame; split per process with the workers' own reports (the bench wraps
   ``process_figures.process_result`` in its case process to read them; no product code
   changes).
2. **Band split overhead**: ``focus_measure_raw(frame[:, cols], rows=(r0, r1))`` over K
   equal row bands (each widened by the operator's reach: the halo), K = 1, 2, 4, 8, 16,
   against the whole frame, in this process (OpenCV and BLAS on one thread, as one worker
   per core would run; the thread's CPU), every K measuring each frame in turn (order
   rotated); bit-identity checked.
   Columns: the 620 the focus stage measures of a frame at 15 mm/s (as bench_pipeline.py).
3. **The model** (stated in the output)::

       frames/s(C) = min(C / T, 1 / G)

   T: total CPU per frame, transport included; G: CPU per frame of the busiest group of
   stages that cannot be split (one process). Today's placement (main: source, speed
   shift, mosaic; worker 1: registration; worker 2: focus measure + depth) and a K-band
   placement of focus measure + accumulation + depth (predicted; built in another form,
   ``processing.bands = "processes"``: band processes that the focus worker hands each
   frame's rows), with registration's pairs in one thread or farmed out to threads of
   their own (built: ``processing.workers``; their share measured by
   ``bench_registration_pairs.py``, whose results this reads).

Writes ``bench/results/scaling.md`` and ``.json`` (command, machine, date, load average).
Not a test: nothing here asserts.
"""

from __future__ import annotations

import argparse
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

ROOT = Path(__file__).resolve().parents[1]
RESULTS = ROOT / "bench" / "results"
sys.path.insert(0, str(ROOT / "bench"))
# bench_pipeline (torch with it) is imported inside functions: the workers of a run in
# processes start by importing this script again (multiprocessing's spawn)

BANDS = (1, 2, 4, 8, 16)
RUSAGE_THREAD = getattr(resource, "RUSAGE_THREAD", resource.RUSAGE_SELF)  # Linux: thread
CORES = (2, 4, 8, 16)
COLUMNS = slice(300, 920)  # the focus stage's columns of a frame at 15 mm/s (48 %)
MAIN, REG, FOCUS = "main", "registration", "focus"
#: processes of today's placement (main, registration worker, focus worker)
PROCESSES = 3
PER_STAGE = "processes, a thread a stage"  # the process placement with one_thread forced off
GROUP_STAGES = {REG: ("registration",), FOCUS: ("focus_measure", "depth")}


def scan_config(mode: str) -> Any:
    """The default scan (bench_pipeline's demo optics) with the default depth method."""
    from bench_pipeline import bench_config
    from sffscan.pipeline.config import ScanConfig
    from sffscan.pipeline.config_groups import Method

    data = bench_config(method=Method.model_fields["depth_method"].default).model_dump()
    data["processing"]["execution"] = mode
    return ScanConfig.model_validate(data)


def run_case(case: dict[str, Any]) -> dict[str, Any]:
    """One end-to-end run in this (fresh) process, pinned to ``case['cores']`` CPUs."""
    os.sched_setaffinity(0, sorted(os.sched_getaffinity(0))[:case["cores"]])
    import sffscan.pipeline.parallel as parallel
    from sffscan.pipeline.heap import keep_freed_memory

    keep_freed_memory()  # as the sffscan command does in its own process (its workers too)
    if case["mode"] == PER_STAGE:  # the placement's rule on more cores than processes
        from bench_parallel import force_one_thread

        force_one_thread(False)
    from bench_pipeline import load_bank, replay_frames
    from sffscan.pipeline.wiring import run_scan

    workers: list[dict[str, Any]] = []
    original = parallel.process_result

    def capture(pipe: Any, outcome: Any, send: Any, forwards: Any, labels: list[str],
                reports: list[dict[str, Any]], *rest: Any) -> Any:
        workers.extend({"label": lb, "cpu_s": r.get("cpu_s"),
                        "stages": [s["name"] for s in r.get("stages", [])]}
                       for lb, r in zip(labels, reports, strict=False))
        return original(pipe, outcome, send, forwards, labels, reports, *rest)

    parallel.process_result = capture  # type: ignore[assignment]
    cfg = scan_config("processes" if case["mode"].startswith("processes") else "threads")
    images = load_bank(cfg, Path(case["bank"]), case["frames"])
    # the run's mosaic stays until the bench ends (main removes the folder): no run pays for
    # the deletion of the one before (bench_parallel.py's docstring)
    tmp = tempfile.mkdtemp(dir=case["tmp"])
    ru0 = resource.getrusage(resource.RUSAGE_SELF)
    rep = run_scan(cfg, frames=replay_frames(cfg, images), output=Path(tmp) / "m.zarr",
                   progress=False)
    ru1 = resource.getrusage(resource.RUSAGE_SELF)
    r = rep.result
    n = rep.frames
    if case["mode"].startswith("processes"):
        total = r.extras["processes"]["cpu_s"]
    else:
        total = ru1.ru_utime + ru1.ru_stime - ru0.ru_utime - ru0.ru_stime
    stages = {s.name: 1e3 * s.cpu_s / n for s in r.stages if s.name not in r.sinks}
    return {"mode": case["mode"], "frames": n, "wall_s": r.wall_s, "fps": n / r.wall_s,
            "dropped": r.dropped, "total_ms": 1e3 * total / n, "stages_ms": stages,
            "workers": [{**w, "cpu_ms": 1e3 * (w["cpu_s"] or 0.0) / n} for w in workers],
            "depth_method": cfg.processing.depth_method}


def spawn_case(case: dict[str, Any]) -> dict[str, Any]:
    env = {**os.environ, "PYTHONPATH": os.pathsep.join(
        [str(ROOT), os.environ.get("PYTHONPATH", "")]).rstrip(os.pathsep)}
    done = subprocess.run([sys.executable, str(Path(__file__).resolve()), "--case",
                           json.dumps(case)], capture_output=True, text=True, env=env,
                          check=False, timeout=900)
    if done.returncode != 0:
        raise RuntimeError(f"case {case} failed:\n{done.stderr[-3000:]}")
    return dict(json.loads(done.stdout.strip().splitlines()[-1]))


def band_overhead(bank: Path, frames: int, rounds: int) -> dict[str, Any]:
    """CPU per frame of the focus measure over K row bands against the whole frame (this
    thread's CPU; OpenCV on one thread, so none is spent elsewhere); every K measures
    each frame in turn (order rotated), so a change of the machine's load hits all K."""
    import cv2
    import numpy as np
    from sffscan.stages.focus_measure import focus_measure_raw
    from sffscan.stages.operators import operator_reach
    from threadpoolctl import threadpool_limits

    h, w = 1024, 1280
    data = np.fromfile(bank, np.uint16, count=frames * h * w).reshape(frames, h, w)
    raws = [np.ascontiguousarray(f) for f in data]
    edges = {k: [round(i * h / k) for i in range(k + 1)] for k in BANDS}
    cpu: dict[int, list[float]] = {k: [] for k in BANDS}
    user: dict[int, list[float]] = {k: [] for k in BANDS}
    sys_: dict[int, list[float]] = {k: [] for k in BANDS}
    faults: dict[int, list[float]] = {k: [] for k in BANDS}
    identical = {k: True for k in BANDS}
    cv_threads = cv2.getNumThreads()
    cv2.setNumThreads(1)
    try:
        with threadpool_limits(limits=1):
            for rnd in range(rounds):
                spent = {k: [0.0, 0.0, 0.0, 0.0] for k in BANDS}  # CPU, user, sys, faults
                for i, raw in enumerate(raws):  # every K on each frame: the load hits all
                    part = raw[:, COLUMNS]
                    j = (i + rnd) % len(BANDS)
                    for k in BANDS[j:] + BANDS[:j]:
                        e = edges[k]
                        c0, u0 = time.thread_time(), resource.getrusage(RUSAGE_THREAD)
                        for r0, r1 in zip(e[:-1], e[1:], strict=True):
                            focus_measure_raw(part, max_value=1023.0, window=9,
                                              rows=None if k == 1 else (r0, r1))
                        c1, u1 = time.thread_time(), resource.getrusage(RUSAGE_THREAD)
                        for n, v in enumerate((c1 - c0, u1.ru_utime - u0.ru_utime,
                                               u1.ru_stime - u0.ru_stime,
                                               u1.ru_minflt - u0.ru_minflt)):
                            spent[k][n] += v
                for k in BANDS:
                    cpu[k].append(1e3 * spent[k][0] / len(raws))
                    user[k].append(1e3 * spent[k][1] / len(raws))
                    sys_[k].append(1e3 * spent[k][2] / len(raws))
                    faults[k].append(spent[k][3] / len(raws))
            part = raws[0][:, COLUMNS]
            whole = focus_measure_raw(part, max_value=1023.0, window=9)[1]
            for k in BANDS[1:]:
                e = edges[k]
                got = np.concatenate([focus_measure_raw(part, max_value=1023.0, window=9,
                                                        rows=(a, b))[1]
                                      for a, b in zip(e[:-1], e[1:], strict=True)])
                identical[k] = bool(np.array_equal(got, whole))
    finally:
        cv2.setNumThreads(cv_threads)
    med = {k: statistics.median(v) for k, v in cpu.items()}
    # the overhead per round (every K measured on the same frames, at the same time)
    ratio = {k: statistics.median(a / b for a, b in zip(cpu[k], cpu[1], strict=True))
             for k in BANDS}
    ratio_user = {k: statistics.median(a / b for a, b in zip(user[k], user[1], strict=True))
                  for k in BANDS}
    reach = operator_reach("glvm", 9)
    rows = {k: sum(min(b + reach, h) - max(a - reach, 0)
                   for a, b in zip(edges[k][:-1], edges[k][1:], strict=True)) / h
            for k in BANDS}
    return {"columns": [COLUMNS.start, COLUMNS.stop], "frames": frames, "rounds": rounds,
            "reach_rows": reach, "halo_rows_share": {str(k): rows[k] for k in BANDS},
            "cpu_ms": {str(k): med[k] for k in BANDS},
            "runs_ms": {str(k): v for k, v in cpu.items()},
            "overhead": {str(k): ratio[k] for k in BANDS},
            "user_ms": {str(k): statistics.median(user[k]) for k in BANDS},
            "sys_ms": {str(k): statistics.median(sys_[k]) for k in BANDS},
            "minor_faults": {str(k): statistics.median(faults[k]) for k in BANDS},
            "overhead_user": {str(k): ratio_user[k] for k in BANDS},
            "bit_identical": {str(k): identical[k] for k in BANDS}}


def med_of(runs: list[dict[str, Any]], key: str) -> float:
    return statistics.median(r[key] for r in runs)


def measured_groups(proc: list[dict[str, Any]]) -> dict[str, dict[str, float]]:
    """Per process of the placement: CPU per frame, its stages' CPU, the difference
    (transport and other threads), medians over the runs."""
    out: dict[str, dict[str, list[float]]] = {g: {"cpu": [], "stages": []}
                                              for g in (MAIN, REG, FOCUS)}
    for run in proc:
        rest = run["total_ms"]
        rest_st = sum(run["stages_ms"].values())
        for w in run["workers"]:
            g = REG if "registration" in w["stages"] else FOCUS
            st = sum(run["stages_ms"].get(s, 0.0) for s in w["stages"])
            out[g]["cpu"].append(w["cpu_ms"])
            out[g]["stages"].append(st)
            rest -= w["cpu_ms"]
            rest_st -= st
        out[MAIN]["cpu"].append(rest)
        out[MAIN]["stages"].append(rest_st)
    res = {}
    for g, v in out.items():
        cpu, st = statistics.median(v["cpu"]), statistics.median(v["stages"])
        res[g] = {"cpu_ms": cpu, "stages_ms": st, "transport_ms": cpu - st}
    return res


def pairs_ratio(path: Path = RESULTS / "registration_pairs.json") -> float | None:
    """The registration stage's time a frame with each pair in a thread of its own, against
    one thread (``bench_registration_pairs.py``'s results: the stage's own part, a band's
    downsampling and its slowest pair, over all of it in one thread); None where it has
    not run."""
    if not path.is_file():
        return None
    r = json.loads(path.read_text())
    return float(r["critical_ms"]) / float(r["one_thread_ms"])


def overlapped_groups(stages: dict[str, float], transport: dict[str, float]
                      ) -> dict[str, float]:
    """Today's placement's groups (main, registration worker, focus worker), CPU ms a frame
    each, with a thread a stage (on more cores than processes,
    :func:`sffscan.pipeline.cores.one_thread_per_process`): a process's stages overlap, so
    that its slowest stage sets its pace; its transport added. (With one thread a process
    its stages add up: :func:`model`'s one-band placement.)"""
    reg = [stages.get(s, 0.0) for s in GROUP_STAGES[REG]]
    fd = [stages.get(s, 0.0) for s in GROUP_STAGES[FOCUS]]
    main = [v for s, v in stages.items() if s not in GROUP_STAGES[REG] + GROUP_STAGES[FOCUS]]
    return {MAIN: max(main) + transport[MAIN], REG: max(reg) + transport[REG],
            FOCUS: max(fd) + transport[FOCUS]}


def model(stages: dict[str, float], transport: dict[str, float],
          ov_focus: dict[str, float], ov_depth: dict[str, float],
          farm_ratio: float | None = None,
          overlapped: tuple[dict[str, float], dict[str, float]] | None = None
          ) -> dict[str, Any]:
    """Predicted frames/s for each core count, today's placement and K-band placements.

    ``stages``: CPU ms per frame of each stage; ``transport``: ms per
    frame of each process beyond its stages' code; ``ov_focus``, ``ov_depth``: K -> CPU of
    K bands / CPU of the whole frame, of the focus measure and of accumulation + depth.
    One message end (a receive or a send of a frame) costs ``x``: half the registration
    worker's transport (it receives and sends each frame and does nothing else).
    ``farm_ratio``: the registration stage's time with its pairs farmed out, against
    one thread (:func:`pairs_ratio`); None: the placements with the pairs farmed out are
    left out. ``overlapped``: the stages' and transport's figures with a thread a stage;
    given, today's placement on more cores than its 3 processes takes them, its groups
    paced by their slowest stage (:func:`overlapped_groups`), and on fewer the figures above
    with each process's stages in turn; None: the latter on every core count (the model
    before 2026-12-04, which a lent 8-core machine measured 1.39x faster than predicted).
    """
    reg = sum(stages.get(s, 0.0) for s in GROUP_STAGES[REG])
    fm, dp = stages.get("focus_measure", 0.0), stages.get("depth", 0.0)
    fd = fm + dp
    main = sum(stages.values()) - reg - fd
    xm, xr, xf = transport[MAIN], transport[REG], transport[FOCUS]
    x = xr / 2
    total = sum(stages.values()) + xm + xr + xf

    def placement(k: int, farmed: bool) -> dict[str, Any]:
        band = fm * ov_focus[str(k)] + dp * ov_depth[str(k)]  # all K bands together
        # each band worker receives every frame (x) and has 1/K of the rest of the focus
        # worker's transport (its blocks, its threads); the registration worker sends each
        # frame K times; farmed out, the registration's pairs run in threads of their own
        # (processing.workers): its time a frame is its own part plus its slowest pair
        # (farm_ratio, measured), its CPU the same (T unchanged)
        t = total + band - fd + 2 * (k - 1) * x
        groups = {MAIN: main + xm,
                  REG: (reg * farm_ratio if farmed and farm_ratio else reg) + xr
                  + (k - 1) * x,
                  f"{FOCUS} band (1 of {k})": band / k + x + (xf - x) / k}
        busiest = max(groups, key=lambda g: groups[g])
        fps = {c: min(c / t, 1.0 / groups[busiest]) * 1e3 for c in CORES}
        return {"bands": k, "registration_farmed": farmed, "total_ms": t,
                "groups_ms": groups, "busiest": busiest, "fps": fps,
                "cores_to_cap": t / groups[busiest]}

    today = placement(1, False)
    if overlapped is not None:  # more cores than processes: a thread a stage
        ovl = overlapped_groups(*overlapped)
        t_ovl = sum(overlapped[0].values()) + sum(overlapped[1].values())
        today["fps"] = {c: min(c / t_ovl, 1.0 / max(ovl.values())) * 1e3
                        if c > PROCESSES else fps for c, fps in today["fps"].items()}
        today["groups_ms_overlapped"] = ovl
        today["busiest_overlapped"] = max(ovl, key=lambda g: ovl[g])
    cases = [today]
    cases += [placement(k, f) for f in (False, True) for k in BANDS[1:]
              if not f or farm_ratio is not None]
    return {"stage_groups_ms": {MAIN: main, REG: reg, FOCUS: fd}, "total_ms": total,
            "message_end_ms": x, "placements": cases, "farm_ratio": farm_ratio}


def fmt_groups(p: dict[str, Any]) -> str:
    return ", ".join(f"{g} {v:.2f}" for g, v in p["groups_ms"].items())


def write(out: Path, res: dict[str, Any]) -> str:
    thr, prc = res["threads"], res["processes"]
    names = list(res["stages_ms"])
    m = res["model"]
    today = m["placements"][0]
    lines = [f"# Scaling model: CPU per frame, measured; frames/s predicted ({res['date']})",
             "", f"Machine: {res['machine']}. Load average before / after: "
             f"{res['load_before']} / {res['load_after']} (a shared machine: other work "
             "lowers every frames/s figure; CPU time per frame is the steadier one).", "",
             f"Command: `{res['command']}` ({res['frames']} frames per run, {res['rounds']} "
             "rounds, threads, processes and processes with a thread a stage in turn, "
             f"pinned to {res['cores']} cores, "
             f"median; whole run {res['run_s']:.0f} s). Scan: 1280 x 1024 uint16, N = 50, "
             f"GLVM k = 9, depth method `{res['depth_method']}` (the default), registration "
             f"on, Zarr mosaic (written in {res.get('outputs', 'the cache folder')}), frames "
             "from memory." + (f" Report: {res['recomputed']}." if res.get("recomputed")
                               else ""), "",
             "## 1. CPU per frame of each stage and of the transport", "",
             "Stage: its thread's CPU inside its own code (`StageStats.cpu_s`) / frames, "
             "in the thread placement (every stage a thread of one process) and in the "
             "process placement (the same stages in their workers; what the model takes). "
             "Every run's own process keeps freed memory as the `sffscan` command's does "
             "(`sffscan.pipeline.heap`).", "",
             "| stage | threads ms/frame | least of the runs | processes ms/frame |"
             " processes, a thread a stage | runs (threads) |",
             "|---|---:|---:|---:|---:|---|"]
    pt = res["stages_ms_processes_thread_a_stage"]
    for s in names:
        each = ", ".join(f"{r['stages_ms'].get(s, 0.0):.2f}" for r in thr)
        lines.append(f"| {s} | {res['stages_ms'][s]:.2f} | {res['stages_ms_min'][s]:.2f} | "
                     f"{res['stages_ms_processes'][s]:.2f} | {pt[s]:.2f} | {each} |")
    s_thr, s_prc = sum(res["stages_ms"].values()), sum(res["stages_ms_processes"].values())
    s_min, s_pt = sum(res["stages_ms_min"].values()), sum(pt.values())
    per = res["processes_thread_a_stage"]
    lines += [f"| **sum of stages** | **{s_thr:.2f}** | **{s_min:.2f}** | **{s_prc:.2f}** | "
              f"**{s_pt:.2f}** | |",
              f"| whole process(es), all threads | {med_of(thr, 'total_ms'):.2f} | | "
              f"{med_of(prc, 'total_ms'):.2f} | {med_of(per, 'total_ms'):.2f} | |", "",
              "Processes: each worker runs its stages in one thread where the cores are no "
              "more than the processes (`sffscan.pipeline.cores.one_thread_per_process`, "
              "as here); \"a thread a stage\": the same placement with that rule forced off, "
              "as it runs on more cores than processes.", "",
              f"- Transport (processes: all processes' CPU while streaming minus the sum of "
              f"their stages): **{res['transport_ms']:.2f} ms/frame** (it includes what any "
              "process spends outside its stages' code: queues, Zarr's codec threads, the "
              "interpreter). For comparison, the thread placement spends "
              f"{med_of(thr, 'total_ms') - s_thr:.2f} ms/frame outside its stages' code, "
              "in one process whose threads contend for one interpreter.", "",
              "Per process of today's placement (medians):", "",
              "| process | CPU ms/frame | its stages | transport and other |",
              "|---|---:|---:|---:|"]
    for g, v in res["groups_measured"].items():
        lines.append(f"| {g} | {v['cpu_ms']:.2f} | {v['stages_ms']:.2f} | "
                     f"{v['transport_ms']:.2f} |")
    b = res["bands"]
    lines += ["", "## 2. The band split's overhead (focus measure, K row bands)", "",
              f"`focus_measure_raw(frame[:, {b['columns'][0]}:{b['columns'][1]}], "
              "rows=(r0, r1))` over K equal bands (each widened by the reach, the halo) "
              f"against the whole frame; {b['frames']} frames, {b['rounds']} rounds; every K "
              "measures each frame in turn (order rotated), OpenCV and BLAS on one thread, "
              "the thread's CPU. / whole frame: the median over rounds of each round's "
              "ratio.", "",
              "| K | CPU ms/frame (all bands) | / whole frame | user ms | sys ms | minor "
              "page faults | user / whole frame's | rows measured / rows (halo) | used in "
              "the model | runs (CPU ms) | bit-identical |",
              "|---:|---:|---:|---:|---:|---:|---:|---:|---:|---|---|"]
    for k in BANDS:
        s = str(k)
        lines.append(f"| {k} | {b['cpu_ms'][s]:.3f} | {b['overhead'][s]:.3f} | "
                     f"{b['user_ms'][s]:.3f} | {b['sys_ms'][s]:.3f} | "
                     f"{b['minor_faults'][s]:.0f} | {b['overhead_user'][s]:.3f} | "
                     f"{b['halo_rows_share'][s]:.3f} | {res['overhead_used'][s]:.3f} | "
                     f"{', '.join(f'{v:.3f}' for v in b['runs_ms'][s])} | "
                     f"{'-' if k == 1 else b['bit_identical'][s]} |")
    lines += ["", f"The halo: {b['reach_rows']} rows each side of a band (the operator's "
              "reach). user / sys: the thread's (getrusage; the split is sampled, the sum "
              "exact); minor page faults per frame. A ratio below 1 means K bands cost less "
              "CPU than the whole frame: the whole frame's temporaries are fresh pages every "
              "call (the sys time and the page faults), the bands' are reused; the user "
              "time, the arithmetic, is what the halo costs. The model does not assume the "
              "gain: the overhead used is the largest of the measured ratio, the user-time "
              "ratio and the halo's share of rows; the measured ratio is shown as a variant "
              "below."]
    sg = m["stage_groups_ms"]
    lines += ["", "## 3. The model", "",
              "    frames/s(C cores) = min(C / T, 1 / G)", "",
              "T: total CPU per frame, transport included; G: CPU per frame of the busiest "
              "group that cannot be split (one process). From the measured figures "
              f"(ms/frame): stages of the main process (source, speed shift, mosaic) "
              f"{sg[MAIN]:.2f}, registration {sg[REG]:.2f}, focus measure + depth "
              f"(accumulation and reduction) {sg[FOCUS]:.2f}, as measured in their "
              f"processes on {res['cores']} cores (each worker runs its stages in one "
              "thread where the cores are no more than its 3 processes, else a thread a "
              "stage: `sffscan.pipeline.cores.one_thread_per_process`); "
              "each process's transport as measured above; T = "
              f"{m['total_ms']:.2f}.", "",
              "- **Today's placement** (built): main, registration worker, focus + depth "
              "worker; up to 3 cores each process's stages one after another, on more "
              "(4, 8, 16) a thread a stage, so that a process goes at the pace of its "
              "slowest stage plus its transport, from the runs with a thread a stage "
              + (f"(groups {', '.join(f'{g} {v:.2f}' for g, v in ovl.items())} ms a frame)"
                 if (ovl := today.get("groups_ms_overlapped")) else "(not measured)")
              + ".",
              "- **K-band placement** (predicted; the band processes built since "
              "(`processing.bands`) are the focus worker's helpers, not workers that each "
              "receive every frame): K workers each own a band "
              "of rows for focus measure + accumulation + depth; their CPU is the focus + "
              "depth CPU times the overhead used for K (step 2, applied to the whole group; "
              "the median's halo in the reduction is not measured), / K; each band worker "
              "receives every frame (one message end, "
              f"x = {m['message_end_ms']:.2f} ms: half the registration worker's transport, "
              "which receives and sends each frame) and has 1 / K of the rest of today's "
              "focus worker's transport; the registration worker sends each frame K times. "
              "Registration runs its pairs in one thread, or farmed out (built: "
              "`processing.workers` > 1 gives the registration a thread a pair, at most "
              "one a lag, and the downsampling in as many bands): its time a frame is then "
              "its own part (the shared spectrum, the solve), a band's downsampling and its "
              "slowest pair, "
              + (f"{m['farm_ratio']:.3f}x its one-thread time "
                 "(bench/results/registration_pairs.md, measured with one worker)"
                 if m.get("farm_ratio") else "not measured here (run "
                 "bench_registration_pairs.py first)")
              + "; its CPU is the same, and the sends stay in its process.", "",
              "| placement | T ms/frame | groups ms/frame | busiest | "
              + " | ".join(f"{c} cores" for c in CORES) + " |",
              "|---|---:|---|---|" + "---:|" * len(CORES)]
    for p in m["placements"]:
        name = ("today (1 registration + 1 focus/depth worker)" if p["bands"] == 1 else
                f"K = {p['bands']} bands, registration "
                + ("farmed out" if p["registration_farmed"] else "one worker"))
        lines.append(f"| {name} | {p['total_ms']:.2f} | {fmt_groups(p)} | {p['busiest']} | "
                     + " | ".join(f"{p['fps'][c]:.0f}" for c in CORES) + " |")
    best8 = max(m["placements"], key=lambda p: p["fps"][8])
    chk = res["check"]
    lines += ["", f"- Best predicted on 8 cores: **{best8['fps'][8]:.0f} frames/s** "
              f"(K = {best8['bands']}, registration "
              f"{'farmed out' if best8['registration_farmed'] else 'one worker'}; "
              f"busiest group: {best8['busiest']}); today's placement: "
              f"{today['fps'][8]:.0f} frames/s (capped by "
              f"{today.get('busiest_overlapped', today['busiest'])}). Bar: >= 300, "
              "which needs T <= 26.7 ms (8 cores / 300 frames/s) and every group <= 3.33 ms "
              "of CPU per frame.",
              "", "The same model with other inputs (frames/s on 2 / 4 / 8 / 16 cores; best: "
              "the best of the K-band placements):", "",
              "| inputs | today | best K-band |", "|---|---|---|"]
    for name, v in res["variants"].items():
        fps0 = v["placements"][0]["fps"]
        lines.append(f"| {name} | {' / '.join(f'{fps0[c]:.0f}' for c in CORES)} | "
                     + " / ".join(f"{max(p['fps'][c] for p in v['placements']):.0f}"
                                  for c in CORES) + " |")
    lines += ["",
              f"- Check on {res['cores']} cores: today's placement predicted "
              f"{chk['predicted_fps']:.0f} frames/s; measured (processes, median) "
              f"{chk['measured_fps']:.1f} frames/s (runs "
              f"{', '.join(f'{v:.1f}' for v in chk['runs_fps'])}), ratio "
              f"{chk['ratio']:.2f}. The measured run used {chk['cores_busy']:.2f} cores' "
              "worth of CPU (frames/s x its CPU per frame): on a loaded machine the "
              "pipeline gets only a share of the cores, so the measured frames/s is a "
              "floor, and the check holds only on a quiet machine.",
              f"- The same stages in the thread placement: {s_thr:.2f} ms of CPU a frame "
              f"against {s_prc:.2f} in their processes (ratio {s_thr / s_prc:.3f}): there "
              "every stage's thread contends for one interpreter (the variant rows above "
              "take those figures).", ""]
    text = "\n".join(lines)
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(text, encoding="utf-8")
    out.with_suffix(".json").write_text(json.dumps(res, indent=1) + "\n", encoding="utf-8")
    return text


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--frames", type=int, default=150, help="frames per end-to-end run")
    ap.add_argument("--rounds", type=int, default=3, help="interleaved rounds (median)")
    ap.add_argument("--cores", type=int, default=2, help="CPUs the runs are pinned to")
    ap.add_argument("--band-frames", type=int, default=40,
                    help="frames of the band-overhead measurement")
    ap.add_argument("--band-rounds", type=int, default=5,
                    help="rounds of the band-overhead measurement")
    ap.add_argument("--cache", type=Path, default=Path(tempfile.gettempdir()) / "sffscan-bench",
                    help="where the rendered frame bank is kept")
    ap.add_argument("--out", type=Path, default=ROOT / "bench" / "results" / "scaling.md")
    ap.add_argument("--outputs", type=Path,
                    help="folder the runs write their mosaics in (default: --cache); on the "
                         "dev VM's journal-less ext4 a new file costs up to ~1 ms of kernel "
                         "CPU after deletions, on tmpfs ~0.05 (bench_parallel.py --outputs)")
    ap.add_argument("--from-json", type=Path, metavar="RESULTS",
                    help="measure nothing: the model computed again from the measurements "
                         "kept in a results JSON this bench wrote (on this machine or "
                         "another), the report written to --out")
    ap.add_argument("--case", help=argparse.SUPPRESS)
    args = ap.parse_args(argv)
    if args.case:
        print(json.dumps(run_case(json.loads(args.case))))
        return 0
    if args.from_json:
        return recompute(args.from_json, args.out)
    from bench_pipeline import frame_bank

    t0 = time.perf_counter()
    load_before = " ".join(f"{v:.2f}" for v in os.getloadavg())
    bank = frame_bank(args.cache, max(args.frames, args.band_frames))
    cores = min(args.cores, len(os.sched_getaffinity(0)))
    outputs = args.outputs or args.cache
    made = not outputs.exists()
    outputs.mkdir(parents=True, exist_ok=True)
    keep = outputs / f"runs-{os.getpid()}"
    keep.mkdir()
    try:
        return measure(args, argv, bank, cores, outputs, keep, t0, load_before)
    finally:
        shutil.rmtree(keep, ignore_errors=True)
        if made and not any(outputs.iterdir()):  # a folder it made for this run (/dev/shm)
            outputs.rmdir()


def measure(args: argparse.Namespace, argv: list[str] | None, bank: Path, cores: int,
            outputs: Path, keep: Path, t0: float, load_before: str) -> int:
    """The runs, the band overhead and the model; writes the report."""
    from bench_parallel import file_system
    from bench_pipeline import machine

    common = {"frames": args.frames, "bank": str(bank), "tmp": str(keep), "cores": cores}
    modes = ["threads", "processes", PER_STAGE]
    runs: dict[str, list[dict[str, Any]]] = {m: [] for m in modes}
    for rnd in range(args.rounds):
        order = modes[rnd % 3:] + modes[:rnd % 3]  # each mode first in turn
        for mode in order:
            got = spawn_case({**common, "mode": mode})
            runs[mode].append(got)
            print(f"round {rnd + 1}, {mode}: {got['fps']:.1f} frames/s, "
                  f"{got['total_ms']:.2f} CPU ms/frame (load {os.getloadavg()[0]:.1f})",
                  file=sys.stderr, flush=True)
    bands = band_overhead(bank, args.band_frames, args.band_rounds)
    print(f"bands: {bands['overhead']}", file=sys.stderr, flush=True)
    meta = {
        "command": "python bench/bench_scaling.py " + " ".join(
            sys.argv[1:] if argv is None else argv),
        "machine": machine(), "date": time.strftime("%Y-%m-%d %H:%M"),
        "load_before": load_before,
        "load_after": " ".join(f"{v:.2f}" for v in os.getloadavg()),
        "frames": args.frames, "rounds": args.rounds, "cores": cores,
        "outputs": f"{outputs} ({file_system(outputs)}; kept until the bench ends)",
        "run_s": time.perf_counter() - t0}
    print(write(args.out, analyse(meta, runs["threads"], runs["processes"], runs[PER_STAGE],
                                  bands)))
    return 0


META = ("command", "machine", "date", "load_before", "load_after", "frames", "rounds",
        "cores", "outputs", "run_s")


def recompute(results: Path, out: Path) -> int:
    """:func:`analyse` again on the runs kept in ``results`` (the model as it is now, the
    measurements as they were); the report says so."""
    try:
        res = json.loads(results.read_text(encoding="utf-8"))
        meta = {k: res[k] for k in META}
        runs = [res[k] for k in ("threads", "processes", "processes_thread_a_stage")]
        bands = res["bands"]
    except (OSError, ValueError, KeyError) as err:
        print(f"--from-json {results}: not a bench_scaling results file ({err!r})",
              file=sys.stderr)
        return 2
    meta["recomputed"] = (f"the model computed again on {time.strftime('%Y-%m-%d %H:%M')} "
                          f"from the measurements in {results.name}")
    print(write(out, analyse(meta, runs[0], runs[1], runs[2], bands)))
    return 0


def analyse(meta: dict[str, Any], thr: list[dict[str, Any]], prc: list[dict[str, Any]],
            per: list[dict[str, Any]], bands: dict[str, Any]) -> dict[str, Any]:
    """The measured runs (threads, processes, processes with a thread a stage) and band
    overheads, summarised, and the model and its variants computed from them (the report's
    contents; ``meta``: command, machine, date, load, frames, rounds, cores, outputs)."""
    cores = meta["cores"]
    names = list(thr[0]["stages_ms"])
    stages = {s: statistics.median(r["stages_ms"].get(s, 0.0) for r in thr) for s in names}
    stages_min = {s: min(r["stages_ms"].get(s, 0.0) for r in thr) for s in names}
    stages_p = {s: statistics.median(r["stages_ms"].get(s, 0.0) for r in prc) for s in names}
    stages_pt = {s: statistics.median(r["stages_ms"].get(s, 0.0) for r in per) for s in names}
    transport_pt = {g: v["transport_ms"] for g, v in measured_groups(per).items()}
    groups = measured_groups(prc)
    transport = {g: v["transport_ms"] for g, v in groups.items()}
    ov, halo = bands["overhead"], bands["halo_rows_share"]
    ov_safe = {k: max(ov[k], bands["overhead_user"][k], halo[k]) for k in ov}
    farm = pairs_ratio()
    mdl = model(stages_p, transport, ov_safe, ov_safe, farm, (stages_pt, transport_pt))
    variants = {
        "stages and transport in their processes, a thread a stage (the rule on more cores "
        "than processes)": model(stages_pt, transport_pt, ov_safe, ov_safe, farm),
        "stages as measured in the thread placement": model(stages, transport, ov_safe,
                                                            ov_safe, farm),
        "least CPU of the thread placement's rounds": model(stages_min, transport, ov_safe,
                                                            ov_safe, farm),
        "measured band ratio for the focus measure only": model(stages_p, transport, ov,
                                                                 ov_safe, farm),
        "measured band ratio for focus measure + accumulation + depth": model(
            stages_p, transport, ov, ov, farm),
    }
    pred = mdl["placements"][0]["fps"].get(cores) or min(
        cores / mdl["total_ms"], 1.0 / max(mdl["placements"][0]["groups_ms"].values())) * 1e3
    meas = med_of(prc, "fps")
    return {
        **meta,
        "depth_method": thr[0]["depth_method"], "threads": thr, "processes": prc,
        "processes_thread_a_stage": per,
        "stages_ms": stages, "stages_ms_min": stages_min, "stages_ms_processes": stages_p,
        "stages_ms_processes_thread_a_stage": stages_pt,
        "transport_ms": med_of(prc, "total_ms") - sum(stages_p.values()),
        "groups_measured": groups, "bands": bands, "model": mdl,
        "overhead_used": ov_safe, "variants": variants,
        "check": {"cores": cores, "predicted_fps": pred, "measured_fps": meas,
                  "runs_fps": [r["fps"] for r in prc], "ratio": meas / pred,
                  "cores_busy": meas * med_of(prc, "total_ms") / 1e3},
    }


if __name__ == "__main__":
    raise SystemExit(main())
