"""The scaling model of bench/bench_scaling.py (issue 28 item 3) with the registration's
pairs farmed out: the measured ratio from bench_registration_pairs.py's results shortens
the registration worker's time a frame, not the total CPU, and without it those
placements are left out."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from tests.bench_modules import load_bench

STAGES = {"source": 0.5, "speed_shift": 0.05, "registration": 2.8, "focus_measure": 2.6,
          "depth": 5.4, "mosaic": 2.2}
TRANSPORT = {"main": 0.7, "registration": 0.6, "focus": 0.4}
OVERHEAD = {str(k): 1.0 for k in (1, 2, 4, 8, 16)}


def test_farmed_registration_takes_the_measured_ratio(tmp_path: Path) -> None:
    bench = load_bench("bench_scaling")
    results = tmp_path / "registration_pairs.json"
    results.write_text(json.dumps({"critical_ms": 1.5, "one_thread_ms": 3.0, "rest_ms": 0.8,
                                   "downsampling_ms": 1.0, "pair_ms": {"1": 0.8}}))
    ratio = bench.pairs_ratio(results)
    assert ratio == pytest.approx(0.5)
    assert bench.pairs_ratio(tmp_path / "missing.json") is None
    m = bench.model(STAGES, TRANSPORT, OVERHEAD, OVERHEAD, ratio)
    one = {p["bands"]: p for p in m["placements"] if not p["registration_farmed"]}
    farmed = {p["bands"]: p for p in m["placements"] if p["registration_farmed"]}
    assert set(farmed) == {2, 4, 8, 16}
    x = TRANSPORT["registration"] / 2  # one message end
    for k, p in farmed.items():
        # the registration's own time halved, its receive, sends (K) the same; CPU the same
        assert p["groups_ms"]["registration"] == pytest.approx(
            2.8 * 0.5 + 0.6 + (k - 1) * x)
        assert one[k]["groups_ms"]["registration"] == pytest.approx(2.8 + 0.6 + (k - 1) * x)
        assert p["total_ms"] == pytest.approx(one[k]["total_ms"])
        assert all(p["fps"][c] >= one[k]["fps"][c] for c in (2, 4, 8, 16))
    assert farmed[4]["fps"][8] > one[4]["fps"][8]  # the registration capped K = 4 bands
    unfarmed = bench.model(STAGES, TRANSPORT, OVERHEAD, OVERHEAD, None)
    assert not any(p["registration_farmed"] for p in unfarmed["placements"])
