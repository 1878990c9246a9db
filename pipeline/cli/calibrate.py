"""``sffscan calibrate sim | show`` and ``sffscan twostep``: calibration and two-step scanning.

``calibrate sim`` runs every calibration routine on simulated targets with known answers
(gauge blocks through a lens whose true step differs from the nominal one, a checkerboard
at several focus levels through a non-telecentric objective, a flat reference seen through
a curved field, two back-to-back measurements), prints each result beside the answer and
writes the calibration file. ``calibrate show`` validates and prints a calibration file.
``twostep`` measures the simulated characterisation plate in stop-and-go fields, full
range and with a coarse prior, and prints the frames saved and both RMSEs.
"""

from __future__ import annotations

import argparse
import logging
import math
import sys
import time
from pathlib import Path

import numpy as np
from sffscan.pipeline.cli.common import EXIT_BAD_INPUT, EXIT_OK, fail, seed
from sffscan.pipeline.metrology.calibration_fit import (
    calibrate_lateral,
    calibrate_z,
    fit_field_curvature,
    measure_height,
    noise_by_subtraction,
)
from sffscan.pipeline.metrology.calibration_model import (
    Calibration,
    load_calibration,
    save_calibration,
)

# Simulated lens: nominal 50 levels of 200 µm from 0; the true lens steps 190 µm from 100 µm.
SIM_TRUE_Z_MIN_UM, SIM_TRUE_STEP_UM = 100.0, 190.0
SIM_GAUGES_UM = (1000.0, 2500.0, 4000.0, 5500.0, 7000.0)
SIM_SCALE_PER_MM = -0.01  # pixel scale change with height, per mm
SIM_CURVATURE_UM_PX2 = (2e-2, 5e-3, 1e-2)


log = logging.getLogger(__name__)


def _log(msg: str) -> None:
    log.info(msg)


def simulated_calibration(*, seed: int = 0, verbose: bool = True) -> Calibration:
    """Every routine on the simulated targets; the known answers are printed alongside."""
    from sffscan.stages.sim.camera import Optics, focus_heights
    from sffscan.stages.sim.targets import (
        curved_field_stack,
        gauge_block_stacks,
        perspective_checkerboards,
    )

    say = _log if verbose else (lambda _msg: None)
    rng = np.random.default_rng(seed)
    n = 50
    true = focus_heights(n_levels=n, z_min_um=SIM_TRUE_Z_MIN_UM, z_step_um=SIM_TRUE_STEP_UM)

    t = time.perf_counter()
    o = Optics(width=128, height=128, pixel_um=8.5)
    stacks = gauge_block_stacks(np.array(SIM_GAUGES_UM), optics=o, focus_heights_um=true,
                                seed=seed, rng=rng)
    z = calibrate_z(stacks, np.array(SIM_GAUGES_UM), max_value=o.max_value)
    say(f"z response ({len(SIM_GAUGES_UM)} gauges): a_z = {z.um_per_level:.3f} µm/level "
        f"(true {SIM_TRUE_STEP_UM}), intercept {z.intercept_um:.1f} µm (true "
        f"{SIM_TRUE_Z_MIN_UM}), r = {z.pearson_r:.7f}, residuals "
        f"{', '.join(f'{r:+.1f}' for r in z.residuals_um)} µm  [{time.perf_counter() - t:.1f} s]")

    t = time.perf_counter()
    ob = Optics(width=640, height=512, pixel_um=8.5, bit_depth=8)
    levels = np.array([0.0, 12.0, 24.0, 36.0, 48.0])
    imgs, scales = perspective_checkerboards(optics=ob, focus_heights_um=true[levels.astype(int)],
                                             scale_per_mm=SIM_SCALE_PER_MM,
                                             reference_um=float(true[24]), square_um=400.0,
                                             squares=(11, 9), rng=rng)
    lat = calibrate_lateral(imgs, levels=levels, squares=(11, 9), square_um=400.0,
                            reference_level=24.0)
    true_slope = ob.pixel_um * SIM_SCALE_PER_MM * SIM_TRUE_STEP_UM / 1000.0
    say(f"lateral scale at level 24: {lat.um_per_px_x:.4f} x {lat.um_per_px_y:.4f} µm/px "
        f"(true {ob.pixel_um}); change {lat.slope_x_per_level:+.5f} µm/px per level "
        f"(true {true_slope:+.5f})  [{time.perf_counter() - t:.1f} s]")

    t = time.perf_counter()
    oc = Optics(width=192, height=160, pixel_um=8.5)
    kw = dict(optics=oc, focus_heights_um=true, curvature_um_px2=SIM_CURVATURE_UM_PX2,
              surface_um=4000.0, seed=seed)
    z1, _ = measure_height(curved_field_stack(**kw, rng=rng),  # type: ignore[arg-type]
                           focus_heights_um=true, max_value=oc.max_value)
    fc = fit_field_curvature(z1, margin_px=10)
    c = fc.coefficients_um
    a, b, cc = SIM_CURVATURE_UM_PX2
    say(f"field curvature: u² {c[3]:+.5f}, uv {c[4]:+.5f}, v² {c[5]:+.5f} µm/px² "
        f"(true {-a:+.5f}, {-b:+.5f}, {-cc:+.5f}), fit residual {fc.rms_residual_um:.1f} µm  "
        f"[{time.perf_counter() - t:.1f} s]")

    z2, _ = measure_height(curved_field_stack(**kw, rng=rng),  # type: ignore[arg-type]
                           focus_heights_um=true, max_value=oc.max_value)
    noise = noise_by_subtraction(z1[10:-10, 10:-10], z2[10:-10, 10:-10])
    say(f"noise by subtraction: N_M = {noise:.2f} µm (sensor noise sigma {oc.noise_sigma})")
    return Calibration(description=f"simulated targets, seed {seed}", z_response=z,
                       lateral=lat, field_curvature=fc, noise_um=noise)


