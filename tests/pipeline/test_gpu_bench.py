"""The prepared GPU run (bench/bench_gpu.py, issue 28 item 4) works here on CPU torch, so
that a session lent a GPU can run it in one call: its agreement section compares the torch
path with the scan's CPU path and must find them equal to float32 round-off; its report
is written; it refuses a CUDA device it cannot see."""

from __future__ import annotations

import json
import os
from pathlib import Path
from types import ModuleType

import numpy as np
import pytest
import zarr

from tests.bench_modules import load_bench

pytest.importorskip("torch")

def _bench() -> ModuleType:
    return load_bench("bench_gpu")


def test_agreement_of_the_torch_path_with_the_cpu_path() -> None:
    got = _bench().agreement("cpu", size_px=48)
    for op in ("glvm", "tenv"):
        assert got[f"{op} focus: largest difference / largest value"] < 1e-5
    assert got["argmax equal share"] == 1.0
    assert got["SPC depth: largest difference, levels"] < 1e-4
    assert got["SPC RMS error device, um"] == pytest.approx(got["SPC RMS error CPU, um"],
                                                            rel=1e-4)


def test_height_difference_counts_pixels_valid_in_one_mosaic_only(tmp_path: Path) -> None:
    for name, value in (("a", 1.0), ("b", 1.25)):
        h = np.full((4, 5), value, np.float32)
        h[0, 0] = np.nan
        if name == "b":
            h[1, 1] = np.nan
        zarr.open_group(str(tmp_path / name), mode="w").create_array(
            "height", shape=h.shape, dtype="f4")[...] = h
    d = _bench().height_difference(tmp_path / "a", tmp_path / "b")
    assert d == {"pixels valid in both": 18, "valid in one only": 1,
                 "RMS difference, um": 0.25, "largest difference, um": 0.25}


def test_main_writes_the_agreement_report_and_refuses_a_missing_cuda(tmp_path: Path) -> None:
    import torch

    b = _bench()
    assert b.main(["--device", "cpu", "--sections", "agreement", "--stack-px", "32",
                   "--out", str(tmp_path)]) == 0
    report = json.loads((tmp_path / "gpu_cpu.json").read_text())
    assert report["agreement"]["argmax equal share"] == 1.0
    md = (tmp_path / "gpu_cpu.md").read_text()
    assert "## 1. Agreement with the CPU path" in md and "## 3." not in md
    with pytest.raises(SystemExit):
        b.main(["--device", "cpu", "--sections", "agreement,nonsense", "--out", str(tmp_path)])
    if not torch.cuda.is_available():
        assert b.main(["--device", "cuda", "--out", str(tmp_path)]) == 2


def test_the_workers_environment_is_set_for_one_case_and_restored(
        monkeypatch: pytest.MonkeyPatch) -> None:
    """Section 3's third case sets OMP_NUM_THREADS for the scan's workers only."""
    env = _bench().worker_env
    monkeypatch.delenv("SFFSCAN_TEST_ENV", raising=False)
    with env("SFFSCAN_TEST_ENV", "1"):
        assert os.environ["SFFSCAN_TEST_ENV"] == "1"
    assert "SFFSCAN_TEST_ENV" not in os.environ
    monkeypatch.setenv("SFFSCAN_TEST_ENV", "4")
    with env("SFFSCAN_TEST_ENV", "1"):
        assert os.environ["SFFSCAN_TEST_ENV"] == "1"
    assert os.environ["SFFSCAN_TEST_ENV"] == "4"
    with env("SFFSCAN_TEST_ENV", None):  # left as it is
        assert os.environ["SFFSCAN_TEST_ENV"] == "4"
