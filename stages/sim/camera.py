"""Simulated camera with an electrically tunable lens: what it sees of a simulated world.

The lens focuses at height ``focus_um``; a surface point at height h is imaged with a
Gaussian point spread of sigma ``min(psf_s0_px + psf_c_px_per_um * |h - focus_um|,
sigma_max_px)`` px. The space-variant blur is rendered from a bank of uniformly blurred
copies of the window (sigmas 0 and 0.5 * sqrt(2)^k px, large ones computed on an area-
downsampled copy and upsampled), interpolated per pixel between the two bank levels that
bracket its sigma (linearly in log sigma; linearly in sigma below 0.5 px). Then the sensor:
intensity ``offset + gain * reflectance`` (full scale 1), additive Gaussian noise, and
quantisation to ``bit_depth`` bits (uint8, or uint16 holding 0..1023).

Real-lens effects (:mod:`sffscan.stages.sim.lens`, all off by default): magnification that
changes with the focus about the optical centre, a curved surface of best focus, and
vignetting. With any of them on, the frame is rendered on the world's unit grid around the
optical axis (the focus of each world pixel displaced by the field curvature at the frame
pixel it lands on), magnified about the centre with a Lanczos warp, then darkened toward
the corners before the sensor adds noise and quantises.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from functools import cached_property

import cv2
import numpy as np
from sffscan.stages.sim.lens import (
    breathing_pad_px,
    curvature_map_um,
    scale_about_centre,
    vignetting_map,
)
from sffscan.stages.sim.world import PlateWorld

BANK_SIGMA0_PX = 0.5  # smallest nonzero bank sigma; the bank grows by sqrt(2) per level
_SHORT_MAX = 32767  # cv2.remap's nearest lookup holds coordinates in int16
_TEXTURE_RANGE = (0.1, 0.9)  # reflectance range the sensor must take without clipping


@dataclass(frozen=True)
class Optics:
    """Camera, objective and tunable lens of the simulated scanner.

    Parameters
    ----------
    width, height : int
        Frame size, px (columns along the motion x, rows across y).
    pixel_um : float
        Object-side pixel scale, µm/px; must equal the world's.
    psf_s0_px : float
        PSF sigma in focus, px (>= 0).
    psf_c_px_per_um : float
        Growth of the PSF sigma with defocus, px per µm (>= 0); 0.004 adds 0.8 px per
        200 µm focus step.
    sigma_max_px : float
        Largest PSF sigma rendered, px (> 0, <= 64).
    noise_sigma : float
        Standard deviation of the additive Gaussian sensor noise, full-scale units (>= 0).
    bit_depth : {8, 10}
        8 -> uint8 frames (0..255); 10 -> uint16 frames holding 0..1023.
    gain, offset : float
        Intensity = ``offset + gain * reflectance`` in full-scale units; reflectances
        0.1 .. 0.9 must map inside [0, 1].
    magnification_per_mm : float
        Relative change of the magnification per mm of focus height (focus breathing of a
        non-telecentric objective), 1/mm; 0.002 = +2 % over 10 mm. 0: telecentric.
    magnification_ref_um : float
        Focus height at which the magnification is 1 (object-side scale ``pixel_um``), µm.
    field_curvature_um : float
        Height of the surface of best focus at the frame corner above the nominal focus, µm
        (quadratic in the radius from the frame centre). 0: flat field.
    vignetting : float
        Illumination lost at the frame corner, fraction in [0, 1) (quadratic in the radius).
    blur_model : {"gather", "scatter"}
        How a blur that varies over the frame is rendered: each pixel takes the texture
        blurred by its own height's sigma (``"gather"``), or each world point spreads its
        light by its own sigma (``"scatter"``, :mod:`sffscan.stages.sim.scatter`: the
        optics of a surface without occlusion; slower; not with field curvature).
    """

    width: int = 1280
    height: int = 1024
    pixel_um: float = 8.5
    psf_s0_px: float = 0.6
    psf_c_px_per_um: float = 0.004
    sigma_max_px: float = 16.0
    noise_sigma: float = 0.005
    bit_depth: int = 10
    gain: float = 1.0
    offset: float = 0.0
    magnification_per_mm: float = 0.0
    magnification_ref_um: float = 0.0
    field_curvature_um: float = 0.0
    vignetting: float = 0.0
    blur_model: str = "gather"

    def __post_init__(self) -> None:
        for name in ("width", "height"):
            v = getattr(self, name)
            if isinstance(v, bool) or int(v) != v or v < 1:
                raise ValueError(f"optics.{name} must be a positive integer, got {v}")
        checks = (
            ("pixel_um", self.pixel_um > 0, "> 0"),
            ("psf_s0_px", self.psf_s0_px >= 0, ">= 0"),
            ("psf_c_px_per_um", self.psf_c_px_per_um >= 0, ">= 0"),
            ("sigma_max_px", 0 < self.sigma_max_px <= 64, "in (0, 64]"),
            ("noise_sigma", self.noise_sigma >= 0, ">= 0"),
            ("gain", self.gain > 0, "> 0"),
            ("magnification_per_mm", abs(self.magnification_per_mm) < 0.1, "in (-0.1, 0.1)"),
            ("magnification_ref_um", True, "finite"),
            ("field_curvature_um", True, "finite"),
            ("vignetting", 0 <= self.vignetting < 1, "in [0, 1)"),
        )
        for name, ok, rule in checks:
            v = getattr(self, name)
            if not (ok and math.isfinite(v)):
                raise ValueError(f"optics.{name} must be {rule}, got {v}")
        if self.blur_model not in ("gather", "scatter"):
            raise ValueError(f"optics.blur_model must be 'gather' or 'scatter', "
                             f"got {self.blur_model!r}")
        if self.blur_model == "scatter" and self.field_curvature_um != 0:
            raise ValueError("optics.blur_model 'scatter' is not built with "
                             f"optics.field_curvature_um (got {self.field_curvature_um})")
        if self.bit_depth not in (8, 10):
            raise ValueError(f"optics.bit_depth must be 8 or 10, got {self.bit_depth}")
        lo, hi = (self.offset + self.gain * r for r in _TEXTURE_RANGE)
        if not (math.isfinite(self.offset) and lo >= 0 and hi <= 1):
            raise ValueError(f"optics.offset must map reflectance 0.1..0.9 into [0, 1] "
                             f"with gain {self.gain}, got {self.offset} (-> {lo:.3g}..{hi:.3g})")

    def magnification(self, focus_um: float) -> float:
        """Relative magnification at a focus height: ``1 + k (focus - ref) / 1000``."""
        m = 1.0 + self.magnification_per_mm * (float(focus_um) - self.magnification_ref_um) / 1e3
        if not m > 0.5:
            raise ValueError(f"focus {focus_um} µm gives magnification {m:.3g}: outside the "
                             "optics' breathing model")
        return m

    @property
    def ideal(self) -> bool:
        """True when no real-lens effect is on (telecentric, flat field, no vignetting)."""
        return (self.magnification_per_mm == 0 and self.field_curvature_um == 0
                and self.vignetting == 0)

    @cached_property
    def noise_table(self) -> np.ndarray:
        """Standard-normal quantiles at (k + 0.5) / 65536, (65536,) float32 (cached).

        Sensor noise is ``noise_sigma * noise_table[u]`` with u uniform 16-bit integers: a
        Gaussian quantised to 65536 values (tails cut at 4.3 sigma), several times faster
        to draw than ``Generator.standard_normal``.
        """
        table = _normal_quantiles((np.arange(65536) + 0.5) / 65536.0).astype(np.float32)
        table.flags.writeable = False
        return table

    @property
    def max_value(self) -> int:
        """Full-scale value of a frame: 255 or 1023."""
        return 255 if self.bit_depth == 8 else 1023

    @property
    def dtype(self) -> type[np.unsignedinteger]:
        """numpy dtype of a frame: uint8 or uint16."""
        return np.uint8 if self.bit_depth == 8 else np.uint16


def blur_bank_sigmas(optics: Optics) -> np.ndarray:
    """Sigmas of the blur bank, px: 0, then ``0.5 * sqrt(2)^k`` up to >= ``sigma_max_px``.

    Returns
    -------
    (L,) float64, increasing; for the default optics
    0, 0.5, 0.71, 1, 1.41, 2, 2.83, 4, 5.66, 8, 11.3, 16.
    """
    k_top = max(0, math.ceil(2.0 * math.log2(optics.sigma_max_px / BANK_SIGMA0_PX) - 1e-9))
    return np.concatenate(([0.0], BANK_SIGMA0_PX * 2.0 ** (np.arange(k_top + 1) / 2.0)))


def focus_heights(*, n_levels: int = 50, z_min_um: float = 0.0,
                  z_step_um: float = 200.0) -> np.ndarray:
    """Heights in focus at the lens staircase's levels: ``z_min_um + k * z_step_um``.

    Returns
    -------
    (n_levels,) float64, µm.
    """
    if isinstance(n_levels, bool) or int(n_levels) != n_levels or n_levels < 1:
        raise ValueError(f"n_levels must be a positive integer, got {n_levels}")
    if not math.isfinite(z_min_um):
        raise ValueError(f"z_min_um must be finite, got {z_min_um}")
    if not (math.isfinite(z_step_um) and z_step_um > 0):
        raise ValueError(f"z_step_um must be > 0, got {z_step_um}")
    return z_min_um + z_step_um * np.arange(int(n_levels), dtype=np.float64)


# ---------------------------------------------------------------------- internals


def _normal_quantiles(p: np.ndarray) -> np.ndarray:
    """Inverse standard-normal CDF for p in (0, 1), float64 (Acklam, rel. error < 1.2e-9)."""
    a = (-3.969683028665376e01, 2.209460984245205e02, -2.759285104469687e02,
         1.383577518672690e02, -3.066479806614716e01, 2.506628277459239e00)
    b = (-5.447609879822406e01, 1.615858368580409e02, -1.556989798598866e02,
         6.680131188771972e01, -1.328068155288572e01, 1.0)
    c = (-7.784894002430293e-03, -3.223964580411365e-01, -2.400758277161838e00,
         -2.549732539343734e00, 4.374664141464968e00, 2.938163982698783e00)
    d = (7.784695709041462e-03, 3.224671290700398e-01, 2.445134137142996e00,
         3.754408661907416e00, 1.0)
    p = np.asarray(p, dtype=np.float64)
    q = p - 0.5
    r = q * q
    x = q * np.polyval(a, r) / np.polyval(b, r)
    tail = np.minimum(p, 1.0 - p)
    t = np.sqrt(-2.0 * np.log(np.maximum(tail, 1e-300)))
    xt = np.polyval(c, t) / np.polyval(d, t)
    return np.where(tail < 0.02425, np.where(q < 0, xt, -xt), x)



def _level_coordinate(sigma: np.ndarray) -> np.ndarray:
    """Fractional bank level of each sigma (level 0 = sigma 0, level 1 + k = 0.5 sqrt2^k)."""
    s0 = np.float32(BANK_SIGMA0_PX)
    u = np.maximum(sigma, s0)
    u *= np.float32(1.0 / BANK_SIGMA0_PX)
    np.log2(u, out=u)
    u *= np.float32(2.0)
    if float(sigma.min()) < BANK_SIGMA0_PX:
        u += np.minimum(sigma, s0) * np.float32(1.0 / BANK_SIGMA0_PX)
    else:
        u += np.float32(1.0)
    return u


def _factor(sigma: float) -> int:
    """Downsampling factor used to render a bank sigma (1 full resolution .. 8)."""
    return 1 if sigma < 2.5 else 2 if sigma < 10.0 else 4 if sigma < 20.0 else 8


def _gauss(img: np.ndarray, sigma: float, dst: np.ndarray | None = None) -> np.ndarray:
    k = 2 * max(1, math.ceil(3.0 * sigma)) + 1
    return cv2.GaussianBlur(img, (k, k), sigma, dst=dst, sigmaY=sigma,
                            borderType=cv2.BORDER_REFLECT_101)


def _upsample_variance(d: int) -> float:
    """Mean variance (full-res px^2) that cv2 INTER_LINEAR upsampling by d adds."""
    phase = np.mod((np.arange(d) + 0.5) / d - 0.5, 1.0)
    return float(d * d * np.mean(phase * (1.0 - phase)))


def _render(tex: np.ndarray, heights: np.ndarray, margin: int, focus_um: float,
            optics: Optics, rng: np.random.Generator | None) -> np.ndarray:
    """One frame from a margin-extended texture window and the window's heights.

    ``tex`` (He, We) float32 has ``margin`` px left/top and at least that much right/bottom,
    He and We divisible by 8; ``heights`` (H, W) float32 µm.
    """
    return _sensor(_blur(tex, heights, margin, focus_um, optics), optics, rng)


def _sigma(heights: np.ndarray, focus_um: float, optics: Optics) -> np.ndarray:
    """The PSF sigma (px, float32) of each height (µm) at ``focus_um``: the module's law."""
    sigma = heights - np.float32(focus_um)
    np.abs(sigma, out=sigma)
    sigma *= np.float32(optics.psf_c_px_per_um)
    sigma += np.float32(optics.psf_s0_px)
    np.minimum(sigma, np.float32(optics.sigma_max_px), out=sigma)
    return sigma


