"""Verdict latency of a print job, cold and warm: from the end of a layer's scan to its
verdict written, on the demo plate (issue 25's bar: <= 3 s for a 20 x 20 mm layer).

Each configuration runs in a **fresh Python process** (so its first layer pays the imports
and the cold expected map, as the first layer of a real job after ``sffscan serve`` starts):

- ``service``: the path a printer uses: ``JobService`` (not strict: the analysis runs in its
  background worker while the next layer is scanned) with the default ``JobStoreHandler``
  (simulated source, the print built from the G-code's beads). The scan's end is when
  ``JobService.layer`` returns; the verdict's time is the modification time of the layer's
  ``verdict.json`` (written last). On this 2-core machine the next layer's scan competes
  with the analysis for the cores, as on a printer's host.
- ``demo``: ``sffscan job demo``'s loop (``run_simulated_print``): the analysis right after
  the scan, nothing else running (its ``verdict_s``).

Writes ``bench/verdict_latency_results.md`` (and ``.json``). Usage::

    nice -n 10 python bench/bench_verdict_latency.py [--layers 3] [--out PREFIX]
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

CHILD = r'''
import json, sys, time
from pathlib import Path
t_start = time.time()
kind, layers, folder = sys.argv[1], int(sys.argv[2]), Path(sys.argv[3])
from sffscan.pipeline.printjob import demo
out = []
if kind.startswith("service"):
    from sffscan.pipeline.printjob.links_store import JobStoreHandler
    from sffscan.pipeline.printjob.service import JobEnd, JobService, JobStart, LayerEvent
    from sffscan.pipeline.printjob.gcode import read_gcode
    zs = read_gcode(demo.demo_gcode()).layer_z_mm
    handler = JobStoreHandler(demo.demo_config(), gcode_dir=demo.demo_gcode().parent,
                              mapping=demo.DEMO_MAPPING, record=False,
                              prepare_ahead=kind != "service-noprep")
    ends = {}
    with JobService(folder, handler, scan_timeout_s=600, verdict_timeout_s=600) as svc:
        svc.start_job(JobStart(job_id="bench", gcode_name=demo.demo_gcode().name))
        for k in range(layers):
            t0 = time.time()
            rec = svc.layer("bench", LayerEvent(layer=k, z_mm=float(zs[k]))).record
            ends[k] = (t0, time.time(), rec.scan)
        svc.end_job("bench", JobEnd(), wait_s=600)
        from sffscan.pipeline.printjob.jobstore import JobStore
        store = JobStore.open(folder / "bench" / "job")
        for k in range(layers):
            r = svc.record("bench", k)
            verdict = store.verdict_path(k)
            t_v = verdict.stat().st_mtime if verdict.is_file() else None
            out.append({"layer": k, "scan_s": ends[k][1] - ends[k][0],
                        "latency_s": None if t_v is None else t_v - ends[k][1],
                        "analysis_s": r.analysis_s, "verdict": r.verdict,
                        "reason": r.reason[:120]})
else:
    def on_layer(k, v, t):
        out.append({"layer": k, "scan_s": t.get("scan_s"), "latency_s": t.get("verdict_s"),
                    "verdict": v.verdict, "reason": v.reason[:120]})
    demo.run_simulated_print(folder / "job", defects=(), layers=list(range(layers)),
                             config=demo.demo_config(), on_layer=on_layer)
print(json.dumps({"layers": out, "process_s": time.time() - t_start}))
'''


def run(kind: str, layers: int) -> dict[str, Any]:
    with tempfile.TemporaryDirectory(prefix=f"sffscan-latency-{kind}-") as d:
        t0 = time.perf_counter()
        proc = subprocess.run([sys.executable, "-c", CHILD, kind, str(layers), d],
                              capture_output=True, text=True, timeout=3600, check=False)
        if proc.returncode != 0:
            raise SystemExit(f"{kind}: exit {proc.returncode}\n{proc.stderr[-3000:]}")
        got = json.loads(proc.stdout.strip().splitlines()[-1])
        got["wall_s"] = time.perf_counter() - t0
        return got


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--layers", type=int, default=3)
    ap.add_argument("--paths", default="service,demo",
                    help="comma-separated: service, service-noprep (no expected map made "
                         "during the scan), demo")
    ap.add_argument("--out", default=str(Path(__file__).with_name("verdict_latency_results")))
    args = ap.parse_args()
    results = {kind: run(kind, args.layers) for kind in args.paths.split(",")}
    sys.path.insert(0, str(Path(__file__).resolve().parent))
    from bench_pipeline import machine  # after the runs: it imports the pipeline and torch
    lines = ["# Verdict latency (issue 25): scan end -> verdict written", "",
             f"`python bench/bench_verdict_latency.py --layers {args.layers} --paths "
             f"{args.paths}`, "
             f"{time.strftime('%Y-%m-%d %H:%M UTC', time.gmtime())}, "
             f"{machine()} (a shared VM: other jobs may have run meanwhile). Each row set "
             "is one fresh process: layer 0 is cold (imports, first expected map).", "",
             "| path | layer | scan s | verdict after scan end, s | verdict | reason (start) |",
             "|---|---|---|---|---|---|"]
    for kind, got in results.items():
        for r in got["layers"]:
            lat = "–" if r["latency_s"] is None else f"{r['latency_s']:.2f}"
            why = r.get("reason", "")[:60].replace("|", "/")
            lines.append(f"| {kind} | {r['layer']} | {r['scan_s']:.1f} | {lat} | "
                         f"{r['verdict']} | {why} |")
    lines += ["", "`service`: JobService (not strict) + JobStoreHandler, the verdict's time "
              "from verdict.json's mtime; `demo`: run_simulated_print's loop (analysis right "
              "after the scan). The bar: <= 3 s."]
    Path(args.out + ".md").write_text("\n".join(lines) + "\n", encoding="utf-8")
    Path(args.out + ".json").write_text(json.dumps(results, indent=2) + "\n",
                                        encoding="utf-8")
    print("\n".join(lines))
    return 0


if __name__ == "__main__":
    sys.exit(main())
