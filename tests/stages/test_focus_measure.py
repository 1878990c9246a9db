"""Tests of sffscan.stages.focus_measure against independent float64 references of the definitions.

The references follow MATLAB: ``imfilter(I, fspecial('average', 9), 'replicate')`` for the
box filter and ``fspecial('sobel')`` (correlation) for the gradients, written here as
explicit sums over the kernel offsets of an edge-padded array.
"""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path

import cv2
import numpy as np
import pytest
import torch
from sffscan.stages.focus_measure import focus_measure, focus_measure_raw, to_unit_float
from sffscan.stages.focus_torch import glvm, glvm_conv2d_baseline, tenv, torch_operator
from sffscan.stages.operators import FOCUS_OPERATORS
from sffscan.stages.operators.opencv import glvm_cv, tenv_cv

WINDOW = 9
# the operators with OpenCV front ends (every operator: test_focus_operators)
FAST_OPERATORS = tuple(name for name, op in FOCUS_OPERATORS.items() if op.opencv)
# Measured on pertuz-simu02 (worst image): torch float32 2.4e-7 (GLVM) / 4.6e-7 (TENV),
# OpenCV float32 1.3e-7 / 3.5e-7, as max|a - b| / max|b| against the float64 reference.
FLOAT32_REL_TOL = 1e-6
FLOAT64_REL_TOL = 1e-6
# Absolute floor for the float64 per-pixel check: rounding of the float64 computation is a
# few hundred ulps of the largest intermediate at most (TENV subtracts box(G)^2 from
# box(G^2)); measured max |a - b| is 3e-15 * max|b|, so 1e-12 * max|b| is a safe floor that
# is still far below any value of interest (min nonzero reference value / max = 5e-8).
FLOAT64_ABS_FLOOR = 1e-12


# ----------------------------------------------------------------------------- references


def ref_box(x: np.ndarray, k: int) -> np.ndarray:
    """k x k mean with replicated borders, explicit sum over the k^2 offsets, float64."""
    r = k // 2
    h, w = x.shape[-2:]
    p = np.pad(x, [(0, 0)] * (x.ndim - 2) + [(r, r), (r, r)], mode="edge")
    s = np.zeros(x.shape, dtype=np.float64)
    for dy in range(k):
        for dx in range(k):
            s += p[..., dy : dy + h, dx : dx + w]
    return s / (k * k)


def ref_glvm(x: np.ndarray, k: int = WINDOW) -> np.ndarray:
    mu = ref_box(x, k)
    return ref_box((x - mu) ** 2, k)


def ref_tenv(x: np.ndarray, k: int = WINDOW) -> np.ndarray:
    """The toolbox's TENV: ``stdfilt(G, ones(k)).^2``, two-pass sample variance of each
    mirrored ('symmetric') k x k window of the Sobel energy G. Image by image: the
    windows of a whole stack at once are a 1.3 GB copy (4x the CPU, same values)."""
    if x.ndim > 2:
        flat = x.reshape(-1, *x.shape[-2:])
        return np.stack([ref_tenv(im, k) for im in flat]).reshape(x.shape)
    sobel = np.array([[1.0, 2.0, 1.0], [0.0, 0.0, 0.0], [-1.0, -2.0, -1.0]])  # fspecial
    h, w = x.shape[-2:]
    p = np.pad(x, [(0, 0)] * (x.ndim - 2) + [(1, 1), (1, 1)], mode="edge")
    gy = sum(sobel[i, j] * p[..., i : i + h, j : j + w] for i in range(3) for j in range(3))
    gx = sum(sobel.T[i, j] * p[..., i : i + h, j : j + w] for i in range(3) for j in range(3))
    g = gx**2 + gy**2
    r = k // 2
    gp = np.pad(g, [(0, 0)] * (x.ndim - 2) + [(r, r), (r, r)], mode="symmetric")
    win = np.lib.stride_tricks.sliding_window_view(gp, (k, k), axis=(-2, -1))
    return win.reshape(*g.shape, k * k).var(axis=-1, ddof=1)


# ----------------------------------------------------------------------------- fixtures


