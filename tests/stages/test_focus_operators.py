"""Every toolbox operator against an independent float64 numpy reference on pertuz-simu02.

The references (:mod:`tests.fm_reference`) follow Pertuz's ``focusmeasure.m`` definitions
with MATLAB's borders. The bar of the issue: 1e-5 relative. float64 torch is checked per
pixel (``|a - b| <= 1e-5 |b|``, with a floor of 1e-9 x the map's largest value for the
operators whose result is signed and crosses zero: DCTM, VOLA, VOLS); float32 torch is
checked as ``max|a - b| <= 1e-5 max|b|`` per image (measured: at most 1.1e-6, GLLV).
Three of the 30 images (the nearest, a middle and the farthest focus) keep the slow
window operators (HISE, EIGV, CHEB) to seconds.
"""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import pytest
import torch
from sffscan.stages.focus_measure import focus_measure
from sffscan.stages.operators import FOCUS_OPERATORS, check_operator, operator_reach

from sffscan import focus_measure as api_focus_measure
from tests.fm_reference import REFERENCES as TOOLBOX_REFERENCES
from tests.wavelet_reference import WAVELET_REFERENCES

REFERENCES = {**TOOLBOX_REFERENCES, **WAVELET_REFERENCES}

WINDOW = 9
REL_TOL = 1e-5
FLOOR = 1e-9


@pytest.fixture(scope="module")
def images(pertuz_dir: Path) -> np.ndarray:
    out = []
    for i in (1, 15, 30):
        raw = cv2.imread(str(pertuz_dir / f"im_{i:02d}.tif"), cv2.IMREAD_UNCHANGED)
        assert raw is not None and raw.dtype == np.uint8
        out.append(raw.astype(np.float64) / 255.0)
    return np.stack(out)


def test_every_operator_has_a_reference() -> None:
    assert set(FOCUS_OPERATORS) == set(REFERENCES)
    assert len(FOCUS_OPERATORS) == 34
    for name, op in FOCUS_OPERATORS.items():
        assert op.name == name and op.torch_function().__name__ == name


@pytest.mark.parametrize("operator", FOCUS_OPERATORS)
def test_operator_matches_reference(operator: str, images: np.ndarray, device: str) -> None:
    ref = np.stack([REFERENCES[operator](im, WINDOW) for im in images])
    assert np.isfinite(ref).all()
    definition = FOCUS_OPERATORS[operator].torch_function()
    t64 = definition(torch.from_numpy(images).to(device), WINDOW)
    assert t64.dtype == torch.float64 and t64.device.type == torch.device(device).type
    a64 = t64.cpu().numpy()
    bad = np.abs(a64 - ref) > REL_TOL * np.abs(ref) + FLOOR * np.abs(ref).max()
    assert not bad.any(), f"{operator}: {bad.sum()} px off, worst {np.abs(a64 - ref).max():.3g}"
    x32 = torch.from_numpy(images.astype(np.float32)).to(device)
    a32 = definition(x32, WINDOW)
    assert a32.dtype == torch.float32 and a32.device.type == torch.device(device).type
    err = np.abs(a32.cpu().numpy() - ref).reshape(len(ref), -1).max(axis=1)
    assert (err <= REL_TOL * np.abs(ref).reshape(len(ref), -1).max(axis=1)).all()


def test_tenv_is_the_sample_variance(images: np.ndarray) -> None:
    """TENV = n / (n - 1) x the population variance in the interior (the 1.25 % at k = 9
    the project's old TENV lacked), and TENV_STD is its square root."""
    x = torch.from_numpy(images[:1])
    tenv = FOCUS_OPERATORS["tenv"].torch_function()(x, WINDOW).numpy()
    std = FOCUS_OPERATORS["tenv_std"].torch_function()(x, WINDOW).numpy()
    np.testing.assert_allclose(std**2, tenv, rtol=1e-12, atol=1e-14 * tenv.max())
    from tests.fm_reference import _sobel_g, nl_windows

    win = nl_windows(_sobel_g(images[0]), WINDOW, mode="symmetric")
    population = win.reshape(*images[0].shape, -1).var(axis=-1)
    inner = (slice(10, -10), slice(10, -10))
    ratio = tenv[0][inner] / population[inner]
    np.testing.assert_allclose(ratio[population[inner] > 1e-6 * population.max()],
                               81 / 80, rtol=1e-9)


@pytest.mark.parametrize("name", ["LAPM", "lapm", "LapM"])
def test_public_api_is_case_insensitive(name: str, images: np.ndarray) -> None:
    img = images[0].astype(np.float32)
    out = api_focus_measure(img, operator=name, window=WINDOW)
    ref = REFERENCES["lapm"](images[0], WINDOW)
    assert out.shape == img.shape and out.dtype == np.float32
    assert np.abs(out - ref).max() <= REL_TOL * np.abs(ref).max()


@pytest.mark.parametrize("operator", ["glvm", "tenv", "lapm", "dcte", "vola"])
def test_reach_covers_the_border(operator: str, images: np.ndarray) -> None:
    """Beyond ``operator_reach`` px from the border a crop's result equals the whole
    image's: what the scan's focus stage relies on when it measures column ranges."""
    full = focus_measure(images[1].astype(np.float32), operator=operator, window=WINDOW)
    crop = focus_measure(images[1, :, 40:140].astype(np.float32), operator=operator,
                         window=WINDOW)
    m = operator_reach(operator, WINDOW)
    np.testing.assert_allclose(crop[:, m:-m], full[:, 40 + m:140 - m], rtol=1e-5,
                               atol=1e-6 * np.abs(full).max())
    assert not np.allclose(crop[:, :1], full[:, 40:41])  # the border does differ


def test_unknown_operator_names_the_choices() -> None:
    with pytest.raises(ValueError, match="lapm"):
        check_operator("wavc")
    assert check_operator("TENV_STD") == "tenv_std"


def test_config_and_cli_offer_every_operator() -> None:
    import typing

    from sffscan.pipeline.cli.common import OPERATOR_CHOICES
    from sffscan.pipeline.config import ProcessingConfig

    field = ProcessingConfig.model_fields["focus_operator"].annotation
    assert tuple(typing.get_args(field)) == OPERATOR_CHOICES == tuple(FOCUS_OPERATORS)
    cfg = ProcessingConfig(focus_operator="LAPM")  # type: ignore[arg-type]
    assert cfg.focus_operator == "lapm"
    assert cfg.focus_reach_px == operator_reach("lapm", cfg.window)


def test_registry_loads_neither_torch_nor_opencv() -> None:
    """The configuration's choices come from the registry: importing it stays light."""
    import subprocess
    import sys

    code = ("import sys\n"
            "from sffscan.stages.operators import FOCUS_OPERATORS, operator_reach\n"
            "assert len(tuple(FOCUS_OPERATORS)) == 34 and operator_reach('glvm', 9) == 8\n"
            "loaded = {'torch', 'cv2', 'numpy'} & set(sys.modules)\n"
            "assert not loaded, loaded\n")
    done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                          timeout=120)
    assert done.returncode == 0, done.stderr
