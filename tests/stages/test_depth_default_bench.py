"""bench/bench_depth_default.py's surface curves are a plate's: each pixel's curve peaks at
its true height, in levels; the e2e table reports the ratios it says."""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np

from tests.bench_modules import load_bench


def test_surface_curves_peak_at_the_plates_true_heights() -> None:
    b = load_bench("bench_depth_default")
    plan = b.frames(3)
    curves = b.SurfaceCurves(plan)
    x, y, _, c0, c1 = plan[0]
    n = b.demo_config().optics.n_levels
    stack = np.stack([curves(0, x, y, level, c0, c1) for level in range(n)])
    r0, u0 = y - curves.origin[1], x - curves.origin[0]
    truth = curves.levels[r0:r0 + stack.shape[1], u0 + c0:u0 + c1]
    assert stack.dtype == np.float32 and np.isfinite(stack).all()
    # the argmax is the nearest level to the true height where the contrast stands over
    # the floor's noise (the curves are Gaussians of sigma 2.5 levels)
    strong = curves.contrast[r0:r0 + stack.shape[1], u0 + c0:u0 + c1] > 0.05
    inside = (truth > 1.0) & (truth < n - 2.0)
    sel = strong & inside
    assert sel.mean() > 0.3
    err = np.abs(stack.argmax(axis=0) - truth)[sel]
    assert np.quantile(err, 0.99) <= 1.0


def test_e2e_table_gives_the_ratios_to_the_first_method(tmp_path: Path) -> None:
    b = load_bench("bench_depth_default")
    res = {"recording": "3 frames of a test",
           "runs": {"a": {"fps": [100.0, 110.0, 90.0], "depth_cpu_ms": [5.0, 4.0, 6.0]},
                    "b": {"fps": [99.0, 88.0, 77.0], "depth_cpu_ms": [4.4, 5.5, 6.6]}}}
    out = tmp_path / "t.md"
    b.write_e2e(res, ["a", "b"], argparse.Namespace(e2e="REC", execution="threads", rounds=3,
                                                    out=out))
    row = next(line for line in out.read_text().splitlines() if line.startswith("| b |"))
    cells = [c.strip() for c in row.strip("|").split("|")]
    # frames/s best 99 / 110, median 88 / 100; CPU least 4.4 / 4.0, median 5.5 / 5.0
    assert cells[4] == "0.900, 0.880"
    assert cells[8] == "1.100, 1.100"
