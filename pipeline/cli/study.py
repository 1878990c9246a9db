"""Command ``sffscan study``: operators x window sizes x depth methods on a stack with a
known truth, as a table (CSV and JSON) and a plot (PNG).

The thesis' settings study (chapter 2 kernel-size sweep, best size 7-9; chapter 3 method
comparison), for the user's own surfaces::

    sffscan study IMAGES... --focus-file focus.txt --truth truth.npy -o study/
    sffscan study --zarr stack.zarr --truth cmm.tif --roi 20,20,200,150 -o study/
    sffscan study --imdata DIR/imdata.mat -o study/          # a toolbox-format stack
    sffscan study --chapter3 --noise 0.005 -o study/         # the thesis' simulation
    sffscan study --families [--imdata DIR/imdata.mat] -o study/   # the held-out protocol

A user's stack is read as ``sffscan stack`` reads it (image files in the natural order of
their names or a Zarr (N, H, W) array; focus positions from ``--focus-file``,
``--focus-start`` with ``--focus-step`` or ``--focus-stop``, or the Zarr array's
``focus_heights_um``), its truth with ``--truth`` as ``sffscan compare`` reads a height map
(.npy, float TIFF or Zarr, µm, in the frame of the focus positions; NaN = not known).
``--roi x,y,w,h`` (px, from the top left corner) limits the scoring to a box; the focus
measure still sees the whole image. ``--imdata`` reads Pertuz's toolbox format
(``imdata.mat`` with ``focus``, ``z``, ``ROI`` and ``images``, the images beside it; e.g. the
pertuz-simu02 dataset), ``--chapter3`` renders the thesis' set-up (300 x 300 px, 60 levels,
sinusoidal surface; ``--noise``: the variance of Gaussian noise added to the 0..1 images).
Every combination is scored by RMSE, CORR and PSNR over the truth's scored pixels (the ROI,
finite truth), raw heights (no post-filter), and the height uncertainty checked: the share
of those pixels whose error is at most twice their uncertainty ('within 2 sigma'; 0.90 ..
0.98 where it is calibrated; n/a for a candidate method, whose uncertainty was never
fitted). Exit 0, or 2 for bad input (the message names the file or option).

``--families`` runs the protocol that chose the default depth method
(:mod:`sffscan.stages.depth_study`): leave one synthetic family out
(:mod:`sffscan.stages.sim.families`: even and lopsided blur, Gaussian and pillbox PSFs, noise
none to heavy, 8-12 bits, textures, flats, slopes, steps, heights near both ends, N =
20..100), the tunable candidates tuned on the other families' training seeds, every
method scored on the held-out family's other seeds (``--crossed``: also the ten families
crossed from those, slopes under every blur, PSF and noise among them); ``--imdata`` adds a
third-party stack
scored with the candidates tuned on all families. Prints the method x family table of held-out
RMSE (levels) and the held-out coverage of the height uncertainty
(:mod:`sffscan.stages.depth_uncertainty`: share of pixels with |error| <= 2 sigma, its
constants fitted without the family), and writes ``held_out.csv`` and ``held_out.md`` (no
figure, no matplotlib). ``--held-out-from SEED`` holds out seeds no earlier run has scored.
"""

from __future__ import annotations

import argparse
import csv
import json
import logging
import math
import sys
import time
from dataclasses import asdict, dataclass, replace
from pathlib import Path
from typing import Any

import numpy as np
from sffscan.pipeline.cli.common import (
    DEPTH_METHOD_CHOICES,
    EXIT_BAD_INPUT,
    EXIT_OK,
    OPERATOR_CHOICES,
)
from sffscan.pipeline.cli.study_stacks import (
    StudyStack,
    chapter3_stack,
    parse_roi,
    read_imdata,
    user_stack,
)
from sffscan.stages.depth import CANDIDATE_METHODS

log = logging.getLogger(__name__)

METHODS = DEPTH_METHOD_CHOICES
"""The methods a study scores unless ``--methods`` says otherwise; the study's candidates
(:data:`~sffscan.stages.depth.CANDIDATE_METHODS`) are accepted by name too."""
DEFAULT_OPERATORS = "glvm,tenv,lapm,teng,lape,sfrq"
DEFAULT_WINDOWS = [3, 5, 7, 9, 11, 13]


