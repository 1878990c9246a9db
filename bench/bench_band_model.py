"""The scaling model for the band processes as built (issue 28, item 3), checked against
scans measured with them. Measures nothing: it reads three results files the other benches
wrote on one machine and writes its report.

    python bench/bench_band_model.py --scaling bench/results/scaling_h200_overlapped.json \\
        --bands bench/results/band_processes_h200.json \\
        --scans bench/results/parallel_async_h200.json --out bench/results/band_model_h200.md

``bench_scaling.py``'s K-band placements model K workers that each receive every frame;
the band processes built (``processing.bands = "processes"``) are helpers of the focus
worker instead: its depth stage hands each frame's rows to K - 1 helper processes and its
own, which measure the focus of their rows and accumulate them; the focus measure stage
passes frames on. So, with K band processes, on more cores than processes (a thread a
stage):

- the focus worker is paced by the wall time a frame of the focus measure and depth stages
  with K band processes (``bench_bands.py --processes``: "K processes", measured on its
  own) plus that worker's transport (``bench_scaling.py``: its CPU beyond its stages, with a
  thread a stage);
- the registration worker by its stage's time, times the measured share of its slowest
  pair when its pairs are farmed out (``processing.workers`` > 1 does both;
  ``bench/results/registration_pairs.json``), plus its transport;
- the main process by its slowest stage plus its transport;
- the CPU a frame T: the stages' CPU with the two stages' replaced by the K band
  processes' CPU a frame, plus every process's transport;

and frames/s(C) = min(C / T, 1 / slowest group). With K = 1 (no band processes) the same
groups with the focus worker paced by its slower stage (today's placement,
``bench_scaling.overlapped_groups``); on no more cores than processes (3), where each
process runs its stages in one thread, today's placement with each process's stages added
up, from the runs in that placement; band processes there (sharing cores) are not
modelled. Not a test: nothing here asserts.
"""

from __future__ import annotations

import argparse
import json
import statistics
import sys
import time
from pathlib import Path
from typing import Any

sys.path.insert(0, str(Path(__file__).resolve().parent))
from bench_parallel import band_workers  # noqa: E402
from bench_scaling import (  # noqa: E402
    FOCUS,
    GROUP_STAGES,
    MAIN,
    PROCESSES,
    REG,
    RESULTS,
    measured_groups,
    overlapped_groups,
    pairs_ratio,
)


def serial_groups(stages: dict[str, float], transport: dict[str, float]) -> dict[str, Any]:
    """Today's placement with each process's stages in one thread (on no more cores than
    processes): a process's stages add up, its transport added."""
    own = {g: sum(stages.get(s, 0.0) for s in names) for g, names in GROUP_STAGES.items()}
    groups = {MAIN: sum(stages.values()) - sum(own.values()) + transport[MAIN],
              REG: own[REG] + transport[REG], FOCUS: own[FOCUS] + transport[FOCUS]}
    return {"bands": 1, "groups_ms": groups,
            "total_ms": sum(stages.values()) + sum(transport.values()),
            "busiest": max(groups, key=lambda g: groups[g])}


def band_groups(stages: dict[str, float], transport: dict[str, float], k: int,
                band_wall_ms: float | None, band_cpu_ms: float | None,
                farm_ratio: float | None) -> dict[str, Any]:
    """Groups (ms a frame), total CPU a frame and the busiest group of the focus worker with
    ``k`` band processes (``band_wall_ms`` / ``band_cpu_ms``: the focus measure and depth
    stages' wall and CPU a frame with them; ignored for ``k`` = 1), a thread a stage.
    ``farm_ratio``: the registration's time with its pairs farmed out against one thread
    (used for ``k`` > 1, as ``processing.workers`` > 1 farms them); None: not farmed."""
    groups = overlapped_groups(stages, transport)
    fd = sum(stages.get(s, 0.0) for s in GROUP_STAGES[FOCUS])
    total = sum(stages.values()) + sum(transport.values())
    if k > 1:
        if band_wall_ms is None or band_cpu_ms is None:
            raise ValueError(f"K = {k}: the band processes' wall and CPU a frame are needed")
        groups[FOCUS] = band_wall_ms + transport[FOCUS]
        if farm_ratio is not None:
            groups[REG] = stages.get("registration", 0.0) * farm_ratio + transport[REG]
        total += band_cpu_ms - fd
    busiest = max(groups, key=lambda g: groups[g])
    return {"bands": k, "groups_ms": groups, "total_ms": total, "busiest": busiest}


def pairs_machine() -> str:
    """The machine the registration's farmed-out share was measured on."""
    path = RESULTS / "registration_pairs.json"
    return str(json.loads(path.read_text(encoding="utf-8")).get("machine", "?"))


def fps(p: dict[str, Any], cores: int) -> float:
    """frames/s on ``cores`` cores: min(C / T, 1 / the busiest group's time)."""
    return min(cores / p["total_ms"], 1.0 / p["groups_ms"][p["busiest"]]) * 1e3


def band_figures(bands: dict[str, Any]) -> dict[int, tuple[float, float]]:
    """K -> (wall, CPU) ms a frame of the two stages with K band processes, medians over
    ``bench_bands.py``'s rounds ("K processes" rows)."""
    out = {}
    for key, walls in bands["wall_ms_per_frame"].items():
        if key.endswith(" processes"):
            k = int(key.split()[0])
            out[k] = (statistics.median(walls),
                      statistics.median(bands["cpu_ms_per_frame"][key]))
    return out


