"""``sffscan calibrate z | lateral | curvature | noise``: calibration from a user's own images.

Each command reads image files (or a Zarr stack), runs one routine of
:mod:`sffscan.pipeline.metrology.calibration_fit` and writes its result into the calibration JSON
given with ``-o``: an existing file is updated (its other sections kept), so a setup is
calibrated step by step into one file, in this order:

1. ``calibrate z --gauge HEIGHT_UM STACK ...`` -- gauge blocks of known heights, one focus
   stack each: the z response (µm per focus level, intercept);
2. ``calibrate lateral --squares NX NY --square-um S --image LEVEL FILE ...`` -- a
   checkerboard in focus at several focus levels: the lateral scale and its change per level
   (the magnification change of a non-telecentric objective);
3. ``calibrate curvature STACK`` -- a flat, evenly lit reference filling the field: the
   vignetting (the mean illumination over the frame) and the field curvature (heights
   through the file's z response when it has one, else the nominal focus table; frames
   first brought to one scale by its lateral section when it has one);
4. ``calibrate noise STACK1 STACK2`` -- two back-to-back stacks of the same surface:
   N_M by subtraction.

A STACK is a folder of images (read in the natural order of their names: ``im_2`` before
``im_10``) or a Zarr (N, H, W) array. Bad input exits 2 with a message naming the file.
"""

from __future__ import annotations

import argparse
import logging
import math
import re
import time
from pathlib import Path

import numpy as np
from sffscan.pipeline.cli.common import (
    EXIT_OK,
    bit_depth,
    check_distinct,
    fail,
    finite,
    finite_positive,
    seed,
)
from sffscan.pipeline.config import ConfigError
from sffscan.pipeline.metrology.calibration_fit import (
    calibrate_lateral,
    calibrate_z,
    fit_field_curvature,
    fit_vignetting,
    measure_height,
    noise_by_subtraction,
)
from sffscan.pipeline.metrology.calibration_model import (
    Calibration,
    CalibrationError,
    calibrated_focus_heights,
    load_calibration,
    save_calibration,
)

log = logging.getLogger(__name__)

IMAGE_SUFFIXES = (".png", ".tif", ".tiff", ".jpg", ".jpeg", ".bmp", ".pgm")


def _natural_key(name: str) -> list[object]:
    return [int(t) if t.isdigit() else t.lower() for t in re.split(r"(\d+)", name)]


def read_stack(path: str | Path, *, grey: bool = False) -> np.ndarray:
    """(N, H, W) stack from a folder of images (natural order) or a Zarr array."""
    from sffscan.stages.fields.stack_io import read_image_stack, read_zarr_stack

    p = Path(path)
    if p.suffix == ".zarr" or (p / "zarr.json").is_file():
        return read_zarr_stack(p)[0]
    if not p.is_dir():
        raise ValueError(f"{p}: not a folder of images or a Zarr array")
    files = sorted((f for f in p.iterdir() if f.suffix.lower() in IMAGE_SUFFIXES),
                   key=lambda f: _natural_key(f.name))
    if not files:
        raise ValueError(f"{p}: no image files ({', '.join(IMAGE_SUFFIXES)})")
    if grey:
        return read_image_stack(files, grey=True)
    return read_image_stack(files)


def read_one(path: str | Path) -> np.ndarray:
    """One grey image (checkerboard)."""
    import cv2

    img = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    if img is None:
        raise ValueError(f"{path}: cannot read as an image")
    if img.ndim == 3:
        img = cv2.cvtColor(img, cv2.COLOR_BGR2GRAY)
    return np.asarray(img)


def _max_value(args: argparse.Namespace, stack: np.ndarray) -> float:
    from sffscan.stages.fields.stationary import default_max_value

    if args.bit_depth is not None:
        return float(2 ** args.bit_depth - 1)
    return default_max_value(stack.dtype)


def _open(path: str) -> Calibration:
    """The calibration to update: the file at ``path`` if it exists, else a new one."""
    return load_calibration(path) if Path(path).is_file() else Calibration()


