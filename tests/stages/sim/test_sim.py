"""Tests of the simulated world (stages.sim.world) and camera (stages.sim.camera)."""

from __future__ import annotations

import dataclasses
import math

import cv2
import numpy as np
import pytest
from sffscan.stages.sim.camera import (
    Optics,
    blur_bank_sigmas,
    focus_heights,
    render_frame,
    render_stack,
)
from sffscan.stages.sim.world import (
    Cylinder,
    Hemisphere,
    PlateWorld,
    Staircase,
    Tetrahedron,
    characterisation_plate,
    sinusoid_world,
)

PX = 8.5
SMALL = Optics(width=160, height=128)
TILE = 512  # small texture tile: fast to generate


def flat(seed: int = 0, base_um: float = 3000.0) -> PlateWorld:
    return PlateWorld(seed=seed, base_um=base_um, texture_tile_px=TILE)


def laplacian_var(img: np.ndarray) -> float:
    lap = cv2.Laplacian(img.astype(np.float64), cv2.CV_64F)
    return float(lap[2:-2, 2:-2].var())


def glvm_mean(img: np.ndarray, k: int = 7) -> float:
    x = img.astype(np.float64)
    mu = cv2.blur(x, (k, k))
    return float(cv2.blur((x - mu) ** 2, (k, k))[k:-k, k:-k].mean())


@pytest.fixture(scope="module")
def plate() -> PlateWorld:
    return characterisation_plate(z_range_um=(0.0, 10000.0))


# ----------------------------------------------------------------------------- world


def test_determinism_by_seed() -> None:
    a, b, c = flat(1), flat(1), flat(2)
    kw = dict(x0=12.3, y0=4.6, focus_um=3100.0, optics=SMALL)
    fa = render_frame(a, rng=np.random.default_rng(5), **kw)  # type: ignore[arg-type]
    fb = render_frame(b, rng=np.random.default_rng(5), **kw)  # type: ignore[arg-type]
    np.testing.assert_array_equal(fa, fb)
    ta, tc = a.texture(0, 0, 64, 64), c.texture(0, 0, 64, 64)
    assert np.corrcoef(ta.ravel(), tc.ravel())[0, 1] < 0.2


def test_height_subwindow_is_crop(plate: PlateWorld) -> None:
    for x0, y0 in [(1150.0, 300.0), (1150.25, 300.5), (3900.75, 410.125)]:
        big = plate.height_um(x0, y0, 300, 200)
        sub = plate.height_um(x0 + 37, y0 + 11, 120, 90)
        assert big.dtype == np.float32 and big.shape == (200, 300)
        np.testing.assert_array_equal(big[11:101, 37:157], sub)
        assert np.ptp(big) > 100.0  # the windows do hold relief
    sw = sinusoid_world(amplitude_um=1000.0, period_px=100.0, offset_um=2000.0)
    np.testing.assert_array_equal(sw.height_um(3.5, 2.25, 80, 60)[5:25, 7:47],
                                  sw.height_um(10.5, 7.25, 40, 20))


def test_texture_subwindow_is_crop() -> None:
    w = flat(3)
    for x0, y0 in [(10.0, 20.0), (10.3, 20.6), (-40.75, 505.5)]:  # the last one wraps the tile
        big = w.texture(x0, y0, 200, 150)
        sub = w.texture(x0 + 13, y0 + 9, 100, 80)
        assert big.dtype == np.float32 and big.shape == (150, 200)
        np.testing.assert_allclose(big[9:89, 13:113], sub, atol=1e-5)


def test_texture_is_periodic_and_bounded_in_memory() -> None:
    w = flat(11)
    wide = w.texture(-100.25, 7.5, TILE + 150, 40)  # wider than the tile: wraps around
    np.testing.assert_allclose(wide[:, TILE:], wide[:, :150], atol=1e-5)
    assert w.texture_tile.shape == (TILE, TILE)
    far = w.texture(1e7 + 0.5, -3e6, 32, 32)  # anywhere: no plate-sized arrays
    assert far.shape == (32, 32) and np.isfinite(far).all()


def test_texture_subpixel_sampling_keeps_sharpness() -> None:
    w = flat(4)
    t0 = w.texture(100.0, 200.0, 256, 192)
    t1 = w.texture(101.0, 200.0, 256, 192)
    half = w.texture(100.5, 200.0, 256, 192)
    # half-way sample ~ mean of the neighbours (exact for linear signals)
    rms = float(np.sqrt(np.mean((half - 0.5 * (t0 + t1)) ** 2)))
    assert rms < 0.05 * float(t0.std())
    # continuity: approaching the next integer position gives its samples
    np.testing.assert_allclose(w.texture(100.99999, 200.0, 64, 64), t1[:64, :64], atol=1e-4)
    for measure in (laplacian_var, glvm_mean):
        ref = measure(t0)
        for f in (0.25, 0.5):
            for xy in ((100.0 + f, 200.0), (100.0 + f, 200.0 + f)):
                v = measure(w.texture(*xy, 256, 192))
                assert abs(v / ref - 1.0) < 0.03, (measure.__name__, xy, v / ref)