@dataclass(frozen=True)
class StudyRow:
    operator: str
    window: int
    method: str
    rmse_um: float
    corr: float
    psnr_db: float
    seconds: float
    within_2sigma: float = math.nan
    """Share of the scored pixels whose raw height errs by at most twice its uncertainty
    (the height uncertainty's check: 0.90 .. 0.98 where it is calibrated); NaN for a
    candidate method, whose uncertainty was never fitted."""


def run_study(stack: StudyStack, *, operators: list[str], windows: list[int],
              methods: list[str], median_size: int = 11) -> list[StudyRow]:
    """Score every operator x window x method on ``stack`` (pure: no files written).

    The focus volume is computed once per operator and window (``seconds`` is that time,
    per image), and reduced by every method.
    """
    from sffscan.pipeline.metrology.evaluate import accuracy
    from sffscan.stages.depth import depth_from_focus, levels_to_height, shape_select_with_bias
    from sffscan.stages.fields.stationary import stack_curves, stack_uncertainty_um
    from sffscan.stages.focus_measure import focus_measure

    depth_range = float(abs(stack.focus_um[-1] - stack.focus_um[0]))
    truth = np.where(stack.mask, stack.truth_um, np.nan)
    rows = []
    for op in operators:
        for k in windows:
            t0 = time.perf_counter()
            vol = focus_measure(stack.images, operator=op, window=k)
            per_image = (time.perf_counter() - t0) / len(stack.images)
            curves = stack_curves(vol)  # what every method's uncertainty reads, once
            for m in methods:
                bias, locking = None, 0.0  # the default's from its own pass
                if m == "shape_select":
                    d, _, bias, locking = shape_select_with_bias(
                        vol, argmax=curves.argmax, median_size=median_size, spread_size=k)
                else:
                    d, _ = depth_from_focus(vol, method=m, median_size=median_size,
                                            spread_size=k, argmax=curves.argmax)
                z = levels_to_height(d, focus_heights_um=stack.focus_um)
                acc = accuracy(np.where(stack.mask, z, np.nan), truth, max_depth=depth_range,
                               mask=stack.mask)
                sigma = stack_uncertainty_um(vol, d, stack.focus_um, method=m,
                                             median_size=median_size, window=k,
                                             bias_levels=bias, locking_levels=locking,
                                             curves=curves)
                rows.append(StudyRow(op, k, m, float(acc.rmse_um), float(acc.corr),
                                     float(acc.psnr_db), per_image,
                                     within_2sigma(z, truth, sigma, stack.mask)))
            log.info("%s k=%d done (%.3f s per image)", op, k, per_image)
    return rows


def within_2sigma(height_um: np.ndarray, truth_um: np.ndarray, sigma_um: np.ndarray | None,
                  mask: np.ndarray) -> float:
    """Share of the ``mask`` pixels with a finite height, truth and uncertainty whose
    |height - truth| <= 2 ``sigma_um``; NaN where ``sigma_um`` is None or no pixel counts
    (the count :func:`sffscan.pipeline.metrology.evaluate.accuracy` makes for a scan)."""
    if sigma_um is None:
        return math.nan
    from sffscan.pipeline.metrology.evaluate import accuracy

    return accuracy(height_um, truth_um, max_depth=1.0, mask=mask, sigma=sigma_um).within_2sigma