def _focus_table(args: argparse.Namespace, cal: Calibration, n: int) -> tuple[np.ndarray, str]:
    if cal.z_response is not None and not args.nominal:
        return calibrated_focus_heights(cal, n), "the calibration's z response"
    if args.focus_start is None or args.focus_step is None:
        raise ValueError("focus positions missing: calibrate z first (into the same -o file) "
                         "or give --focus-start and --focus-step (µm)")
    return args.focus_start + args.focus_step * np.arange(n, dtype=np.float64), "nominal"


def _unbreathe(cal: Calibration, stack: np.ndarray, max_value: float) -> np.ndarray:
    """Frames flat-fielded (``vignetting``) and frame k resampled to the reference level's
    scale (``lateral``), as the corrected pipeline sees them."""
    from sffscan.pipeline.metrology.optics_correction import StackCorrection

    if cal.lateral is not None:
        log.info("frames resampled to one scale by the calibration's lateral section first")
    return StackCorrection(cal).frames(stack, max_value=max_value)


def _distinct(paths: list[str], what: str) -> None:
    """No stack or image given twice (one gauge's stack for two heights, one flat for both
    stacks of the noise, one board for two levels)."""
    check_distinct(paths, what, why=f"each {what} is its own stack or image")


def _level(text: str) -> float:
    """An ``--image LEVEL``: a finite number, or a message naming it."""
    try:
        value = float(text)
    except ValueError:
        value = math.nan
    if not math.isfinite(value):
        raise ValueError(f"--image {text}: the focus level must be a finite number")
    return value


def _margin(args: argparse.Namespace, shape: tuple[int, ...]) -> int:
    """``--margin-px``: 0 up to less than half the frame's smaller side."""
    m = int(args.margin_px)
    if not 0 <= m < min(shape[-2:]) // 2:
        raise ValueError(f"--margin-px must be 0 .. {min(shape[-2:]) // 2 - 1} for frames of "
                         f"{shape[-1]} x {shape[-2]} px, got {m}")
    return m


def cmd_z(args: argparse.Namespace) -> int:
    _distinct([s for _, s in args.gauge], "--gauge")
    cal = _open(args.output)
    heights = np.array([float(h) for h, _ in args.gauge])
    stacks = [read_stack(s, grey=args.grey) for _, s in args.gauge]
    shapes = {s.shape for s in stacks}
    if len(shapes) != 1:
        raise ValueError(f"the gauge stacks differ in shape: {sorted(shapes)}")
    z = calibrate_z(np.stack(stacks), heights, max_value=_max_value(args, stacks[0]),
                    patch_px=args.patch_px)
    print(f"z response ({heights.size} gauges): a_z = {z.um_per_level:.3f} µm/level, intercept "
          f"{z.intercept_um:.1f} µm, r = {z.pearson_r:.7f}, residuals "
          + ", ".join(f"{r:+.1f}" for r in z.residuals_um) + " µm")
    cal = cal.model_copy(update={"z_response": z})
    print(f"wrote {save_calibration(cal, args.output)}")
    return EXIT_OK


def cmd_lateral(args: argparse.Namespace) -> int:
    _distinct([f for _, f in args.image], "--image")
    if min(args.squares) < 4:  # OpenCV finds boards of at least 3 x 3 inner corners
        raise ValueError(f"--squares {args.squares[0]} {args.squares[1]}: a board needs at "
                         "least 4 squares along each side")
    cal = _open(args.output)
    levels = np.array([_level(lv) for lv, _ in args.image])
    images = [read_one(f) for _, f in args.image]
    if len({im.shape for im in images}) != 1:
        raise ValueError("the checkerboard images differ in shape")
    lat = calibrate_lateral(np.stack(images), levels=levels, squares=tuple(args.squares),
                            square_um=args.square_um, reference_level=args.reference_level)
    for m in lat.per_level:
        print(f"  level {m.level:g}: {m.um_per_px_x:.5f} x {m.um_per_px_y:.5f} µm/px")
    print(f"lateral scale at level {lat.reference_level:g}: {lat.um_per_px_x:.5f} x "
          f"{lat.um_per_px_y:.5f} µm/px; change {lat.slope_x_per_level:+.6f} / "
          f"{lat.slope_y_per_level:+.6f} µm/px per level")
    print(f"every level is resampled to the scale at level {lat.reference_level:g}: a scan or "
          f"stack using this file needs optics.pixel_um / --pixel-um "
          f"{0.5 * (lat.um_per_px_x + lat.um_per_px_y):.5f} (refused when 1 px off at a corner)")
    cal = cal.model_copy(update={"lateral": lat})
    print(f"wrote {save_calibration(cal, args.output)}")
    return EXIT_OK


