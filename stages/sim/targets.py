"""Simulated calibration targets with known answers (SFF_NOTES.md section 6).

Every target is rendered by the simulated camera (:func:`sffscan.stages.sim.camera.render_stack`),
so it goes through the same blur, noise and quantisation as a scan:

* :func:`gauge_block_stacks` -- one stationary focus stack per gauge block of a known height
  (a block wider than the field, textured like the plate), for the z response. The lens's
  true focus heights are an argument, so a lens whose real step differs from its nominal
  one can be simulated and recovered.
* :func:`checkerboard_image` -- a checkerboard of known square size in focus, for the
  lateral scale (:class:`CheckerboardWorld` renders it exactly box-filtered per pixel).
* :func:`perspective_checkerboards` -- the same board moved to each focus level while the
  objective's object-side pixel scale changes linearly with the height in focus (a
  non-telecentric objective), for the per-level scale.
* :func:`curved_field_stack` -- a flat textured reference seen through a lens whose surface
  of best focus is curved (field curvature, a quadratic in the frame coordinates).

Field curvature: a lens whose focus height at frame pixel (u, v) is ``focus_um + c(u, v)``
blurs a point at height h with ``|h - focus_um - c(u, v)|``; for a stationary camera that is
exactly a perfect lens looking at the surface ``h - c(u, v)``, which is how it is rendered
(:class:`FieldCurvature`, a relief tied to the camera's position).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from sffscan.stages.sim.camera import Optics, render_stack
from sffscan.stages.sim.world import PlateWorld

__all__ = [
    "Block",
    "CheckerboardWorld",
    "FieldCurvature",
    "checkerboard_image",
    "curved_field_stack",
    "gauge_block_stacks",
    "perspective_checkerboards",
]


# ---------------------------------------------------------------------- features


@dataclass(frozen=True)
class Block:
    """A rectangular gauge block: flat top ``height_um`` above the base over a box, µm."""

    x0_um: float
    y0_um: float
    x1_um: float
    y1_um: float
    height_um: float

    @property
    def bbox_um(self) -> tuple[float, float, float, float]:
        return self.x0_um, self.y0_um, self.x1_um, self.y1_um

    def relief_um(self, x_um: np.ndarray, y_um: np.ndarray) -> np.ndarray:
        ix = (x_um >= self.x0_um) & (x_um < self.x1_um)
        iy = (y_um >= self.y0_um) & (y_um < self.y1_um)
        return (np.outer(iy, ix) * np.float32(self.height_um)).astype(np.float32)


@dataclass(frozen=True)
class FieldCurvature:
    """Unbounded relief ``-(a u^2 + b u v + c v^2)`` about a centre (u, v in px, relief µm).

    ``u = x_um / pixel_um - cx_px``, ``v = y_um / pixel_um - cy_px``: the apparent surface of a
    flat reference seen by a lens whose focus height at frame offset (u, v) from the optical
    centre is ``focus + a u^2 + b u v + c v^2`` (µm, coefficients in µm/px^2).
    """

    cx_px: float
    cy_px: float
    pixel_um: float
    a_um_px2: float
    b_um_px2: float
    c_um_px2: float

    @property
    def bbox_um(self) -> tuple[float, float, float, float]:
        return -math.inf, -math.inf, math.inf, math.inf

    def relief_um(self, x_um: np.ndarray, y_um: np.ndarray) -> np.ndarray:
        u = (np.asarray(x_um) / self.pixel_um - self.cx_px)[None, :]
        v = (np.asarray(y_um) / self.pixel_um - self.cy_px)[:, None]
        c = self.a_um_px2 * u * u + self.b_um_px2 * u * v + self.c_um_px2 * v * v
        return (-c).astype(np.float32)


# ---------------------------------------------------------------------- checkerboard


def _square_wave_integral(u: np.ndarray, n: int) -> np.ndarray:
    """Integral from 0 to u (in squares) of the +-1 square wave that is +1 on [0, 1),
    zero outside [0, n)."""
    uc = np.clip(u, 0.0, float(n))
    return 1.0 - np.abs(np.mod(uc, 2.0) - 1.0)


def _box_avg(x_px: np.ndarray, pixel_um: float, origin_um: float, square_um: float,
             n: int) -> tuple[np.ndarray, np.ndarray]:
    """Per-pixel means of the board's indicator and of its signed square wave along one axis.

    Pixel x covers world [x - 0.5, x + 0.5] px. Returns (inside, signed), each (len(x),)
    float64 in [0, 1] and [-1, 1].
    """
    du = pixel_um / square_um
    u = (x_px * pixel_um - origin_um) / square_um
    lo, hi = u - du / 2.0, u + du / 2.0
    inside = (np.clip(hi, 0, n) - np.clip(lo, 0, n)) / du
    signed = (_square_wave_integral(hi, n) - _square_wave_integral(lo, n)) / du
    return inside, signed


@dataclass(frozen=True)
class CheckerboardWorld(PlateWorld):
    """A flat checkerboard of ``squares = (nx, ny)`` squares of ``square_um``, on white.

    The square at the board's top-left corner ``origin_um`` is bright (0.9), its neighbours
    dark (0.1); outside the board the reflectance is ``white`` (0.9). Every pixel holds the
    exact mean of the pattern over its area (box filtered, so it is alias-free to first
    order and sub-pixel positions are exact). The board's inner corners, the pattern
    OpenCV detects, are ``(nx - 1, ny - 1)``; corner (i, j) lies at
    ``origin_um + ((i + 1) * square_um, (j + 1) * square_um)``.
    """

    square_um: float = 400.0
    squares: tuple[int, int] = (9, 7)
    origin_um: tuple[float, float] = (0.0, 0.0)
    white: float = 0.9

    def __post_init__(self) -> None:
        super().__post_init__()
        if not (math.isfinite(self.square_um) and self.square_um > 0):
            raise ValueError(f"board.square_um must be > 0, got {self.square_um}")
        if len(self.squares) != 2 or min(self.squares) < 3:
            raise ValueError(f"board.squares must be two counts >= 3, got {self.squares}")

    def texture(self, x0: float, y0: float, width: int, height: int) -> np.ndarray:
        """Reflectance over a window of world pixels (box-filtered board), (H, W) float32."""
        nx, ny = (int(v) for v in self.squares)
        xs = x0 + np.arange(int(width), dtype=np.float64)
        ys = y0 + np.arange(int(height), dtype=np.float64)
        gx, fx = _box_avg(xs, self.pixel_um, self.origin_um[0], self.square_um, nx)
        gy, fy = _box_avg(ys, self.pixel_um, self.origin_um[1], self.square_um, ny)
        mean, amp = self.texture_mean, self.texture_contrast
        r = self.white - (self.white - mean) * np.outer(gy, gx) + amp * np.outer(fy, fx)
        return np.ascontiguousarray(r, dtype=np.float32)


def _frame_origin(optics: Optics, centre_um: tuple[float, float], pixel_um: float
                  ) -> tuple[float, float]:
    """World px of the frame's first pixel that puts the frame centre on ``centre_um``."""
    return (centre_um[0] / pixel_um - (optics.width - 1) / 2.0,
            centre_um[1] / pixel_um - (optics.height - 1) / 2.0)


