"""Streaming focus volume: columns complete at all N levels, in world coordinates."""

from __future__ import annotations

import numpy as np
import pytest
from sffscan.stages.depth import depth_from_focus, levels_to_height
from sffscan.stages.focus_volume import FocusVolume

N, H, W = 12, 48, 96
HEIGHTS = [100.0 * k for k in range(N)]


def _true_depth(x: np.ndarray | np.float64, y: np.ndarray | np.float64) -> np.ndarray:
    """Depth in levels of world pixel (x, y): a smooth ramp with a bump, 2..9 levels."""
    return 2.0 + 7.0 * (0.5 + 0.5 * np.sin(x / 37.0)) * (0.8 + 0.2 * np.cos(y / 11.0))


def _frame(x0: int, y0: int, level: int) -> tuple[np.ndarray, np.ndarray]:
    yy, xx = np.mgrid[y0:y0 + H, x0:x0 + W].astype(float)
    d = _true_depth(xx, yy)
    fm = np.exp(-((level - d) ** 2) / (2 * 1.5**2)).astype(np.float32)
    return fm, (0.5 + 0.01 * level + 0 * fm).astype(np.float32)


def _scan(direction: int, *, step: int = 5, n_frames: int = 80, method: str = "gauss3",
          reuse: FocusVolume | None = None):
    vol = FocusVolume(n_levels=N, frame_shape=(H, W), focus_heights_um=HEIGHTS, margin=3,
                      direction=direction, method=method, median_size=3, block_columns=16,
                      reuse=reuse)
    assert vol.fv is not None
    ring_bytes = vol.fv.nbytes
    blocks = []
    for k in range(n_frames):
        x = 200 + direction * k * step
        fm, img = _frame(x, 30, k % N)
        blocks += vol.add(fm, img, x=x, y=30, level=k % N)
    blocks += vol.finish()
    assert vol.fv.nbytes == ring_bytes  # fixed memory
    return blocks


@pytest.mark.parametrize("method", ["adaptive", "shape_select", "gauss3"])
@pytest.mark.parametrize("same", [False, True])
def test_a_pass_on_the_last_pass_ring_gives_the_same_blocks(method: str, same: bool) -> None:
    """The next pass takes over the last one's N-level ring, stale values and all. The
    pixels whose curves lack levels (the scan's first and last columns, the rows the frames
    miss) read those values; they must reach no valid pixel: not the block's choice of
    method and SPC bias, not the neighbours' height uncertainty (its mean curve width)."""
    first = FocusVolume(n_levels=N, frame_shape=(H, W), focus_heights_um=HEIGHTS, margin=3,
                        method=method, median_size=3, block_columns=16, row_slack=3,
                        spread_size=3)
    if same:  # the pass itself before: the ring holds its levels
        wobbly_frames_into(first, 1)
    for k in range(60 * (not same)):  # a pass the other way, elsewhere: the ring is dirty
        fm, img = _frame(900 - 7 * k, 34, (3 * k) % N)
        first.add(fm * 3.0, img, x=900 - 7 * k, y=34, level=(3 * k) % N)
    assert first.fv is not None and first.fv.any()
    fresh = _wobbly_scan(method, 1)
    assert_same_blocks(fresh, _wobbly_scan(method, 1, reuse=first))
    assert sum(int(np.isnan(b.height_um).sum()) for b in fresh) > 100  # curves lacking levels


@pytest.mark.parametrize("direction", [1, -1])
def test_columns_complete_and_recover_depth(direction: int) -> None:
    blocks = _scan(direction)
    if direction == -1:
        blocks = blocks[::-1]  # blocks come in the order the motion completes them
    for a, b in zip(blocks, blocks[1:], strict=False):
        assert a.x0 + a.height_um.shape[1] == b.x0
    xs = np.concatenate([np.arange(b.x0, b.x0 + b.height_um.shape[1]) for b in blocks])
    heights = np.concatenate([b.height_um for b in blocks], axis=1)
    y0 = blocks[0].y0
    yy, xx = np.mgrid[y0:y0 + heights.shape[0], 0:len(xs)]
    truth = 100.0 * _true_depth(xs[xx].astype(float), yy.astype(float))
    valid = np.isfinite(heights)
    complete = sum(b.complete for b in blocks)
    # frames move 5 px, the usable width is 90 px: a column is seen >= 18 frames >= N
    assert complete >= 79 * 5 - W
    err = heights[valid] - truth[valid]
    assert np.abs(err).max() < 1.0  # µm (100 µm per level): Gaussian curves, exact fit
    # the rows outside the frame's margins are invalid, the rows inside valid
    rows_valid = valid.any(axis=1)
    assert rows_valid.sum() == H - 2 * 3