@pytest.fixture(scope="module")
def pertuz_stack(pertuz_dir: Path) -> np.ndarray:
    """The 30 pertuz-simu02 images, (30, 256, 256) float64 in 0..1."""
    images = []
    for i in range(1, 31):
        raw = cv2.imread(str(pertuz_dir / f"im_{i:02d}.tif"), cv2.IMREAD_UNCHANGED)
        assert raw is not None and raw.dtype == np.uint8 and raw.ndim == 2
        images.append(raw.astype(np.float64) / 255.0)
    return np.stack(images)


@pytest.fixture(scope="module")
def references(pertuz_stack: np.ndarray) -> dict[str, np.ndarray]:
    return {"glvm": ref_glvm(pertuz_stack), "tenv": ref_tenv(pertuz_stack)}


TORCH_OPS = {"glvm": glvm, "tenv": tenv}
CV_OPS = {"glvm": glvm_cv, "tenv": tenv_cv}


def test_registry_front_ends() -> None:
    """One registry: the OpenCV front ends are GLVM's and TENV's, the torch front ends
    wrap the registered definitions, and the registry cannot be changed."""
    assert FAST_OPERATORS == ("glvm", "tenv")
    assert FOCUS_OPERATORS["glvm"].opencv_function() is glvm_cv
    assert FOCUS_OPERATORS["tenv"].opencv_function() is tenv_cv
    assert FOCUS_OPERATORS["lapm"].opencv_function() is None
    assert repr(FOCUS_OPERATORS) == repr(tuple(FOCUS_OPERATORS))
    with pytest.raises(TypeError):
        FOCUS_OPERATORS["glvm"] = FOCUS_OPERATORS["tenv"]  # type: ignore[index]
    x = torch.rand((2, 20, 24), generator=torch.Generator().manual_seed(2))
    for name, front in (("glvm", glvm), ("tenv", tenv)):
        assert torch.equal(front(x, window=5), FOCUS_OPERATORS[name].torch_function()(x, 5))
        assert torch.equal(torch_operator(name)(x, window=5), front(x, window=5))


def test_opencv_glvm_from_raw_equals_from_scaled() -> None:
    """GLVM's one OpenCV front end: the local mean from the raw image (the scan's path)
    equals the mean from the scaled image to float32 round-off; a raw image of another
    shape is refused."""
    rng = np.random.default_rng(4)
    raw = rng.integers(0, 1024, (45, 70)).astype(np.uint16)
    image01 = to_unit_float(raw, max_value=1023)
    scaled = glvm_cv(image01, window=WINDOW)
    from_raw = glvm_cv(image01, window=WINDOW, raw=raw, max_value=1023)
    np.testing.assert_allclose(from_raw, scaled, rtol=0,
                               atol=FLOAT32_REL_TOL * np.abs(scaled).max())
    with pytest.raises(ValueError, match="raw must have the image's shape"):
        glvm_cv(image01, raw=raw[:, 1:], max_value=1023)


def worst_image_rel_error(a: np.ndarray, b: np.ndarray) -> float:
    """max over images of max|a - b| / max|b|."""
    err = np.abs(a - b).reshape(len(b), -1).max(axis=1)
    return float((err / np.abs(b).reshape(len(b), -1).max(axis=1)).max())


# ----------------------------------------------------------------------------- accuracy


@pytest.mark.parametrize("operator", FAST_OPERATORS)
def test_torch_float64_matches_reference(
    operator: str, pertuz_stack: np.ndarray, references: dict[str, np.ndarray], device: str
) -> None:
    ref = references[operator]
    out = TORCH_OPS[operator](torch.from_numpy(pertuz_stack).to(device), window=WINDOW)
    a = out.cpu().numpy()
    floor = FLOAT64_ABS_FLOOR * np.abs(ref).max()
    bad = np.abs(a - ref) > FLOAT64_REL_TOL * np.abs(ref) + floor
    assert not bad.any(), f"{bad.sum()} pixels off, worst {np.abs(a - ref).max():.3g}"


@pytest.mark.parametrize("operator", FAST_OPERATORS)
def test_float32_paths_match_reference(
    operator: str, pertuz_stack: np.ndarray, references: dict[str, np.ndarray], device: str
) -> None:
    ref = references[operator]
    img32 = pertuz_stack.astype(np.float32)
    torch32 = TORCH_OPS[operator](torch.from_numpy(img32).to(device), window=WINDOW)
    cv32 = np.stack([CV_OPS[operator](im, window=WINDOW) for im in img32])
    assert torch32.dtype == torch.float32 and cv32.dtype == np.float32
    assert worst_image_rel_error(torch32.cpu().numpy(), ref) <= FLOAT32_REL_TOL
    assert worst_image_rel_error(cv32, ref) <= FLOAT32_REL_TOL


