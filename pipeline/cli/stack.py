"""Focus-stack commands: ``sffscan stack``, ``sffscan stopgo``.

- ``stack``: one field from a focus stack (image files with their focus positions, or a Zarr
  array) -> a mosaic Zarr group (height, all-in-focus texture, confidence, weight);
- ``stopgo``: a simulated stop-and-go grid of fields stitched into one mosaic.

The steps of ``stack`` that say what they do are in :mod:`sffscan.pipeline.cli.stack_steps`.
Exit codes as :mod:`sffscan.pipeline.cli.main`: 0 ok, 2 bad input (the message names the file or
option), 130 interrupted.
"""

from __future__ import annotations

import argparse
import logging
import math
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np
from sffscan.pipeline.cli.common import (
    DEPTH_METHOD_CHOICES,
    EXIT_FAILED,
    EXIT_INTERRUPTED,
    EXIT_OK,
    OPERATOR_CHOICES,
    bit_depth,
    fail,
    seed,
)
from sffscan.pipeline.cli.stack_steps import (
    image_order,
    read_images,
    reconstruct_with_progress,
)
from sffscan.stages.depth import CANDIDATE_METHODS

UNIT_TO_UM = {"um": 1.0, "mm": 1000.0, "m": 1e6}

log = logging.getLogger(__name__)


def _settings_options(p: argparse.ArgumentParser) -> None:
    import types
    from dataclasses import fields

    from sffscan.stages.fields.stationary import StackSettings

    # the defaults without an instance (validating one would load torch for '--help')
    d = types.SimpleNamespace(**{f.name: f.default for f in fields(StackSettings)})
    p.add_argument("--operator", type=str.lower, choices=OPERATOR_CHOICES, default=d.operator,
                   metavar="OPERATOR",
                   help=f"focus measure operator, a toolbox acronym (default {d.operator}): "
                        + ", ".join(OPERATOR_CHOICES))
    p.add_argument("--window", type=int, default=d.window,
                   help=f"focus measure window k, odd, px (default {d.window})")
    p.add_argument("--method", default=d.method,
                   choices=(*DEPTH_METHOD_CHOICES, *CANDIDATE_METHODS),
                   help=f"depth method (default {d.method}); also the study's candidates "
                        f"{', '.join(CANDIDATE_METHODS)} (docs/depth-study.md)")
    p.add_argument("--median-size", type=int, default=d.median_size,
                   help=f"SPC median filter size, odd, px (default {d.median_size})")
    p.add_argument("--filter-size", type=int, default=d.filter_size,
                   help="confidence-weighted median of the height map, odd, px; 1 = off "
                        f"(default {d.filter_size})")
    p.add_argument("--min-confidence", type=float, default=d.min_confidence,
                   help="mark pixels below this confidence invalid (NaN), 0..1 (default 0)")


def _settings(args: argparse.Namespace):  # noqa: ANN202 - StackSettings, imported lazily
    from sffscan.stages.fields.stationary import StackSettings

    return StackSettings(operator=args.operator, window=args.window, method=args.method,
                         median_size=args.median_size, filter_size=args.filter_size,
                         min_confidence=args.min_confidence)


# ----------------------------------------------------------------------------- stack


def _focus_table(args: argparse.Namespace, n: int, from_zarr: np.ndarray | None) -> np.ndarray:
    from sffscan.stages.fields.stack_io import read_focus_positions

    scale = UNIT_TO_UM[args.focus_unit]
    if args.focus_file:
        table = read_focus_positions(args.focus_file, scale_to_um=scale)
        source = str(args.focus_file)
    elif args.focus_start is not None and args.focus_stop is not None:
        if args.focus_step is not None:
            raise ValueError("give --focus-step or --focus-stop, not both")
        table = np.linspace(args.focus_start, args.focus_stop, n) * scale
        source = "--focus-start/--focus-stop"
    elif args.focus_start is not None and args.focus_step is not None:
        table = (args.focus_start + args.focus_step * np.arange(n)) * scale
        source = "--focus-start/--focus-step"
    elif from_zarr is not None:
        table = from_zarr
        source = f"{args.zarr}: attribute focus_heights_um"
    else:
        raise ValueError("focus positions missing: give --focus-file, or --focus-start and "
                         "--focus-step (or --focus-stop), or a Zarr stack with a "
                         "focus_heights_um attribute")
    if table.size != n:
        raise ValueError(f"{source}: {table.size} focus positions for {n} images")
    # checked here, before the stack is processed, so that the message names the source
    bad = np.flatnonzero(~np.isfinite(table))
    if bad.size:
        raise ValueError(f"{source}: focus position {bad[0]} is not a number ({table[bad[0]]})")
    step = np.diff(table)
    if not ((step > 0).all() or (step < 0).all()):
        k = int(np.flatnonzero(np.sign(step) != np.sign(step[0]) if step[0] != 0
                               else step == 0)[0]) + 1
        raise ValueError(f"{source}: focus positions must be strictly monotonic; position "
                         f"{k} ({table[k]:g} µm) follows {table[k - 1]:g} µm")
    return table


