"""The dense-block form of the separable resampling (:class:`ScaleResampler`, what
:func:`scale_warp` and the scan's breathing correction run) against the sparse matrices
that define it (:func:`resample_matrix`)."""

from __future__ import annotations

import numpy as np
import pytest
from sffscan.stages.fields.resample import (
    BLOCK,
    ScaleResampler,
    resample_matrix,
    scale_warp,
)


def _map(s: float, c: tuple[float, float]) -> np.ndarray:
    return np.array([[s, 0.0, c[0] * (1 - s)], [0.0, s, c[1] * (1 - s)]])


@pytest.mark.parametrize("s", [0.97, 1.0043, 1.03])
def test_blocks_equal_the_sparse_products(s: float) -> None:
    rng = np.random.default_rng(4)
    h, w = 2 * BLOCK + 17, 3 * BLOCK + 5  # a partial last block on both axes
    img = rng.random((h, w))
    m = _map(s, (w / 2 - 0.3, h / 2 + 0.2))
    want = resample_matrix(h, h, m[1, 1], m[1, 2]) @ (
        resample_matrix(w, w, m[0, 0], m[0, 2]) @ img.T).T
    got64 = ScaleResampler(img.shape, m, dtype=np.float64)(img)
    assert got64.dtype == np.float64
    np.testing.assert_allclose(got64, want, rtol=0, atol=1e-12)
    rs = ScaleResampler(img.shape, m)  # float32 by default
    buffers = rs.buffers()
    got32 = rs(img.astype(np.float32), buffers=buffers)
    assert got32.dtype == np.float32 and got32 is buffers[1]
    np.testing.assert_allclose(got32, want, rtol=0, atol=2e-6)
    # an integer frame is converted in the buffers: the same sums
    grey = (img * 1023).astype(np.uint16)
    want_grey = resample_matrix(h, h, m[1, 1], m[1, 2]) @ (
        resample_matrix(w, w, m[0, 0], m[0, 2]) @ grey.T.astype(np.float64)).T
    np.testing.assert_allclose(rs(grey, buffers=buffers), want_grey, rtol=0, atol=2e-3)
    # scale_warp takes the prepared resampler and its buffers: the same frame
    np.testing.assert_array_equal(scale_warp(grey, m, resampler=rs, buffers=buffers),
                                  scale_warp(grey, m))


def test_shapes_are_checked() -> None:
    rs = ScaleResampler((40, 50), _map(1.01, (25.0, 20.0)))
    with pytest.raises(ValueError, match=r"image of shape \(50, 40\)"):
        rs(np.zeros((50, 40)))
    with pytest.raises(ValueError, match="buffers must be float32 of shape"):
        rs(np.zeros((40, 50)), buffers=(np.empty((40, 50), np.float64),
                                       np.empty((40, 50), np.float64)))
    with pytest.raises(ValueError, match="rotation or shear"):
        ScaleResampler((40, 50), np.array([[1.0, 0.02, 0.0], [0.0, 1.0, 0.0]]))