def _blur(tex: np.ndarray, heights: np.ndarray, margin: int, focus_um: float,
          optics: Optics) -> np.ndarray:
    """The space-variant blur of :func:`_render`: (H, W) float32 reflectance."""
    h, w = heights.shape
    he, we = tex.shape
    bank = blur_bank_sigmas(optics)
    u = _level_coordinate(_sigma(heights, focus_um, optics))
    l_lo = max(0, min(len(bank) - 1, math.floor(float(u.min()))))
    l_hi = max(l_lo, min(len(bank) - 1, math.ceil(float(u.max()))))
    n_lev = l_hi - l_lo + 1
    if margin < math.ceil(3.0 * bank[l_hi]):
        raise AssertionError("texture margin too small for the blur")  # internal invariant

    # Bank levels l_lo..l_hi, interleaved by row: row y of level l at stack row y*n + l.
    stack = np.empty((he, n_lev, we), dtype=np.float32)
    pyramid = {1: tex}
    for i, s in enumerate(bank[l_lo:l_hi + 1]):
        view = stack[:, i, :]
        d = _factor(s)
        if s == 0:
            np.copyto(view, tex)
        elif d == 1:
            _gauss(tex, s, dst=view)
        else:
            for f in (2, 4, 8):
                if f <= d and f not in pyramid:
                    src = pyramid[f // 2]
                    pyramid[f] = cv2.resize(src, (src.shape[1] // 2, src.shape[0] // 2),
                                            interpolation=cv2.INTER_AREA)
            s_small = math.sqrt(s * s - (d * d - 1) / 12.0 - _upsample_variance(d)) / d
            small = _gauss(pyramid[d], s_small)
            cv2.resize(small, (we, he), dst=view, interpolation=cv2.INTER_LINEAR)

    if n_lev == 1:
        img = np.ascontiguousarray(stack[margin:margin + h, 0, margin:margin + w])
    else:
        # Per pixel, linear interpolation between the two bracketing levels: one bilinear
        # remap down the interleaved stack (x exact; the level weight is quantised by cv2 to
        # 1/32, well under 1 LSB), in row chunks so the lookup rows stay within int16.
        u -= np.float32(l_lo)
        np.clip(u, 0.0, np.float32(n_lev - 1), out=u)
        flat = stack.reshape(he * n_lev, we)
        map_x = np.tile(np.arange(margin, margin + w, dtype=np.float32), (h, 1))
        img = np.empty((h, w), dtype=np.float32)
        chunk = max(1, (_SHORT_MAX - 2 * n_lev) // n_lev)
        for r0 in range(0, h, chunk):
            r1 = min(h, r0 + chunk)
            src = flat[(margin + r0) * n_lev:(margin + r1) * n_lev]
            map_y = u[r0:r1] + (np.arange(r1 - r0, dtype=np.float32) * n_lev)[:, None]
            cv2.remap(src, map_x[r0:r1], map_y, cv2.INTER_LINEAR, dst=img[r0:r1],
                      borderMode=cv2.BORDER_REPLICATE)
    return img


def _sensor(img: np.ndarray, optics: Optics, rng: np.random.Generator | None) -> np.ndarray:
    """Intensity, noise and quantisation of a (H, W) float32 reflectance image."""
    h, w = img.shape
    full = float(optics.max_value)
    out_type = cv2.CV_8U if optics.bit_depth == 8 else cv2.CV_16U
    if rng is not None and optics.noise_sigma > 0:
        noise = optics.noise_table.take(rng.integers(0, 65536, (h, w), dtype=np.uint16))
        out = cv2.addWeighted(img, optics.gain * full, noise, optics.noise_sigma * full,
                              optics.offset * full, dtype=out_type)
    else:
        out = cv2.addWeighted(img, optics.gain * full, img, 0.0, optics.offset * full,
                              dtype=out_type)
    if optics.bit_depth == 10:
        np.minimum(out, np.uint16(1023), out=out)
    return np.asarray(out)


def _check(world: PlateWorld, optics: Optics, x0: float, y0: float) -> None:
    if not isinstance(optics, Optics):
        raise ValueError(f"optics must be an Optics, got {type(optics).__name__}")
    if abs(world.pixel_um - optics.pixel_um) > 1e-9 * optics.pixel_um:
        raise ValueError(f"optics.pixel_um ({optics.pixel_um}) must equal "
                         f"world.pixel_um ({world.pixel_um})")
    if not (math.isfinite(x0) and math.isfinite(y0)):
        raise ValueError(f"x0, y0 must be finite, got {x0}, {y0}")


def _texture_window(world: PlateWorld, x0: float, y0: float, optics: Optics,
                    margin: int, *, pad: int = 0) -> np.ndarray:
    """Texture over the frame (grown by ``pad`` px each side, its first pixel at x0, y0) plus
    ``margin`` px each side, padded to multiples of 8."""
    he = optics.height + 2 * pad + 2 * margin
    we = optics.width + 2 * pad + 2 * margin
    he += -he % 8
    we += -we % 8
    return world.texture(x0 - margin, y0 - margin, we, he)


def _margin_for(heights: np.ndarray, focus_um: float, optics: Optics) -> int:
    """Texture margin (px) the blur of a frame needs: 3 sigma of its top bank level, and more.

    Rounded up to a multiple of 8 so that the downsampled bank levels sit on the same grid
    relative to the frame whatever the margin (render_stack equals render_frame).
    """
    bank = blur_bank_sigmas(optics)
    dz = max(abs(float(heights.max()) - focus_um), abs(float(heights.min()) - focus_um))
    s = min(optics.psf_s0_px + optics.psf_c_px_per_um * dz, optics.sigma_max_px)
    top = bank[min(len(bank) - 1, int(np.searchsorted(bank, s - 1e-6)))]
    return 8 * math.ceil((3.0 * top + 1.0) / 8.0)  # multiple of 8: same pyramid grid


def _scattered(world: PlateWorld, x0: float, y0: float, focus_um: float, optics: Optics,
               heights: np.ndarray, pad: int = 0) -> np.ndarray:
    """The reflectance of the frame grown by ``pad`` px, its light scattered from each world
    point (:func:`sffscan.stages.sim.scatter.scatter_blur`): the texture and the heights over
    a margin wide enough for the largest blur of the window's points and the margin's own."""
    from sffscan.stages.sim.scatter import scatter_blur

    margin = _margin_for(heights, focus_um, optics)
    while True:  # the margin's own points may blur wider (the margin grows to sigma_max's)
        tex = _texture_window(world, x0 - pad, y0 - pad, optics, margin, pad=pad)
        ext = world.height_um(x0 - pad - margin, y0 - pad - margin, tex.shape[1], tex.shape[0])
        wider = _margin_for(ext, focus_um, optics)
        if wider <= margin:
            break
        margin = wider
    return scatter_blur(tex, _sigma(ext, focus_um, optics), margin, heights.shape,
                        blur_bank_sigmas(optics))


def _lens_frame(world: PlateWorld, x0: float, y0: float, focus_um: float, optics: Optics,
                rng: np.random.Generator | None) -> np.ndarray:
    """A frame through the real-lens effects (module docstring), sensor included."""
    shape = (optics.height, optics.width)
    m = optics.magnification(focus_um)
    pad = 0 if m == 1.0 else breathing_pad_px(shape, m)
    heights = world.height_um(x0 - pad, y0 - pad, optics.width + 2 * pad,
                              optics.height + 2 * pad)
    if optics.field_curvature_um != 0:
        heights -= curvature_map_um(shape, field_curvature_um=optics.field_curvature_um,
                                    scale=m, pad=pad)
    if optics.blur_model == "scatter":
        img = _scattered(world, x0, y0, focus_um, optics, heights, pad)
    else:
        margin = _margin_for(heights, focus_um, optics)
        tex = _texture_window(world, x0 - pad, y0 - pad, optics, margin, pad=pad)
        img = _blur(tex, heights, margin, focus_um, optics)
    if m != 1.0:
        img = scale_about_centre(img, m, out_shape=shape, pad=pad)
    if optics.vignetting != 0:
        img *= vignetting_map(shape, vignetting=optics.vignetting)
    return _sensor(img, optics, rng)


# ---------------------------------------------------------------------- public


def render_frame(world: PlateWorld, *, x0: float, y0: float, focus_um: float,
                 optics: Optics, rng: np.random.Generator | None) -> np.ndarray:
    """The image the camera takes with its first pixel on world (x0, y0), focused at focus_um.

    Parameters
    ----------
    world : PlateWorld
        The simulated world (same ``pixel_um`` as the optics).
    x0, y0 : float
        World position of the frame's top-left pixel (column, row), px; fractional allowed.
    focus_um : float
        Height in focus, µm.
    optics : Optics
        Camera and lens model.
    rng : numpy.random.Generator or None
        Source of the sensor noise; None renders noise-free.

    Returns
    -------
    (optics.height, optics.width) uint8 (bit_depth 8) or uint16 in 0..1023 (bit_depth 10).
    """
    _check(world, optics, x0, y0)
    if not math.isfinite(focus_um):
        raise ValueError(f"focus_um must be finite, got {focus_um}")
    if not optics.ideal:
        return _lens_frame(world, x0, y0, focus_um, optics, rng)
    heights = world.height_um(x0, y0, optics.width, optics.height)
    if optics.blur_model == "scatter":
        return _sensor(_scattered(world, x0, y0, focus_um, optics, heights), optics, rng)
    margin = _margin_for(heights, focus_um, optics)
    tex = _texture_window(world, x0, y0, optics, margin)
    return _render(tex, heights, margin, focus_um, optics, rng)


def render_stack(world: PlateWorld, *, x0: float, y0: float, focus_heights_um: np.ndarray,
                 optics: Optics, rng: np.random.Generator | None) -> np.ndarray:
    """A stationary focus stack: one frame per focus height, the camera at (x0, y0) px.

    Parameters
    ----------
    world, x0, y0, optics, rng
        As in :func:`render_frame`; noise is drawn frame after frame from ``rng``.
    focus_heights_um : (N,) array_like of float
        Heights in focus, µm.

    Returns
    -------
    (N, optics.height, optics.width) uint8 or uint16, as :func:`render_frame`.
    """
    _check(world, optics, x0, y0)
    zs = np.asarray(focus_heights_um, dtype=np.float64).reshape(-1)
    if zs.size == 0 or not np.all(np.isfinite(zs)):
        raise ValueError("focus_heights_um must be a non-empty array of finite heights")
    if not optics.ideal or optics.blur_model == "scatter":
        return np.stack([render_frame(world, x0=x0, y0=y0, focus_um=float(z), optics=optics,
                                      rng=rng) for z in zs])
    heights = world.height_um(x0, y0, optics.width, optics.height)
    margin = max(_margin_for(heights, float(z), optics) for z in zs)
    tex = _texture_window(world, x0, y0, optics, margin)
    out = np.empty((zs.size, optics.height, optics.width), dtype=optics.dtype)
    for k, z in enumerate(zs):
        out[k] = _render(tex, heights, margin, float(z), optics, rng)
    return out
