"""bench/bench_depth_pooled.py pools what it says: RMSE over the stacks of the seeds given,
per family and per set of six, and the pooled best method's own worst set."""

from __future__ import annotations

import json
import math
from collections.abc import Callable
from pathlib import Path

import numpy as np
import pytest

from tests.bench_modules import load_bench


def test_ratios_pool_squared_errors_over_pixels() -> None:
    b = load_bench("bench_depth_pooled")
    rows = [(1, ([4.0, 9.0], 1)), (2, ([0.0, 7.0], 3)), (3, ([100.0, 0.0], 1))]
    np.testing.assert_allclose(b.ratios(rows, [1, 2]), [math.sqrt(4 / 4), math.sqrt(16 / 4)])
    np.testing.assert_allclose(b.ratios(rows, [3]), [10.0, 0.0])


def _run_on(b, tmp_path: Path, monkeypatch: pytest.MonkeyPatch, seeds: int,  # noqa: ANN001
            default_sse: Callable[[int], float], *, others: float) -> tuple[dict, str]:
    """bench_depth_pooled's main on one family whose stacks (100 pixels each) give the
    default ``default_sse(seed)``, wcentroid 100 and every other method ``others``: its row
    and its table."""
    methods = list(b.DEPTH_METHODS)
    d, wc = methods.index(b.DEFAULT_METHOD), methods.index("wcentroid")

    def fake_scores(score, seeds, *, imdata, jobs, blur_model):  # noqa: ANN001, ANN202 - the hook
        assert blur_model == "gather"  # the bench's default: the study's generator
        out = []
        for s in seeds:
            sse = [others] * len(methods)
            sse[d], sse[wc] = default_sse(s), 100.0
            out.append((s, (sse, 100)))
        return {"fam": out}

    monkeypatch.setattr(b, "NAMES", ["fam"])
    monkeypatch.setattr(b, "score_stacks", fake_scores)
    out = tmp_path / "t"
    assert b.main(["--seeds", "0", str(seeds), "--imdata", "", "--out", str(out)]) == 0
    row = json.loads(out.with_suffix(".json").read_text())["rows"][0]
    return row, out.with_suffix(".md").read_text()


def test_table_from_known_errors(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    b = load_bench("bench_depth_pooled")
    # first set of six: the default 1.21x wcentroid's squared error; second: 0.64x
    row, table = _run_on(b, tmp_path, monkeypatch, 12, lambda s: 121.0 if s < 6 else 64.0,
                         others=100.0)
    # pooled: the default's sum 6 * 121 + 6 * 64 against wcentroid's (and the others') 1200
    assert row["best"] == b.DEFAULT_METHOD
    assert row["default_over_best"] == pytest.approx(1.0)
    assert row["worst_set"] == pytest.approx(1.1)  # sqrt(121 / 100) on seeds 0..5
    assert row["sets_over_1_05"] == 1
    assert row["pooled_best_worst_set"] == pytest.approx(1.1)
    assert "1 of 2" in table
    # each stack's RMSE per method, for comparing two runs stack by stack
    assert set(row["stack_rmse_levels"]) == {str(s) for s in range(12)}
    assert row["stack_rmse_levels"]["0"][b.DEFAULT_METHOD] == pytest.approx(1.1)  # sqrt(121/100)
    assert row["stack_rmse_levels"]["7"]["wcentroid"] == pytest.approx(1.0)


def test_per_stack_ratios_against_each_stacks_best(tmp_path: Path,
                                                   monkeypatch: pytest.MonkeyPatch) -> None:
    b = load_bench("bench_depth_pooled")
    default_sse = {3: 169.0, 4: 125.44}  # 1.3x and 1.12x wcentroid's RMSE; the rest 1.0x
    row, table = _run_on(b, tmp_path, monkeypatch, 6, lambda s: default_sse.get(s, 100.0),
                         others=400.0)
    assert row["stacks_over_1_10"] == 2
    assert row["worst_stack"] == pytest.approx(1.3)
    assert row["worst_stack_seed"] == 3
    # wcentroid, the pooled best, is each stack's best: none over
    assert row["best"] == "wcentroid" and row["pooled_best_stacks_over_1_10"] == 0
    assert "| 2 of 6 | 1.300x (3) | 0 of 6 |" in table


def test_compare_reads_two_runs_stack_by_stack(tmp_path: Path) -> None:
    """compare_depth_pooled: per family the pooled ratios and the stacks over the line in
    each run, then every stack that crossed it, with both ratios; runs that do not match
    are refused by name."""
    c = load_bench("compare_depth_pooled")

    def run(name: str, stacks: dict[str, dict[str, float]], pooled: float) -> Path:
        path = tmp_path / name
        path.write_text(json.dumps({"default": "shape_select", "rows": [
            {"family": "fam", "default_over_best": pooled, "stack_rmse_levels": stacks}]}))
        return path

    a = run("a.json", {"1": {"shape_select": 2.0, "pc": 1.0},
                       "2": {"shape_select": 1.0, "pc": 1.05}}, 1.3)
    b = run("b.json", {"1": {"shape_select": 1.0, "pc": 1.0},
                       "2": {"shape_select": 1.2, "pc": 1.0}}, 1.1)
    lines = c.compare(a, b, over=1.10)
    assert "| fam | 1.300x | 1.100x | 1 -> 1 |" in lines
    assert "- fam seed 1: 2.000x -> 1.000x" in lines
    assert "- fam seed 2: 1.000x -> 1.200x" in lines
    other = run("c.json", {"3": {"shape_select": 1.0, "pc": 1.0}}, 1.0)
    with pytest.raises(SystemExit, match="fam: the runs hold different seeds"):
        c.compare(a, other)
    (tmp_path / "bad.json").write_text("{}")
    with pytest.raises(SystemExit, match="bad.json: not a bench_depth_pooled.py JSON"):
        c.compare(a, tmp_path / "bad.json")