def write_outputs(rows: list[StudyRow], out: Path, *, title: str,
                  scored_pixels: int | None = None) -> list[Path]:
    """``study.csv``, ``study.json`` and ``study.png`` (RMSE against window per operator for
    the best method of each, and RMSE per method at each operator's best window).

    The table is written first; the figure needs matplotlib (an optional dependency,
    imported here only): without it a message says so and the PNG is left out (not in the
    returned paths)."""
    out.mkdir(parents=True, exist_ok=True)
    paths = [out / "study.csv", out / "study.json", out / "study.png"]
    with paths[0].open("w", newline="") as f:
        writer = csv.DictWriter(f, fieldnames=list(StudyRow.__dataclass_fields__))
        writer.writeheader()
        writer.writerows(asdict(r) for r in rows)
    paths[1].write_text(json.dumps({"stack": title, "scored_pixels": scored_pixels,
                                    "rows": [asdict(r) for r in rows]}, indent=1))
    try:
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt
    except ImportError:
        print("sffscan study: matplotlib is not installed: no figure (study.png); the "
              "table is in study.csv and study.json (pip install matplotlib for the figure)",
              file=sys.stderr)
        return paths[:2]
    fig, (ax1, ax2) = plt.subplots(1, 2, figsize=(12, 4.5))
    ops = sorted({r.operator for r in rows})
    methods = list(dict.fromkeys(r.method for r in rows))
    for op in ops:
        sub = [r for r in rows if r.operator == op]
        best_m = min(sub, key=lambda r: r.rmse_um).method
        pts = sorted((r.window, r.rmse_um) for r in sub if r.method == best_m)
        ax1.plot(*zip(*pts, strict=True), marker="o", label=f"{op.upper()} ({best_m})")
        best_k = min(sub, key=lambda r: r.rmse_um).window
        ax2.plot(range(len(methods)),
                 [next(r.rmse_um for r in sub if r.method == m and r.window == best_k)
                  for m in methods], marker="o", label=f"{op.upper()} k={best_k}")
    ax1.set(xlabel="window k (px)", ylabel="RMSE (µm)", title="kernel size sweep")
    ax2.set_xticks(range(len(methods)), methods, rotation=30)
    ax2.set(ylabel="RMSE (µm)", title="depth methods at the best window")
    for ax in (ax1, ax2):
        ax.set_yscale("log")
        ax.grid(True, alpha=0.3)
        ax.legend(fontsize=7)
    fig.suptitle(title)
    fig.tight_layout()
    fig.savefig(paths[2], dpi=110)
    plt.close(fig)
    return paths


def format_ranking(rows: list[StudyRow], *, top: int = 10) -> str:
    """The ``top`` combinations by RMSE, best first, as a Markdown table."""
    ranked = sorted(rows, key=lambda r: (np.isnan(r.rmse_um), r.rmse_um))[:max(top, 1)]
    lines = ["| rank | operator | k | method | RMSE (µm) | CORR | PSNR (dB) | within 2 sigma |",
             "|---:|---|---:|---|---:|---:|---:|---:|"]
    lines += [f"| {i} | {r.operator.upper()} | {r.window} | {r.method} | {r.rmse_um:.2f} | "
              f"{r.corr:.4f} | {r.psnr_db:.2f} | "
              f"{'n/a' if math.isnan(r.within_2sigma) else f'{r.within_2sigma:.3f}'} |"
              for i, r in enumerate(ranked, start=1)]
    return "\n".join(lines)


def _int_list(text: str) -> list[int]:
    try:
        return [int(v) for v in text.split(",") if v.strip()]
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected integers separated by commas, got {text!r}"
                                         ) from None


def families_study(args: argparse.Namespace) -> int:
    """``--families``: the leave-one-family-out protocol, printed and written."""
    from sffscan.stages.depth import levels_from_heights
    from sffscan.stages.depth_study import (
        format_coverage,
        format_spread,
        format_table,
        leave_one_family_out,
    )
    from sffscan.stages.focus_measure import focus_measure
    from sffscan.stages.sim.families import family_names

    operator = args.operators.split(",")[0].strip().lower() if args.operators else "glvm"
    window = args.windows[0] if args.windows else 9
    if operator not in OPERATOR_CHOICES or window < 3 or window % 2 == 0:
        print(f"sffscan study: unknown operator {operator!r} or a window that is not an odd "
              f"integer >= 3 ({window})", file=sys.stderr)
        return EXIT_BAD_INPUT
    third: dict[str, tuple[np.ndarray, np.ndarray, np.ndarray]] = {}
    try:
        names = ([v.strip() for v in args.family.split(",") if v.strip()]
                 if args.family else family_names(crossed=True) if args.crossed else None)
        if args.imdata is not None:
            st = read_imdata(Path(args.imdata))
            vol = focus_measure(st.images, operator=operator, window=window)
            truth = levels_from_heights(st.truth_um, focus_heights_um=st.focus_um)
            third[st.name] = (vol, truth, st.mask)
        if args.seeds < 1:
            raise ValueError(f"--seeds must be >= 1, got {args.seeds}")
        if args.held_out_from is not None and args.held_out_from < args.seeds:
            raise ValueError(f"--held-out-from {args.held_out_from}: the held-out seeds "
                             f"would overlap the training seeds 0 .. {args.seeds - 1}")
        table = leave_one_family_out(families=names, seeds=args.seeds, operator=operator,
                                     window=window, third_party=third,
                                     held_out_from=args.held_out_from,
                                     blur_model=args.blur_model)
    except (ValueError, FileNotFoundError) as err:
        print(f"sffscan study: {err}", file=sys.stderr)
        return EXIT_BAD_INPUT
    out = Path(args.output)
    out.mkdir(parents=True, exist_ok=True)
    rows = [(f, "held-out family", r) for f, r in table.rmse.items()]
    rows += [(n, "third party", r) for n, r in table.third_party.items()]
    with (out / "held_out.csv").open("w", newline="") as f:
        writer = csv.writer(f)
        writer.writerow(["set", "kind", "method", "rmse_levels", "ratio_to_best"])
        for name, kind, r in rows:
            best = min(v for m, v in r.items() if m in METHODS)
            for m in table.methods:
                writer.writerow([name, kind, m, f"{r[m]:.6g}", f"{r[m] / best:.4f}"])
    md = format_table(table)
    summary = (f"chosen by the held-out results: {table.chosen} (worst ratio to the best "
               f"method {table.worst_ratio[table.chosen]:.2f}; {operator.upper()} "
               f"k={window}, {args.seeds} training + {args.seeds} held-out seeds per family"
               + ("" if args.held_out_from is None else
                  f", held out {args.held_out_from} .. {args.held_out_from + args.seeds - 1}")
               + ("" if args.blur_model == "gather" else
                  f"; the stacks rendered with the {args.blur_model} blur model")
               + ")")
    cov = ("height uncertainty of the default method, held out:\n\n"
           + format_coverage(table))
    spread = ("how far each family's figures rest on its few held-out stacks (the stacks "
              "resampled with replacement, 2000 times; the spread of these stacks, not of "
              "the family):\n\n" + format_spread(table))
    (out / "held_out.md").write_text(md + "\n\n" + summary + "\n\n" + cov + "\n\n"
                                     + spread + "\n")
    print(md)
    print(summary)
    print(cov)
    print(spread)
    print(f"wrote {out / 'held_out.csv'}, {out / 'held_out.md'}")
    return EXIT_OK


