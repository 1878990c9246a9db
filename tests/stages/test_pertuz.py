"""pertuz-simu02 (third-party stack with a true depth map): stationary reconstruction accuracy.

Every depth method x focus operator is scored over ALL ROI pixels (217 x 217), without
and with the confidence-weighted median post-filter (`stages.fields.stationary`); ``pytest -s``
prints the table that the README gives. Focus step 15.5 mm; toolbox figure: GLVM 9 +
argmax 36.9 mm.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import scipy.io
from sffscan.pipeline.cli.main import main
from sffscan.stages.depth import DEFAULT_METHOD, DEPTH_METHODS
from sffscan.stages.fields.stack_io import read_image_stack
from sffscan.stages.fields.stationary import StackSettings, reconstruct_field

OPERATORS = ("glvm", "tenv")  # the table's columns (every operator: test_focus_operators)
BAR_M = 0.015  # the bar over all ROI pixels
# Measured 2026-11-30 with the documented settings (GLVM 9, the default depth method
# "adaptive", weighted median 15): 4.43 mm (gauss3, the default before: 4.48 mm); a
# regression of more than 1 mm fails.
DOCUMENTED_M = 0.00443


@pytest.fixture(scope="module")
def pertuz(pertuz_dir: Path) -> dict[str, np.ndarray]:
    im = scipy.io.loadmat(pertuz_dir / "imdata.mat", squeeze_me=True,
                          struct_as_record=False)["imdata"]
    stack = read_image_stack([pertuz_dir / f"im_{i:02d}.tif" for i in range(1, 31)])
    x, y, w, h = (int(v) for v in im.ROI)
    roi = np.zeros(stack.shape[1:], dtype=bool)
    roi[y - 1:y - 1 + h, x - 1:x - 1 + w] = True
    return {"stack": stack, "focus_um": np.asarray(im.focus, dtype=np.float64) * 1e6,
            "truth_um": np.asarray(im.z, dtype=np.float64) * 1e6, "roi": roi}


def _rmse_m(z_um: np.ndarray, p: dict[str, np.ndarray]) -> float:
    e = (z_um.astype(np.float64) - p["truth_um"])[p["roi"]]
    assert np.isfinite(e).all(), "every ROI pixel must have a height (nothing left out)"
    return float(np.sqrt(np.mean(e**2))) / 1e6


def test_pertuz_full_table(pertuz: dict[str, np.ndarray]) -> None:
    raw: dict[tuple[str, str], float] = {}
    filtered: dict[tuple[str, str], float] = {}
    for op in OPERATORS:
        for method in DEPTH_METHODS:
            r = reconstruct_field(pertuz["stack"], focus_heights_um=pertuz["focus_um"],
                                  settings=StackSettings(operator=op, method=method))
            raw[op, method] = _rmse_m(r.raw_height_um, pertuz)
            filtered[op, method] = _rmse_m(r.height_um, pertuz)
            assert np.isfinite(r.height_um).all()  # the filter leaves out / fills nothing
    step_mm = float(np.mean(np.diff(pertuz["focus_um"]))) / 1e3
    print(f"\npertuz-simu02, window 9, ROI RMSE over all {int(pertuz['roi'].sum())} px, mm "
          f"(focus step {step_mm:.1f} mm): raw / confidence-weighted median 15x15")
    print("| method | GLVM raw | GLVM filtered | TENV raw | TENV filtered |")
    for method in DEPTH_METHODS:
        cells = " | ".join(f"{raw[op, method] * 1e3:.1f} | {filtered[op, method] * 1e3:.1f}"
                           for op in OPERATORS)
        print(f"| {method} | {cells} |")

    assert 0.030 <= raw["glvm", "argmax"] <= 0.045  # the toolbox's 36.9 mm
    best = filtered["glvm", DEFAULT_METHOD]  # the documented settings = StackSettings()
    assert best <= BAR_M
    assert abs(best - DOCUMENTED_M) <= 0.001
    assert best <= filtered["glvm", "gauss3"]  # stack's default before
    for key in raw:  # the post-filter helps every combination on this stack
        assert filtered[key] < raw[key], key


def test_pertuz_filter_size_sweep(pertuz: dict[str, np.ndarray]) -> None:
    """The bar is met by a range of filter sizes, not one tuned value."""
    out = {}
    for size in (1, 9, 15, 21):
        r = reconstruct_field(pertuz["stack"], focus_heights_um=pertuz["focus_um"],
                              settings=StackSettings(filter_size=size))
        out[size] = _rmse_m(r.height_um, pertuz)
    print(f"\npertuz-simu02, GLVM 9 {DEFAULT_METHOD}, weighted median size -> ROI RMSE mm: "
          + ", ".join(f"{k}: {v * 1e3:.1f}" for k, v in out.items()))
    assert out[1] > 0.010  # no filter: the raw figure (13.9 mm)
    assert out[15] <= BAR_M and out[21] <= BAR_M
    assert out[9] < out[1]


def test_pertuz_stack_and_compare_commands(pertuz_dir: Path, pertuz: dict[str, np.ndarray],
                                           tmp_path: Path,
                                           capsys: pytest.CaptureFixture[str]) -> None:
    np.savetxt(tmp_path / "focus_m.txt", pertuz["focus_um"] / 1e6)
    np.save(tmp_path / "truth_um.npy", pertuz["truth_um"])
    images = [str(pertuz_dir / f"im_{i:02d}.tif") for i in range(1, 31)]
    out = tmp_path / "pz.zarr"
    assert main(["stack", *images, "--focus-file", str(tmp_path / "focus_m.txt"),
                 "--focus-unit", "m", "--pixel-um", "1", "-o", str(out)]) == 0
    capsys.readouterr()
    assert main(["compare", str(out), str(tmp_path / "truth_um.npy"),
                 "--region", "19,19,236,236", "--json", str(tmp_path / "c.json")]) == 0
    from sffscan.pipeline.metrology.compare import CompareReport

    rep = CompareReport.model_validate_json((tmp_path / "c.json").read_text())
    assert rep.pixels == 217 * 217 and rep.coverage == 1.0
    assert rep.rmse_um is not None and abs(rep.rmse_um / 1e6 - DOCUMENTED_M) <= 0.001