def read_stack_input(args: argparse.Namespace) -> tuple[np.ndarray, np.ndarray]:
    """The (N, H, W) stack and its (N,) focus table (µm) that the options of
    :func:`stack_input_options` name (used by ``stack`` and ``study``).

    Raises
    ------
    ValueError
        If a file cannot be read, or the focus table is missing, not monotonic or of another
        length than the stack (the message names the file or option).
    """
    from sffscan.stages.fields.stack_io import read_zarr_stack

    if args.zarr:
        if args.images:
            raise ValueError("give image files or --zarr, not both")
        stack, zarr_table = read_zarr_stack(args.zarr, array=args.array)
    else:
        stack, zarr_table = read_images(image_order(args), grey=args.grey,
                                        progress=not getattr(args, "quiet", False)), None
    return stack, _focus_table(args, stack.shape[0], zarr_table)


def cmd_stack(args: argparse.Namespace) -> int:
    from sffscan.pipeline import locks
    from sffscan.pipeline.run import check_file_output

    try:  # one writer a mosaic, refused before the stack is read and reconstructed
        if not 0 < args.pixel_um < math.inf:
            raise ValueError(f"--pixel-um must be a finite number > 0, got {args.pixel_um}")
        out = Path(args.output).resolve()
        for src in [args.zarr] if args.zarr else []:  # the mosaic inside the input store
            if out == Path(src).resolve() or Path(src).resolve() in out.parents:
                raise ValueError(f"-o {args.output}: inside the input {src}; writing the "
                                 "mosaic there would change it, choose another path")
        if args.save_npy:  # the name np.save writes (.npy appended when missing)
            npy = args.save_npy if str(args.save_npy).endswith(".npy") else f"{args.save_npy}.npy"
            check_file_output(npy, "--save-npy", stores=[args.output], overwrite=args.overwrite)
        held = locks.claim_mosaic(args.output, overwrite=args.overwrite)
    except (ValueError, FileExistsError) as err:
        return fail(str(err))
    with held:
        return _stack(args)


