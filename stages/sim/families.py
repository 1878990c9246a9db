"""Synthetic families of focus stacks with a known surface, for choosing a depth method by
a protocol that cannot overfit (leave one family out: ``sffscan study --families``).

A *family* is a kind of instrument and surface: how the blur grows with defocus (``even``:
linearly in z, the same above and below focus; ``lens``: a thin lens, linear in 1/z, so
the focus curve is lopsided), the point-spread function (Gaussian or pillbox), the sensor
noise (shot + read noise, quantised to 8..12 bits), the texture (scale and contrast) and
the surface (sinusoid, flat, steep slope, steps, heights near both ends of the range).
Within a family each *seed* draws its own number of levels N (20..100), blur per level,
texture and surface parameters, so a method tuned on some seeds is scored on others.

Rendering is per pixel and exact up to the blur bank: the texture is blurred with a bank
of PSF radii, and each pixel of the image at level k takes the bank image of its own blur
radius (linear interpolation between the two nearest radii: ``blur_model="gather"``, every
figure of the depth study). Images are small (64 x 64 px by default): a stack takes
milliseconds. ``blur_model="scatter"`` renders the same draws as optics image a surface
without occlusion: each point of the world spreads its light over its own blur radius, so
at an edge or on a slope the defocused side's light spills over the focused side and the
light is conserved (a second generator for the held-out benches; slower, one blur per bank
radius in use per level).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

import cv2
import numpy as np
from sffscan.stages.sim.scatter import scatter_levels

__all__ = ["BLUR_MODELS", "CROSSED_FAMILIES", "FAMILIES", "Family", "SimStack", "family_names",
           "family_stack"]

BLUR_MODELS = ("gather", "scatter")
"""How :func:`family_stack` applies a blur that varies over the image: each image pixel takes
the texture blurred by its own radius (``"gather"``), or each world point spreads its light
over its own radius (``"scatter"``, the optics of a surface without occlusion)."""

BANK_RADII_PX = np.array([0.0, 0.35, 0.7, 1.0, 1.4, 2.0, 2.8, 3.8, 5.0, 6.5, 8.5, 11.0, 14.0])
"""Blur radii (px) of the bank; larger blurs are clamped to the last (the texture is gone)."""

STEP_UM = 10.0
"""Height between focus levels, µm (every family; errors are reported in levels)."""

OVERSAMPLE = 4
"""Stacks with breathing (and their breathing-free twins) render the world on a grid this
many times finer and integrate it over each sensor pixel (an area average), so that the
magnified views are resampled where the texture is smooth, not by an interpolation at the
sensor's own resolution (which would attenuate each frame's finest texture differently)."""


@dataclass(frozen=True)
class Family:
    """One kind of instrument and surface; the ranges are drawn per seed.

    Attributes
    ----------
    name : str
        Short name (the table's row).
    blur : {"even", "lens"}
        Blur radius ``b |z - f|`` (even in z) or a thin lens' ``b D^2 |1/(D + f) - 1/(D + z)|``
        with the working distance D = 0.6 of the focus range (lopsided: the blur grows
        about 7x faster with defocus at the near end of the range than at the far end, and
        at any height faster below focus than above it).
    psf : {"gauss", "pillbox"}
        Gaussian (sigma = radius) or uniform disc of the radius.
    noise : {"none", "light", "heavy"}
        Full well and read noise (electrons): none (quantisation only), light (20000, 5),
        heavy (1500, 15) scaled by the texture's contrast.
    bits : tuple of int
        Bit depths drawn from.
    surface : {"sinus", "flat", "slope", "steps", "ends"}
        Sinusoid of up to 0.35 of the range; a flat plate (slightly tilted); a slope of
        0.1..0.45 levels per px (at the focus window's limit: 9 px span 1..4 levels); three
        or four terraces; two plateaus 1..3 levels from either end of the range.
    texture_px : (float, float)
        Range of the texture's grain size, px.
    contrast : (float, float)
        Range of the texture's standard deviation (0..1 images, mean 0.5).
    blur_per_level_px : (float, float)
        Range of the blur radius added per level of defocus (``b * STEP``), px.
    texture : {"uniform", "mixed"}
        One texture over the image, or two (the drawn one and one 3x coarser with twice its
        contrast, capped at 0.3) blended by a smooth random map of patches about 10 px
        across, so that texture scale and contrast, and with them the focus curves' width
        and height, vary from pixel to pixel within a stack as in a real scene (a uniform
        family's stacks are unchanged by this option's existence: its draws come after
        theirs).
    """

    name: str
    blur: Literal["even", "lens"] = "even"
    psf: Literal["gauss", "pillbox"] = "gauss"
    noise: Literal["none", "light", "heavy"] = "light"
    bits: tuple[int, ...] = (8, 10, 12)
    surface: Literal["sinus", "flat", "slope", "steps", "ends"] = "sinus"
    texture_px: tuple[float, float] = (1.0, 3.0)
    contrast: tuple[float, float] = (0.1, 0.25)
    blur_per_level_px: tuple[float, float] = (0.4, 1.2)
    texture: Literal["uniform", "mixed"] = "uniform"


FAMILIES: tuple[Family, ...] = (
    Family("even-gauss"),
    Family("even-noisy", noise="heavy", contrast=(0.04, 0.12)),
    Family("lens-gauss", blur="lens"),
    Family("pillbox", psf="pillbox"),
    Family("lens-pillbox-noisy", blur="lens", psf="pillbox", noise="heavy",
           contrast=(0.05, 0.15)),
    Family("steps", surface="steps"),
    Family("slopes", surface="slope", blur="lens"),
    Family("ends", surface="ends", noise="heavy", contrast=(0.06, 0.15)),
    Family("flat-fine-8bit", surface="flat", bits=(8,), texture_px=(0.7, 1.2),
           contrast=(0.03, 0.08), noise="heavy"),
    Family("clean-coarse", noise="none", bits=(12,), texture_px=(2.5, 5.0),
           contrast=(0.15, 0.3), blur_per_level_px=(0.8, 2.0)),
)
"""The families of the study: each differs from the first in one or two ways."""

CROSSED_FAMILIES: tuple[Family, ...] = (
    Family("slopes-lens-noisy", surface="slope", blur="lens", noise="heavy",
           contrast=(0.04, 0.12)),
    Family("slopes-even-noisy", surface="slope", noise="heavy", contrast=(0.04, 0.12)),
    Family("slopes-even", surface="slope"),
    Family("slopes-pillbox-noisy", surface="slope", psf="pillbox", noise="heavy",
           contrast=(0.05, 0.15)),
    Family("slopes-8bit-fine", surface="slope", bits=(8,), texture_px=(0.7, 1.2),
           contrast=(0.03, 0.08), noise="heavy"),
    Family("slopes-lens-pillbox", surface="slope", blur="lens", psf="pillbox"),
    Family("slopes-coarse-clean", surface="slope", noise="none", bits=(12,),
           texture_px=(2.5, 5.0), contrast=(0.15, 0.3), blur_per_level_px=(0.8, 2.0)),
    Family("sinus-lens-light", blur="lens", noise="light", contrast=(0.05, 0.12)),
    Family("steps-lens-noisy", surface="steps", blur="lens", noise="heavy",
           contrast=(0.05, 0.15)),
    Family("flat-lens-12bit", surface="flat", blur="lens", bits=(12,), noise="light"),
)
"""More families, each crossing the settings of two or three of :data:`FAMILIES` (slopes
under each blur, PSF and noise; a thin lens' sinusoid, steps and flat): not in the study's
default table (``sffscan study --families --crossed`` runs the protocol on both sets), a
check of the choice on kinds of stack it was not made on (docs/depth-method-log.md)."""

_NOISE_E = {"none": None, "light": (20000.0, 5.0), "heavy": (1500.0, 15.0)}


@dataclass(frozen=True)
class SimStack:
    """A rendered stack: ``images`` (N, H, W) float32 0..1, ``focus_um`` (N,) float64,
    ``truth_um`` (H, W) float32, and the draws that made it (``info``)."""

    images: np.ndarray
    focus_um: np.ndarray
    truth_um: np.ndarray
    family: str
    seed: int
    info: dict[str, float]


def family_names(*, crossed: bool = False) -> list[str]:
    """The names of :data:`FAMILIES`, in order (then :data:`CROSSED_FAMILIES`'s with
    ``crossed``)."""
    return [f.name for f in FAMILIES + (CROSSED_FAMILIES if crossed else ())]


def _family(name: str | Family) -> Family:
    if isinstance(name, Family):
        return name
    for f in FAMILIES + CROSSED_FAMILIES:
        if f.name == name:
            return f
    raise ValueError(f"unknown family {name!r}; families: "
                     f"{', '.join(family_names(crossed=True))}")


def _texture(rng: np.random.Generator, shape: tuple[int, int], grain_px: float,
             contrast: float) -> np.ndarray:
    """Band-limited random texture, mean 0.5 and standard deviation ``contrast``."""
    t = np.asarray(cv2.GaussianBlur(rng.standard_normal(shape).astype(np.float32), (0, 0),
                                    grain_px * 0.5, borderType=cv2.BORDER_REFLECT),
                   dtype=np.float32)
    t = (t - t.mean()) * np.float32(contrast / max(float(t.std()), 1e-9))
    return np.clip(t + np.float32(0.5), 0.0, 1.0)


def _mixed_texture(rng: np.random.Generator, shape: tuple[int, int], grain_px: float,
                   contrast: float, q: int) -> np.ndarray:
    """:attr:`Family.texture` ``"mixed"``: the drawn texture and one 3x coarser with twice
    the contrast (at most 0.3), blended by a logistic of a smooth random field (patches
    ~10 px across at the sensor's scale, ``q`` times finer here)."""
    fine = _texture(rng, shape, grain_px, contrast)
    coarse = _texture(rng, shape, 3.0 * grain_px, min(2.0 * contrast, 0.3))
    field = cv2.GaussianBlur(rng.standard_normal(shape).astype(np.float32), (0, 0),
                             3.0 * q, borderType=cv2.BORDER_REFLECT)
    w = 1.0 / (1.0 + np.exp(-4.0 * field / max(float(field.std()), 1e-9)))
    return np.clip(w * fine + (1.0 - w) * coarse, 0.0, 1.0).astype(np.float32)


def _disc(radius: float) -> np.ndarray:
    """Anti-aliased uniform disc of ``radius`` px (4x supersampled), sum 1."""
    r = int(np.ceil(radius)) + 1
    s = (np.arange(-r * 4, r * 4 + 4) + 0.5) / 4.0 - 0.5
    yy, xx = np.meshgrid(s, s, indexing="ij")
    inside = (yy**2 + xx**2 <= radius**2).astype(np.float32)
    k = inside.reshape(2 * r + 1, 4, 2 * r + 1, 4).mean(axis=(1, 3))
    return k / k.sum()


def _blurred(img: np.ndarray, radius: float, psf: str) -> np.ndarray:
    """``img`` (float32) blurred by the PSF of ``radius`` px (itself at 0)."""
    if radius == 0:
        return img
    if psf == "gauss":
        return cv2.GaussianBlur(img, (0, 0), float(radius), borderType=cv2.BORDER_REFLECT)
    return cv2.filter2D(img, -1, _disc(max(float(radius), 0.5)), borderType=cv2.BORDER_REFLECT)


def _bank(tex: np.ndarray, psf: str, q: int = 1) -> np.ndarray:
    """The texture blurred by each radius of :data:`BANK_RADII_PX` (times ``q``, px)."""
    out = np.empty((len(BANK_RADII_PX), *tex.shape), np.float32)
    for i, r in enumerate(BANK_RADII_PX * q):
        out[i] = _blurred(tex, float(r), psf)
    return out


def _bank_weights(r: np.ndarray, radii: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """For radii ``r`` (px, within the bank's), the lower bank index ``i`` and the weight
    ``t`` of bank ``i + 1`` (linear in the radius)."""
    i = np.clip(np.searchsorted(radii, r, side="right") - 1, 0, len(radii) - 2)
    return i, (r - radii[i]) / (radii[i + 1] - radii[i])


def _scatter(tex: np.ndarray, i: np.ndarray, t: np.ndarray, radii: np.ndarray,
             psf: str) -> np.ndarray:
    """The image of a texture each of whose points spreads by its own radius: the texture's
    share at each bank radius (the weights of :func:`_bank_weights`) blurred by that radius,
    summed (float64; :func:`sffscan.stages.sim.scatter.scatter_levels`)."""
    return scatter_levels(tex, i, t, lambda src, j: _blurred(src, float(radii[j]), psf),
                          dtype=np.float64)


def _surface(fam: Family, rng: np.random.Generator, shape: tuple[int, int], n: int
             ) -> np.ndarray:
    """True height in levels (0 .. N-1), (H, W) float64."""
    h, w = shape
    yy, xx = np.mgrid[0:h, 0:w].astype(np.float64)
    mid = (n - 1) / 2.0
    if fam.surface == "sinus":
        amp = rng.uniform(0.15, 0.35) * (n - 1)
        period = rng.uniform(30.0, 90.0)
        phase = rng.uniform(0, 2 * np.pi, 2)
        z = mid + amp * np.sin(2 * np.pi * xx / period + phase[0]) * np.cos(
            2 * np.pi * yy / (1.3 * period) + phase[1])
    elif fam.surface == "flat":
        z = rng.uniform(0.2, 0.8) * (n - 1) + rng.uniform(-0.02, 0.02) * (xx - w / 2)
    elif fam.surface == "slope":
        slope = min(rng.uniform(0.1, 0.45), 0.8 * (n - 1) / w)
        ang = rng.uniform(0, 2 * np.pi)
        t = (xx - w / 2) * np.cos(ang) + (yy - h / 2) * np.sin(ang)
        z = mid + slope * t
    elif fam.surface == "steps":
        n_steps = int(rng.integers(3, 5))
        levels = rng.uniform(0.15, 0.85, n_steps) * (n - 1)
        cuts = np.sort(rng.uniform(0.15, 0.85, n_steps - 1)) * w
        z = levels[np.searchsorted(cuts, xx)]
        z = z + np.where(yy > h / 2, rng.uniform(-0.1, 0.1) * (n - 1), 0.0)
    else:  # ends: plateaus near both ends, gently tilted
        lo, hi = rng.uniform(1.0, 3.0), (n - 1) - rng.uniform(1.0, 3.0)
        z = np.where(xx < w / 2, lo, hi) + rng.uniform(-0.01, 0.01) * (yy - h / 2)
    return np.clip(z, 0.0, n - 1.0)


def _blur_radius(fam: Family, z: np.ndarray, f: float, b: float, n: int) -> np.ndarray:
    """Blur radius, px, of surface heights ``z`` (levels) at focus level ``f``."""
    if fam.blur == "even":
        return b * np.abs(z - f)
    d = 0.6 * (n - 1)  # the working distance: 0.6 of the focus range
    return b * d * d * np.abs(1.0 / (d + f) - 1.0 / (d + z))


def _sensor(img: np.ndarray, fam: Family, rng: np.random.Generator, bits: int) -> np.ndarray:
    full = float(2**bits - 1)
    noise = _NOISE_E[fam.noise]
    if noise is not None:
        well, read = noise
        e = img * well
        e = e + rng.standard_normal(img.shape) * np.sqrt(np.maximum(e, 0.0) + read**2)
        img = e / well
    return (np.clip(np.round(img * full), 0, full) / full).astype(np.float32)


def _view(world: np.ndarray, pad: int, size_px: int, mag: float, q: int = 1) -> np.ndarray:
    """The ``size_px`` square a frame of magnification ``mag`` sees of the padded world
    (rendered ``q`` times finer): fine px (u, v) shows the world at ``centre + (u - c, v - c)
    / mag`` (Lanczos on the fine grid; the plain crop for ``mag == 1``), then each sensor
    pixel the mean of its q x q fine pixels."""
    s, p = size_px * q, pad * q
    if mag == 1.0:
        v = world[p:p + s, p:p + s]
    else:
        a = 1.0 / mag
        c = (s - 1) / 2.0
        mat = np.array([[a, 0.0, p + c * (1.0 - a)], [0.0, a, p + c * (1.0 - a)]])
        v = cv2.warpAffine(world.astype(np.float32), mat, (s, s),
                           flags=cv2.INTER_LANCZOS4 | cv2.WARP_INVERSE_MAP)
    if q > 1:
        v = cv2.resize(v, (size_px, size_px), interpolation=cv2.INTER_AREA)
    return np.asarray(v, dtype=np.float64)


def family_stack(family: str | Family, seed: int, *, size_px: int = 64,
                 n_levels: int | None = None, breathing: float = 0.0,
                 pad_for_breathing: float | None = None,
                 blur_model: Literal["gather", "scatter"] = "gather") -> SimStack:
    """Render one stack of a family.

    Parameters
    ----------
    family : str or Family
        A name of :data:`FAMILIES` or a :class:`Family`.
    seed : int
        Seed of every draw (N, blur, texture, surface, noise).
    size_px : int, keyword-only
        Image width and height, px. Default 64.
    n_levels : int, optional, keyword-only
        Number of focus levels; drawn from 20..100 when not given.
    breathing : float, keyword-only
        Focus breathing, magnification change per level (0.012: 1.2 %/level): the image at
        level k shows the world magnified ``(1 + breathing)^(k - N // 2)`` about the image
        centre (a non-telecentric lens), before the sensor. The draws (and so the noise
        realisation) are those of the same seed and ``pad_for_breathing`` without
        breathing. Such stacks are rendered :data:`OVERSAMPLE` times finer and integrated
        over each pixel (slower; the draws differ from those of a stack without either
        argument). Default 0.
    pad_for_breathing : float, optional, keyword-only
        The breathing the rendered world's margin is sized for (default ``breathing``): give
        the breathing stack's value with ``breathing=0`` for its breathing-free twin (the
        same world, texture and noise; the two differ by the breathing only).
    blur_model : {"gather", "scatter"}, keyword-only
        :data:`BLUR_MODELS`: each image pixel takes the texture blurred by its own height's
        radius (default; every figure of the depth study), or each world point spreads its
        light over its own radius (the same draws; slower).

    Returns
    -------
    SimStack
        Images 0..1 (N, size, size) float32, focus heights ``k * STEP_UM`` µm, truth µm.
    """
    fam = _family(family)
    rng = np.random.default_rng([seed, sum(map(ord, fam.name))])
    n = int(n_levels if n_levels is not None else rng.integers(20, 101))
    if n < 3:
        raise ValueError(f"n_levels must be >= 3, got {n}")
    if blur_model not in BLUR_MODELS:
        raise ValueError(f"blur_model must be one of {BLUR_MODELS}, got {blur_model!r}")
    for name, v in (("breathing", breathing), ("pad_for_breathing", pad_for_breathing)):
        if v is not None and not -0.5 < v < 0.5:
            raise ValueError(f"{name} must be in -0.5 .. 0.5 per level, got {v}")
    mags = (1.0 + breathing) ** (np.arange(n) - n // 2)
    widest = (1.0 + (breathing if pad_for_breathing is None else pad_for_breathing)) ** (
        np.array([0, n - 1]) - n // 2)
    # the world a frame sees beyond the image (magnification < 1) and the blur's reach
    pad = 16 + int(np.ceil(0.5 * size_px * max(0.0, 1.0 / float(widest.min()) - 1.0)))
    shape = (size_px + 2 * pad, size_px + 2 * pad)
    q = 1 if breathing == 0.0 and pad_for_breathing is None else OVERSAMPLE
    fine = (shape[0] * q, shape[1] * q)
    grain = float(rng.uniform(*fam.texture_px))
    contrast = float(rng.uniform(*fam.contrast))
    b = float(rng.uniform(*fam.blur_per_level_px))
    bits = int(rng.choice(fam.bits))
    tex = _texture(rng, fine, grain * q, contrast)
    z = _surface(fam, rng, shape, n)
    if fam.texture == "mixed":  # drawn after the uniform families' draws: theirs unchanged
        tex = _mixed_texture(rng, fine, grain * q, contrast, q)
    zf = z if q == 1 else cv2.resize(z, fine[::-1], interpolation=cv2.INTER_LINEAR)
    radii = BANK_RADII_PX * q
    flat_bank = _bank(tex, fam.psf, q).reshape(len(radii), -1) if blur_model == "gather" else None
    idx = np.arange(fine[0] * fine[1])
    images = np.empty((n, size_px, size_px), np.float32)
    for k in range(n):
        r = np.clip(q * _blur_radius(fam, zf, float(k), b, n), 0.0, radii[-1]).reshape(-1)
        i, t = _bank_weights(r, radii)
        if flat_bank is None:
            img = _scatter(tex, i.reshape(fine), t.reshape(fine), radii, fam.psf)
        else:
            img = ((1 - t) * flat_bank[i, idx] + t * flat_bank[i + 1, idx]).reshape(fine)
        images[k] = _sensor(_view(img, pad, size_px, float(mags[k]), q), fam, rng, bits)
    truth = (z[pad:-pad, pad:-pad] * STEP_UM).astype(np.float32)
    info = {"n_levels": float(n), "grain_px": grain, "contrast": contrast,
            "blur_per_level_px": b, "bits": float(bits), "breathing": float(breathing)}
    return SimStack(images, np.arange(n) * STEP_UM, truth, fam.name, seed, info)

