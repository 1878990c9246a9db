"""bench/bench_band_model.py: the scaling model of the band processes as built (the focus
worker paced by its K band processes' wall time a frame, the registration's pairs farmed
out), by hand on round figures, and the scans it is checked on."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from tests.bench_modules import load_bench

STAGES = {"source": 0.5, "speed_shift": 0.05, "registration": 4.0, "focus_measure": 3.0,
          "depth": 8.0, "mosaic": 3.0}
TRANSPORT = {"main": 1.0, "registration": 1.0, "focus": 2.0}


def test_groups_with_and_without_band_processes() -> None:
    bench = load_bench("bench_band_model")
    one = bench.band_groups(STAGES, TRANSPORT, 1, None, None, 0.5)
    # today's placement, a thread a stage: each process at its slowest stage's pace
    assert one["groups_ms"] == pytest.approx({"main": 4.0, "registration": 5.0, "focus": 10.0})
    assert one["total_ms"] == pytest.approx(18.55 + 4.0) and one["busiest"] == "focus"
    assert bench.fps(one, 8) == pytest.approx(100.0)
    four = bench.band_groups(STAGES, TRANSPORT, 4, 3.0, 13.0, 0.5)
    # the focus worker: the bands' wall time + its transport; the registration halved
    assert four["groups_ms"] == pytest.approx({"main": 4.0, "registration": 3.0, "focus": 5.0})
    assert four["total_ms"] == pytest.approx(22.55 - 11.0 + 13.0)
    assert bench.fps(four, 8) == pytest.approx(200.0)
    assert bench.fps(four, 2) == pytest.approx(2e3 / 24.55)  # the cores cap it
    with pytest.raises(ValueError, match="K = 4"):
        bench.band_groups(STAGES, TRANSPORT, 4, None, None, 0.5)
    # on no more cores than processes each process's stages add up
    few = bench.serial_groups(STAGES, TRANSPORT)
    assert few["groups_ms"] == pytest.approx({"main": 4.55, "registration": 5.0,
                                              "focus": 13.0})
    assert few["total_ms"] == pytest.approx(22.55) and few["busiest"] == "focus"
    assert bench.fps(few, 2) == pytest.approx(1e3 / 13.0)  # the focus worker caps it


def test_only_scans_with_band_processes_or_none_are_checked() -> None:
    bench = load_bench("bench_band_model")

    def row(**case: object) -> dict[str, object]:
        base = {"mode": "processes", "source": "memory", "record": False, "cores": 8}
        return {"case": {**base, **case}, "runs": [{"fps": 100.0, "cpu_ms_per_frame": 20.0},
                                                   {"fps": 120.0, "cpu_ms_per_frame": 22.0}]}

    got = bench.measured_scans({"rows": [
        row(), row(workers=4, bands="threads"), row(workers="auto", bands="processes"),
        row(mode="threads"), row(record=True)]})
    assert [(g["cores"], g["bands"], g["fps"]) for g in got] == [(8, 1, 110.0), (8, 6, 110.0)]
    assert bench.band_figures({"wall_ms_per_frame": {"1": [9.0], "4 processes": [3.0, 5.0]},
                               "cpu_ms_per_frame": {"1": [9.0], "4 processes": [12.0, 14.0]}}
                              ) == {4: (4.0, 13.0)}


def test_the_lent_machine_report(tmp_path: Path,
                                 capsys: pytest.CaptureFixture[str]) -> None:
    bench = load_bench("bench_band_model")
    res = bench.RESULTS
    out = tmp_path / "m.md"
    assert bench.main(["--scaling", str(res / "scaling_h200_overlapped.json"),
                       "--bands", str(res / "band_processes_h200.json"),
                       "--scans", str(res / "parallel_async_h200.json"),
                       "--out", str(out)]) == 0
    rows = json.loads(out.with_suffix(".json").read_text())
    assert {(r["cores"], r["bands"]) for r in rows} == {(8, 1), (8, 4), (16, 1), (16, 4),
                                                        (16, 8)}
    assert all(0.8 < r["ratio"] < 1.1 for r in rows)
    assert bench.main(["--scaling", str(tmp_path / "none.json"), "--bands", "x", "--scans",
                       "y", "--out", str(out)]) == 2
    assert "--scaling" in capsys.readouterr().err
    # a good scaling file and a bad bands file: the message names the bands file
    assert bench.main(["--scaling", str(res / "scaling_h200_overlapped.json"), "--bands",
                       str(tmp_path / "none.json"), "--scans", "y", "--out", str(out)]) == 2
    assert f"--bands {tmp_path / 'none.json'}:" in capsys.readouterr().err
