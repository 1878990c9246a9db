"""bench/bench_parallel.py's case labels and the busiest stage it reports (the figures a
lent many-core machine's run is read by)."""

from __future__ import annotations

from tests.bench_modules import load_bench


def _case(**kw: object) -> dict[str, object]:
    return {"source": "memory", "mode": "processes", "record": False, "cores": 8, **kw}


def test_auto_workers_are_labelled_as_resolved_under_the_pinning() -> None:
    label = load_bench("bench_parallel").label
    assert "auto = 6 band workers in band processes" in label(
        _case(workers="auto", bands="processes"))
    # 'auto' on 2 cores is one band: no band processes, whatever the kind asked for
    two = label(_case(cores=2, workers="auto", bands="processes"))
    assert "auto = 1 band workers" in two and "band processes" not in two
    assert "band" not in label(_case(workers=1, bands="processes"))
    assert "4 band workers in band processes" in label(_case(workers=4, bands="processes"))


def test_busiest_stage_is_the_one_with_most_wall_time_a_frame() -> None:
    busiest = load_bench("bench_parallel").busiest
    runs = [{"fps": 100.0, "busy": {"registration": 4.0, "depth": 9.0}},
            {"fps": 125.0, "busy": {"registration": 5.0, "depth": 7.0}},
            {"fps": 80.0, "busy": {"registration": 6.0, "depth": 8.0}}]
    # medians: depth 8.0, registration 5.0; the period 1000 / 100 frames/s
    assert busiest(runs) == "depth 8.00 / 10.00 ms"
    assert busiest([{"fps": 100.0}]) == ""  # runs from before the figure was kept


def test_cases_that_run_the_same_placement_run_once() -> None:
    unique = load_bench("bench_parallel").unique_cases
    cases = [_case(cores=c, workers=k, bands=b) for c in (2, 8) for k in (1, 4, "auto")
             for b in ("threads", "processes")]
    got = unique(cases)
    # 2 cores: 1 and auto (= 1) one case, 4 in threads and in processes; 8 cores: 1 once,
    # 4 and auto (= 6) each in threads and processes
    assert [(g["cores"], g["workers"], g["bands"]) for g in got] == [
        (2, 1, "threads"), (2, 4, "threads"), (2, 4, "processes"),
        (8, 1, "threads"), (8, 4, "threads"), (8, 4, "processes"),
        (8, "auto", "threads"), (8, "auto", "processes")]


def test_a_report_cut_short_is_written(tmp_path) -> None:  # type: ignore[no-untyped-def]
    # a lent machine's run, cut short after its first round, lost its report: the file
    # creation times had only their 'before' figure then
    bench = load_bench("bench_parallel")
    run = {"fps": 100.0, "fps_with_startup": 90.0, "startup_s": 1.0, "cpu_ms_per_frame": 20.0,
           "busy": {"depth": 8.0}}
    meta = {"machine": "m", "load_before": "1", "load_after": "(cut short)", "command": "c",
            "frames": 10, "rounds": 1, "run_s": 5.0, "baseline_fps": 10.0, "method": "x",
            "file_create_ms": {str(tmp_path): [0.25]}}
    out = tmp_path / "r.md"
    bench.write_report(out, meta, [{"case": _case(), "runs": [run]}])
    text = out.read_text(encoding="utf-8")
    assert "0.250 ms of CPU before the runs (median" in text
    assert "| 100.0 |" in text and "depth 8.00 / 10.00 ms" in text
    meta["file_create_ms"] = {str(tmp_path): [0.25, 0.5]}
    bench.write_report(out, meta, [{"case": _case(), "runs": [run]}])
    assert "before the runs, 0.500 after" in out.read_text(encoding="utf-8")
