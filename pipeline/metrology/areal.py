"""Areal surface texture parameters of a height-map region (ISO 25178-2 height parameters).

With z(x, y) the height relative to the reference surface over the N finite pixels of the
region (float64):

- Sq = sqrt(mean(z^2)), root-mean-square height;
- Sa = mean(|z|), arithmetic mean height;
- Sp = max(z), Sv = -min(z), Sz = Sp + Sv, maximum height;
- Ssk = mean(z^3) / Sq^3, skewness;  Sku = mean(z^4) / Sq^4, kurtosis.

The reference surface (``level``): ``"plane"`` (default) the least-squares plane of the
region, the usual F-operator of a flat part (removes form and tilt); ``"mean"`` the mean
height; ``"none"`` z as given. No S-filter or L-filter (wavelength cut-off) is applied: the
values are those of the primary surface of the sampled region, at the map's pixel size.
NaN pixels are left out (their count is reported), never filled.
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass

import numpy as np
from sffscan.pipeline.metrology.compare import fit_plane

__all__ = ["LEVELS", "ArealParameters", "areal_parameters", "level_surface"]

LEVELS = ("plane", "mean", "none")


@dataclass(frozen=True)
class ArealParameters:
    """Height parameters of a region, µm (Ssk, Sku dimensionless)."""

    sa_um: float
    sq_um: float
    sz_um: float
    sp_um: float
    sv_um: float
    ssk: float
    sku: float
    pixels: int
    missing: int
    level: str

    def as_dict(self) -> dict[str, float | int | str]:
        return asdict(self)

    def format(self) -> str:
        return (f"Sa {self.sa_um:.3f} µm  Sq {self.sq_um:.3f} µm  Sz {self.sz_um:.3f} µm "
                f"(Sp {self.sp_um:.3f}, Sv {self.sv_um:.3f})  Ssk {self.ssk:.4f}  "
                f"Sku {self.sku:.4f}  over {self.pixels} px ({self.missing} missing), "
                f"reference: {self.level}")


def level_surface(z: np.ndarray, *, level: str = "plane") -> np.ndarray:
    """Heights relative to the reference surface, float64, NaN kept.

    Parameters
    ----------
    z : (H, W) ndarray of float
        Heights, µm; NaN = missing.
    level : {"plane", "mean", "none"}, keyword-only
        Reference surface (see the module docstring).
    """
    if level not in LEVELS:
        raise ValueError(f"level must be one of {LEVELS}, got {level!r}")
    z = np.asarray(z, dtype=np.float64)
    if z.ndim != 2:
        raise ValueError(f"height map must be 2-D, got shape {z.shape}")
    if level == "none":
        return z.copy()
    ok = np.isfinite(z)
    if not ok.any():
        raise ValueError("the region has no finite height")
    if level == "mean":
        return z - z[ok].mean()
    a, b, c = fit_plane(z)
    yy, xx = np.indices(z.shape, dtype=np.float64)
    return z - (a + b * xx + c * yy)


def areal_parameters(z: np.ndarray, *, level: str = "plane") -> ArealParameters:
    """Sa, Sq, Sz (Sp, Sv), Ssk, Sku of a height-map region.

    Parameters
    ----------
    z : (H, W) ndarray of float
        Heights, µm; NaN = missing (left out).
    level : {"plane", "mean", "none"}, keyword-only
        Reference surface.

    Returns
    -------
    ArealParameters
        Ssk and Sku are NaN when Sq is 0 (a perfectly flat region).

    Raises
    ------
    ValueError
        If ``z`` is not 2-D or has no finite height (too few for a plane with ``"plane"``).
    """
    r = level_surface(z, level=level)
    v = r[np.isfinite(r)]
    if v.size == 0:
        raise ValueError("the region has no finite height")
    v2 = v * v
    sq = math.sqrt(float(v2.mean()))
    sp, sv = float(v.max()), float(-v.min())
    ssk = float((v2 * v).mean()) / sq**3 if sq > 0 else math.nan
    sku = float((v2 * v2).mean()) / sq**4 if sq > 0 else math.nan
    return ArealParameters(sa_um=float(np.abs(v).mean()), sq_um=sq, sz_um=sp + sv, sp_um=sp,
                           sv_um=sv, ssk=ssk, sku=sku, pixels=int(v.size),
                           missing=int(r.size - v.size), level=level)