def test_conv2d_baseline_is_glvm(pertuz_stack: np.ndarray, device: str) -> None:
    x = torch.from_numpy(pertuz_stack[:4]).to(device)
    a = glvm_conv2d_baseline(x, window=WINDOW)
    b = glvm(x, window=WINDOW)
    torch.testing.assert_close(a, b, rtol=1e-12, atol=1e-15)


@pytest.mark.parametrize("operator", FAST_OPERATORS)
@pytest.mark.parametrize("window", [3, 7, 15])
def test_torch_and_opencv_agree(operator: str, window: int, device: str) -> None:
    rng = np.random.default_rng(window)
    img = rng.random((37, 53), dtype=np.float32)  # odd, non-square, smaller than 3 windows
    ref = TORCH_OPS[operator](torch.from_numpy(img.astype(np.float64)), window=window).numpy()
    a = TORCH_OPS[operator](torch.from_numpy(img).to(device), window=window).cpu().numpy()
    b = CV_OPS[operator](img, window=window)
    scale = np.abs(ref).max()
    assert np.abs(a - b).max() <= FLOAT32_REL_TOL * scale
    assert np.abs(b - ref).max() <= FLOAT32_REL_TOL * scale
    assert (a >= 0).all() and (b >= 0).all()


def test_constant_image_is_zero(device: str) -> None:
    x = torch.full((2, 20, 30), 0.25, dtype=torch.float64, device=device)
    assert torch.equal(glvm(x), torch.zeros_like(x))
    assert torch.equal(tenv(x), torch.zeros_like(x))
    assert not glvm_cv(np.full((20, 30), 0.25, np.float32)).any()
    assert not tenv_cv(np.full((20, 30), 0.25, np.float32)).any()


# ----------------------------------------------------------------------------- API


@pytest.mark.parametrize("op", [glvm, tenv, glvm_conv2d_baseline])
@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
@pytest.mark.parametrize("shape", [(16, 24), (3, 16, 24), (2, 3, 16, 24)])
def test_torch_output_device_dtype_shape(
    op: Callable[..., torch.Tensor], dtype: torch.dtype, shape: tuple[int, ...], device: str
) -> None:
    x = torch.rand(shape, dtype=dtype, generator=torch.Generator().manual_seed(0)).to(device)
    out = op(x, window=5)
    assert out.shape == x.shape and out.dtype == dtype and out.device == x.device
    # batch elements are independent
    torch.testing.assert_close(out.reshape(-1, 16, 24)[0], op(x.reshape(-1, 16, 24)[0], window=5))


@pytest.mark.parametrize("operator", FAST_OPERATORS)
def test_focus_measure_dispatch(operator: str, device: str) -> None:
    rng = np.random.default_rng(1)
    batch = rng.random((3, 40, 50)).astype(np.float64)  # float64 in, float32 out
    cv = focus_measure(batch, operator=operator, window=7, backend="opencv")
    th = focus_measure(batch, operator=operator, window=7, backend="torch", device=device)
    single = focus_measure(batch[1], operator=operator, window=7)
    for out in (cv, th):
        assert out.dtype == np.float32 and out.shape == batch.shape
    assert single.shape == batch.shape[1:]
    np.testing.assert_array_equal(single, cv[1])
    np.testing.assert_allclose(th, cv, rtol=0, atol=FLOAT32_REL_TOL * np.abs(cv).max())
    readonly = batch.astype(np.float32)
    readonly.flags.writeable = False
    focus_measure(readonly, operator=operator, backend="torch", device=device)