def test_texture_range_and_fine_grain() -> None:
    t = flat(5).texture(0.0, 0.0, 512, 512)
    assert 0.08 < t.min() and t.max() < 0.92
    assert 0.15 < t.std() < 0.3
    # signal at 1-8 px everywhere: every 16 x 16 block has local contrast
    blocks = t.reshape(32, 16, 32, 16).std(axis=(1, 3))
    assert blocks.min() > 0.03
    assert laplacian_var(t) > 1e-3


def test_plate_geometry(plate: PlateWorld) -> None:
    base = 500.0
    assert plate.base_um == pytest.approx(base)
    tet, hemi, stair, cyl = plate.features
    assert isinstance(tet, Tetrahedron) and isinstance(hemi, Hemisphere)
    assert isinstance(stair, Staircase) and isinstance(cyl, Cylinder)

    def at(x_um: float, y_um: float) -> float:
        return float(plate.height_um(x_um / PX, y_um / PX, 1, 1)[0, 0])

    # regular tetrahedron, 10 mm edge, apex 8164.97 um above the base
    assert tet.edge_um == pytest.approx(10000.0)
    ax, ay = tet.apex_um
    assert at(ax, ay) == pytest.approx(base + 10000.0 * math.sqrt(2 / 3), rel=1e-5)
    assert at(ax, ay + 2000.0) == pytest.approx(base + 8164.97 * (1 - 2000.0 / 5773.5), rel=1e-3)
    x_lo, y_lo, x_hi, y_hi = tet.bbox_um
    assert 0 < y_lo and y_hi < 9000.0 and (y_lo + y_hi) / 2 == pytest.approx(4500.0)
    assert at(x_lo - 50.0, 4500.0) == pytest.approx(base)
    # hemisphere radius 3 mm
    assert at(hemi.cx_um, 4500.0) == pytest.approx(base + 3000.0)
    assert at(hemi.cx_um + 1800.0, 4500.0) == pytest.approx(base + 2400.0, rel=1e-4)
    # staircase: 5 steps of 800 um (40 % of 10 mm in total), 2 mm each along x
    for k in range(5):
        assert at(stair.x_start_um + 2000.0 * k + 1000.0, 4500.0) == pytest.approx(
            base + 800.0 * (k + 1))
    # cylinder, flat top at 50 % of the range
    assert at(cyl.cx_um, 4500.0) == pytest.approx(5000.0)
    assert at(cyl.cx_um + 2000.0, 4500.0 + 1000.0) == pytest.approx(5000.0)
    assert at(cyl.cx_um + 2600.0, 4500.0) == pytest.approx(base)
    # order along x, inside the plate; base off the features and outside the plate
    xs = [f.bbox_um for f in plate.features]
    assert all(a[2] < b[0] for a, b in zip(xs, xs[1:], strict=False))
    assert xs[0][0] > 0 and xs[-1][2] < 60000.0
    for x, y in [(-500.0, -500.0), (500.0, 4500.0), (59500.0, 8900.0), (80000.0, 4500.0)]:
        assert at(x, y) == pytest.approx(base)


@pytest.mark.parametrize(("width_mm", "rows"), [(2.0, 1), (9.0, 1), (24.0, 3)])
def test_plate_features_fit(width_mm: float, rows: int) -> None:
    w = characterisation_plate(width_mm=width_mm, length_mm=60.0, z_range_um=(0.0, 9800.0))
    assert len(w.features) == 4 * rows
    for f in w.features:
        x0, y0, x1, y1 = f.bbox_um
        assert 0 < x0 < x1 < 60000.0 and 0 < y0 < y1 < width_mm * 1000.0
    # every row (band of the width) carries relief reaching over a third of the range
    band = width_mm * 1000.0 / rows / PX
    for r in range(rows):
        h = w.height_um(0.0, r * band, int(60000 / PX), int(band))
        assert h.max() - w.base_um > 0.3 * 9800.0
        assert h.max() <= 0.9 * 9800.0 + 1e-3


def test_sinusoid_world_known_answer() -> None:
    w = sinusoid_world(amplitude_um=1500.0, period_px=200.0, offset_um=4000.0)
    h = w.height_um(0.0, 0.0, 400, 3)
    assert h[0, 50] == pytest.approx(5500.0) and h[0, 150] == pytest.approx(2500.0)
    assert h[0, 0] == pytest.approx(4000.0)
    assert w.height_um(50.0, 100.0, 1, 1)[0, 0] == pytest.approx(2500.0)