def _stack(args: argparse.Namespace) -> int:
    from dataclasses import replace

    from sffscan.pipeline.metrology.optics_correction import applied
    from sffscan.pipeline.mosaic.writer import MosaicWriter
    from sffscan.pipeline.stopgo import feather_weights, stitch_field
    from sffscan.stages.fields.align import describe_alignment, mask_uncovered, prepare_stack
    from sffscan.stages.fields.aperture import stack_noise_floor

    try:
        settings = _settings(args)
        stack, table = read_stack_input(args)
        correction = _stack_correction(args)
        if correction is not None:
            table = correction.focus_heights_um(table)
            stack = correction.frames(stack, max_value=None if args.bit_depth is None
                                      else float(2**args.bit_depth - 1))
        max_value = None if args.bit_depth is None else float(2**args.bit_depth - 1)
        taken = stack
        stack, covered, alignment = prepare_stack(stack, align=args.align)
        floor = None
        if alignment is not None:
            print(describe_alignment(alignment), file=sys.stderr)
            floor, sigma = stack_noise_floor(taken, alignment, operator=settings.operator,
                                             window=settings.window, max_value=max_value)
            log.info(f"stack: sensor noise {100 * sigma:.2f} % of full scale; the aligned "
                     f"frames' noise floor corrected by {floor.min():+.3g} .. "
                     f"{floor.max():+.3g} (focus measure units)")
        del taken
        log.info(f"stack: {stack.shape[0]} images of {stack.shape[2]}x{stack.shape[1]} px "
                 f"{stack.dtype}, focus {table[0]:g} .. {table[-1]:g} µm; {settings.operator} "
                 f"k={settings.window}, {settings.method}, weighted median "
                 f"{settings.filter_size}x{settings.filter_size}")
        t0 = time.perf_counter()
        result = reconstruct_with_progress(stack, table, settings, max_value, floor,
                                           progress=not args.quiet, valid=covered)
        if correction is not None:
            result = correction.field(result)
        if covered is not None:  # pixels some aligned frame does not cover: not measured
            result = replace(result, height_um=mask_uncovered(
                result.height_um, covered, reach_px=2 * (settings.window // 2) + 1))
        writer = MosaicWriter(args.output, origin_px=(0, 0), shape=result.height_um.shape,
                              pixel_um=args.pixel_um, overwrite=args.overwrite,
                              attrs={"processing": {"mode": "stationary", **settings.as_dict(),
                                                    "alignment": None if alignment is None
                                                    else alignment.as_dict(),
                                                    "calibration": args.calibration,
                                                    "calibration_applied": [] if correction
                                                    is None else applied(correction.calibration)},
                                     "focus_heights_um": [float(v) for v in table]})
    except ValueError as err:
        return fail(str(err))
    except KeyboardInterrupt:
        return EXIT_INTERRUPTED
    try:
        valid = stitch_field(writer, result, x0_px=0, y0_px=0,
                             feather=feather_weights(result.height_um.shape, overlap_px=0))
    except BaseException:
        writer.set_status("failed")
        raise
    writer.set_status("complete", valid_pixels=valid, blocks=1)
    if args.save_npy:
        np.save(args.save_npy, result.height_um)
    conf = result.confidence
    print(f"wrote {args.output}: {valid} of {conf.size} pixels valid, height "
          f"{np.nanmin(result.height_um):.1f} .. {np.nanmax(result.height_um):.1f} µm, "
          f"median confidence {float(np.median(conf)):.3f}, {time.perf_counter() - t0:.2f} s")
    return EXIT_OK


# ----------------------------------------------------------------------------- stop-and-go


def _realistic_optics(zs: np.ndarray) -> dict[str, Any]:
    """The simulator's realistic [optics] (``demo --realistic``), breathing about mid-range."""
    from sffscan.pipeline.config import REALISTIC_OPTICS

    return {**REALISTIC_OPTICS, "magnification_ref_um": 0.5 * float(zs[0] + zs[-1])}


def _stack_correction(args: argparse.Namespace):  # noqa: ANN202 - StackCorrection, lazily
    """The calibration ``--calibration`` names, as applied to stationary stacks (or None)."""
    if not getattr(args, "calibration", None):
        return None
    from sffscan.pipeline.metrology.calibration_model import load_calibration
    from sffscan.pipeline.metrology.optics_correction import StackCorrection, applied

    cal = load_calibration(args.calibration)
    log.info("calibration %s: correcting %s", args.calibration,
             ", ".join(applied(cal)) or "nothing (the file has no section that applies)")
    return StackCorrection(cal, um_per_px=args.pixel_um)


def cmd_stopgo(args: argparse.Namespace) -> int:
    from sffscan.pipeline.progress import ProgressDisplay
    from sffscan.pipeline.stopgo import SimFieldCamera, plan_grid, run_stop_and_go
    from sffscan.stages.sim.camera import Optics, focus_heights
    from sffscan.stages.sim.world import characterisation_plate

    try:
        settings = _settings(args)
        if args.levels < 3:  # before any field: a stack needs three images
            raise ValueError(f"--levels must be >= 3, got {args.levels}")
        from sffscan.stages.fitted_constants import uncalibrated_focus_measure

        why = uncalibrated_focus_measure(settings.operator, settings.window)
        if why is not None:
            log.warning("stopgo: %s", why)
        for opt, value, top in (("--pixel-um", args.pixel_um, 10_000.0),  # as [optics] and
                                ("--plate-length-mm", args.plate_length_mm, 2_000.0),  # [source]
                                ("--plate-width-mm", args.plate_width_mm, 2_000.0)):
            if not 0 < value <= top:
                raise ValueError(f"{opt} must be > 0 and <= {top:g}, got {value:g}")
        if not all(-1e5 <= v <= 1e5 for v in args.area_mm):  # as motion.x_start_mm ...
            raise ValueError(f"--area-mm {' '.join(f'{v:g}' for v in args.area_mm)}: "
                             "coordinates must be finite and within +-100000 mm (100 m)")
        zs = focus_heights(n_levels=args.levels, z_step_um=args.z_step_um)
        world = characterisation_plate(seed=args.seed, pixel_um=args.pixel_um,
                                       length_mm=args.plate_length_mm,
                                       width_mm=args.plate_width_mm, z_range_um=(0, zs[-1]))
        optics = Optics(width=args.field[0], height=args.field[1], pixel_um=args.pixel_um,
                        **(_realistic_optics(zs) if args.realistic else {}))
        camera = SimFieldCamera(world, optics, zs, seed=args.seed)
        correction = _stack_correction(args)
        x0, x1, y0, y1 = args.area_mm
        grid = plan_grid(x_um=(x0 * 1000, x1 * 1000), y_um=(y0 * 1000, y1 * 1000),
                         field_px=(optics.width, optics.height), pixel_um=args.pixel_um,
                         overlap_px=args.overlap_px)
        log.info(f"stop-and-go: {len(grid)} fields of {optics.width}x{optics.height} px, "
                 f"overlap >= {args.overlap_px} px, N = {zs.size} levels of "
                 f"{args.z_step_um:g} µm")
        display = None if args.quiet else ProgressDisplay(len(grid), desc="fields")
        try:
            report = run_stop_and_go(
                camera, grid, args.output, settings=settings, overlap_px=args.overlap_px,
                overwrite=args.overwrite, correction=correction,
                progress=None if display is None else lambda d, _n, t: display.update(d, t))
        finally:
            if display is not None:
                display.close()
    except ValueError as err:
        return fail(str(err))
    except KeyboardInterrupt:
        print(f"sffscan: interrupted; {args.output} keeps the fields done (status 'failed')",
              file=sys.stderr)
        return EXIT_INTERRUPTED
    from sffscan.pipeline.metrology.compare import compare_height_maps, read_height_map

    hm = read_height_map(report.path)
    assert hm.origin_px is not None
    h, w = hm.height_um.shape
    truth = world.height_um(float(hm.origin_px[0]), float(hm.origin_px[1]), w, h)
    cmp = compare_height_maps(hm.height_um, truth, max_depth_um=float(zs[-1] - zs[0]))
    if cmp.rmse_um is None:  # nothing measured: not a result to score
        print(f"sffscan: {report.path}: {report.fields} fields, no valid pixel to score "
              "against the true surface", file=sys.stderr)
        return EXIT_FAILED
    corr = "n/a (a map without variation)" if cmp.corr is None else f"{cmp.corr:.5f}"
    psnr = "n/a" if cmp.psnr_db is None else f"{cmp.psnr_db:.2f} dB"
    print(f"wrote {report.path}: {report.fields} fields in {report.seconds:.1f} s; against the "
          f"true surface: RMSE {cmp.rmse_um:.1f} µm, CORR {corr}, PSNR {psnr}, coverage "
          f"{100 * cmp.coverage:.1f} %")
    if hm.uncertainty_um is not None:  # the mosaic's own, scored as a scan's is
        from sffscan.pipeline.metrology.evaluate import accuracy, uncertainty_line

        a = accuracy(hm.height_um, truth, max_depth=1.0, sigma=hm.uncertainty_um)
        if a.sigma_pixels:
            print(uncertainty_line(a.within_2sigma, a.sigma_pixels, truth="the true surface"))
    return EXIT_OK


# ----------------------------------------------------------------------------- parser


def stack_input_options(p: argparse.ArgumentParser) -> None:
    """The options naming a focus stack and its focus positions (``stack``, ``study``):
    image files or ``--zarr``, ``--focus-file`` / ``--focus-start`` ..., ``--bit-depth``;
    read with :func:`read_stack_input`."""
    p.add_argument("images", nargs="*",
                   help="image files, one per focus level; taken in the natural order of "
                        "their names (im_2 before im_10), see --keep-order")
    p.add_argument("--keep-order", action="store_true",
                   help="take the image files in the order given, not sorted by name")
    p.add_argument("--grey", action="store_true",
                   help="convert colour images to luma (ITU-R BT.601, as OpenCV's cvtColor); "
                        "without it a colour image is refused")
    p.add_argument("--zarr", help="read the stack from this Zarr (N, H, W) array or group")
    p.add_argument("--array", help="array inside the Zarr group given with --zarr")
    p.add_argument("--focus-file", help="focus positions, one per image (text)")
    p.add_argument("--focus-start", type=float, help="focus position of the first image")
    p.add_argument("--focus-step", type=float, help="focus step between images")
    p.add_argument("--focus-stop", type=float,
                   help="focus position of the last image (with --focus-start: evenly spaced)")
    p.add_argument("--focus-unit", choices=sorted(UNIT_TO_UM), default="um",
                   help="unit of the focus positions (default um)")
    p.add_argument("--bit-depth", type=bit_depth,
                   help="bit depth of the images, 1..16 (default: the dtype's)")


def register(sub: argparse._SubParsersAction) -> None:  # type: ignore[type-arg]
    p = sub.add_parser("stack", help="reconstruct one field from a focus stack",
                       description="Height, all-in-focus image and confidence of one field "
                                   "from a focus stack, written as a mosaic Zarr group.")
    stack_input_options(p)
    p.add_argument("--pixel-um", type=float, required=True, help="object pixel size, µm/px")
    p.add_argument("-o", "--output", required=True, help="mosaic Zarr group to write")
    p.add_argument("--overwrite", action="store_true",
                   help="replace an existing mosaic (and --save-npy file)")
    p.add_argument("--save-npy", help="also save the height map (µm) as .npy")
    p.add_argument("--align", action="store_true",
                   help="align the frames first: each frame's scale and shift against the "
                        "middle frame (OpenCV ECC), printed per frame, then warped; pixels "
                        "not covered by every frame are left invalid. Without it, a stack "
                        "that looks misaligned gets a warning")
    p.add_argument("--calibration", metavar="FILE",
                   help="calibration file ('sffscan calibrate'): vignetting and magnification "
                        "per level corrected in the frames (frame k at focus level k), its z "
                        "response replaces the focus positions, field curvature removed")
    _settings_options(p)
    p.set_defaults(func=cmd_stack)

    p = sub.add_parser("stopgo", help="simulated stop-and-go grid stitched into a mosaic",
                       description="Stop-and-go measurement of the simulated characterisation "
                                   "plate: a grid of stationary fields, blended by stage "
                                   "position into one mosaic, scored against the true surface.")
    p.add_argument("-o", "--output", default="sffscan-stopgo.zarr", help="mosaic Zarr group")
    p.add_argument("--overwrite", action="store_true", help="replace an existing mosaic")
    p.add_argument("--area-mm", type=float, nargs=4, default=[2.0, 22.0, 0.0, 4.0],
                   metavar=("X0", "X1", "Y0", "Y1"), help="area to cover, mm")
    p.add_argument("--field", type=int, nargs=2, default=[320, 256], metavar=("W", "H"),
                   help="field size, px (default 320 256)")
    p.add_argument("--pixel-um", type=float, default=17.0, help="pixel size, µm (default 17)")
    p.add_argument("--overlap-px", type=int, default=40, help="least overlap, px (default 40)")
    p.add_argument("--levels", type=int, default=50, help="focus levels (default 50)")
    p.add_argument("--z-step-um", type=float, default=200.0, help="focus step, µm")
    p.add_argument("--plate-length-mm", type=float, default=24.0,
                   help="simulated characterisation plate's length (x), mm (default 24)")
    p.add_argument("--plate-width-mm", type=float, default=4.0,
                   help="simulated plate's width (y), mm (default 4)")
    p.add_argument("--seed", type=seed, default=0,
                   help="seed of the simulated texture and sensor noise (default 0)")
    p.add_argument("--realistic", action="store_true",
                   help="real-lens optics as 'demo --realistic' (breathing, field curvature, "
                        "vignetting)")
    p.add_argument("--calibration", metavar="FILE",
                   help="calibration file applied to every field (as for 'stack')")
    _settings_options(p)
    p.set_defaults(func=cmd_stopgo)