def cmd_study(args: argparse.Namespace) -> int:
    from sffscan.pipeline.run import zarr_store_of

    out = Path(args.output).resolve()
    store = out if (out / "zarr.json").is_file() else zarr_store_of(out)
    if store is not None:  # its tables and figure would land among a mosaic's arrays
        print(f"sffscan study: -o {args.output}: inside the Zarr store {store}; choose a "
              "folder outside it", file=sys.stderr)
        return EXIT_BAD_INPUT
    if args.families:
        return families_study(args)
    args.operators = args.operators or DEFAULT_OPERATORS
    args.windows = args.windows or DEFAULT_WINDOWS
    operators = [v.strip().lower() for v in args.operators.split(",") if v.strip()]
    methods = [v.strip().lower() for v in args.methods.split(",") if v.strip()]
    bad = [o for o in operators if o not in OPERATOR_CHOICES]
    bad += [m for m in methods if m not in (*METHODS, *CANDIDATE_METHODS)]
    if bad or not operators or not methods:
        print(f"sffscan study: unknown operator or method {', '.join(bad) or '(none given)'}; "
              f"operators: {', '.join(OPERATOR_CHOICES)}; methods: {', '.join(METHODS)} "
              f"(candidates: {', '.join(CANDIDATE_METHODS)})", file=sys.stderr)
        return EXIT_BAD_INPUT
    if any(k < 3 or k % 2 == 0 for k in args.windows):
        print(f"sffscan study: --windows must be odd integers >= 3, got {args.windows}",
              file=sys.stderr)
        return EXIT_BAD_INPUT
    user = bool(args.images or args.zarr)
    sources = [n for n, on in (("image files or --zarr", user), ("--imdata", args.imdata),
                               ("--chapter3", args.chapter3)) if on]
    if len(sources) != 1:
        print("sffscan study: give one stack: image files or --zarr (with --truth), --imdata "
              f"or --chapter3{'; got ' + ', '.join(sources) if sources else ''}",
              file=sys.stderr)
        return EXIT_BAD_INPUT
    if user != (args.truth is not None):
        print("sffscan study: --truth FILE (the true height map, µm) goes with image files "
              "or --zarr" + ("" if user else "; --imdata and --chapter3 carry their own"),
              file=sys.stderr)
        return EXIT_BAD_INPUT
    try:
        if user:
            stack = user_stack(args)
        elif args.imdata is not None:
            stack = read_imdata(Path(args.imdata))
        else:
            stack = chapter3_stack(noise=args.noise)
        if args.roi is not None:
            mask = stack.mask & parse_roi(args.roi, stack.truth_um.shape)
            if not mask.any():
                raise ValueError(f"--roi {args.roi}: no pixel of the box has a known truth")
            stack = replace(stack, mask=mask)
        log.info("study: %s, %d images of %d x %d px, %d pixels scored", stack.name,
                 len(stack.images), stack.images.shape[2], stack.images.shape[1],
                 int(stack.mask.sum()))
        rows = run_study(stack, operators=operators, windows=args.windows, methods=methods,
                         median_size=args.median_size)
    except (ValueError, FileNotFoundError) as err:
        print(f"sffscan study: {err}", file=sys.stderr)
        return EXIT_BAD_INPUT
    paths = write_outputs(rows, Path(args.output), title=stack.name,
                          scored_pixels=int(stack.mask.sum()))
    print(format_ranking(rows, top=args.top))
    best = min(rows, key=lambda r: r.rmse_um)
    print(f"best: {best.operator.upper()} k={best.window} {best.method}: RMSE "
          f"{best.rmse_um:.1f} µm, CORR {best.corr:.4f}, PSNR {best.psnr_db:.1f} dB")
    print("wrote " + ", ".join(str(p) for p in paths))
    return EXIT_OK


