"""Metrology commands: ``sffscan compare``, ``sffscan export``.

- ``compare``: RMSE, CORR, PSNR and the error histogram of two height maps;
- ``export``: a mosaic region as PLY / x3p, and its areal parameters (Sa, Sq, Sz, Ssk, Sku).

The commands that make a mosaic from a focus stack (``stack``, ``stopgo``) are in
:mod:`sffscan.pipeline.cli.stack`. Exit codes as :mod:`sffscan.pipeline.cli.main`: 0 ok, 2 bad
input (the message names the file or option).
"""

from __future__ import annotations

import argparse
import json
import logging
import math
from pathlib import Path

import numpy as np
from sffscan.pipeline.cli.common import (
    EXIT_OK,
    REGION_HELP,
    fail,
    parse_region,
)

log = logging.getLogger(__name__)


def _mosaic_pixel_um(path: str) -> float | None:
    """µm per px of an sffscan mosaic (for ``--region`` in mm or µm), None for anything else."""
    import zarr

    try:
        value = zarr.open_group(str(path), mode="r", use_consolidated=False).attrs.get("pixel_um")
    except Exception:  # noqa: BLE001 - not a group: the reader names the problem
        return None
    return float(value) if isinstance(value, int | float) else None


# ----------------------------------------------------------------------------- compare


def cmd_compare(args: argparse.Namespace) -> int:
    from sffscan.pipeline.formats.exports import check_trust
    from sffscan.pipeline.metrology.compare import (
        compare_height_maps,
        format_report,
        overlap_by_origin,
        overlap_uncertainty,
        read_height_map,
        region_mask,
    )
    from sffscan.pipeline.run import check_file_output

    try:
        if args.json:
            check_file_output(args.json, "--json", overwrite=args.overwrite)
        check_trust([args.estimate, args.reference], allow=args.allow_untrustworthy)
        est = read_height_map(args.estimate, array=args.array)
        ref = read_height_map(args.reference, array=args.array)
        a, b, origin = overlap_by_origin(est, ref)
        region = parse_region(args.region, pixel_um=est.pixel_um or ref.pixel_um)
        mask = None if region is None else region_mask(a.shape, origin, region)
        if args.max_depth_um is not None and not 0 < args.max_depth_um < math.inf:
            raise ValueError(f"--max-depth-um must be a finite number > 0, got "
                             f"{args.max_depth_um:g}")  # 0 was taken for 'not given'
        max_depth = args.max_depth_um or est.max_depth_um or ref.max_depth_um
        note = ""
        if max_depth is None:
            finite = b[np.isfinite(b)]
            if finite.size == 0:
                raise ValueError(f"{args.reference}: no finite height")
            max_depth = float(finite.max() - finite.min()) or 1.0
            note = " (MAX_d = the reference's height range; set --max-depth-um)"
        report = compare_height_maps(a, b, max_depth_um=max_depth, align=args.align,
                                     bins=args.bins, range_um=args.range_um,
                                     max_shift_px=args.max_shift_px, mask=mask,
                                     names=(str(args.estimate), str(args.reference)),
                                     sigma=overlap_uncertainty(est, ref))
    except ValueError as err:
        return fail(str(err))
    print(format_report(report) + note)
    if args.json:
        Path(args.json).write_text(report.model_dump_json(indent=2) + "\n", encoding="utf-8")
        log.info("wrote %s", args.json)
    return EXIT_OK


# ----------------------------------------------------------------------------- export