def cmd_curvature(args: argparse.Namespace) -> int:
    cal = _open(args.output)
    raw = read_stack(args.stack, grey=args.grey)
    margin = _margin(args, raw.shape)
    vig = fit_vignetting(raw, margin_px=margin)
    print(f"vignetting: {100 * vig.corner_loss:.1f} % less light at the frame corners")
    cal = cal.model_copy(update={"vignetting": vig})
    stack = _unbreathe(cal, raw, _max_value(args, raw))
    table, source = _focus_table(args, cal, stack.shape[0])
    height, _ = measure_height(stack, focus_heights_um=table, max_value=_max_value(args, stack))
    fit = fit_field_curvature(height, margin_px=margin)
    c = fit.coefficients_um
    cx, cy = fit.centre_px
    corner = c[3] * cx * cx + c[4] * cx * cy + c[5] * cy * cy
    print(f"field curvature ({source} heights): u² {c[3]:+.3e}, uv {c[4]:+.3e}, v² {c[5]:+.3e} "
          f"µm/px²; the flat reads {corner:+.1f} µm at the frame corner; fit residual "
          f"{fit.rms_residual_um:.1f} µm")
    cal = cal.model_copy(update={"field_curvature": fit})
    print(f"wrote {save_calibration(cal, args.output)}")
    return EXIT_OK


def cmd_noise(args: argparse.Namespace) -> int:
    _distinct([args.stack1, args.stack2], "stack")  # one stack twice: a noise of 0
    cal = _open(args.output)
    s1 = read_stack(args.stack1, grey=args.grey)
    s1 = _unbreathe(cal, s1, _max_value(args, s1))
    s2 = _unbreathe(cal, read_stack(args.stack2, grey=args.grey), _max_value(args, s1))
    table, source = _focus_table(args, cal, s1.shape[0])
    mv = _max_value(args, s1)
    z1, _ = measure_height(s1, focus_heights_um=table, max_value=mv)
    z2, _ = measure_height(s2, focus_heights_um=table, max_value=mv)
    m = _margin(args, s1.shape)
    inner = (slice(m, -m or None), slice(m, -m or None))
    noise = noise_by_subtraction(z1[inner], z2[inner])
    print(f"noise by subtraction ({source} heights): N_M = {noise:.2f} µm")
    cal = cal.model_copy(update={"noise_um": noise})
    print(f"wrote {save_calibration(cal, args.output)}")
    return EXIT_OK


def cmd_targets(args: argparse.Namespace) -> int:
    import shlex

    from sffscan.pipeline.config import REALISTIC_OPTICS, demo_config, load_config
    from sffscan.pipeline.progress import ProgressDisplay
    from sffscan.pipeline.sim_source import make_optics
    from sffscan.stages.sim.optics_targets import calibration_commands, write_optics_targets

    if args.config:
        cfg = load_config(args.config)
    else:
        cfg = demo_config(optics=dict(REALISTIC_OPTICS) if args.realistic else {})
    log.info("rendering the calibration targets through the optics (%d focus levels of "
             "%d x %d px) into %s ...", cfg.optics.n_levels, cfg.optics.width_px,
             cfg.optics.height_px, args.folder)
    t0 = time.perf_counter()
    shown: list[ProgressDisplay] = []  # made at the first count (it gives the total)

    def progress(done: int, total: int) -> None:
        if not shown:
            shown.append(ProgressDisplay(total, desc="images"))
        shown[0].update(done, time.perf_counter() - t0)

    try:
        t = write_optics_targets(args.folder, optics=make_optics(cfg),
                                 focus_heights_um=np.array(cfg.optics.focus_heights_um()),
                                 seed=args.seed, progress=None if args.quiet else progress)
    finally:
        for display in shown:
            display.close()
    log.info("rendered in %.1f s", time.perf_counter() - t0)
    print(f"wrote {len(t.gauges)} gauge stacks, {len(t.boards)} board images and 2 flat stacks "
          f"under {t.folder}; calibrate with:")
    for cmd in calibration_commands(t, args.output):
        print("  sffscan " + " ".join(shlex.quote(c) for c in cmd))
    return EXIT_OK