def measured_scans(scans: dict[str, Any]) -> list[dict[str, Any]]:
    """The process-placement scans from memory of a ``bench_parallel.py`` results file:
    cores, band processes K (1 without), median frames/s and CPU a frame."""
    out = []
    for row in scans["rows"]:
        case, runs = row["case"], row["runs"]
        if case["mode"] != "processes" or case["source"] != "memory" or case["record"]:
            continue
        k = band_workers(case)
        if k > 1 and case.get("bands") != "processes":
            continue  # band threads: not this model's
        out.append({"cores": case["cores"], "bands": k,
                    "fps": statistics.median(r["fps"] for r in runs),
                    "cpu_ms": statistics.median(r["cpu_ms_per_frame"] for r in runs),
                    "runs": [r["fps"] for r in runs]})
    return out


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--scaling", type=Path, required=True,
                    help="bench_scaling.py's results JSON (stages and transport)")
    ap.add_argument("--bands", type=Path, required=True,
                    help="bench_bands.py --processes results JSON")
    ap.add_argument("--scans", type=Path, required=True,
                    help="bench_parallel.py results JSON (the scans the model is checked on)")
    ap.add_argument("--out", type=Path, required=True, help="the report (.md; .json beside)")
    args = ap.parse_args(argv)
    what = "--scaling"
    try:
        sc = json.loads(args.scaling.read_text(encoding="utf-8"))
        stages = sc["stages_ms_processes_thread_a_stage"]
        transport = {g: v["transport_ms"]
                     for g, v in measured_groups(sc["processes_thread_a_stage"]).items()}
        stages_one = sc["stages_ms_processes"]  # one thread a process (<= 3 cores)
        transport_one = {g: v["transport_ms"] for g, v in sc["groups_measured"].items()}
        what = "--bands"
        bands = json.loads(args.bands.read_text(encoding="utf-8"))
        figs = band_figures(bands)
        what = "--scans"
        scans = json.loads(args.scans.read_text(encoding="utf-8"))
        measured = measured_scans(scans)
    except (OSError, ValueError, KeyError) as err:
        print(f"bench_band_model: {what} {getattr(args, what[2:])}: not a results file of "
              f"its bench ({err!r})", file=sys.stderr)
        return 2
    farm = pairs_ratio()
    rows = []
    for m in measured:
        k, few = m["bands"], m["cores"] <= PROCESSES
        if k > 1 and (few or k not in figs):
            continue  # band processes sharing cores; no bench_bands figure for that K
        wall, cpu = figs.get(k, (None, None))
        p = (serial_groups(stages_one, transport_one) if few
             else band_groups(stages, transport, k, wall, cpu, farm))
        pred = fps(p, m["cores"])
        rows.append({**m, **p, "predicted_fps": pred, "ratio": m["fps"] / pred})
    write(args, sc, bands, scans, farm, stages, transport, rows)
    return 0


def write(args: argparse.Namespace, sc: dict[str, Any], bands: dict[str, Any],
          scans: dict[str, Any], farm: float | None, stages: dict[str, float],
          transport: dict[str, float], rows: list[dict[str, Any]]) -> None:
    g = " ".join(f"{k} {v:.2f}" for k, v in transport.items())
    lines = [f"# The band processes' model against measured scans "
             f"({time.strftime('%Y-%m-%d %H:%M')})", "",
             "Command: `python bench/bench_band_model.py "
             + " ".join(sys.argv[1:]) + "` (measures nothing; the model: the script's "
             "docstring).", "",
             f"- Stages and transport: `{sc['command']}`, {sc['machine']}, {sc['date']}: "
             "stages (ms a frame, processes with a thread a stage) "
             + ", ".join(f"{s} {v:.2f}" for s, v in stages.items())
             + f"; transport {g}.",
             f"- Band processes: `{bands['command']}`, {bands['machine']}.",
             f"- Scans: `{scans['meta']['command']}`, {scans['meta']['machine']}.",
             f"- Registration farmed out: {farm:.3f} of one thread's time "
             f"(bench/results/registration_pairs.json, {pairs_machine()}: not measured on "
             "the scans' machine)" if farm is not None else
             "- Registration's pairs not farmed out (no registration_pairs.json).", "",
             "| cores | band processes K | groups ms a frame (main, registration, focus) |"
             " busiest | T ms | predicted frames/s | measured (median; runs) | "
             "measured / predicted | measured CPU ms a frame |",
             "|---:|---:|---|---|---:|---:|---|---:|---:|"]
    for r in rows:
        gr = ", ".join(f"{r['groups_ms'][x]:.2f}" for x in (MAIN, REG, FOCUS))
        lines.append(f"| {r['cores']} | {r['bands']} | {gr} | {r['busiest']} | "
                     f"{r['total_ms']:.2f} | {r['predicted_fps']:.0f} | {r['fps']:.1f} ("
                     f"{', '.join(f'{v:.0f}' for v in r['runs'])}) | {r['ratio']:.2f} | "
                     f"{r['cpu_ms']:.2f} |")
    lines.append("")
    args.out.write_text("\n".join(lines), encoding="utf-8")
    args.out.with_suffix(".json").write_text(json.dumps(rows, indent=1), encoding="utf-8")
    print("\n".join(lines))


if __name__ == "__main__":
    raise SystemExit(main())