def cmd_export(args: argparse.Namespace) -> int:
    from sffscan.pipeline.formats import exports as ex
    from sffscan.pipeline.metrology.areal import areal_parameters
    from sffscan.pipeline.run import check_file_output

    try:
        for flag, value in (("--ply", args.ply), ("--x3p", args.x3p), ("--json", args.json)):
            if value:  # never into a Zarr store (the mosaic's zarr.json...), nor over a file
                check_file_output(value, flag, stores=[args.mosaic], overwrite=args.overwrite)
        ex.check_trust([args.mosaic], allow=args.allow_untrustworthy)
        region = parse_region(args.region, pixel_um=_mosaic_pixel_um(args.mosaic))
        ex.check_export_size(args.mosaic, region)
        if args.ply:
            n = ex.write_ply(args.ply, args.mosaic, region)
            print(f"wrote {args.ply}: {n['points']} points (x y z mm, red green blue = texture)"
                  + (f", {n['no_texture']} without texture (black)" if n["no_texture"] else ""))
        if args.x3p:
            n = ex.write_x3p(args.x3p, args.mosaic, region)
            print(f"wrote {args.x3p}: {n['rows']}x{n['cols']} surface, {n['missing']} points "
                  "not measured")
        reg = ex.read_region(args.mosaic, region)
        params = areal_parameters(reg.height_um, level=args.level)
    except ValueError as err:
        return fail(str(err))
    box = (reg.x0_px, reg.y0_px, reg.x0_px + reg.height_um.shape[1],
           reg.y0_px + reg.height_um.shape[0])
    print(f"region x {box[0]}..{box[2]} y {box[1]}..{box[3]} px: {params.format()}")
    if args.json:
        Path(args.json).write_text(json.dumps({"region_px": box, **params.as_dict()}, indent=2)
                                   + "\n", encoding="utf-8")
    return EXIT_OK


# ----------------------------------------------------------------------------- parser


def _allow_option(p: argparse.ArgumentParser) -> None:
    p.add_argument("--allow-untrustworthy", action="store_true",
                   help="use a mosaic with torn tiles, or still being written, or without a "
                        "final status (refused otherwise, exit 2)")


def register(sub: argparse._SubParsersAction) -> None:  # type: ignore[type-arg]
    p = sub.add_parser("compare", help="RMSE, CORR, PSNR and error histogram of two height maps",
                       description="Compare a height map (mosaic, Zarr array, .npy or float "
                                   "TIFF, µm) with a reference; mosaics are lined up by their "
                                   "world origin.")
    p.add_argument("estimate", help="height map to score, µm (mosaic, Zarr array, .npy or "
                                    "float TIFF)")
    p.add_argument("reference", help="reference height map, µm, same kinds")
    p.add_argument("--array", default="height", help="array of a Zarr group (default height)")
    p.add_argument("--align", choices=["none", "offset", "plane", "shift"], default="none",
                   help="remove an offset, a plane, or a lateral shift and a plane first")
    p.add_argument("--max-shift-px", type=int, default=10, help="shift search range, px")
    p.add_argument("--region", help="score only this " + REGION_HELP + " (array px when "
                                    "neither map has a world origin)")
    p.add_argument("--max-depth-um", type=float, help="MAX_d of the PSNR, µm")
    p.add_argument("--bins", type=int, default=20, help="histogram bins (default 20)")
    p.add_argument("--range-um", type=float, nargs=2, metavar=("LO", "HI"),
                   help="histogram range, µm (default +-99.9th percentile of |error|)")
    p.add_argument("--json", help="write the report (schemas/compare_report.v1.json)")
    p.add_argument("--overwrite", action="store_true",
                   help="replace an existing --json file (refused otherwise)")
    _allow_option(p)
    p.set_defaults(func=cmd_compare)

    p = sub.add_parser("export", help="export a mosaic region (PLY, x3p) and its Sa, Sq, ...",
                       description="Export a mosaic region as a binary PLY point cloud (x y z "
                                   "mm, the texture as red/green/blue) and/or an ISO 25178-72 "
                                   "x3p surface, and print its areal parameters Sa, Sq, Sz, "
                                   "Ssk, Sku.")
    p.add_argument("mosaic", help="mosaic to export (a Zarr group written by sffscan)")
    p.add_argument("--region", help=REGION_HELP + " (default: the whole mosaic)")
    p.add_argument("--ply", help="write a binary PLY point cloud")
    p.add_argument("--x3p", help="write an ISO 25178-72 x3p file")
    p.add_argument("--level", choices=["plane", "mean", "none"], default="plane",
                   help="reference surface of the areal parameters (default plane)")
    p.add_argument("--json", help="write the areal parameters as JSON")
    p.add_argument("--overwrite", action="store_true",
                   help="replace existing --ply, --x3p and --json files (refused otherwise)")
    _allow_option(p)
    p.set_defaults(func=cmd_export)