# ----------------------------------------------------------------------------- camera


def test_focus_physics_flat_patch() -> None:
    w = flat(6, base_um=3000.0)
    steps = [0, 1, 2, 5]
    for sign in (1, -1):
        sharp = [laplacian_var(render_frame(w, x0=7.25, y0=3.5, focus_um=3000.0 + sign * 200 * k,
                                            optics=SMALL, rng=None)) for k in steps]
        assert all(a > b for a, b in zip(sharp, sharp[1:], strict=False)), sharp
        assert sharp[0] > 2.0 * sharp[1]


def test_in_focus_render_is_sharp_texture() -> None:
    w = flat(7, base_um=3000.0)
    o = dataclasses.replace(SMALL, noise_sigma=0.0)
    img = render_frame(w, x0=20.5, y0=9.25, focus_um=3000.0, optics=o, rng=None)
    m = 8
    tex = w.texture(20.5 - m, 9.25 - m, 160 + 2 * m, 128 + 2 * m).astype(np.float64)
    ref = cv2.GaussianBlur(tex, (7, 7), o.psf_s0_px)[m:-m, m:-m] * 1023.0
    diff = img.astype(np.float64) - ref
    assert float(np.sqrt(np.mean(diff**2))) < 1.0  # LSB
    assert np.corrcoef(img.ravel(), ref.ravel())[0, 1] > 0.999


@pytest.mark.parametrize("sigma", [1.2, 3.3, 8.0, 13.0])
def test_defocus_blur_matches_gaussian(sigma: float) -> None:
    """Space-invariant case: the bank (incl. downsampled levels) gives the asked sigma."""
    w = flat(8, base_um=3000.0)
    o = SMALL
    focus = 3000.0 + (sigma - o.psf_s0_px) / o.psf_c_px_per_um
    img = render_frame(w, x0=3.0, y0=2.5, focus_um=focus, optics=o, rng=None) / 1023.0
    m = 60
    tex = w.texture(3.0 - m, 2.5 - m, 160 + 2 * m, 128 + 2 * m).astype(np.float64)
    k = 2 * math.ceil(4 * sigma) + 1
    ref = cv2.GaussianBlur(tex, (k, k), sigma)[m:-m, m:-m]
    assert float(np.sqrt(np.mean((img - ref) ** 2))) < 0.05 * float(ref.std())


def test_space_variant_blur_follows_height(plate: PlateWorld) -> None:
    """Focused on the cylinder top: the top is sharp, the base around it blurred."""
    cyl = plate.features[3]
    assert isinstance(cyl, Cylinder)
    x0 = (cyl.cx_um - cyl.radius_um) / PX - 40.0
    y0 = cyl.cy_um / PX - 64.0
    img = render_frame(plate, x0=x0, y0=y0, focus_um=5000.0, optics=SMALL, rng=None)
    assert laplacian_var(img[:, 90:150]) > 5.0 * laplacian_var(img[:, 0:30])


def test_dtype_range_and_no_clipping() -> None:
    w = flat(9)
    for bits, dtype, full in ((8, np.uint8, 255), (10, np.uint16, 1023)):
        o = dataclasses.replace(SMALL, bit_depth=bits)
        assert o.dtype is dtype and o.max_value == full
        img = render_frame(w, x0=0.0, y0=0.0, focus_um=3000.0, optics=o,
                           rng=np.random.default_rng(0))
        assert img.dtype == dtype and img.shape == (128, 160)
        assert 0 < img.min() and img.max() < full
        assert 0.1 * full <= np.percentile(img, 0.5) and np.percentile(img, 99.5) <= 0.9 * full


def test_noise_level() -> None:
    w = flat(10)
    o = dataclasses.replace(SMALL, noise_sigma=0.02)
    clean = render_frame(w, x0=1.0, y0=1.0, focus_um=3000.0, optics=o, rng=None)
    noisy = render_frame(w, x0=1.0, y0=1.0, focus_um=3000.0, optics=o,
                         rng=np.random.default_rng(1))
    d = (noisy.astype(np.float64) - clean) / 1023.0
    assert abs(d.mean()) < 0.002 and d.std() == pytest.approx(0.02, rel=0.05)


def test_render_stack_matches_frames() -> None:
    w = sinusoid_world(amplitude_um=2000.0, period_px=120.0, offset_um=5000.0, seed=1)
    w = dataclasses.replace(w, texture_tile_px=TILE)
    zs = focus_heights(n_levels=5, z_min_um=3000.0, z_step_um=1000.0)
    st = render_stack(w, x0=4.5, y0=1.0, focus_heights_um=zs, optics=SMALL, rng=None)
    assert st.shape == (5, 128, 160) and st.dtype == np.uint16
    for k, z in enumerate(zs):
        np.testing.assert_array_equal(
            st[k], render_frame(w, x0=4.5, y0=1.0, focus_um=float(z), optics=SMALL, rng=None))


