"""The stacks ``sffscan study`` scores: :class:`StudyStack` (images, focus heights, truth and
the scored pixels) and its readers, a toolbox-format ``imdata.mat``, the user's own stack
with its truth, the thesis' chapter-3 simulation, and the ``--roi`` box.

The command, its scoring and its outputs are in :mod:`sffscan.pipeline.cli.study`.
"""

from __future__ import annotations

import argparse
from dataclasses import dataclass
from pathlib import Path

import numpy as np


@dataclass(frozen=True)
class StudyStack:
    """A focus stack with its truth: images (N, H, W) float32 0..1, focus heights (N,) and
    truth (H, W) in µm, the scored pixels (H, W) bool."""

    images: np.ndarray
    focus_um: np.ndarray
    truth_um: np.ndarray
    mask: np.ndarray
    name: str


def read_imdata(path: Path) -> StudyStack:
    """A stack in the toolbox's format: ``imdata.mat`` and the images beside it."""
    import scipy.io
    from sffscan.stages.fields.stack_io import read_image_stack

    try:
        im = scipy.io.loadmat(path, squeeze_me=True, struct_as_record=False)["imdata"]
    except (OSError, ValueError, KeyError) as err:
        raise ValueError(f"{path}: not a toolbox imdata.mat ({err})") from None
    names = [str(n) for n in np.atleast_1d(im.images)]
    raw = read_image_stack([path.parent / Path(n).name for n in names])
    full = float(np.iinfo(raw.dtype).max) if raw.dtype.kind in "ui" else 1.0
    x, y, w, h = (int(v) for v in im.ROI)
    mask = np.zeros(raw.shape[1:], bool)
    mask[y - 1:y - 1 + h, x - 1:x - 1 + w] = True
    return StudyStack(raw.astype(np.float32) / full, np.asarray(im.focus, float) * 1e6,
                      np.asarray(im.z, float) * 1e6, mask, path.parent.name)


def user_stack(args: argparse.Namespace) -> StudyStack:
    """The stack the options of ``sffscan stack`` name (image files or ``--zarr`` and the
    focus positions) with the truth ``--truth`` names; every pixel with a finite truth is
    scored.

    Raises
    ------
    ValueError
        If a file cannot be read, the focus table does not match the images, an image
        exceeds the full scale, or the truth's shape differs from the images' (the message
        names the file).
    """
    from sffscan.pipeline.cli.stack import read_stack_input
    from sffscan.pipeline.metrology.compare import read_height_map
    from sffscan.stages.fields.stationary import stack_to_unit

    raw, focus_um = read_stack_input(args)
    source = str(args.zarr) if args.zarr else str(Path(args.images[0]).resolve().parent)
    truth = read_height_map(args.truth, array=args.truth_array).height_um
    if truth.shape != raw.shape[1:]:
        raise ValueError(f"{args.truth}: truth of {truth.shape[1]} x {truth.shape[0]} px, the "
                         f"images ({source}) are {raw.shape[2]} x {raw.shape[1]} px")
    try:
        images = stack_to_unit(raw, max_value=None if args.bit_depth is None
                               else float(2**args.bit_depth - 1))
    except ValueError as err:
        raise ValueError(f"{source}: {err}") from None
    mask = np.isfinite(truth)
    if not mask.any():
        raise ValueError(f"{args.truth}: no finite height")
    return StudyStack(images, focus_um, truth.astype(np.float32), mask,
                      f"{source} ({raw.shape[0]} images, truth {Path(args.truth).name})")


def parse_roi(text: str, shape: tuple[int, ...]) -> np.ndarray:
    """The (H, W) bool mask of the box ``x,y,w,h`` (px, 0-based from the top left corner)."""
    try:
        x, y, w, h = (int(v) for v in text.replace(",", " ").split())
    except ValueError:
        raise ValueError(f"--roi must be four integers x,y,w,h (px), got {text!r}") from None
    if w < 1 or h < 1 or x < 0 or y < 0 or x + w > shape[1] or y + h > shape[0]:
        raise ValueError(f"--roi {text}: the box x {x}..{x + w}, y {y}..{y + h} px is empty or "
                         f"leaves the {shape[1]} x {shape[0]} px images")
    mask = np.zeros(shape[:2], bool)
    mask[y:y + h, x:x + w] = True
    return mask


def chapter3_stack(*, noise: float, seed: int = 5) -> StudyStack:
    """The thesis' chapter-3 simulation (:mod:`sffscan.stages.sim.chapter3`) as a study
    stack: every pixel scored."""
    from sffscan.stages.sim.chapter3 import chapter3_stack as simulate

    images, heights, truth = simulate(noise=noise, seed=seed)
    return StudyStack(images, heights, truth, np.ones(truth.shape, bool),
                      f"chapter3 noise {noise:g}")