def cmd_calibrate_sim(args: argparse.Namespace) -> int:
    cal = simulated_calibration(seed=args.seed)
    path = save_calibration(cal, args.output)
    print(f"wrote {path}")
    return EXIT_OK


def cmd_calibrate_show(args: argparse.Namespace) -> int:
    cal = load_calibration(args.file)
    print(f"{args.file}: {cal.format} v{cal.format_version}, created {cal.created}")
    if cal.z_response:
        z = cal.z_response
        print(f"  z response: a_z {z.um_per_level:.4f} µm/level, intercept "
              f"{z.intercept_um:.2f} µm, r {z.pearson_r:.7f}, {len(z.heights_um)} gauges, "
              f"max |residual| {max(abs(r) for r in z.residuals_um):.2f} µm")
    if cal.lateral:
        la = cal.lateral
        print(f"  lateral: {la.um_per_px_x:.5f} x {la.um_per_px_y:.5f} µm/px at level "
              f"{la.reference_level:g}, {la.slope_x_per_level:+.6f} / "
              f"{la.slope_y_per_level:+.6f} µm/px per level")
    if cal.field_curvature:
        f = cal.field_curvature
        print(f"  field curvature: {f.frame_width_px} x {f.frame_height_px} px, coefficients "
              + ", ".join(f"{v:.4g}" for v in f.coefficients_um) + " µm")
    if cal.vignetting:
        print(f"  vignetting: {100 * cal.vignetting.corner_loss:.1f} % less light at the corners")
    if cal.noise_um is not None:
        print(f"  noise N_M: {cal.noise_um:.3f} µm")
    return EXIT_OK


def cmd_twostep(args: argparse.Namespace) -> int:
    from sffscan.pipeline.metrology.evaluate import accuracy
    from sffscan.stages.fields.coarse_prior import simulated_prior, two_step_fields
    from sffscan.stages.sim.camera import Optics, focus_heights
    from sffscan.stages.sim.world import characterisation_plate

    px = args.pixel_um
    try:  # bad options: a clear message and exit 2, before anything is rendered
        if not 0 < px < math.inf:
            raise ValueError(f"--pixel-um must be a finite number > 0, got {px}")
        if not 1 <= args.field_px * px <= 9_000:
            raise ValueError(f"--field-px {args.field_px} x --pixel-um {px:g} = "
                             f"{args.field_px * px / 1000:g} mm: a field must fit the 9 mm "
                             "width of the simulated plate")
        if not 0 <= args.margin_um < math.inf:
            raise ValueError(f"--margin-um must be a finite number >= 0, got {args.margin_um}")
        heights = focus_heights(n_levels=50, z_min_um=0.0, z_step_um=200.0)
        span = (0.0, float(heights[-1]))
        world = characterisation_plate(seed=args.seed, pixel_um=px, length_mm=60.0,
                                       width_mm=9.0, z_range_um=span)
        region = (0, 0, int(60_000 / px), int(9_000 / px))
        pad = 2 * args.field_px
        cover = world.height_um(float(-pad), float(-pad), region[2] + 2 * pad,
                                region[3] + 2 * pad)
        prior = simulated_prior(cover, step_px=args.prior_step_px,
                                uncertainty_um=args.margin_um, origin_px=(-pad, -pad),
                                rng=np.random.default_rng(args.seed + 3))
        optics = Optics(width=args.field_px, height=args.field_px, pixel_um=px)
        t = time.perf_counter()
        r = two_step_fields(world, optics=optics, region_px=region, focus_heights_um=heights,
                            prior=prior, pad_levels=args.pad_levels, seed=args.seed)
    except ValueError as err:
        print(f"sffscan twostep: {err}", file=sys.stderr)
        return EXIT_BAD_INPUT
    a_full = accuracy(r.height_full_um, r.truth_um, max_depth=span[1])
    a_prior = accuracy(r.height_prior_um, r.truth_um, max_depth=span[1])
    print(f"plate 60 x 9 mm, {len(r.levels_per_field)} fields of {args.field_px} px "
          f"({args.field_px * px / 1000:.2f} mm), N = 50, prior every {args.prior_step_px} px "
          f"± {args.margin_um:g} µm, pad {args.pad_levels} levels  "
          f"[{time.perf_counter() - t:.1f} s]")
    print(f"frames: full range {r.frames_full}, with prior {r.frames_prior} "
          f"({100 * r.frames_saved:.1f} % fewer)")
    print(f"RMSE: full range {a_full.rmse_um:.1f} µm, with prior {a_prior.rmse_um:.1f} µm "
          f"(ratio {a_prior.rmse_um / a_full.rmse_um:.3f})")
    return EXIT_OK


