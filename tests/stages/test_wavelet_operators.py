"""WAVS, WAVV, WAVR: MATLAB's wavelet conventions, established piece by piece.

The operators themselves are checked against the independent reference
(:mod:`tests.wavelet_reference`) with every other operator in ``test_focus_operators.py``.
Here: the reference's (and PyWavelets') decomposition against MATLAB's own ``dwt`` output,
its filters against Daubechies' conditions, its reconstruction (MATLAB's ``upsconv2`` and
central ``wkeep2``) by perfect reconstruction, and the decimation grid that crops (the
scan's focus stage) must start on.
"""

from __future__ import annotations

import json
import math
from pathlib import Path

import cv2
import numpy as np
import pytest
import torch
from sffscan.stages.focus_measure import FocusMeasureStage, focus_measure
from sffscan.stages.messages import FrameHeader, PlacedFrame
from sffscan.stages.operators import FOCUS_OPERATORS, operator_alignment, operator_reach
from sffscan.stages.operators.wavelets import LEVELS

from tests import wavelet_reference as ref

WAVELET_OPERATORS = {name: op.torch_function() for name, op in FOCUS_OPERATORS.items()
                     if op.module == "wavelets"}

MATLAB = Path(__file__).resolve().parents[1] / "data" / "matlab_dwt_db6_sym.json"


@pytest.fixture(scope="module")
def image(pertuz_dir: Path) -> np.ndarray:
    raw = cv2.imread(str(pertuz_dir / "im_15.tif"), cv2.IMREAD_UNCHANGED)
    assert raw is not None
    return raw.astype(np.float64) / 255.0


def test_decomposition_matches_matlab_output() -> None:
    """MATLAB R2012a's ``dwt(data, 'db6', 'mode', 'sym')`` of an even and an odd length (the
    default mode of ``wavedec2``): the reference and PyWavelets both to 1e-10."""
    import pywt

    cases = json.loads(MATLAB.read_text())["cases"]
    assert [len(c["data"]) for c in cases] == [12, 13]
    for c in cases:
        x = np.asarray(c["data"])
        ma, md = np.asarray(c["ma"]), np.asarray(c["md"])
        assert len(ma) == (len(x) + 11) // 2
        np.testing.assert_allclose(ref.dwt_axis(x, ref.LO_D, 0), ma, rtol=0, atol=1e-10)
        np.testing.assert_allclose(ref.dwt_axis(x, ref.HI_D, 0), md, rtol=0, atol=1e-10)
        pa, pd = pywt.dwt(x, "db6", mode="symmetric")
        np.testing.assert_allclose(pa, ma, rtol=0, atol=1e-10)
        np.testing.assert_allclose(pd, md, rtol=0, atol=1e-10)


def test_reference_filters_are_daubechies_6() -> None:
    lo, hi = ref.LO_R, ref.HI_R
    assert len(lo) == 12
    assert lo.sum() == pytest.approx(math.sqrt(2.0), abs=1e-13)
    for m in range(6):  # orthonormal to its even shifts
        assert float(lo[2 * m:] @ lo[:12 - 2 * m]) == pytest.approx(float(m == 0), abs=1e-13)
    t = np.arange(12.0)
    for p in range(6):  # six vanishing moments
        assert float(hi @ t**p) == pytest.approx(0.0, abs=1e-9 * 11.0**p)


@pytest.mark.parametrize("shape", [(40, 52), (37, 45)])
def test_reference_reconstruction_is_perfect(shape: tuple[int, int]) -> None:
    """The branches add up to the image (MATLAB's 'sym' mode is perfect reconstruction):
    this pins the reconstruction's central crop; a crop one sample off does not add up."""
    x = np.random.default_rng(1).random(shape)
    dec, sizes = ref.wavedec2(x, 3)
    total = ref.wrcoef2("a", dec, sizes, 3) + sum(
        ref.wrcoef2(c, dec, sizes, n) for c in "hvd" for n in (1, 2, 3))
    np.testing.assert_allclose(total, x, rtol=0, atol=1e-12)
    one = ref.wrcoef2("a", dec, sizes, 1) + sum(ref.wrcoef2(c, dec, sizes, 1) for c in "hvd")
    np.testing.assert_allclose(one, x, rtol=0, atol=1e-12)
    if shape[0] % 2:  # an odd surplus to crop: the other rounding is 1 px off
        a, h, v, d = dec[0]
        other = ref.idwt2(a, h, v, d, shape, ceil_first=True)
        assert np.abs(other - x).max() > 0.1


@pytest.mark.parametrize("operator", sorted(LEVELS))
def test_crop_on_the_grid_equals_the_whole_image(operator: str, image: np.ndarray) -> None:
    """A crop starting on the operator's grid (2^level px) equals the whole image beyond
    ``operator_reach``; one starting 1 px off does not, even far from its border."""
    assert operator_alignment(operator) == 2 ** LEVELS[operator]
    assert set(WAVELET_OPERATORS) == set(LEVELS)
    wide = np.concatenate([image, image[:, ::-1]], axis=1)  # 512 px: room for WAVR's reach
    full = focus_measure(wide.astype(np.float32), operator=operator, window=9)
    m = operator_reach(operator, 9)
    a0 = 8 * 5
    crop = focus_measure(wide[:, a0:a0 + 2 * m + 60].astype(np.float32), operator=operator,
                         window=9)
    np.testing.assert_allclose(crop[:, m:-m], full[:, a0 + m:a0 + m + 60], rtol=1e-5,
                               atol=1e-6 * np.abs(full).max())
    off = focus_measure(wide[:, a0 + 1:a0 + 1 + 2 * m + 60].astype(np.float32),
                        operator=operator, window=9)
    assert np.abs(off[:, m:-m] - full[:, a0 + 1 + m:a0 + 1 + m + 60]).max() > 1e-3 * np.abs(
        full).max()


def test_focus_stage_measures_wavelets_on_the_grid(image: np.ndarray) -> None:
    """The scan's focus stage widens each measured column range to start on the grid, so
    every frame's columns equal the whole frame's WAVS."""
    frame = (image[:64, :200] * 255).round().astype(np.uint8)
    m = operator_reach("wavs", 9)
    stage = FocusMeasureStage(operator="wavs", window=9, max_value=255.0, margin=m)
    whole = focus_measure(frame.astype(np.float32) / 255.0, operator="wavs", window=9)
    starts = []
    for i, x in enumerate((0, 37, 74)):  # one focus level: each frame 37 px on
        hdr = FrameHeader(frame_id=i, timestamp_ns=i, focus_index=0)
        (out,) = stage.process(PlacedFrame(hdr, frame, (float(x), 0.0), (x, 0)))
        starts.append(out.col0)
        cols = slice(out.col0, out.col0 + out.focus.shape[1])
        np.testing.assert_allclose(out.focus, whole[:, cols], rtol=1e-5,
                                   atol=1e-6 * np.abs(whole).max())
    assert any((c - m) % 2 for c in starts[1:])  # a range that had to be widened


def test_wavelets_keep_device_and_dtype(image: np.ndarray) -> None:
    x = torch.from_numpy(image[None, :40, :48].astype(np.float32))
    for fn in WAVELET_OPERATORS.values():
        out = fn(x, 5)
        assert out.dtype == torch.float32 and out.shape == x.shape and torch.isfinite(out).all()
    with pytest.raises(ValueError, match="2 x 2"):
        WAVELET_OPERATORS["wavs"](torch.zeros(1, 1, 5), 3)
