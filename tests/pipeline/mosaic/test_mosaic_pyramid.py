"""The mosaic's resolution pyramid: level k is the 2^k x 2^k reduction of level 0 while the
scan streams, after a kill and ``--resume``; ``valid_pixels`` counts overlaps once."""

from __future__ import annotations

import multiprocessing as mp
import signal
import warnings
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import zarr
from sffscan.pipeline.formats.recording_reader import open_recording
from sffscan.pipeline.formats.recording_writer import RecordingWriter
from sffscan.pipeline.mosaic.layout import ARRAYS
from sffscan.pipeline.mosaic.ngff import level_path
from sffscan.pipeline.mosaic.reader import tile_states
from sffscan.pipeline.mosaic.stage import MosaicStage
from sffscan.pipeline.mosaic.writer import MosaicWriter
from sffscan.pipeline.sim_source import simulate_frames
from sffscan.pipeline.wiring import run_scan
from sffscan.stages.messages import DepthBlock, DepthBlockHeader
from sffscan.stages.mosaic import REDUCTION, default_levels, downsample

from sffscan.api import replay
from tests.pyramid_children import torn_replay
from tests.scan_helpers import small_config


def block_reduce(a: np.ndarray, f: int, how: str) -> np.ndarray:
    """Reference: reduce f x f blocks of ``a`` (edge blocks cut by the array's end) with
    numpy's own nanmean / mean / sum over each block's own elements: the array is padded to
    whole blocks and each block's f x f values reduced together (the padding is NaN, left
    out by nanmean, and counted out of mean and sum)."""
    rows, cols = a.shape
    out_r, out_c = -(-rows // f), -(-cols // f)
    pad = np.full((out_r * f, out_c * f), np.nan)
    pad[:rows, :cols] = a
    blocks = pad.reshape(out_r, f, out_c, f).transpose(0, 2, 1, 3).reshape(out_r, out_c, -1)
    inside = np.zeros(pad.shape, bool)
    inside[:rows, :cols] = True
    inside = inside.reshape(out_r, f, out_c, f).transpose(0, 2, 1, 3).reshape(out_r, out_c, -1)
    if how == "nanmean":
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", RuntimeWarning)  # an all-NaN block: NaN
            return np.nanmean(blocks, axis=2)
    total = np.sum(np.where(inside, blocks, 0.0), axis=2)  # a NaN inside stays NaN
    if how == "sum":
        return total
    assert how == "mean", how
    return total / np.count_nonzero(inside, axis=2)


def how(name: str) -> str:
    """The reduction of array ``name`` from one level to the next."""
    return REDUCTION.get(name, "nanmean")


def assert_pyramid_consistent(path: Path, *, stale: list[int] | None = None) -> int:
    """Every level k of every array equals the reduction of level 0 (outside the blocks that
    meet the world px box ``stale``, if given); returns the levels."""
    g = zarr.open_group(str(path), mode="r")
    levels = len(g.attrs["ome"]["multiscales"][0]["datasets"])  # type: ignore[index]
    ox, oy = g.attrs["origin_px"]  # type: ignore[misc]
    for name in ARRAYS:
        base = np.asarray(g[name])  # type: ignore[index]
        for k in range(1, levels):
            got = np.asarray(g[level_path(name, k)])  # type: ignore[index]
            want = block_reduce(base, 2 ** k, how(name))
            assert got.shape == want.shape, (name, k)
            if stale is not None:  # leave out the blocks under the box
                f = 2 ** k
                r0, c0 = (stale[1] - oy) // f, (stale[0] - ox) // f
                r1, c1 = -(-(stale[1] - oy + stale[3]) // f), -(-(stale[0] - ox + stale[2]) // f)
                got, want = got.copy(), want.copy()
                got[max(r0, 0):max(r1, 0), max(c0, 0):max(c1, 0)] = 0
                want[max(r0, 0):max(r1, 0), max(c0, 0):max(c1, 0)] = 0
            assert np.array_equal(np.isnan(got), np.isnan(want)), (name, k)
            np.testing.assert_allclose(got, want, rtol=2e-6, atol=1e-6, equal_nan=True,
                                       err_msg=f"{name} level {k}")
    return levels


def test_downsample_is_the_blockwise_reduction_not_a_mean_of_means() -> None:
    rng = np.random.default_rng(0)
    shape = (45, 70)  # not multiples of 8: edge blocks are cut
    h = rng.normal(100, 20, shape).astype(np.float32)
    h[rng.random(shape) < 0.4] = np.nan
    h[:8, :8] = np.nan  # an all-NaN block stays NaN
    h[8:16, 0:8] = np.nan
    h[9, 1] = 7.0  # one finite value among 63 NaNs: the level-3 value is that value
    values = {"height": h, "texture": np.where(np.isfinite(h), 0.5, np.nan).astype(np.float32),
              "confidence": rng.random(shape).astype(np.float32),
              "weight": rng.random(shape).astype(np.float32)}
    levels = downsample(values, 4)
    assert len(levels) == 3
    for k, level in enumerate(levels, start=1):
        for name in values:
            want = block_reduce(values[name], 2 ** k, how(name))
            np.testing.assert_allclose(level[name], want, rtol=2e-6, equal_nan=True)
    assert np.isnan(levels[2]["height"][0, 0]) and levels[2]["height"][1, 0] == 7.0
    # a mean of level-1 means would weigh this block's one value like a full pair
    l1 = levels[0]["height"]
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)
        mean_of_means = np.nanmean(l1[:2, :2])
    assert not np.isclose(mean_of_means, levels[0 + 1]["height"][0, 0])


def test_downsample_reduces_any_mosaic_array() -> None:
    """An array beyond the four (an uncertainty, or one the format does not list yet) gets
    its reduction too, without changing the others' values."""
    rng = np.random.default_rng(1)
    shape = (21, 34)
    base = {name: rng.random(shape).astype(np.float32) for name in ARRAYS
            if name != "uncertainty"}  # the four before it
    u = rng.random(shape).astype(np.float32)
    u[rng.random(shape) < 0.3] = np.nan
    extra = {**base, "uncertainty": u, "other": u}
    plain, more = downsample(base, 3), downsample(extra, 3)
    for k, (a, b) in enumerate(zip(plain, more, strict=True), start=1):
        for name in base:
            assert np.array_equal(a[name], b[name], equal_nan=True)
        for name in ("uncertainty", "other"):  # NaN-aware means
            np.testing.assert_allclose(b[name], block_reduce(u, 2 ** k, "nanmean"),
                                       rtol=2e-6, equal_nan=True)


def test_default_levels() -> None:
    assert default_levels((300, 700)) == 4  # at least 4
    assert default_levels((1908, 7304)) == 4  # the demo: top level 239 x 913
    assert default_levels((31_623, 31_623)) == 6  # 10^9 px: top level 989 px
    assert default_levels((10**6, 10**6)) == 10  # at most 10


def _block(x0: int, y0: int, pass_index: int, rng: np.random.Generator, rows: int = 40,
           cols: int = 24) -> DepthBlock:
    h = rng.normal(50, 10, (rows, cols)).astype(np.float32)
    h[rng.random((rows, cols)) < 0.2] = np.nan
    header = DepthBlockHeader(x0_px=x0, y0_px=y0, width_px=cols, height_px=rows,
                              pass_index=pass_index, complete_columns=cols, incomplete_columns=0)
    return DepthBlock(header, h, np.where(np.isfinite(h), 0.5, np.nan).astype(np.float32),
                      rng.random((rows, cols)).astype(np.float32))


@pytest.mark.parametrize("lag_s", [0.0, np.inf])
def test_streamed_pyramid_is_current_after_every_band(tmp_path: Path, lag_s: float) -> None:
    """Two overlapping passes of blocks: after each band write, every level of the mosaic
    equals the reduction of what level 0 holds then, except under the journaled box of the
    chunks the writer has not written back yet (none with lag_s=0; with no time limit, the
    box spans at most the top level's chunk width, and the pyramid still grows)."""
    rng = np.random.default_rng(3)
    path = tmp_path / "m.zarr"
    writer = MosaicWriter(path, origin_px=(-37, -11), shape=(60, 100), pixel_um=8.5,
                          chunk_px=32, levels=4, pyramid_lag_s=lag_s)
    stage = MosaicStage(writer)
    checked = 0
    orig = writer.write_region
    grown = []

    def checked_write(*args: Any, **kwargs: Any) -> None:
        nonlocal checked
        orig(*args, **kwargs)
        g = zarr.open_group(str(path), mode="r")
        stale = g.attrs["pyramid_stale"]
        if lag_s == 0:
            assert stale is None
        else:
            assert stale is not None and stale[2] <= 32 * 8  # one level-3 chunk wide
        assert_pyramid_consistent(path, stale=stale)  # type: ignore[arg-type]
        level1 = np.asarray(g[level_path("height", 1)])  # type: ignore[index]
        grown.append(int(np.isfinite(level1).sum()))
        checked += 1

    writer.write_region = checked_write  # type: ignore[method-assign]
    for p, y0 in ((0, -11), (1, 5)):  # the second pass overlaps the first by 24 rows
        for x0 in range(-37, 150, 24):  # grows the mosaic beyond its initial 100 columns
            list(stage.process(_block(x0, y0, p, rng)))
    list(stage.finish())
    stage.close(failed=False)
    assert checked >= 10
    assert grown[checked // 2] > 0  # the levels are written while the scan runs
    g = zarr.open_group(str(path), mode="r")
    assert g.attrs["pyramid_stale"] is None
    height = np.asarray(g["height"])  # type: ignore[index]
    assert height.shape[1] > 100
    assert g.attrs["valid_pixels"] == int(np.isfinite(height).sum())
    assert assert_pyramid_consistent(path) == 4
    for name in ARRAYS:  # each array carries its own unit
        assert g[name].attrs["units"] == g[level_path(name, 3)].attrs["units"]  # type: ignore[index]
    assert g["height"].attrs["units"] == "µm"  # type: ignore[index]


@pytest.fixture(scope="module")
def two_pass(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, Path]:
    """A two-pass recording (the passes overlap) and its uninterrupted replay."""
    d = tmp_path_factory.mktemp("pyr")
    cfg = small_config(motion={"x_start_mm": 2.0, "x_end_mm": 8.0, "passes": 2},
                       processing={"registration": False})
    rec, ref = d / "rec.zarr", d / "ref.zarr"
    writer = RecordingWriter(rec, cfg)
    for frame in simulate_frames(cfg):
        writer.write(frame)
    writer.close()
    replay(rec, output=ref)
    return rec, ref


def test_valid_pixels_count_overlaps_once(two_pass: tuple[Path, Path]) -> None:
    """Issue 11: a multi-pass mosaic reported more valid pixels than it has finite heights."""
    _, ref = two_pass
    g = zarr.open_group(str(ref), mode="r")
    finite = int(np.isfinite(np.asarray(g["height"])).sum())  # type: ignore[index]
    # the passes overlap: many pixels carry the weight of two contributions
    weight = np.asarray(g["weight"])  # type: ignore[index]
    assert (weight > 1.5 * float(np.median(weight[weight > 0]))).sum() > 1000
    assert g.attrs["valid_pixels"] == finite


def _arrays(path: Path) -> dict[str, np.ndarray]:
    g = zarr.open_group(str(path), mode="r")
    levels = len(g.attrs["ome"]["multiscales"][0]["datasets"])  # type: ignore[index]
    return {level_path(n, k): np.asarray(g[level_path(n, k)])  # type: ignore[index]
            for n in ARRAYS for k in range(levels)}


def _bands(rng: np.random.Generator) -> list[tuple[int, int, dict[str, np.ndarray]]]:
    """Band writes of two overlapping passes, the second one backwards: (x0, y0, sums)."""
    out = []
    for y0, xs in ((-11, range(-37, 200, 32)), (13, range(187, -40, -32))):
        for x0 in xs:
            w = rng.random((40, 32))
            w[rng.random(w.shape) < 0.2] = 0.0
            out.append((x0, y0, {"height": rng.normal(50, 10, w.shape) * w,
                                 "texture": 0.5 * w, "weight": w,
                                 "confidence": rng.random(w.shape).astype(np.float32)}))
    return out


def test_pyramid_cache_lost_between_writes_is_recomputed(tmp_path: Path) -> None:
    """A writer that stops between two writes (as after a kill: its cache of upper-level
    chunks is lost) leaves a pyramid that differs from level 0 only under the journaled box;
    reopening and writing the same bands again gives the uninterrupted mosaic bit for bit."""
    bands = _bands(np.random.default_rng(5))
    kw: dict[str, Any] = {"origin_px": (-37, -11), "shape": (60, 100), "pixel_um": 8.5,
                          "chunk_px": 32, "levels": 4, "pyramid_lag_s": np.inf}
    ref = MosaicWriter(tmp_path / "ref.zarr", **kw)
    for x0, y0, new in bands:
        ref.write_region(x0, y0, new)
    ref.set_status("complete")
    torn = MosaicWriter(tmp_path / "torn.zarr", **kw)
    for x0, y0, new in bands[:10]:
        torn.write_region(x0, y0, new)
    del torn  # no set_status: nothing of the cache is written
    stale = zarr.open_group(str(tmp_path / "torn.zarr"), mode="r").attrs["pyramid_stale"]
    assert stale is not None
    with pytest.raises(AssertionError):
        assert_pyramid_consistent(tmp_path / "torn.zarr")
    assert_pyramid_consistent(tmp_path / "torn.zarr", stale=stale)  # type: ignore[arg-type]
    with pytest.raises(ValueError, match=r"different configuration \(differs in processing, "
                       r"version\)"):  # a top-level key such as version is named, not iterated
        MosaicWriter.reopen(tmp_path / "torn.zarr",
                            scan_config={"version": 2, "processing": {"depth_method": "spc"}})
    again = MosaicWriter.reopen(tmp_path / "torn.zarr", scan_config={})
    assert zarr.open_group(str(tmp_path / "torn.zarr"), mode="r").attrs["pyramid_stale"] is None
    for x0, y0, new in bands:
        again.write_region(x0, y0, new)
    again.set_status("complete")
    want, got = _arrays(tmp_path / "ref.zarr"), _arrays(tmp_path / "torn.zarr")
    for key, value in want.items():
        assert np.array_equal(got[key], value, equal_nan=True), key
    assert assert_pyramid_consistent(tmp_path / "torn.zarr") == 4


@pytest.mark.parametrize("where", ["level0", "pyramid"])
def test_pyramid_after_kill_and_resume(tmp_path: Path, two_pass: tuple[Path, Path],
                                       where: str) -> None:
    rec, ref = two_pass
    reference = _arrays(ref)
    writes = int(zarr.open_group(str(ref), mode="r").attrs["writes_done"])  # type: ignore[arg-type]
    kill_at = writes - 3  # a second-pass write, over first-pass bands
    out = tmp_path / "torn.zarr"
    ctx = mp.get_context("forkserver")
    ctx.set_forkserver_preload(["tests.pyramid_children", "sffscan.pipeline.wiring"])
    proc = ctx.Process(target=torn_replay, args=(str(rec), str(out), kill_at, where))
    proc.start()
    proc.join(120)
    assert proc.exitcode == -signal.SIGKILL
    proc.close()
    _, info = tile_states(out)
    assert info["writes_done"] == kill_at
    assert info["writing"] is not None
    # the chunks the writer had not written back yet
    assert zarr.open_group(str(out), mode="r").attrs["pyramid_stale"] is not None
    with pytest.raises(AssertionError):  # the kill left a pyramid level 0 does not match
        assert_pyramid_consistent(out)
    # resume, as 'sffscan replay --resume' does
    recording = open_recording(rec)
    cfg = recording.config.model_copy(deep=True)
    cfg.output.path = str(out)
    writer = MosaicWriter.reopen(out, scan_config=cfg.model_dump(mode="json"))
    run_scan(cfg, frames=recording.frames(), writer=writer, progress=False)
    assert assert_pyramid_consistent(out) >= 4
    resumed = _arrays(out)
    for key, want in reference.items():
        assert np.array_equal(resumed[key], want, equal_nan=True), key
    g = zarr.open_group(str(out), mode="r")
    assert g.attrs["status"] == "complete"
    assert g.attrs["valid_pixels"] == int(np.isfinite(resumed["height"]).sum())


def test_info_lists_the_pyramid_levels(tmp_path: Path, capsys: pytest.CaptureFixture[str]
                                       ) -> None:
    """``sffscan info MOSAIC``: level, shape and pixel size of every level, and the box of
    levels not written yet while a writer holds them."""
    from sffscan.pipeline.cli.main import main

    path = tmp_path / "m.zarr"
    writer = MosaicWriter(path, origin_px=(0, 0), shape=(60, 100), pixel_um=8.5, chunk_px=32,
                          levels=4, pyramid_lag_s=np.inf)
    for x0, y0, new in _bands(np.random.default_rng(2))[:3]:
        writer.write_region(x0 + 37, y0 + 11, new)
    assert main(["info", str(path)]) == 0
    out = capsys.readouterr().out
    assert "levels      4 " in out
    for k, (shape, um) in enumerate([("60 x 100", "8.5"), ("30 x 50", "17"),
                                     ("15 x 25", "34"), ("8 x 13", "68")]):
        assert f"  {k:>2}        {shape} px, {um} µm" in out, out
    assert "not written yet" in out  # the writer's cache holds levels over the last band
    writer.set_status("complete")
    assert main(["info", str(path)]) == 0
    assert "not written yet" not in capsys.readouterr().out
