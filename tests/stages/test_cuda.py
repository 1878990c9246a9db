"""The torch device path: raw frames up, focus measure and depth accumulation on the device.

Runs on the ``--device`` torch device (default ``cpu``, where it checks the same code on
CPU torch); ``python -m pytest tests/stages/test_cuda.py --device cuda`` runs it on a GPU.
"""

from __future__ import annotations

import numpy as np
import pytest
import torch
from sffscan.stages.depth import depth_from_focus, depth_from_harmonics
from sffscan.stages.focus_measure import focus_measure_raw
from sffscan.stages.focus_torch import DeviceFocus, accumulate_levels_torch, new_accumulator_torch

FLOAT32_REL_TOL = 1e-6


@pytest.mark.parametrize("operator", ["glvm", "tenv"])
@pytest.mark.parametrize(("dtype", "full"), [(np.uint8, 255), (np.uint16, 1023)])
def test_device_focus_from_raw_frames(operator: str, dtype: type, full: int,
                                      device: str) -> None:
    rng = np.random.default_rng(5)
    batch: np.ndarray = rng.integers(0, full + 1, (3, 40, 70)).astype(dtype)
    df = DeviceFocus(device=device, operator=operator, window=9, max_value=full)
    for _ in range(3):  # staging buffers are reused turn by turn
        image01, fm = df.measure(batch)
    assert fm.device.type == torch.device(device).type and fm.dtype == torch.float32
    single = df.measure(batch[1])[1].cpu().numpy()
    got = fm.cpu().numpy()
    for i in range(3):
        w01, want = focus_measure_raw(batch[i], max_value=full, operator=operator, window=9)
        np.testing.assert_allclose(image01[i].cpu().numpy(), w01, rtol=1e-6, atol=0)
        np.testing.assert_allclose(got[i], want, rtol=0,
                                   atol=FLOAT32_REL_TOL * np.abs(want).max())
    np.testing.assert_allclose(single, got[1], rtol=0, atol=FLOAT32_REL_TOL * got[1].max())
    readonly = batch[2].copy()
    readonly.flags.writeable = False  # e.g. a frame from a read-only replay
    np.testing.assert_array_equal(df.measure(readonly)[1].cpu().numpy(),
                                  df.measure(batch[2].copy())[1].cpu().numpy())
    with pytest.raises(ValueError, match="uint8 or uint16"):
        df.measure(batch.astype(np.float32))


@pytest.mark.parametrize("method", ["argmax", "centroid", "pc", "spc"])
@pytest.mark.parametrize("quantised", [False, True])
def test_device_accumulation_equals_depth_from_focus(method: str, quantised: bool,
                                                     device: str) -> None:
    n, h, w = 12, 24, 31
    rng = np.random.default_rng(7)
    k = np.arange(n)[:, None, None]
    peak = rng.uniform(2, 9, (1, h, w))
    vol = (np.exp(-((k - peak) ** 2) / 4.5) + 0.05 * rng.random((n, h, w))).astype(np.float32)
    if quantised:  # exact ties of the maximum
        vol = (np.round(vol * 4) / 4).astype(np.float32)
    acc = new_accumulator_torch(n_levels=n, shape=(h, w), device=device)
    order = rng.permutation(n)  # levels arrive in any order, in uneven batches
    for part in np.split(order, [5, 6]):
        accumulate_levels_torch(acc, torch.from_numpy(vol[part]).to(device),
                                torch.from_numpy(part))
    sums = acc["sums"].cpu().numpy()
    np.testing.assert_allclose(sums[0], vol.sum(axis=0), rtol=1e-5)
    np.testing.assert_array_equal(acc["argmax"].cpu().numpy(), np.argmax(vol, axis=0))
    got, gconf = depth_from_harmonics(sums, acc["argmax"].cpu().numpy(), n_levels=n,
                                      method=method, median_size=3)
    want, wconf = depth_from_focus(vol, method=method, median_size=3)
    np.testing.assert_allclose(got, want, atol=1e-3)  # levels, float32 sums
    np.testing.assert_allclose(gconf, wconf, atol=1e-5)
