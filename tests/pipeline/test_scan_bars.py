"""The issue's accuracy bars, on small simulated scans (quarter-resolution thesis geometry).

Each test prints its figures (run with ``-s`` to see them); the README quotes them.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from sffscan.pipeline.config import max_speed_thesis_mm_s

from tests.scan_helpers import (
    mosaic_height,
    scan,
    score,
    small_config,
    stationary_height,
    strip_region,
)


@pytest.fixture(scope="module")
def reference(tmp_path_factory: pytest.TempPathFactory) -> dict:
    """The 15 mm/s scan, no wobble, and the stationary reference over the same pixels."""
    cfg = small_config()
    out = tmp_path_factory.mktemp("ref") / "scan.zarr"
    report = scan(cfg, out)
    region = strip_region(cfg)
    stat = stationary_height(cfg, region)
    mask = np.isfinite(stat)
    est = mosaic_height(out, region)
    return {"cfg": cfg, "report": report, "region": region, "mask": mask,
            "stationary": score(cfg, stat, region, mask), "scan": score(cfg, est, region, mask),
            "coverage": float(np.isfinite(est).mean())}


def test_scan_matches_stationary_measurement(reference: dict) -> None:
    stat, sc = reference["stationary"], reference["scan"]
    print(f"\n15 mm/s scan RMSE {sc.rmse_um:.1f} µm (CORR {sc.corr:.4f}) vs stationary "
          f"{stat.rmse_um:.1f} µm: ratio {sc.rmse_um / stat.rmse_um:.3f}")
    assert reference["coverage"] == 1.0  # the whole strip is measured
    assert reference["report"].result.dropped == 0
    assert sc.rmse_um <= 1.05 * stat.rmse_um
    assert sc.corr >= reference["stationary"].corr - 0.002


def test_faster_than_the_thesis_limit(reference: dict, tmp_path: Path) -> None:
    base = reference["cfg"]
    speed = 1.7 * max_speed_thesis_mm_s(base)
    cfg = small_config(motion={"speed_mm_s": speed})
    scan(cfg, tmp_path / "fast.zarr")
    region, mask = reference["region"], reference["mask"]
    est = mosaic_height(tmp_path / "fast.zarr", region)
    sc = score(cfg, est, region, mask)
    stat = reference["stationary"]
    print(f"\n{speed:.1f} mm/s (1.7x the thesis limit): RMSE {sc.rmse_um:.1f} µm, ratio to "
          f"stationary {sc.rmse_um / stat.rmse_um:.3f}, coverage {np.isfinite(est).mean():.4f}")
    assert np.isfinite(est).all()  # full coverage of the scanned strip
    assert sc.rmse_um <= 1.10 * stat.rmse_um


def test_registration_removes_wobble(reference: dict, tmp_path: Path) -> None:
    region, mask = reference["region"], reference["mask"]
    no_wobble = reference["scan"]
    results = {}
    for reg in (True, False):
        cfg = small_config(motion={"wobble_along_px": 3.0, "wobble_across_px": 3.0},
                           processing={"registration": reg})
        out = tmp_path / f"wobble-{reg}.zarr"
        scan(cfg, out)
        results[reg] = score(cfg, mosaic_height(out, region), region, mask)
    print(f"\nwobble ±3 px: RMSE with registration {results[True].rmse_um:.1f} µm "
          f"({results[True].rmse_um / no_wobble.rmse_um:.3f}x the no-wobble run), without "
          f"{results[False].rmse_um:.1f} µm ({results[False].rmse_um / no_wobble.rmse_um:.3f}x)")
    assert results[True].rmse_um <= 1.10 * no_wobble.rmse_um
    assert results[True].rmse_um < results[False].rmse_um
