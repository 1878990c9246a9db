"""Relief features of the simulated world: analytic heights above a flat base, in µm.

Each feature knows its bounding box and evaluates its relief on a grid, vectorised, so
that a window of the world costs only the features that touch it.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Protocol

import numpy as np


class Feature(Protocol):
    """A relief feature: height above the base over a bounding box (µm)."""

    @property
    def bbox_um(self) -> tuple[float, float, float, float]:
        """(x_min, y_min, x_max, y_max) outside which the relief is 0, µm (may be ±inf)."""
        ...

    def relief_um(self, x_um: np.ndarray, y_um: np.ndarray) -> np.ndarray:
        """Relief at the grid ``x_um`` (W,) x ``y_um`` (H,), float64 µm -> (H, W) float32."""
        ...


@dataclass(frozen=True)
class Tetrahedron:
    """Triangular pyramid: one base edge parallel to x, apex above the base's centroid.

    ``(cx_um, cy_um)`` is the centre of the triangle's bounding box (the centroid sits
    ``edge/(4*sqrt(3))`` below it in y, so the apex is at ``cy_um - edge_um*sqrt(3)/12``).
    Regular when ``height_um == edge_um * sqrt(2/3)``.
    """

    cx_um: float
    cy_um: float
    edge_um: float
    height_um: float

    @property
    def apex_um(self) -> tuple[float, float]:
        return self.cx_um, self.cy_um - self.edge_um * math.sqrt(3.0) / 12.0

    @property
    def bbox_um(self) -> tuple[float, float, float, float]:
        a, hy = self.edge_um / 2.0, self.edge_um * math.sqrt(3.0) / 4.0
        return self.cx_um - a, self.cy_um - hy, self.cx_um + a, self.cy_um + hy

    def relief_um(self, x_um: np.ndarray, y_um: np.ndarray) -> np.ndarray:
        ax, ay = self.apex_um
        r_in = self.edge_um / (2.0 * math.sqrt(3.0))  # inradius: centroid to each edge
        dx = ((x_um - ax) / r_in).astype(np.float32)[None, :]
        dy = ((y_um - ay) / r_in).astype(np.float32)[:, None]
        # 1 - (distance towards an edge) / r_in for the edges below (y < apex), upper left,
        # upper right; the relief is the smallest, clipped at 0 (planes through the apex).
        s3 = np.float32(math.sqrt(3.0) / 2.0)
        bottom = 1.0 + dy
        left = 1.0 - np.float32(0.5) * dy + s3 * dx
        right = 1.0 - np.float32(0.5) * dy - s3 * dx
        rel = np.minimum(np.minimum(left, right), bottom)
        np.maximum(rel, 0.0, out=rel)
        rel *= np.float32(self.height_um)
        return rel


@dataclass(frozen=True)
class _Round:
    cx_um: float
    cy_um: float
    radius_um: float
    height_um: float

    @property
    def bbox_um(self) -> tuple[float, float, float, float]:
        r = self.radius_um
        return self.cx_um - r, self.cy_um - r, self.cx_um + r, self.cy_um + r


@dataclass(frozen=True)
class Hemisphere(_Round):
    """Half ellipsoid of revolution: lateral radius ``radius_um``, top ``height_um`` above."""

    def relief_um(self, x_um: np.ndarray, y_um: np.ndarray) -> np.ndarray:
        dx2 = (((x_um - self.cx_um) / self.radius_um) ** 2).astype(np.float32)[None, :]
        dy2 = (((y_um - self.cy_um) / self.radius_um) ** 2).astype(np.float32)[:, None]
        q = 1.0 - dx2 - dy2
        np.maximum(q, 0.0, out=q)
        np.sqrt(q, out=q)
        q *= np.float32(self.height_um)
        return q


@dataclass(frozen=True)
class Cylinder(_Round):
    """Upright cylinder of radius ``radius_um`` with a flat top ``height_um`` above the base."""

    def relief_um(self, x_um: np.ndarray, y_um: np.ndarray) -> np.ndarray:
        dx2 = ((x_um - self.cx_um) ** 2).astype(np.float32)[None, :]
        dy2 = ((y_um - self.cy_um) ** 2).astype(np.float32)[:, None]
        inside = (dx2 + dy2) <= np.float32(self.radius_um**2)
        return inside.astype(np.float32) * np.float32(self.height_um)


@dataclass(frozen=True)
class Staircase:
    """Steps rising along +x: step k (0-based) of ``n_steps`` is ``(k+1) * step_height_um``.

    Occupies x in [x_start_um, x_start_um + n_steps * step_length_um), and y within
    ``half_width_um`` of ``cy_um``.
    """

    x_start_um: float
    cy_um: float
    n_steps: int
    step_length_um: float
    step_height_um: float
    half_width_um: float

    @property
    def bbox_um(self) -> tuple[float, float, float, float]:
        x1 = self.x_start_um + self.n_steps * self.step_length_um
        return self.x_start_um, self.cy_um - self.half_width_um, x1, self.cy_um + self.half_width_um

    def relief_um(self, x_um: np.ndarray, y_um: np.ndarray) -> np.ndarray:
        k = np.floor((x_um - self.x_start_um) / self.step_length_um)
        step = np.where((k >= 0) & (k < self.n_steps), (k + 1) * self.step_height_um, 0.0)
        inside = np.abs(y_um - self.cy_um) < self.half_width_um
        return (inside[:, None] * step.astype(np.float32)[None, :]).astype(np.float32)


@dataclass(frozen=True)
class Sinusoid:
    """Unbounded relief ``amplitude_um * sin(2 pi x / P) * cos(2 pi y / P)``, P in µm."""

    amplitude_um: float
    period_um: float

    @property
    def bbox_um(self) -> tuple[float, float, float, float]:
        return -math.inf, -math.inf, math.inf, math.inf

    def relief_um(self, x_um: np.ndarray, y_um: np.ndarray) -> np.ndarray:
        w = 2.0 * math.pi / self.period_um
        sx = (self.amplitude_um * np.sin(w * x_um)).astype(np.float32)
        cy = np.cos(w * y_um).astype(np.float32)
        return np.outer(cy, sx)