def test_incomplete_columns_are_invalid_not_filled() -> None:
    # 30 px per frame: a column is seen only 3 times, far fewer than N = 12 levels
    blocks = _scan(1, step=30, n_frames=30)
    assert sum(b.complete for b in blocks) == 0
    for b in blocks:
        assert np.isnan(b.height_um).all()
        assert (b.confidence == 0).all()


def test_dropped_frame_is_made_up_by_a_later_frame_of_its_level() -> None:
    vol = FocusVolume(n_levels=N, frame_shape=(H, W), focus_heights_um=HEIGHTS, margin=3,
                      method="gauss3", median_size=3, block_columns=16)
    blocks = []
    for k in range(60):
        if k == 30:
            continue  # lost frame: its level comes N frames later for the columns in view
        fm, img = _frame(k * 5, 0, k % N)
        blocks += vol.add(fm, img, x=k * 5, y=0, level=k % N)
    blocks += vol.finish()
    by_col = {b.x0 + c: b.height_um[H // 2, c] for b in blocks
              for c in range(b.height_um.shape[1])}
    entered_at_30 = range(30 * 5 + W - 3 - 5, 30 * 5 + W - 3)
    for x in entered_at_30:
        assert np.isfinite(by_col[x])
        y = np.float64(blocks[0].y0 + H // 2)
        assert by_col[x] == pytest.approx(100 * _true_depth(np.float64(x), y), abs=1.0)


def test_a_jump_past_the_ring_finishes_what_was_stored_and_goes_on() -> None:
    vol = FocusVolume(n_levels=N, frame_shape=(H, W), focus_heights_um=HEIGHTS, margin=3,
                      method="gauss3", median_size=3, block_columns=16)
    blocks = []
    positions = [k * 5 for k in range(30)] + [2000 + k * 5 for k in range(40)]
    for k, x in enumerate(positions):
        fm, img = _frame(x, 0, k % N)
        blocks += vol.add(fm, img, x=x, y=0, level=k % N)
    blocks += vol.finish()
    starts = [b.x0 for b in blocks]
    assert starts == sorted(starts)  # still in order, each column once
    ends = [b.x0 + b.height_um.shape[1] for b in blocks]
    assert all(e <= s for e, s in zip(ends, starts[1:], strict=False))
    before = [b for b in blocks if b.x0 < 1000]
    after = [b for b in blocks if b.x0 >= 2000]
    assert sum(b.complete for b in before) > 0 and sum(b.complete for b in after) > 0
    y = blocks[0].y0 + H // 2
    for b in after:
        for c in range(b.height_um.shape[1]):
            v = b.height_um[H // 2, c]
            if np.isfinite(v):
                assert v == pytest.approx(100 * _true_depth(np.float64(b.x0 + c), np.float64(y)),
                                          abs=1.0)


def _reference_volume(positions: list[int], levels: list[int], frame, xs: np.ndarray,
                      rows: int, margin: int):  # noqa: ANN001
    """The first observation of every (level, world column) from the frames, by brute force."""
    vol = np.full((N, rows, xs.size), np.nan, np.float32)
    for x, level in zip(positions, levels, strict=True):
        fm, _ = frame(x, 0, level)
        for j, wx in enumerate(xs):
            c = wx - x
            if margin <= c < W - margin and np.isnan(vol[level, 0, j]):
                vol[level, :, j] = fm[:, c]
    return vol


@pytest.mark.parametrize("method", ["argmax", "centroid", "pc", "spc", "wcentroid", "adaptive"])
@pytest.mark.parametrize(("quantised", "strips"), [(False, False), (True, False), (True, True)])
def test_streaming_sums_equal_depth_from_focus_on_the_stored_curves(method: str,
                                                                   quantised: bool,
                                                                   strips: bool) -> None:
    """The accumulating path (no N-level ring) gives depth_from_focus's depth and confidence
    on the curves a ring would have stored; with quantised values (exact ties of the
    maximum) the argmax still takes the lowest level, as depth_from_focus does. wcentroid
    keeps the ring (it reads the levels about the filtered peak) but its running argmax and
    confidence sums are accumulated the same way; so does adaptive (its spread of the
    filtered peaks over 3 x 3 px reaches one pixel further)."""

    def frame(x0: int, y0: int, level: int) -> tuple[np.ndarray, np.ndarray]:
        fm, img = _frame(x0, y0, level)
        return (np.round(fm * 4) / 4 if quantised else fm).astype(np.float32), img

    vol = FocusVolume(n_levels=N, frame_shape=(H, W), focus_heights_um=HEIGHTS, margin=3,
                      method=method, median_size=3, block_columns=16, row_slack=0,
                      spread_size=3)
    assert (vol.fv is None) == (method not in ("wcentroid", "adaptive"))
    if strips:  # rows added in strips of 8, as large frames are
        vol.cache_bytes = 1024
    positions = [7 * k for k in range(40)]
    levels = [(k + 5) % N for k in range(40)]  # the first column starts mid-staircase
    blocks = []
    for x, level in zip(positions, levels, strict=True):
        fm, img = frame(x, 0, level)
        blocks += vol.add(fm, img, x=x, y=0, level=level)
    blocks += vol.finish()
    xs = np.concatenate([np.arange(b.x0, b.x0 + b.height_um.shape[1]) for b in blocks])
    got_h = np.concatenate([b.height_um for b in blocks], axis=1)
    got_c = np.concatenate([b.confidence for b in blocks], axis=1)
    ref = _reference_volume(positions, levels, frame, xs, H, 3)
    complete = ~np.isnan(ref).any(axis=(0, 1))
    # columns whose median-filter halo (1 px) is complete too, rows inside the margins
    inner = complete & np.roll(complete, 1) & np.roll(complete, -1)
    assert inner.sum() > 100
    depth, conf = depth_from_focus(np.nan_to_num(ref[:, 3:-3][:, :, inner]), method=method,
                                   median_size=3, spread_size=3)
    want_h = levels_to_height(depth, focus_heights_um=np.asarray(HEIGHTS))
    if method in ("wcentroid", "adaptive"):
        # its window follows the filtered argmax, which differs where the median's 3 x 3
        # (and adaptive's spread window) reaches beyond the pixels compared here (the
        # ring's margin rows, the columns left out): compare one (two) more pixels in
        r = 1 if method == "wcentroid" else 2
        core = inner.copy()
        for _ in range(r):
            core = core & np.roll(core, 1) & np.roll(core, -1)
        core = core[inner]
        cmp_h, want_h = got_h[3 + r:-3 - r][:, inner][:, core], want_h[r:-r][:, core]
        cmp_c, conf = got_c[3 + r:-3 - r][:, inner][:, core], conf[r:-r][:, core]
        assert core.sum() > 100
    else:
        cmp_h, cmp_c = got_h[3:-3][:, inner], got_c[3:-3][:, inner]
    np.testing.assert_allclose(cmp_h, want_h, atol=1e-3)  # µm
    np.testing.assert_allclose(cmp_c, conf, atol=1e-5)
    assert np.isnan(got_h[:, ~complete]).all()


@pytest.mark.parametrize("method",
                         ["spc", "adaptive", "gauss3", "wcentroid", "centroid", "argmax"])
def test_blocks_carry_the_height_uncertainty(method: str) -> None:
    """Every block has an uncertainty (µm) where it has a height, NaN where not; away from
    the block's edges (its scatter window) it is the whole field's
    height_uncertainty_um of the same depth and curves, with the block's own bias (a peak
    method's centroid pull, the 9-level centroid's departure from the peaks) in quadrature;
    a streaming scan's SPC measures its departure on the curves of the rows it keeps. The
    whole-curve centroid's departure from its curve's phase, per pixel, from the running
    sums, as the whole field's."""
    from sffscan.stages.depth import focus_sums
    from sffscan.stages.depth_uncertainty import height_uncertainty_um

    vol = FocusVolume(n_levels=N, frame_shape=(H, W), focus_heights_um=HEIGHTS, margin=3,
                      method=method, median_size=3, block_columns=16, row_slack=0,
                      spread_size=3)
    positions = [7 * k for k in range(40)]
    levels = [(k + 5) % N for k in range(40)]
    blocks = []
    for x, level in zip(positions, levels, strict=True):
        fm, img = _frame(x, 0, level)
        blocks += vol.add(fm, img, x=x, y=0, level=level)
    blocks += vol.finish()
    for b in blocks:
        assert b.uncertainty_um is not None
        assert b.uncertainty_um.shape == b.height_um.shape
        np.testing.assert_array_equal(np.isnan(b.uncertainty_um), np.isnan(b.height_um))
        assert (b.uncertainty_um[np.isfinite(b.uncertainty_um)] > 0).all()
    xs = np.concatenate([np.arange(b.x0, b.x0 + b.height_um.shape[1]) for b in blocks])
    got = np.concatenate([b.uncertainty_um for b in blocks if b.uncertainty_um is not None],
                         axis=1)
    got_h = np.concatenate([b.height_um for b in blocks], axis=1)
    ref = _reference_volume(positions, levels, _frame, xs, H, 3)
    complete = ~np.isnan(ref).any(axis=(0, 1))
    ref = np.nan_to_num(ref[:, 3:-3])
    depth = (got_h[3:-3] / 100.0).astype(np.float32)  # the streamed depth, levels
    want = height_uncertainty_um(np.where(complete, depth, 0.0), focus_sums(ref),
                                 ref.min(axis=0), method=method, n_levels=N,
                                 focus_heights_um=np.asarray(HEIGHTS),
                                 window=3)
    edge = np.concatenate([np.arange(b.height_um.shape[1]) for b in blocks])
    core = complete & (edge >= 3) & (edge < 13)  # 2 px (median) + 1 px (window) in
    core &= np.roll(complete, 3) & np.roll(complete, -3)
    assert core.sum() > 50
    # the sums are accumulated frame by frame in float32 (SPC), or summed in another order
    # than focus_sums': the curve widths differ by round-off, which the excess width
    # (sqrt(w^2 - mean^2), ill-conditioned where a curve is as wide as its neighbours)
    # magnifies; the floor term (c = 0.0001 levels since shape_select is the default: 0.01
    # um here) no longer hides it. Measured: up to 0.017 um (SPC), 7e-5 um (the others)
    # the argmax: up to 0.77 um on 52 of 4608 px (its sigma 15-20 um here), the same with
    # its block bias or without: where its integer depth leaves a curve as wide as the mean
    # of its neighbours', the excess width's square root magnifies the sums' round-off
    atol = {"spc": 0.02, "centroid": 0.02, "argmax": 1.0}.get(method, 2e-4)  # centroid: 0.008
    # each block's bias (a peak method's centroid pull, one value a block) in quadrature
    step = float(np.diff(HEIGHTS).mean())
    bias = np.concatenate([np.full(b.height_um.shape[1], b.bias_levels) for b in blocks])
    # a streaming scan's SPC judges its departure on the rows it keeps (the grid): these
    # curves, 2..9 levels of 12 with a width of 1.5, are cut by the range's ends
    assert ((bias > 0).any() if method in ("adaptive", "wcentroid", "spc", "argmax")
            else (bias == 0).all())
    want = np.sqrt(want.astype(np.float64) ** 2 + (bias * step)[None] ** 2)
    np.testing.assert_allclose(got[6:-6][:, core], want[3:-3][:, core], rtol=1e-4, atol=atol)


def _wobbly_scan(method: str, direction: int, **kwargs) -> list:  # noqa: ANN003
    """Blocks of a scan whose frames wobble across the motion, with exact ties of the
    maximum (quantised values), partial column ranges and a dropped frame."""
    vol = FocusVolume(n_levels=N, frame_shape=(H, W), focus_heights_um=HEIGHTS, margin=3,
                      direction=direction, method=method, median_size=3, block_columns=16,
                      row_slack=3, spread_size=3, **kwargs)
    return wobbly_frames_into(vol, direction)


def wobbly_frames_into(vol: FocusVolume, direction: int) -> list:
    """:func:`_wobbly_scan`'s frames added to ``vol``, and its blocks (finished)."""
    blocks = []
    for k in range(70):
        if k == 25:
            continue
        x, y = 100 + direction * 4 * k, 10 + (k * 7) % 5 - 2
        fm, img = _frame(x, y, k % N)
        fm = (np.round(fm * 4) / 4).astype(np.float32)
        c0 = 3 + (k % 3) * 10  # the columns the focus stage measured
        blocks += vol.add(fm[:, c0:], img[:, c0:], x=x, y=y, level=k % N, col0=c0)
    return blocks + vol.finish()


@pytest.mark.parametrize("direction", [1, -1])
@pytest.mark.parametrize("defer", [1, 7])
@pytest.mark.parametrize("method", ["spc", "pc", "argmax"])
def test_a_streaming_scan_keeps_the_judged_rows_of_every_curve(method: str, defer: int,
                                                              direction: int) -> None:
    """SPC, PC and the argmax accumulate sums or a running maximum, not curves; for their
    block's departure bias they keep
    every level of every 16th row (``grid``), which holds what the N-level ring of a
    method that stores every level holds there, slot for slot (wobble across the motion,
    partial column ranges, a dropped frame, deferred writes); without an uncertainty,
    nothing."""
    kw = {"n_levels": N, "frame_shape": (H, W), "focus_heights_um": HEIGHTS, "margin": 3,
          "direction": direction, "median_size": 3, "block_columns": 16, "row_slack": 3,
          "spread_size": 3}
    mine = FocusVolume(method=method, defer_writes=defer, **kw)
    ring = FocusVolume(method="wcentroid", **kw)  # the same geometry, every level stored
    assert mine.fv is None and mine.grid is not None and ring.fv is not None
    assert mine.grid.shape == (N, -(-mine.rows // 16), mine.ring)
    blocks = wobbly_frames_into(mine, direction)
    wobbly_frames_into(ring, direction)
    np.testing.assert_array_equal(mine.grid, ring.fv[:, ::16])
    assert any(b.bias_levels > 0 for b in blocks)
    # the next pass takes the grid over, stale values and all, and gives the same blocks
    again = FocusVolume(method=method, defer_writes=defer, reuse=mine, **kw)
    assert again.grid is mine.grid
    assert_same_blocks(wobbly_frames_into(again, direction), blocks)
    assert FocusVolume(method=method, uncertainty=False, **kw).grid is None


def assert_same_blocks(a: list, b: list) -> None:
    """Blocks equal bit for bit: position, complete columns and every array."""
    assert len(a) == len(b)
    for u, v in zip(a, b, strict=True):
        assert (u.x0, u.y0, u.complete, u.bias_levels) == (v.x0, v.y0, v.complete,
                                                            v.bias_levels)
        for p, q in zip(u[2:5] + (u.uncertainty_um,), v[2:5] + (v.uncertainty_um,),
                        strict=True):
            assert p.dtype == q.dtype and p.shape == q.shape
            assert p.tobytes() == q.tobytes()


@pytest.mark.parametrize("method", ["shape_select", "gauss3"])
def test_blocks_do_not_depend_on_what_the_scratch_arrays_held(method: str) -> None:
    """A block's scratch arrays (``b_*``) are new, unset memory (and, cut to each block's
    shape, hold the last block's values elsewhere); the reduction writes every pixel it
    reads for a valid pixel. Filled with NaN or with large numbers beforehand, the blocks
    are the same bit for bit."""
    out = []
    for junk in (np.nan, 1e30):
        vol = FocusVolume(n_levels=N, frame_shape=(H, W), focus_heights_um=HEIGHTS, margin=3,
                          direction=1, method=method, median_size=3, block_columns=16,
                          row_slack=3, spread_size=3)
        for name, arr in vol.arrays.items():
            if name.startswith("b_"):
                arr.fill(junk)
        out.append(wobbly_frames_into(vol, 1))
    assert_same_blocks(*out)


def test_the_uncertainty_of_valid_pixels_ignores_the_invalid_ones_curves() -> None:
    """block_uncertainty with a validity mask: whatever sums and minima the invalid pixels
    hold, the valid pixels' uncertainty is the same; without the mask it is not."""
    from sffscan.stages.block_depth import block_uncertainty

    rng = np.random.default_rng(5)
    rows, cols, n = 40, 24, 30
    depth = (10 + 3 * rng.random((rows, cols))).astype(np.float32)
    k = np.arange(n)[:, None, None]
    vol = np.exp(-0.5 * ((k - depth[None]) / (2 + rng.random((rows, cols)))) ** 2)
    vol = (vol + 0.05 * rng.random(vol.shape)).astype(np.float32)
    from sffscan.stages.depth import focus_sums

    sums, low = focus_sums(vol).astype(np.float32), vol.min(axis=0)
    valid = np.ones((rows, cols), bool)
    valid[:4] = False
    valid[:, -3:] = False
    stale_sums, stale_low = sums.copy(), low.copy()
    stale_sums[:, ~valid] = rng.random((3, int((~valid).sum()))) * 50
    stale_low[~valid] = 0.0

    def unc(s: np.ndarray, m: np.ndarray, mask: np.ndarray | None) -> np.ndarray:
        return block_uncertainty(depth, s, m, (0, rows), method="shape_select",
                                 n_levels=n,
                                 focus_heights_um=np.arange(n) * 2.0, window=3, valid=mask)

    clean, stale = unc(sums, low, valid), unc(stale_sums, stale_low, valid)
    assert clean[valid].tobytes() == stale[valid].tobytes()
    leak = unc(stale_sums, stale_low, None) != unc(sums, low, None)
    assert leak[valid].any()  # the leak the mask closes
    # every pixel valid: the mask changes nothing
    assert (unc(sums, low, np.ones_like(valid)).tobytes() == unc(sums, low, None).tobytes())


@pytest.mark.parametrize("method", ["spc", "centroid", "adaptive", "gauss3"])
@pytest.mark.parametrize("direction", [1, -1])
def test_deferred_writes_in_strips_are_bit_identical_to_frame_by_frame(method: str,
                                                                      direction: int) -> None:
    """Writes held for many frames and applied in strips of 8 rows (the state in cache)
    give every block bit for bit as each frame applied at once, whole (issue 28)."""
    now = _wobbly_scan(method, direction, defer_writes=1)
    FocusVolume.cache_bytes, saved = 1 << 40, FocusVolume.cache_bytes  # one strip a frame
    try:
        whole = _wobbly_scan(method, direction, defer_writes=1)
    finally:
        FocusVolume.cache_bytes = saved
    FocusVolume.cache_bytes = 64  # strips of 8 rows
    try:
        deferred = _wobbly_scan(method, direction, defer_writes=1000)
    finally:
        FocusVolume.cache_bytes = saved
    assert sum(b.complete for b in whole) > 100
    for other in (now, deferred):
        assert len(other) == len(whole)
        for a, b in zip(whole, other, strict=True):
            assert (a.x0, a.y0, a.complete) == (b.x0, b.y0, b.complete)
            for u, v in zip(a[2:5] + (a.uncertainty_um,), b[2:5] + (b.uncertainty_um,),
                            strict=True):
                assert u.dtype == v.dtype and u.tobytes() == v.tobytes()


def test_refuses_no_deferred_writes() -> None:
    with pytest.raises(ValueError, match="defer_writes must be >= 1, got 0"):
        FocusVolume(n_levels=N, frame_shape=(H, W), focus_heights_um=HEIGHTS, margin=3,
                    defer_writes=0)


@pytest.mark.parametrize("method", ["window_pc", "gauss_window_fit", "wavr"])
def test_refuses_a_method_the_scan_does_not_run(method: str) -> None:
    """Only the scan's methods: the study's candidates read beyond a block's halo (window_pc
    pools the curve widths over 11 x 11 px), so a block's depth would depend on its edges."""
    with pytest.raises(ValueError, match=f"method must be one of .*got '{method}'"):
        FocusVolume(n_levels=N, frame_shape=(H, W), focus_heights_um=HEIGHTS, margin=3,
                    method=method)


@pytest.mark.parametrize("n", [12, 50, 100])
@pytest.mark.parametrize("width", [16, 128, 7, 130])
def test_curve_sums_read_in_place_equal_the_copied_strips(n: int, width: int) -> None:
    """The reduction's curve sums (confidence, the curve's width) from a block of the ring
    read in place equal, bit for bit, the float32 products over strips copied out of it
    (volume_strips), which the sums were before (issue 28); adaptive_block takes the same."""
    from sffscan.stages.depth_adaptive import adaptive_block
    from sffscan.stages.depth_harmonics import focus_sums, harmonic_table, volume_strips

    rng = np.random.default_rng(n + width)
    ring = rng.gamma(2.0, size=(n, 300, 150)).astype(np.float32)
    vol = ring[:, 5:293, 9:9 + width]  # 288 rows: strips of whole rows and a shorter last
    table = harmonic_table(n)[[0, 2, 3]].astype(np.float32)
    want = np.empty((3, vol.shape[1] * width), np.float32)
    for p0, p1, strip in volume_strips(vol):
        np.matmul(table, strip, out=want[:, p0:p1])
    want = want.reshape(3, *vol.shape[1:])
    assert focus_sums(vol).tobytes() == want.tobytes()
    sums = np.empty_like(want)
    low = np.empty(vol.shape[1:], np.float32)
    centre = rng.integers(0, n, vol.shape[1:])
    adaptive_block(vol, centre, rng.integers(0, 5, vol.shape[1:]), sums_out=sums, min_out=low)
    assert sums.tobytes() == want.tobytes()
    np.testing.assert_array_equal(low, vol.min(axis=0))


SHAPED_N = 24


def _shaped_frame(x0: int, y0: int, level: int, lopsided: bool
                  ) -> tuple[np.ndarray, np.ndarray]:
    """Gaussian focus curves about a depth of levels 8 .. 15 of 24; ``lopsided``: the upper
    flank twice as wide."""
    yy, xx = np.mgrid[y0:y0 + H, x0:x0 + W].astype(float)
    d = 6.0 + _true_depth(xx, yy)
    s = np.where(lopsided & (level > d), 3.0, 1.5)
    fm = np.exp(-((level - d) ** 2) / (2 * s**2)).astype(np.float32)
    return fm, np.full(fm.shape, 0.5, np.float32)


def _shaped_scan(method: str, lopsided: bool) -> list[np.ndarray]:
    """The heights of every block of a scan of :func:`_shaped_frame` curves."""
    n = SHAPED_N
    vol = FocusVolume(n_levels=n, frame_shape=(H, W), margin=3, method=method,
                      focus_heights_um=[100.0 * k for k in range(n)], median_size=3,
                      block_columns=16, spread_size=3)
    blocks = []
    for k in range(100):
        fm, img = _shaped_frame(3 * k, 0, k % n, lopsided)
        blocks += vol.add(fm, img, x=3 * k, y=0, level=k % n)
    return [b.height_um for b in blocks + vol.finish()]


@pytest.mark.parametrize("lopsided", [False, True])
def test_shape_select_takes_spc_or_adaptive_for_each_block(lopsided: bool) -> None:
    """``shape_select`` chooses per block from the block's curves: each block is SPC's
    averaged with its fallback's (``adaptive_centroid``'s block) by one share of SPC's in
    1/2 .. 1 (:func:`sffscan.stages.depth_spc.spc_weight`; the streaming SPC's, to float32
    round-off: the levels are summed in another order) or ``adaptive``'s, bit for bit. Even,
    clean curves (peaks at levels 8 .. 15 of 24) take SPC, curves whose upper flank is twice
    as wide take adaptive."""
    from sffscan.stages.block_depth import block_method

    chosen = _shaped_scan("shape_select", lopsided)
    spc, adaptive = _shaped_scan("spc", lopsided), _shaped_scan("adaptive", lopsided)
    fallback = _shaped_scan("adaptive_centroid", lopsided)
    measured = [i for i, a in enumerate(chosen) if np.isfinite(a).any()]
    assert len(chosen) == len(spc) == len(adaptive) == len(fallback) and len(measured) > 8
    took_spc = 0
    for i in measured:
        if np.array_equal(chosen[i], adaptive[i], equal_nan=True):
            continue
        # one share of SPC's for the block (least squares over its pixels)
        apart, moved = spc[i] - fallback[i], chosen[i] - fallback[i]
        ok = np.isfinite(apart)
        w = float(np.sum(moved[ok] * apart[ok]) / max(float(np.sum(apart[ok] ** 2)), 1e-30))
        assert 0.5 <= w <= 1.001, w  # SPC and its fallback within 0.1 µm: w to round-off
        np.testing.assert_allclose(moved[ok], np.float32(w) * apart[ok], atol=1e-2)  # µm
        took_spc += 1
    assert took_spc == (0 if lopsided else len(measured)), (took_spc, len(measured))
    fm = np.stack([_shaped_frame(0, 0, k, lopsided)[0] for k in range(SHAPED_N)])
    argmax = np.argmax(fm, axis=0).astype(np.uint8)
    # even: SPC, with adaptive_centroid's choice (these clean curves: the 3-point Gaussian)
    # at the pixels near the range's ends, of which these blocks have none
    assert block_method(fm[:, :, 4:20], argmax[:, 4:20]) == ("adaptive" if lopsided
                                                             else "spc+gauss3")


@pytest.mark.parametrize("lopsided", [False, True])
def test_adaptive_centroid_takes_the_centroid_on_even_blocks_only(lopsided: bool) -> None:
    """``adaptive_centroid`` judges each block's curves: lopsided ones give ``adaptive``'s
    blocks bit for bit; even ones the 5-level centroid where the filtered peaks span <= 2
    levels (another depth than adaptive's 3-point Gaussian there, within 0.08 levels of the
    truth on these clean curves, as the offline method: tests/stages/test_depth.py)."""
    from sffscan.stages.block_depth import block_method
    from sffscan.stages.depth_statistics import centroid_pull

    chosen = _shaped_scan("adaptive_centroid", lopsided)
    adaptive = _shaped_scan("adaptive", lopsided)
    measured = [i for i, a in enumerate(chosen) if np.isfinite(a).any()]
    assert len(chosen) == len(adaptive) and len(measured) > 8
    same = sum(np.array_equal(chosen[i], adaptive[i], equal_nan=True) for i in measured)
    if lopsided:  # pulled by 0.2 levels: every block
        assert same == len(measured), (same, len(measured))
    else:  # these blocks of 48 rows judge 3-6 curves, whose median pull scatters by
        # +-0.05 levels about 0 (a scan's block judges 520): most blocks, not all (14 of 16)
        assert same <= len(measured) // 5, (same, len(measured))
    for i in measured:  # the same pixels measured
        np.testing.assert_array_equal(np.isnan(chosen[i]), np.isnan(adaptive[i]))
        assert np.nanmax(np.abs(chosen[i] - adaptive[i])) <= 100.0 * 0.6  # µm: within a level
    # a block of 480 rows (60 curves judged): the choice, and the pull of all its curves
    fm = np.stack([np.concatenate([_shaped_frame(0, y0, k, lopsided)[0][:, 4:20]
                                   for y0 in range(0, 10 * H, H)]) for k in range(SHAPED_N)])
    argmax = np.argmax(fm, axis=0).astype(np.uint8)
    assert (block_method(fm, argmax, method="adaptive_centroid")
            == ("adaptive" if lopsided else "adaptive_centroid"))
    pull = centroid_pull(fm, argmax)
    assert (pull > 0.15) if lopsided else (abs(pull) < 0.01), pull


def test_shape_select_judges_only_the_curves_with_data() -> None:
    """A block's rows beyond the frames (flat: no data) and its columns not seen at every
    level do not count in its choice; with none left it takes adaptive."""
    from sffscan.stages.block_depth import SPC_BLOCKS, block_method

    n = 24
    k = np.arange(n, dtype=np.float64)[:, None, None]
    # even triangles peaking on levels (a centroid about the argmax is not pulled from
    # the 3-point fit there: the pull that shape_select also asks SPC's curves for is 0)
    d = 10.0 + np.floor(np.linspace(0.0, 2.99, 64 * 16)).reshape(64, 16)
    fm = np.maximum(1.0 - np.abs(k - d) / 3.0, 0.0).astype(np.float32)
    fm[:, 24:] = 0.0  # the wobble's slack rows, never written: counted, they would tip it
    argmax = np.argmax(fm, axis=0)
    assert block_method(fm, argmax) in SPC_BLOCKS
    assert block_method(fm, argmax, np.ones(16, bool)) in SPC_BLOCKS
    assert block_method(fm, argmax, np.zeros(16, bool)) == "adaptive"
    assert block_method(np.zeros_like(fm), argmax) == "adaptive"
