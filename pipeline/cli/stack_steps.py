"""The steps of ``sffscan stack`` that say what they do: the image files checked and read
with a progress display, the reconstruction timed, the weighted median with a progress
display (on large photographs it is the longest step)."""

from __future__ import annotations

import argparse
import logging
import time
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np
from sffscan.pipeline.cli.common import check_distinct

if TYPE_CHECKING:
    from sffscan.stages.fields.stationary import FieldResult, StackSettings

log = logging.getLogger("sffscan.pipeline.cli.stack")


def check_files_exist(paths: list[str]) -> None:
    """Every image file exists: a shell glob that matched nothing comes as its own pattern
    (``'d/*.tif'``), named as such, before anything else is said about the images; and no
    file is given twice (two globs that overlap would make one image two focus levels)."""
    for p in paths:
        if not Path(p).exists():
            if any(c in p for c in "*?["):
                raise ValueError(f"no file matches the pattern {p!r} (the shell passes a "
                                 "pattern that matches nothing as it is)")
            raise ValueError(f"{p}: file not found")
    check_distinct(paths, "images", first=0, why="each focus level is one image")


def _display(total: int, desc: str, show: bool) -> Any:
    """A progress display, or a stand-in that shows nothing (``-q``)."""
    from sffscan.pipeline.progress import ProgressDisplay

    return ProgressDisplay(total, desc=desc) if show else _NoDisplay()


class _NoDisplay:
    """What ``with ProgressDisplay(...) as display`` gives, showing nothing."""

    def __enter__(self) -> _NoDisplay:
        return self

    def __exit__(self, *exc: object) -> None:
        pass

    def update(self, *_: object) -> None:
        pass


def read_images(paths: list[str], *, grey: bool, progress: bool = True) -> np.ndarray:
    """The images of ``paths`` as an (N, H, W) stack
    (:func:`sffscan.stages.fields.stack_io.read_image_stack`, its checks), with a progress
    display of the files read (none without ``progress``)."""
    from sffscan.stages.fields.stack_io import read_image_stack

    t0 = time.perf_counter()
    with _display(len(paths), "images", progress) as display:
        stack = read_image_stack(paths, grey=grey, on_image=lambda k: display.update(
            k, time.perf_counter() - t0))
    log.info("stack: read %d images in %.1f s", len(stack), time.perf_counter() - t0)
    return stack


def reconstruct_with_progress(stack: np.ndarray, table: np.ndarray, settings: StackSettings,
                              max_value: float | None,
                              noise_floor: np.ndarray | None = None, *,
                              progress: bool = True,
                              valid: np.ndarray | None = None) -> FieldResult:
    """:func:`~sffscan.stages.fields.stationary.reconstruct_field` with what it does said on
    stderr: the reconstruction (its time), then the weighted median with a progress display
    of its rows (on large photographs it is the longer part; none without ``progress``);
    ``valid``: an aligned stack's covered pixels (reconstructed on their bounding box)."""
    from dataclasses import replace

    from sffscan.stages.fields.stationary import reconstruct_field
    from sffscan.stages.fields.weighted_median import confidence_weighted_median

    t0 = time.perf_counter()
    log.info("stack: reconstruction (focus measure, depth, all-in-focus image) ...")
    raw = reconstruct_field(stack, focus_heights_um=table, max_value=max_value,
                            settings=replace(settings, filter_size=1, min_confidence=0.0),
                            noise_floor=noise_floor, valid=valid)
    log.info("stack: reconstruction done in %.1f s", time.perf_counter() - t0)
    if raw.uncertainty_um is None:
        log.warning("stack: no height uncertainty: method %s is a study's candidate, whose "
                    "uncertainty was never fitted; the outputs hold none", settings.method)
    else:
        from sffscan.stages.fitted_constants import uncalibrated_focus_measure

        why = uncalibrated_focus_measure(settings.operator, settings.window)
        if why is not None:
            log.warning("stack: %s", why)
    if settings.filter_size == 1:
        height = raw.height_um
    else:
        t1 = time.perf_counter()
        with _display(raw.height_um.shape[0], "median rows", progress) as display:
            height = confidence_weighted_median(
                raw.raw_height_um, raw.confidence, size=settings.filter_size,
                progress=lambda done, _n: display.update(done, time.perf_counter() - t1))
        log.info("stack: weighted median %dx%d done in %.1f s", settings.filter_size,
                 settings.filter_size, time.perf_counter() - t1)
    if settings.min_confidence > 0:
        height[raw.confidence < settings.min_confidence] = np.nan
    out = replace(raw, height_um=height, settings=settings)
    unc = getattr(out, "uncertainty_um", None)
    if unc is not None:  # as reconstruct_field leaves it: NaN where the height is
        unc = np.array(unc, dtype=np.float32)
        unc[~np.isfinite(height)] = np.nan
        out = replace(out, uncertainty_um=unc)  # type: ignore[call-arg,unused-ignore]
    return out


def image_order(args: argparse.Namespace) -> list[str]:
    """The image files in focus order: natural order of their names (``im_2`` before
    ``im_10``, whatever the shell's glob did), said in a status line, with a warning when the
    names leave the order ambiguous; ``--keep-order`` keeps the order given."""
    from sffscan.stages.fields.image_io import natural_order

    given = [str(p) for p in args.images]
    check_files_exist(given)
    if args.keep_order or len(given) < 2:
        return given
    ordered, ambiguous = natural_order(given)
    names = [p.name for p in ordered]
    span = f"{names[0]}, {names[1]}, ... {names[-1]}" if len(names) > 2 else ", ".join(names)
    moved = [str(p) for p in ordered] != given
    log.info("stack: images in natural order of their names (%s)%s; --keep-order keeps the "
             "order given", span, ", reordered" if moved else "")
    if ambiguous:
        log.warning("stack: the focus order of the images is ambiguous: %s. Check it, or give "
                    "the files in focus order with --keep-order", ambiguous)
    return [str(p) for p in ordered]