@pytest.mark.parametrize("bad", [0, 1, 2, 8, -3, 3.0, True, "9"])
def test_bad_window_rejected(bad: object) -> None:
    img = np.zeros((20, 20), np.float32)
    for call in (
        lambda: glvm(torch.from_numpy(img), window=bad),  # type: ignore[arg-type]
        lambda: tenv(torch.from_numpy(img), window=bad),  # type: ignore[arg-type]
        lambda: glvm_conv2d_baseline(torch.from_numpy(img), window=bad),  # type: ignore[arg-type]
        lambda: glvm_cv(img, window=bad),  # type: ignore[arg-type]
        lambda: tenv_cv(img, window=bad),  # type: ignore[arg-type]
        lambda: focus_measure(img, window=bad),  # type: ignore[arg-type]
    ):
        with pytest.raises(ValueError, match="window"):
            call()


def test_bad_inputs_rejected() -> None:
    img = np.zeros((20, 20), np.float32)
    with pytest.raises(ValueError, match="operator"):
        focus_measure(img, operator="wavc")  # left out (see sffscan.stages.operators)
    with pytest.raises(ValueError, match="backend"):
        focus_measure(img, backend="cupy")
    with pytest.raises(ValueError, match="floating"):
        focus_measure(img.astype(np.uint8))
    with pytest.raises(ValueError, match="shape"):
        focus_measure(np.zeros((2, 2, 20, 20), np.float32))
    with pytest.raises(ValueError, match="floating"):
        glvm(torch.zeros((20, 20), dtype=torch.int64))
    with pytest.raises(ValueError, match="shape"):
        tenv(torch.zeros(20))
    with pytest.raises(ValueError, match="2-D"):
        glvm_cv(np.zeros((2, 20, 20), np.float32))


def test_to_unit_float() -> None:
    u8 = np.array([[0, 51, 255]], dtype=np.uint8)
    np.testing.assert_allclose(to_unit_float(u8, max_value=255), [[0.0, 0.2, 1.0]], rtol=1e-7)
    u16 = np.array([[0, 1023]], dtype=np.uint16)
    out = to_unit_float(u16, max_value=1023)
    assert out.dtype == np.float32
    np.testing.assert_array_equal(out, [[0.0, 1.0]])
    f64 = np.array([[0.5, 0.25]])
    np.testing.assert_array_equal(to_unit_float(f64, max_value=1.0), f64.astype(np.float32))


def test_to_unit_float_rejects() -> None:
    img = np.zeros((4, 5))
    img[2, 3] = np.nan
    with pytest.raises(ValueError, match=r"NaN \(first at row 2, column 3\)"):
        to_unit_float(img, max_value=1.0)
    img[2, 3] = np.inf
    with pytest.raises(ValueError, match="inf"):
        to_unit_float(img, max_value=1.0)
    with pytest.raises(ValueError, match="2-D"):
        to_unit_float(np.zeros((2, 4, 5), np.uint8), max_value=255)
    with pytest.raises(ValueError, match="max_value"):
        to_unit_float(np.zeros((4, 5), np.uint8), max_value=0)


@pytest.mark.parametrize("operator", FAST_OPERATORS)
@pytest.mark.parametrize(("dtype", "full"), [(np.uint8, 255), (np.uint16, 1023)])
def test_raw_fast_path_equals_scale_then_measure(operator: str, dtype: type, full: int) -> None:
    rng = np.random.default_rng(3)
    frame: np.ndarray = rng.integers(0, full + 1, (61, 90)).astype(dtype)
    view = frame[:, 7:80]  # a strided column range, as the focus stage passes it
    image01, fm = focus_measure_raw(view, max_value=full, operator=operator, window=9)
    want01 = to_unit_float(view, max_value=full)
    want = focus_measure(want01, operator=operator, window=9)
    np.testing.assert_array_equal(image01, want01)
    assert fm.dtype == np.float32 and fm.shape == view.shape
    np.testing.assert_allclose(fm, want, rtol=0, atol=FLOAT32_REL_TOL * np.abs(want).max())
    assert (fm >= 0).all()


def test_scan_path_does_not_import_torch() -> None:
    """The CPU scan (command line, workers, stages) runs without torch (about 1 s and
    300 MB of memory per process); the torch path still loads at its first use."""
    import subprocess
    import sys

    code = (
        "import sys\n"
        "import sffscan.pipeline.cli.main, sffscan.pipeline.scan_processes\n"
        "import sffscan.pipeline.worker, sffscan.pipeline.sim_workers\n"
        "from sffscan.stages import focus_measure as fm\n"
        "import numpy as np\n"
        "raw = (np.arange(64 * 80).reshape(64, 80) % 1024).astype(np.uint16)\n"
        "img01, f = fm.focus_measure_raw(raw, max_value=1023.0)\n"
        "assert 'torch' not in sys.modules, 'torch imported by the CPU scan path'\n"
        "g = fm.focus_measure(img01, operator='lapm')  # a torch-only operator\n"
        "assert 'torch' in sys.modules and g.shape == img01.shape\n"
        "from sffscan.stages.focus_torch import glvm\n"
        "assert glvm.__module__ == 'sffscan.stages.focus_torch'\n"
    )
    done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                          timeout=120)
    assert done.returncode == 0, done.stderr