def cmd_restrict(args: argparse.Namespace) -> int:
    from sffscan.pipeline.config import config_to_toml, load_config, max_speed_sliding_mm_s
    from sffscan.pipeline.restrict import prior_from_mosaic, restrict_scan, strip_level_range
    from sffscan.pipeline.run import check_file_output

    cfg = load_config(args.config)
    try:  # never over a file (the scan's own configuration) unless asked
        check_file_output(args.output, "-o", overwrite=args.overwrite)
        prior = prior_from_mosaic(args.prior, uncertainty_um=args.uncertainty_um,
                                  pixel_um=cfg.optics.pixel_um)
    except ValueError as err:
        return fail(str(err))
    levels = strip_level_range(cfg, prior, pad_levels=args.pad_levels)
    n = cfg.optics.n_levels
    if levels.size == n:
        return fail(f"{args.prior} does not cover the planned strip everywhere (or has NaN "
              "in it): every focus level stays; nothing written")
    restricted = restrict_scan(cfg, levels)
    o = restricted.optics
    print(f"levels {int(levels[0])}..{int(levels[-1])} of 0..{n - 1} kept ({levels.size} of "
          f"{n}, {100 * (1 - levels.size / n):.0f} % fewer per staircase): heights "
          f"{o.z_min_um:g}..{o.focus_heights_um()[-1]:g} µm (prior ± {args.uncertainty_um:g} µm, "
          f"pad {args.pad_levels} levels)")
    print(f"speed limit (sliding window) {max_speed_sliding_mm_s(cfg):.1f} -> "
          f"{max_speed_sliding_mm_s(restricted):.1f} mm/s; the DAQ staircase runs the kept "
          "levels only")
    Path(args.output).write_text(config_to_toml(restricted), encoding="utf-8")
    log.info("wrote %s", args.output)
    return EXIT_OK


def register(sub: argparse._SubParsersAction) -> None:  # type: ignore[type-arg]
    p = sub.add_parser("calibrate", help="calibration: from your images (z, lateral, curvature, "
                                         "noise), on simulated targets (sim), show a file")
    cs = p.add_subparsers(dest="calibrate_command", required=True)
    q = cs.add_parser("sim", help="calibrate on simulated targets with known answers")
    q.add_argument("-o", "--output", default="sffscan-calibration.json",
                   help="calibration file to write (default sffscan-calibration.json)")
    q.add_argument("--seed", type=seed, default=0, help="texture and noise seed")
    q.set_defaults(func=cmd_calibrate_sim)
    q = cs.add_parser("show", help="validate and print a calibration file")
    q.add_argument("file", help="calibration JSON file to validate and print")
    q.set_defaults(func=cmd_calibrate_show)
    from sffscan.pipeline.cli.calibrate_images import register_subcommands

    register_subcommands(cs)
    from sffscan.pipeline.cli.job import add_printer_fit

    add_printer_fit(cs, "printer")

    p = sub.add_parser("twostep", help="simulated two-step measurement: coarse prior vs full")
    p.add_argument("--field-px", type=int, default=128, help="field size, px (default 128)")
    p.add_argument("--pixel-um", type=float, default=34.0, help="pixel scale, µm (default 34)")
    p.add_argument("--prior-step-px", type=int, default=8,
                   help="coarse prior's lateral resolution, px (default 8)")
    p.add_argument("--margin-um", type=float, default=50.0,
                   help="coarse prior's uncertainty = margin, µm (default 50)")
    p.add_argument("--pad-levels", type=int, default=8,
                   help="levels added beyond the range on each side (default 8)")
    p.add_argument("--seed", type=seed, default=0,
                   help="seed of the simulated surface's texture and noise (default 0)")
    p.set_defaults(func=cmd_twostep)

    p = sub.add_parser("restrict", help="restrict a scan's focus levels by a coarse prior",
                       description="Two-step scanning for a continuous scan: the previous "
                                   "layer's mosaic bounds the heights of the planned strip; "
                                   "write the configuration whose lens staircase runs only "
                                   "the levels inside that range, the prior's uncertainty and "
                                   "pad levels (fewer levels: a higher speed limit).")
    p.add_argument("--config", required=True, help="the scan's TOML configuration")
    p.add_argument("--prior", required=True, help="previous layer's mosaic (Zarr group)")
    p.add_argument("--uncertainty-um", type=float, required=True,
                   help="uncertainty of the prior, µm (added to both ends of the range)")
    p.add_argument("--pad-levels", type=int, default=8,
                   help="levels added at each end so every focus curve keeps its peak and "
                        "flanks (default 8)")
    p.add_argument("-o", "--output", required=True, help="restricted configuration (TOML)")
    p.add_argument("--overwrite", action="store_true",
                   help="replace an existing -o file (refused otherwise)")
    p.set_defaults(func=cmd_restrict)