def checkerboard_image(*, optics: Optics, square_um: float = 400.0,
                       squares: tuple[int, int] = (9, 7), focus_um: float = 0.0,
                       board_height_um: float | None = None,
                       rng: np.random.Generator | None = None) -> np.ndarray:
    """One image of a checkerboard centred in the frame, the lens focused at ``focus_um``.

    Parameters
    ----------
    optics : Optics
        Camera model; ``optics.pixel_um`` is the true scale the calibration must recover.
    square_um : float, keyword-only
        Square side, µm.
    squares : (int, int), keyword-only
        Squares along x and y; OpenCV's pattern size is ``(nx - 1, ny - 1)``.
    focus_um : float, keyword-only
        Height in focus, µm.
    board_height_um : float or None, keyword-only
        Height of the board's surface, µm; None puts it in focus (``focus_um``).
    rng : numpy.random.Generator or None, keyword-only
        Sensor noise source; None renders noise-free.

    Returns
    -------
    (optics.height, optics.width) uint8 or uint16 image.
    """
    nx, ny = squares
    h = focus_um if board_height_um is None else board_height_um
    world = CheckerboardWorld(pixel_um=optics.pixel_um, base_um=float(h), square_um=square_um,
                              squares=(int(nx), int(ny)), texture_tile_px=64,
                              origin_um=(-nx * square_um / 2.0, -ny * square_um / 2.0))
    x0, y0 = _frame_origin(optics, (0.0, 0.0), optics.pixel_um)
    return render_stack(world, x0=x0, y0=y0, focus_heights_um=np.array([focus_um]),
                        optics=optics, rng=rng)[0]


def perspective_checkerboards(*, optics: Optics, focus_heights_um: np.ndarray,
                              scale_per_mm: float, reference_um: float = 0.0,
                              square_um: float = 400.0, squares: tuple[int, int] = (9, 7),
                              rng: np.random.Generator | None = None
                              ) -> tuple[np.ndarray, np.ndarray]:
    """A checkerboard at each focus height, seen by a non-telecentric objective.

    The board is moved to each height in focus (a z stage), centred on the optical axis;
    the object-side pixel scale at height z is
    ``optics.pixel_um * (1 + scale_per_mm * (z - reference_um) / 1000)``.

    Parameters
    ----------
    optics : Optics
        Camera model; its ``pixel_um`` is the scale at ``reference_um``.
    focus_heights_um : (K,) array_like of float
        Heights at which a board image is taken, µm.
    scale_per_mm : float, keyword-only
        Relative change of the pixel scale per mm of height (e.g. -0.01: 1 % smaller
        µm/px per mm closer to the camera).
    reference_um, square_um, squares, rng
        As above; ``reference_um`` is the height where the scale is ``optics.pixel_um``.

    Returns
    -------
    images : (K, H, W) uint8 or uint16
    true_um_per_px : (K,) float64, the pixel scale used for each image, µm/px.
    """
    zs = np.asarray(focus_heights_um, dtype=np.float64).reshape(-1)
    scales = optics.pixel_um * (1.0 + scale_per_mm * (zs - reference_um) / 1000.0)
    if zs.size == 0 or not (np.all(np.isfinite(scales)) and np.all(scales > 0)):
        raise ValueError("focus_heights_um must be non-empty and give positive pixel scales")
    out = np.empty((zs.size, optics.height, optics.width), dtype=optics.dtype)
    for k, (z, s) in enumerate(zip(zs, scales, strict=True)):
        o_k = Optics(width=optics.width, height=optics.height, pixel_um=float(s),
                     psf_s0_px=optics.psf_s0_px, psf_c_px_per_um=optics.psf_c_px_per_um,
                     sigma_max_px=optics.sigma_max_px, noise_sigma=optics.noise_sigma,
                     bit_depth=optics.bit_depth, gain=optics.gain, offset=optics.offset)
        out[k] = checkerboard_image(optics=o_k, square_um=square_um, squares=squares,
                                    focus_um=float(z), rng=rng)
    return out, scales


