"""Procedural simulated world: surface height and reflectance, evaluated only where looked at.

A :class:`PlateWorld` is a flat base of height ``base_um`` carrying a few analytic relief
features (tetrahedron, hemisphere, staircase, cylinder, sinusoid) and a fine random
reflectance texture, as on an additively manufactured surface. Nothing is stored per plate
pixel: heights are computed per requested window from the features' formulas, and the
texture is one periodic tile (``texture_tile_px`` squared, generated from the seed on first
use and cached on the instance) sampled with a band-limited sub-pixel shift, so memory does
not grow with the plate.

Coordinates: world pixel (x, y) has its centre at (x * pixel_um, y * pixel_um) µm; x is the
column (the motion axis), y the row. Windows are [row, col] = [y, x] arrays. The base
extends without limit; the plate's length and width only place the features.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from functools import cached_property, lru_cache

import cv2
import numpy as np
from sffscan.stages.sim.features import (
    Cylinder,
    Feature,
    Hemisphere,
    Sinusoid,
    Staircase,
    Tetrahedron,
)

__all__ = [
    "Cylinder",
    "Feature",
    "Hemisphere",
    "PlateWorld",
    "Sinusoid",
    "Staircase",
    "Tetrahedron",
    "characterisation_plate",
    "shift_kernel",
    "sinusoid_world",
]

SHIFT_HALF_TAPS = 6  # half-width of the Lanczos sub-pixel shift kernel, px


def _check_window(width: int, height: int, x0: float, y0: float) -> None:
    if int(width) != width or width < 1:
        raise ValueError(f"width must be a positive integer, got {width}")
    if int(height) != height or height < 1:
        raise ValueError(f"height must be a positive integer, got {height}")
    if not (math.isfinite(x0) and math.isfinite(y0)):
        raise ValueError(f"x0, y0 must be finite, got {x0}, {y0}")


def _wrapped(tile: np.ndarray, r0: int, nr: int, c0: int, nc: int) -> np.ndarray:
    """Rows r0..r0+nr-1 and columns c0..c0+nc-1 of the periodic tile (a copy), float32."""
    t = tile.shape[0]

    def runs(start: int, n: int) -> list[tuple[int, int, int]]:
        # (destination offset, tile offset, length) of the contiguous pieces of a range
        out, done = [], 0
        while done < n:
            src = (start + done) % t
            k = min(n - done, t - src)
            out.append((done, src, k))
            done += k
        return out

    out = np.empty((nr, nc), dtype=tile.dtype)
    for dr, sr, kr in runs(r0, nr):
        for dc, sc, kc in runs(c0, nc):
            out[dr:dr + kr, dc:dc + kc] = tile[sr:sr + kr, sc:sc + kc]
    return out


def shift_kernel(frac: float, *, half_taps: int = SHIFT_HALF_TAPS) -> np.ndarray:
    """Lanczos kernel that samples a band-limited signal ``frac`` px past each sample.

    Parameters
    ----------
    frac : float
        Sub-pixel offset in [0, 1), px.
    half_taps : int
        Lanczos order a; the kernel covers offsets ``-a .. a``.

    Returns
    -------
    (2a+1,) float32, normalised to sum 1; tap j weights the sample at offset ``j - a``.
    ``frac = 0`` gives a unit impulse (exact sampling).
    """
    u = np.arange(-half_taps, half_taps + 1, dtype=np.float64) - frac
    k = np.sinc(u) * np.sinc(u / half_taps)
    k[np.abs(u) >= half_taps] = 0.0
    return (k / k.sum()).astype(np.float32)


@dataclass(frozen=True)
class PlateWorld:
    """A plate: flat base, relief features and a fine random reflectance texture.

    Parameters
    ----------
    seed : int
        Seed of the texture tile.
    pixel_um : float
        World pixel scale, µm/px (> 0).
    length_mm, width_mm : float
        Nominal plate size along x and y, mm (> 0); used to lay out the features only.
    base_um : float
        Height of the flat base, µm; also the height everywhere off the features.
    features : tuple of Feature
        Relief features; their bounding boxes must not overlap (reliefs are summed).
    texture_tile_px : int
        Side of the periodic texture tile, px (>= 64).
    texture_scales_px : tuple of float
        Gaussian scales of the texture's grain, px (equal variance per scale).
    texture_prefilter_px : float
        Gaussian band limit applied last, px (sigma); makes sub-pixel sampling sharp-stable.
    texture_mean, texture_contrast : float
        Reflectance is ``mean + contrast * tanh(0.8 z)`` (z the unit-variance grain), then
        prefiltered: values lie in ``mean +- contrast`` (default 0.1 .. 0.9).
    """

    seed: int = 0
    pixel_um: float = 8.5
    length_mm: float = 60.0
    width_mm: float = 9.0
    base_um: float = 0.0
    features: tuple[Feature, ...] = ()
    texture_tile_px: int = 2048
    texture_scales_px: tuple[float, ...] = (1.0, 2.0, 4.0, 8.0)
    texture_prefilter_px: float = 0.7
    texture_mean: float = 0.5
    texture_contrast: float = 0.4
    _bboxes: tuple[tuple[float, float, float, float], ...] = field(
        init=False, repr=False, compare=False, default=()
    )

    def __post_init__(self) -> None:
        if isinstance(self.seed, bool) or int(self.seed) != self.seed or self.seed < 0:
            raise ValueError(f"world.seed must be a non-negative integer, got {self.seed}")
        if not (math.isfinite(self.pixel_um) and self.pixel_um > 0):
            raise ValueError(f"world.pixel_um must be > 0, got {self.pixel_um}")
        for name in ("length_mm", "width_mm"):
            v = getattr(self, name)
            if not v > 0:
                raise ValueError(f"world.{name} must be > 0, got {v}")
        if not math.isfinite(self.base_um):
            raise ValueError(f"world.base_um must be finite, got {self.base_um}")
        if int(self.texture_tile_px) != self.texture_tile_px or self.texture_tile_px < 64:
            raise ValueError(f"world.texture_tile_px must be an integer >= 64, "
                             f"got {self.texture_tile_px}")
        if not self.texture_scales_px or min(self.texture_scales_px) <= 0:
            raise ValueError(f"world.texture_scales_px must be positive, "
                             f"got {self.texture_scales_px}")
        if not self.texture_prefilter_px >= 0:
            raise ValueError(f"world.texture_prefilter_px must be >= 0, "
                             f"got {self.texture_prefilter_px}")
        if not 0 <= self.texture_contrast <= min(self.texture_mean, 1 - self.texture_mean):
            raise ValueError("world.texture_contrast must be in [0, min(mean, 1 - mean)], "
                             f"got {self.texture_contrast} (mean {self.texture_mean})")
        boxes = tuple(f.bbox_um for f in self.features)
        for i, a in enumerate(boxes):
            for j, b in enumerate(boxes[:i]):
                if a[0] < b[2] and b[0] < a[2] and a[1] < b[3] and b[1] < a[3]:
                    raise ValueError(f"world.features[{j}] and [{i}] overlap: {b} and {a} µm")
        object.__setattr__(self, "_bboxes", boxes)

    # ------------------------------------------------------------------ heights
    def height_um(self, x0: float, y0: float, width: int, height: int) -> np.ndarray:
        """True surface height over a window of world pixels.

        Parameters
        ----------
        x0, y0 : float
            World position of the window's first pixel (column, row), px; may be fractional.
        width, height : int
            Window size, px.

        Returns
        -------
        (height, width) float32, µm: the height at world pixels (x0 + i, y0 + j).
        """
        _check_window(width, height, x0, y0)
        p = self.pixel_um
        out = np.full((height, width), self.base_um, dtype=np.float32)
        for feat, (bx0, by0, bx1, by1) in zip(self.features, self._bboxes, strict=True):
            # the box's pixels, one more each side (reliefs are 0 there; no rounding issues)
            i0 = max(0, math.ceil(bx0 / p - x0) - 1) if math.isfinite(bx0) else 0
            i1 = min(width, math.floor(bx1 / p - x0) + 2) if math.isfinite(bx1) else width
            j0 = max(0, math.ceil(by0 / p - y0) - 1) if math.isfinite(by0) else 0
            j1 = min(height, math.floor(by1 / p - y0) + 2) if math.isfinite(by1) else height
            if i0 >= i1 or j0 >= j1:
                continue
            xs = (x0 + np.arange(i0, i1, dtype=np.float64)) * p
            ys = (y0 + np.arange(j0, j1, dtype=np.float64)) * p
            out[j0:j1, i0:i1] += feat.relief_um(xs, ys)
        return out

    # ------------------------------------------------------------------ texture
    @cached_property
    def texture_tile(self) -> np.ndarray:
        """The periodic reflectance tile, (T, T) float32, generated from the seed (cached)."""
        return _texture_tile(int(self.seed), int(self.texture_tile_px),
                             tuple(float(s) for s in self.texture_scales_px),
                             float(self.texture_prefilter_px), float(self.texture_mean),
                             float(self.texture_contrast))

    def texture(self, x0: float, y0: float, width: int, height: int) -> np.ndarray:
        """Reflectance over a window of world pixels.

        Samples the periodic tile at (x0 + i, y0 + j) with a separable Lanczos shift of the
        fractional parts, so sharpness does not depend on the sub-pixel offset.

        Parameters
        ----------
        x0, y0 : float
            World position of the window's first pixel (column, row), px; may be fractional.
        width, height : int
            Window size, px.

        Returns
        -------
        (height, width) float32 reflectance, about 0.1 .. 0.9 (unitless).
        """
        _check_window(width, height, x0, y0)
        tile = self.texture_tile
        ix, iy = math.floor(x0), math.floor(y0)
        fx, fy = x0 - ix, y0 - iy
        n = SHIFT_HALF_TAPS
        nx = n if fx > 0 else 0
        ny = n if fy > 0 else 0
        src = _wrapped(tile, iy - ny, height + 2 * ny, ix - nx, width + 2 * nx)
        if nx == 0 and ny == 0:
            return src
        kx = shift_kernel(fx) if nx else np.ones(1, np.float32)
        ky = shift_kernel(fy) if ny else np.ones(1, np.float32)
        out = cv2.sepFilter2D(src, cv2.CV_32F, kx, ky, borderType=cv2.BORDER_REPLICATE)
        return np.ascontiguousarray(out[ny:ny + height, nx:nx + width])


# The tile is a pure function of these six numbers. A process makes many worlds with the
# same ones (a scan's render workers, a test module's scans): making a 2048 px tile takes
# ~0.9 s of CPU (four 2048^2 FFTs and the spectral shape in float64), and 130 of the 167
# tiles the test suite made in its two workers repeated one the same process had made.
# The tiles are read-only (16 MiB at 2048 px), so worlds share them; at most 8 are kept.
@lru_cache(maxsize=8)
def _texture_tile(seed: int, t: int, scales: tuple[float, ...], prefilter: float,
                  mean: float, contrast: float) -> np.ndarray:
    """The periodic reflectance tile of :attr:`PlateWorld.texture_tile`, (t, t) float32,
    read-only."""
    rng = np.random.default_rng([seed, 0x5FF])
    noise = rng.standard_normal((t, t))
    fy = np.fft.fftfreq(t)[:, None]
    fx = np.fft.rfftfreq(t)[None, :]
    f2 = fx**2 + fy**2
    shape = sum(s * np.exp(-2.0 * math.pi**2 * s**2 * f2) for s in scales)
    z = np.fft.irfft2(np.fft.rfft2(noise) * shape, s=(t, t))
    z /= z.std()
    r = mean + contrast * np.tanh(0.8 * z)
    if prefilter > 0:
        g = np.exp(-2.0 * math.pi**2 * prefilter**2 * f2)
        r = np.fft.irfft2(np.fft.rfft2(r) * g, s=(t, t))
    tile = np.ascontiguousarray(r, dtype=np.float32)
    tile.flags.writeable = False
    return tile


# ---------------------------------------------------------------------- worlds

# Nominal (unscaled) feature sizes of the characterisation plate, µm.
_TETRA_EDGE_UM = 10_000.0
_SPHERE_R_UM = 3_000.0
_STEP_LEN_UM = 2_000.0
_STAIR_WIDTH_UM = 6_000.0
_CYL_R_UM = 2_500.0
_N_STEPS = 5
_EDGE_GAP_UM = 100.0  # clearance between features and the plate's / a row's y edges
_MIN_GAP_UM = 1_000.0  # smallest gap between features along x
_ROW_PITCH_MM = 9.0  # a row of features per ~9 mm of plate width


def characterisation_plate(
    *,
    seed: int = 0,
    pixel_um: float = 8.5,
    length_mm: float = 60.0,
    width_mm: float = 9.0,
    z_range_um: tuple[float, float] = (0.0, 10000.0),
) -> PlateWorld:
    """A plate like the thesis' characterisation target.

    Layout (z = z_range_um, R = its span):

    - base at ``z[0] + 0.05 R``; no feature top above ``z[0] + 0.9 R``;
    - ``n_rows = max(1, round(width_mm / 9))`` rows of features, row r centred at
      ``y = (r + 0.5) * width_mm / n_rows`` (one row, on the centre line, for widths
      below 13.5 mm; 24 mm gives 3 rows, so every pass of a multi-pass scan sees relief);
    - each row holds, left to right, a tetrahedron (10 mm edge along x, regular: 8.165 mm
      high), a hemisphere (radius 3 mm), a 5-step staircase rising along +x (2 mm per
      step, 6 mm wide, total 0.4 R) and a cylinder (radius 2.5 mm, top at ``z[0] + 0.5 R``);
      row r starts the sequence at feature ``r mod 4`` (rotated order);
    - the features of a row are spread evenly along x with equal gaps (ends included),
      each centred in its slot;
    - lateral sizes are scaled by one factor ``s <= 1`` so the tetrahedron's 8.66 mm
      footprint fits the row's width less 0.2 mm and the four slots fit the length with
      gaps of at least 1 mm (60 x 9 mm: s = 1; 60 x 24 mm: 0.90; 60 x 2 mm: 0.21);
    - the tetrahedron and the hemisphere keep their shape (regular; round): each is scaled
      as a whole by ``min(s, 0.85 R / nominal height)``; the staircase (total 0.4 R) and
      the cylinder (top at ``z[0] + 0.5 R``) keep their heights and scale laterally by s.

    Parameters
    ----------
    seed : int
        Texture seed.
    pixel_um : float
        World pixel scale, µm/px.
    length_mm, width_mm : float
        Plate size along x and y, mm.
    z_range_um : (float, float)
        Heights the lens can focus on (lowest, highest), µm.

    Returns
    -------
    PlateWorld
    """
    z0, z1 = (float(v) for v in z_range_um)
    if not z1 > z0:
        raise ValueError(f"z_range_um must be increasing, got {z_range_um}")
    if not (length_mm > 0 and width_mm > 0):
        raise ValueError(f"length_mm and width_mm must be > 0, got {length_mm}, {width_mm}")
    span = z1 - z0
    base = z0 + 0.05 * span
    cap = 0.85 * span  # relief limit: tops at most z0 + 0.9 R
    n_rows = max(1, math.floor(width_mm / _ROW_PITCH_MM + 0.5))
    row_w = width_mm * 1000.0 / n_rows
    length = length_mm * 1000.0
    tetra_y = _TETRA_EDGE_UM * math.sqrt(3.0) / 2.0
    extents = [_TETRA_EDGE_UM, 2 * _SPHERE_R_UM, _N_STEPS * _STEP_LEN_UM, 2 * _CYL_R_UM]
    scale = min(1.0, (row_w - 2 * _EDGE_GAP_UM) / tetra_y,
                (length - 5 * _MIN_GAP_UM) / sum(extents))
    if scale <= 0:
        raise ValueError(f"plate {length_mm} x {width_mm} mm is too small for the features")
    feats: list[Feature] = []
    gap = (length - scale * sum(extents)) / 5.0
    for r in range(n_rows):
        cy = (r + 0.5) * row_w
        order = [(r + i) % 4 for i in range(4)]
        x = gap
        for kind in order:
            e = scale * extents[kind]
            cx = x + e / 2.0
            if kind == 0:
                tall = _TETRA_EDGE_UM * math.sqrt(2.0 / 3.0)
                f = min(scale, cap / tall)
                feats.append(Tetrahedron(cx, cy, f * _TETRA_EDGE_UM, f * tall))
            elif kind == 1:
                f = min(scale, cap / _SPHERE_R_UM)
                feats.append(Hemisphere(cx, cy, f * _SPHERE_R_UM, f * _SPHERE_R_UM))
            elif kind == 2:
                feats.append(Staircase(x, cy, _N_STEPS, scale * _STEP_LEN_UM,
                                       0.4 * span / _N_STEPS, scale * _STAIR_WIDTH_UM / 2.0))
            else:
                feats.append(Cylinder(cx, cy, scale * _CYL_R_UM, z0 + 0.5 * span - base))
            x += e + gap
    return PlateWorld(seed=seed, pixel_um=pixel_um, length_mm=length_mm, width_mm=width_mm,
                      base_um=base, features=tuple(feats))


def sinusoid_world(
    *,
    seed: int = 0,
    pixel_um: float = 8.5,
    amplitude_um: float,
    period_px: float,
    offset_um: float,
    length_mm: float = 60.0,
    width_mm: float = 9.0,
) -> PlateWorld:
    """Smooth known-answer surface ``h = offset + A sin(2 pi x / P) cos(2 pi y / P)``.

    x, y in world px. The sinusoid covers the whole (unbounded) world; ``length_mm`` and
    ``width_mm`` are nominal.

    Parameters
    ----------
    seed : int
        Texture seed.
    pixel_um : float
        World pixel scale, µm/px.
    amplitude_um : float
        Amplitude A, µm (>= 0).
    period_px : float
        Period P along x and y, px (> 0).
    offset_um : float
        Mean height, µm.
    """
    if not amplitude_um >= 0:
        raise ValueError(f"amplitude_um must be >= 0, got {amplitude_um}")
    if not period_px > 0:
        raise ValueError(f"period_px must be > 0, got {period_px}")
    return PlateWorld(seed=seed, pixel_um=pixel_um, length_mm=length_mm, width_mm=width_mm,
                      base_um=offset_um,
                      features=(Sinusoid(amplitude_um, period_px * pixel_um),))