def test_bank_and_focus_heights() -> None:
    np.testing.assert_allclose(
        blur_bank_sigmas(Optics()),
        [0, 0.5, 0.7071, 1, 1.4142, 2, 2.8284, 4, 5.6569, 8, 11.3137, 16], atol=1e-4)
    assert blur_bank_sigmas(Optics(sigma_max_px=3.0))[-1] == pytest.approx(4.0)
    z = focus_heights()
    assert z.dtype == np.float64 and z.shape == (50,) and z[-1] == pytest.approx(9800.0)
    np.testing.assert_allclose(focus_heights(n_levels=3, z_min_um=100.0, z_step_um=50.0),
                               [100.0, 150.0, 200.0])


def test_validation_names_the_field() -> None:
    with pytest.raises(ValueError, match=r"optics\.pixel_um must be > 0, got -1"):
        Optics(pixel_um=-1)
    with pytest.raises(ValueError, match=r"optics\.bit_depth"):
        Optics(bit_depth=12)
    with pytest.raises(ValueError, match=r"optics\.offset"):
        Optics(gain=1.0, offset=0.5)
    with pytest.raises(ValueError, match=r"optics\.width"):
        Optics(width=0)
    with pytest.raises(ValueError, match=r"world\.pixel_um"):
        PlateWorld(pixel_um=0.0)
    with pytest.raises(ValueError, match=r"optics\.pixel_um .* world\.pixel_um"):
        render_frame(PlateWorld(pixel_um=5.0), x0=0, y0=0, focus_um=0.0, optics=SMALL, rng=None)
    with pytest.raises(ValueError, match="focus_um"):
        render_frame(flat(), x0=0, y0=0, focus_um=math.nan, optics=SMALL, rng=None)
    with pytest.raises(ValueError, match="z_step_um"):
        focus_heights(z_step_um=0.0)
    with pytest.raises(ValueError, match="overlap"):
        PlateWorld(features=(Cylinder(0, 0, 100, 10), Cylinder(50, 0, 100, 10)))


def test_scattered_light_agrees_on_a_flat_and_spills_at_an_edge(plate: PlateWorld) -> None:
    """``blur_model="scatter"`` (stages/sim/scatter.py): on a flat part every point has one
    sigma and the frame is the gathered one (within the gather's level weight, quantised to
    1/32, and its halving pyramid); focused on the cylinder's top, the base's light spills
    over the top's edge (gathered, the top is the sharp texture up to its edge); the
    configuration names the field it refuses."""
    from sffscan.pipeline.config import ConfigError, config_from_dict

    o = dataclasses.replace(SMALL, noise_sigma=0.0)
    s = dataclasses.replace(o, blur_model="scatter")
    w = flat(8, base_um=3000.0)
    for focus in (3000.0, 3400.0, 5000.0):
        g = render_frame(w, x0=3.0, y0=2.5, focus_um=focus, optics=o, rng=None).astype(float)
        c = render_frame(w, x0=3.0, y0=2.5, focus_um=focus, optics=s, rng=None).astype(float)
        assert float(np.sqrt(np.mean((g - c) ** 2))) < 0.03 * float(g.std()), focus
    np.testing.assert_array_equal(  # a stack is its frames
        render_stack(w, x0=3.0, y0=2.5, focus_heights_um=np.array([3000.0, 3400.0]),
                     optics=s, rng=None)[1],
        render_frame(w, x0=3.0, y0=2.5, focus_um=3400.0, optics=s, rng=None))
    cyl = plate.features[3]
    assert isinstance(cyl, Cylinder)
    x0 = (cyl.cx_um - cyl.radius_um) / PX - 40.0  # the top's left edge at column 40
    y0 = cyl.cy_um / PX - 64.0
    g = render_frame(plate, x0=x0, y0=y0, focus_um=5000.0, optics=o, rng=None).astype(float)
    c = render_frame(plate, x0=x0, y0=y0, focus_um=5000.0, optics=s, rng=None).astype(float)
    inside = (slice(48, 80), slice(41, 47))  # the focused top, within the base's blur
    far = (slice(48, 80), slice(110, 130))  # the focused top, far from its edge
    assert float(np.mean(np.abs(c[inside] - g[inside]))) > 4.0 * float(
        np.mean(np.abs(c[far] - g[far])))
    with pytest.raises(ValueError, match=r"optics\.blur_model"):
        Optics(blur_model="splat")
    with pytest.raises(ValueError, match=r"optics\.blur_model 'scatter' .*field_curvature_um"):
        Optics(blur_model="scatter", field_curvature_um=50.0)
    with pytest.raises(ConfigError, match="blur_model"):
        config_from_dict({"optics": {"blur_model": "scatter", "field_curvature_um": 50.0}})