# ---------------------------------------------------------------------- z and curvature


def gauge_block_stacks(heights_um: np.ndarray, *, optics: Optics,
                       focus_heights_um: np.ndarray, seed: int = 0, base_um: float = 0.0,
                       rng: np.random.Generator | None = None) -> np.ndarray:
    """One stationary focus stack per gauge block, the block filling the field.

    Each block (top at ``heights_um[i]`` µm, textured like the plate) is a third wider
    than the field on every side and centred under the camera, as when a gauge block is
    placed under the objective; blocks are measured one after the other.

    Parameters
    ----------
    heights_um : (B,) array_like of float
        True heights of the blocks' tops, µm.
    optics : Optics
        Camera model.
    focus_heights_um : (N,) array_like of float
        The lens's true focus heights, µm (the nominal table may differ: that is what the
        z calibration measures).
    seed : int, keyword-only
        Texture seed; block i uses ``seed + i``.
    base_um : float, keyword-only
        Height of the surface the blocks stand on, µm (blocks are taller than the field).
    rng : numpy.random.Generator or None, keyword-only
        Sensor noise source.

    Returns
    -------
    (B, N, H, W) uint8 or uint16 stacks.
    """
    hs = np.asarray(heights_um, dtype=np.float64).reshape(-1)
    if hs.size == 0 or not np.all(np.isfinite(hs)):
        raise ValueError("heights_um must be a non-empty array of finite heights")
    p = optics.pixel_um
    w_um, h_um = optics.width * p, optics.height * p
    out = np.empty((hs.size, np.size(focus_heights_um), optics.height, optics.width),
                   dtype=optics.dtype)
    for i, h in enumerate(hs):
        block = Block(-w_um, -h_um, w_um, h_um, float(h) - base_um)
        world = PlateWorld(seed=seed + i, pixel_um=p, base_um=base_um, features=(block,),
                           texture_tile_px=256)
        x0, y0 = _frame_origin(optics, (0.0, 0.0), p)
        out[i] = render_stack(world, x0=x0, y0=y0, focus_heights_um=focus_heights_um,
                              optics=optics, rng=rng)
    return out


def curved_field_stack(*, optics: Optics, focus_heights_um: np.ndarray,
                       curvature_um_px2: tuple[float, float, float], surface_um: float,
                       seed: int = 0, x_offset_px: float = 0.0,
                       rng: np.random.Generator | None = None) -> np.ndarray:
    """Focus stack of a flat textured reference seen through a curved field.

    The lens's surface of best focus lies ``a u^2 + b u v + c v^2`` µm above its nominal
    height at frame offset (u, v) px from the frame centre ((W - 1) / 2, (H - 1) / 2); a
    perfect measurement of the flat surface at ``surface_um`` therefore reads
    ``surface_um - (a u^2 + b u v + c v^2)``.

    Parameters
    ----------
    optics : Optics
        Camera model.
    focus_heights_um : (N,) array_like of float
        Heights in focus at the frame centre, µm.
    curvature_um_px2 : (a, b, c), keyword-only
        Field curvature coefficients, µm/px^2.
    surface_um : float, keyword-only
        Height of the flat reference, µm.
    seed : int, keyword-only
        Texture seed.
    x_offset_px : float, keyword-only
        Where on the reference the camera stands, px (another patch of texture).
    rng : numpy.random.Generator or None, keyword-only
        Sensor noise source.

    Returns
    -------
    (N, H, W) uint8 or uint16 stack.
    """
    a, b, c = (float(v) for v in curvature_um_px2)
    p = optics.pixel_um
    x0 = x_offset_px - (optics.width - 1) / 2.0
    y0 = -(optics.height - 1) / 2.0
    curv = FieldCurvature(cx_px=x_offset_px, cy_px=0.0, pixel_um=p, a_um_px2=a, b_um_px2=b,
                          c_um_px2=c)
    world = PlateWorld(seed=seed, pixel_um=p, base_um=float(surface_um), features=(curv,),
                       texture_tile_px=256)
    return render_stack(world, x0=x0, y0=y0, focus_heights_um=focus_heights_um, optics=optics,
                        rng=rng)