@pytest.mark.parametrize("operator", FAST_OPERATORS)
@pytest.mark.parametrize(("dtype", "full"), [(np.uint8, 255), (np.uint16, 1023)])
def test_bands_of_rows_equal_the_whole_frame(operator: str, dtype: type, full: int) -> None:
    """A band of rows measured on its own (widened by the operator's reach) is
    bit-identical to those rows of the whole frame, for every split: what band workers
    and a strip-blocked loop rely on."""
    rng = np.random.default_rng(6)
    frame = cv2.GaussianBlur(rng.random((83, 64), dtype=np.float32) * full, (0, 0), 1.2)
    frame = frame.round().astype(dtype)
    whole01, whole = focus_measure_raw(frame, max_value=full, operator=operator)
    for step in (1, 7, 40):
        bands = [focus_measure_raw(frame, max_value=full, operator=operator,
                                   rows=(r0, min(r0 + step, 83))) for r0 in range(0, 83, step)]
        np.testing.assert_array_equal(np.concatenate([b[0] for b in bands]), whole01)
        np.testing.assert_array_equal(np.concatenate([b[1] for b in bands]), whole)
    for bad in ((0, 0), (-1, 5), (10, 84)):
        with pytest.raises(ValueError, match="rows must satisfy"):
            focus_measure_raw(frame, max_value=full, operator=operator, rows=bad)


def test_band_of_a_torch_operator() -> None:
    rng = np.random.default_rng(8)
    frame = rng.integers(0, 256, (50, 40)).astype(np.uint8)
    whole = focus_measure_raw(frame, max_value=255, operator="lapm")[1]
    band = focus_measure_raw(frame, max_value=255, operator="lapm", rows=(20, 31))[1]
    np.testing.assert_allclose(band, whole[20:31], rtol=1e-6, atol=1e-7 * whole.max())


def test_torch_stage_limits_torch_threads_while_it_runs() -> None:
    """The torch backend's stage sets torch's intra-op threads at its first frame (the
    scan passes 1: sffscan.pipeline.measuring.TORCH_THREADS) and restores them when it
    closes; the OpenCV backend and None leave them alone."""
    from sffscan.pipeline.config import demo_config
    from sffscan.pipeline.measuring import TORCH_THREADS, measure_stages
    from sffscan.stages.focus_measure import FocusMeasureStage
    from sffscan.stages.messages import FrameHeader, PlacedFrame

    hdr = FrameHeader(frame_id=0, timestamp_ns=0, focus_index=0, pass_index=0)
    raw = (np.arange(40 * 48).reshape(40, 48) % 1024).astype(np.uint16)
    frame = PlacedFrame(hdr, raw, (0.0, 0.0), (0, 0))
    before = torch.get_num_threads()
    try:
        for threads, expect in ((before + 1, before + 1), (None, before)):
            stage = FocusMeasureStage(backend="torch", max_value=1023.0, margin=4,
                                      torch_threads=threads)
            assert torch.get_num_threads() == before  # not before its first frame
            (out,) = stage.process(frame)
            assert torch.get_num_threads() == expect and out.focus.shape[0] == 40
            stage.close(failed=False)
            assert torch.get_num_threads() == before
    finally:
        torch.set_num_threads(before)
    with pytest.raises(ValueError, match="torch_threads must be >= 1"):
        FocusMeasureStage(backend="torch", margin=4, torch_threads=0)
    cfg = demo_config()
    fm, = measure_stages(cfg.model_copy(update={"processing": cfg.processing.model_copy(
        update={"backend": "torch"})}), only=("focus_measure",))
    assert TORCH_THREADS == 1 and fm.torch_threads == 1  # type: ignore[attr-defined]
