"""Calibration targets seen through the simulated scanner's own optics, written as image files.

What a user of a real setup photographs to calibrate it (``sffscan calibrate z | lateral |
curvature | noise``), rendered by the scanner's camera (:func:`make_optics`: breathing,
field curvature and vignetting included) at its focus levels:

* ``gauge_<h>/img_<k>.png`` -- focus stacks of gauge blocks of known heights ``h`` µm
  (filling the field);
* ``board_<k>.png`` -- a checkerboard moved into focus at level ``k`` (a z stage), for the
  scale at several levels;
* ``flat1/``, ``flat2/`` -- two back-to-back focus stacks of a flat textured reference.

:func:`calibration_commands` gives the ``sffscan`` command lines that calibrate from them.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np
from sffscan.stages.sim.camera import Optics, render_stack
from sffscan.stages.sim.targets import CheckerboardWorld
from sffscan.stages.sim.world import PlateWorld

__all__ = ["OpticsTargets", "calibration_commands", "write_optics_targets"]

GAUGE_FRACTIONS = (0.15, 0.32, 0.5, 0.68, 0.85)  # gauge heights, fractions of the range
BOARD_SQUARES = (9, 7)


@dataclass(frozen=True)
class OpticsTargets:
    """Where :func:`write_optics_targets` put the targets, and what they are."""

    folder: Path
    gauges: tuple[tuple[float, Path], ...]  # (height µm, stack folder)
    boards: tuple[tuple[int, Path], ...]  # (focus level, image)
    squares: tuple[int, int]
    square_um: float
    flats: tuple[Path, Path]
    bit_depth: int


def _write_stack(folder: Path, stack: np.ndarray) -> Path:
    folder.mkdir(parents=True, exist_ok=True)
    for k, img in enumerate(stack):
        if not cv2.imwrite(str(folder / f"img_{k}.png"), img):
            raise OSError(f"{folder}: cannot write img_{k}.png")
    return folder


def write_optics_targets(folder: str | Path, *, optics: Optics, focus_heights_um: np.ndarray,
                         seed: int = 0, n_boards: int = 5,
                         progress: Callable[[int, int], None] | None = None) -> OpticsTargets:
    """Render every calibration target through ``optics`` and write it under ``folder``.

    Parameters
    ----------
    folder : str or Path
        Created if missing; an existing folder must be empty (the calibrate commands read
        every image of a target's folder, and a user's images there would be replaced).
    optics : Optics
        The camera and lens to calibrate (with its real-lens effects).
    focus_heights_um : (N,) array_like of float
        The lens's true focus heights, µm.
    seed : int, keyword-only
        Texture and noise seed.
    n_boards : int, keyword-only
        Focus levels the board is imaged at (spread over the range, ends included).
    progress : callable, keyword-only
        Called as ``progress(images_done, images)`` after each target is written.

    Returns
    -------
    OpticsTargets
    """
    out = Path(folder)
    if out.exists() and (not out.is_dir() or any(out.iterdir())):
        raise ValueError(f"{out}: exists and is not an empty folder; the target images are "
                         "written into a new or empty folder")
    out.mkdir(parents=True, exist_ok=True)
    zs = np.asarray(focus_heights_um, dtype=np.float64)
    rng = np.random.default_rng(seed + 7)
    p = optics.pixel_um
    w_um, h_um = optics.width * p, optics.height * p
    lo, hi = float(zs.min()), float(zs.max())
    levels = np.unique(np.rint(np.linspace(0, zs.size - 1, n_boards)).astype(int))
    total, done = (len(GAUGE_FRACTIONS) + 2) * zs.size + levels.size, 0

    def step(images: int) -> None:
        nonlocal done
        done += images
        if progress is not None:
            progress(done, total)

    gauges = []
    for i, frac in enumerate(GAUGE_FRACTIONS):
        h = round(lo + frac * (hi - lo), 1)
        world = PlateWorld(seed=seed + i, pixel_um=p, base_um=h, texture_tile_px=512)
        st = render_stack(world, x0=-(optics.width - 1) / 2, y0=-(optics.height - 1) / 2,
                          focus_heights_um=zs, optics=optics, rng=rng)
        gauges.append((h, _write_stack(out / f"gauge_{h:g}", st)))
        step(zs.size)

    nx, ny = BOARD_SQUARES
    square = round(0.6 * min(w_um / nx, h_um / ny), 1)  # board covers <= 60 % of the frame
    boards = []
    for k in levels:
        world = CheckerboardWorld(pixel_um=p, base_um=float(zs[k]), square_um=square,
                                  squares=(nx, ny), texture_tile_px=64,
                                  origin_um=(-nx * square / 2.0, -ny * square / 2.0))
        img = render_stack(world, x0=-(optics.width - 1) / 2, y0=-(optics.height - 1) / 2,
                           focus_heights_um=zs[k:k + 1], optics=optics, rng=rng)[0]
        path = out / f"board_{k}.png"
        if not cv2.imwrite(str(path), img):
            raise OSError(f"{path}: cannot write")
        boards.append((int(k), path))
        step(1)

    flat = PlateWorld(seed=seed + 100, pixel_um=p, base_um=round(0.5 * (lo + hi), 1),
                      texture_tile_px=1024)
    flats = []
    for name in ("flat1", "flat2"):
        flats.append(_write_stack(out / name, render_stack(
            flat, x0=0.0, y0=0.0, focus_heights_um=zs, optics=optics, rng=rng)))
        step(zs.size)
    return OpticsTargets(folder=out, gauges=tuple(gauges), boards=tuple(boards),
                         squares=(nx, ny), square_um=square, flats=(flats[0], flats[1]),
                         bit_depth=optics.bit_depth)


def calibration_commands(t: OpticsTargets, output: str | Path) -> list[list[str]]:
    """``sffscan`` argument lists, in order, that calibrate from the targets into ``output``."""
    bits = ["--bit-depth", str(t.bit_depth)]
    z = ["calibrate", "z", "-o", str(output), *bits]
    for h, d in t.gauges:
        z += ["--gauge", f"{h:g}", str(d)]
    lat = ["calibrate", "lateral", "-o", str(output), "--squares", str(t.squares[0]),
           str(t.squares[1]), "--square-um", f"{t.square_um:g}"]
    for k, f in t.boards:
        lat += ["--image", str(k), str(f)]
    curv = ["calibrate", "curvature", str(t.flats[0]), "-o", str(output), *bits]
    noise = ["calibrate", "noise", str(t.flats[0]), str(t.flats[1]), "-o", str(output), *bits]
    return [z, lat, curv, noise]