def _guarded(func):  # noqa: ANN001, ANN202 - argparse handler wrapper
    def run(args: argparse.Namespace) -> int:
        try:
            return int(func(args))
        except (ValueError, ConfigError, CalibrationError) as err:
            return fail(str(err))
    return run


def _common(q: argparse.ArgumentParser) -> None:
    q.add_argument("-o", "--output", default="sffscan-calibration.json",
                   help="calibration file to write; an existing one is updated, its other "
                        "sections kept (default sffscan-calibration.json)")
    q.add_argument("--bit-depth", type=bit_depth,
                   help="bit depth of the images, 1..16 (default: the dtype's)")
    q.add_argument("--grey", action="store_true", help="convert colour images to grey")


def _table_options(q: argparse.ArgumentParser) -> None:
    q.add_argument("--focus-start", type=finite,
                   help="nominal focus height of the first image, µm")
    q.add_argument("--focus-step", type=finite, help="nominal focus step, µm")
    q.add_argument("--nominal", action="store_true",
                   help="use the nominal table even when the file has a z response")
    q.add_argument("--margin-px", type=int, default=10,
                   help="frame border left out (focus window and filter reach), px (default 10)")


def register_subcommands(cs: argparse._SubParsersAction) -> None:  # type: ignore[type-arg]
    """Add ``z``, ``lateral``, ``curvature`` and ``noise`` to ``sffscan calibrate``."""
    q = cs.add_parser("z", help="z response from gauge-block focus stacks (image folders)")
    q.add_argument("--gauge", nargs=2, action="append", required=True,
                   metavar=("HEIGHT_UM", "STACK"),
                   help="a gauge block's known height, µm, and its focus stack (folder of "
                        "images or Zarr array); at least 3")
    q.add_argument("--patch-px", type=int, default=64,
                   help="central patch whose focus curve is averaged, px (default 64)")
    _common(q)
    q.set_defaults(func=_guarded(cmd_z))

    q = cs.add_parser("lateral", help="lateral scale and its change per focus level from "
                                      "checkerboard images")
    q.add_argument("--image", nargs=2, action="append", required=True,
                   metavar=("LEVEL", "FILE"),
                   help="focus level at which the board is in focus, and its image")
    q.add_argument("--squares", type=int, nargs=2, required=True, metavar=("NX", "NY"),
                   help="squares of the board along x and y")
    q.add_argument("--square-um", type=finite_positive, required=True, help="square side, µm")
    q.add_argument("--reference-level", type=finite,
                   help="level the stored scale refers to (default the mean level)")
    _common(q)
    q.set_defaults(func=_guarded(cmd_lateral))

    q = cs.add_parser("curvature", help="field curvature from a flat reference's focus stack")
    q.add_argument("stack", help="folder of images or Zarr array")
    _table_options(q)
    _common(q)
    q.set_defaults(func=_guarded(cmd_curvature))

    q = cs.add_parser("targets", help="simulated target images to practise the commands on",
                      description="Render the calibration targets (gauge stacks, boards at "
                                  "several levels, two flat stacks) through the simulated "
                                  "scanner's optics into a folder, and print the calibrate "
                                  "commands that use them.")
    q.add_argument("folder", help="folder to write the target images into (created)")
    q.add_argument("--config", help="scan configuration whose [optics] to use (default demo)")
    q.add_argument("--realistic", action="store_true",
                   help="the demo with real-lens optics (as 'demo --realistic')")
    q.add_argument("--seed", type=seed, default=0,
                   help="seed of the targets' texture and noise (default 0)")
    q.add_argument("-o", "--output", default="sffscan-calibration.json",
                   help="calibration file the printed commands write")
    q.set_defaults(func=_guarded(cmd_targets))

    q = cs.add_parser("noise", help="noise N_M from two back-to-back stacks of one surface")
    q.add_argument("stack1", help="first focus stack of the surface (image folder, glob or "
                                  "Zarr array)")
    q.add_argument("stack2", help="second stack of the same surface, taken right after the "
                                  "first with nothing moved")
    _table_options(q)
    _common(q)
    q.set_defaults(func=_guarded(cmd_noise))