def register(sub: Any) -> None:
    p = sub.add_parser("study", help="operators x windows x depth methods on a stack with a "
                       "known truth: table (CSV, JSON) and plot (PNG)",
                       description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    from sffscan.pipeline.cli.stack import stack_input_options

    stack_input_options(p)
    p.add_argument("--truth", metavar="FILE",
                   help="with image files or --zarr: the true height map, µm, in the frame of "
                        "the focus positions (.npy, float TIFF or Zarr; NaN = unknown)")
    p.add_argument("--truth-array", default="height",
                   help="array of a Zarr group given with --truth (default height)")
    p.add_argument("--roi", metavar="X,Y,W,H",
                   help="score only this box, px from the top left corner (default: all)")
    p.add_argument("--imdata", metavar="MAT", help="toolbox-format imdata.mat (images beside)")
    p.add_argument("--chapter3", action="store_true", help="the thesis' chapter-3 simulation")
    p.add_argument("--noise", type=float, default=0.0,
                   help="--chapter3: variance of the added Gaussian noise (thesis: 0.005)")
    p.add_argument("--operators", default=None,
                   help="comma-separated operators (default glvm,tenv,lapm,teng,lape,sfrq)")
    p.add_argument("--windows", type=_int_list, default=None,
                   help="comma-separated odd window sizes (default 3,5,7,9,11,13)")
    p.add_argument("--methods", default=",".join(METHODS),
                   help=f"comma-separated depth methods (default {','.join(METHODS)}); "
                        f"also the candidates {', '.join(CANDIDATE_METHODS)}")
    p.add_argument("--median-size", type=int, default=11,
                   help="median filter of SPC, wcentroid and adaptive, odd, px (default 11)")
    p.add_argument("--top", type=int, default=10,
                   help="rows of the ranking printed (default 10; the CSV holds all)")
    p.add_argument("--families", action="store_true",
                   help="the leave-one-family-out protocol on synthetic families (with "
                        "--imdata: and that stack as a third-party set)")
    p.add_argument("--family", metavar="NAMES",
                   help="--families: comma-separated family names (default: all the "
                        "study's)")
    p.add_argument("--crossed", action="store_true",
                   help="--families: the study's families and the ten crossed from them "
                        "(sffscan.stages.sim.families.CROSSED_FAMILIES)")
    p.add_argument("--seeds", type=int, default=3,
                   help="--families: training seeds per family, as many held out (default 3; "
                        "a family's ratios move by up to 0.4 between sets of 3 held-out "
                        "seeds: take 6 or more to read a bar of a few per cent)")
    p.add_argument("--held-out-from", type=int, metavar="SEED",
                   help="--families: the first held-out seed (default: --seeds): hold out "
                        "SEED .. SEED + seeds - 1, seeds no earlier run has scored")
    p.add_argument("--blur-model", choices=("gather", "scatter"), default="gather",
                   help="--families: how the stacks apply a blur that varies over the image: "
                        "each pixel takes its own height's blur (gather, the default: the "
                        "generator the shipped settings were chosen on) or each world point "
                        "spreads its light over its own blur (scatter: the optics of a "
                        "surface without occlusion)")
    p.add_argument("-o", "--output", default="sffscan-study", help="output folder")
    p.set_defaults(func=cmd_study)
