"""Command ``sffscan study``: operators x window sizes x depth methods on a stack with a
known truth, as a table (CSV and JSON) and a plot (PNG).

The thesis' settings study (chapter 2 kernel-size sweep, best size 7-9; chapter 3 method
comparison), for the user's own surfaces::

    sffscan study --imdata DIR/imdata.mat -o study/          # a toolbox-format stack
    sffscan study --chapter3 --noise 0.005 -o study/         # the thesis' simulation

``--imdata`` reads Pertuz's toolbox format (``imdata.mat`` with ``focus``, ``z``, ``ROI``
and ``images``, the images beside it; e.g. the pertuz-simu02 dataset), ``--chapter3``
renders the thesis' set-up (300 x 300 px, 60 levels, sinusoidal surface; ``--noise``: the
variance of Gaussian noise added to the 0..1 images). Every combination is scored by RMSE,
CORR and PSNR over the truth's scored pixels (the ROI), raw heights (no post-filter).
Exit 0, or 2 for bad input (the message names the file or option).
"""

from __future__ import annotations

import argparse
import csv
import json
import logging
import sys
import time
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

import numpy as np
from sffscan.pipeline.cli.common import (
    DEPTH_METHOD_CHOICES,
    EXIT_BAD_INPUT,
    EXIT_OK,
    OPERATOR_CHOICES,
)

log = logging.getLogger(__name__)

METHODS = DEPTH_METHOD_CHOICES


@dataclass(frozen=True)
class StudyStack:
    """A focus stack with its truth: images (N, H, W) float32 0..1, focus heights (N,) and
    truth (H, W) in µm, the scored pixels (H, W) bool."""

    images: np.ndarray
    focus_um: np.ndarray
    truth_um: np.ndarray
    mask: np.ndarray
    name: str


@dataclass(frozen=True)
class StudyRow:
    operator: str
    window: int
    method: str
    rmse_um: float
    corr: float
    psnr_db: float
    seconds: float


def run_study(stack: StudyStack, *, operators: list[str], windows: list[int],
              methods: list[str], median_size: int = 11) -> list[StudyRow]:
    """Score every operator x window x method on ``stack`` (pure: no files written).

    The focus volume is computed once per operator and window (``seconds`` is that time,
    per image), and reduced by every method.
    """
    from sffscan.pipeline.metrology.evaluate import accuracy
    from sffscan.stages.depth import depth_from_focus, levels_to_height
    from sffscan.stages.focus_measure import focus_measure

    depth_range = float(abs(stack.focus_um[-1] - stack.focus_um[0]))
    truth = np.where(stack.mask, stack.truth_um, np.nan)
    rows = []
    for op in operators:
        for k in windows:
            t0 = time.perf_counter()
            vol = focus_measure(stack.images, operator=op, window=k)
            per_image = (time.perf_counter() - t0) / len(stack.images)
            for m in methods:
                d, _ = depth_from_focus(vol, method=m, median_size=median_size, spread_size=k)
                z = levels_to_height(d, focus_heights_um=stack.focus_um)
                acc = accuracy(np.where(stack.mask, z, np.nan), truth, max_depth=depth_range,
                               mask=stack.mask)
                rows.append(StudyRow(op, k, m, float(acc.rmse_um), float(acc.corr),
                                     float(acc.psnr_db), per_image))
            log.info("%s k=%d done (%.3f s per image)", op, k, per_image)
    return rows


def read_imdata(path: Path) -> StudyStack:
    """A stack in the toolbox's format: ``imdata.mat`` and the images beside it."""
    import scipy.io
    from sffscan.stages.fields.stationary import read_image_stack

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


def chapter3_stack(*, noise: float, seed: int = 5) -> StudyStack:
    """The thesis' chapter-3 simulation (:mod:`sffscan.stages.sim.chapter3`) as a study
    stack: every pixel scored."""
    from sffscan.stages.sim.chapter3 import chapter3_stack as simulate

    images, heights, truth = simulate(noise=noise, seed=seed)
    return StudyStack(images, heights, truth, np.ones(truth.shape, bool),
                      f"chapter3 noise {noise:g}")


def write_outputs(rows: list[StudyRow], out: Path, *, title: str) -> list[Path]:
    """``study.csv``, ``study.json`` and ``study.png`` (RMSE against window per operator for
    the best method of each, and RMSE per method at each operator's best window)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    out.mkdir(parents=True, exist_ok=True)
    paths = [out / "study.csv", out / "study.json", out / "study.png"]
    with paths[0].open("w", newline="") as f:
        writer = csv.DictWriter(f, fieldnames=list(StudyRow.__dataclass_fields__))
        writer.writeheader()
        writer.writerows(asdict(r) for r in rows)
    paths[1].write_text(json.dumps({"stack": title, "rows": [asdict(r) for r in rows]},
                                   indent=1))
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


def _int_list(text: str) -> list[int]:
    try:
        return [int(v) for v in text.split(",") if v.strip()]
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected integers separated by commas, got {text!r}"
                                         ) from None


def cmd_study(args: argparse.Namespace) -> int:
    operators = [v.strip().lower() for v in args.operators.split(",") if v.strip()]
    methods = [v.strip().lower() for v in args.methods.split(",") if v.strip()]
    bad = [o for o in operators if o not in OPERATOR_CHOICES]
    bad += [m for m in methods if m not in METHODS]
    if bad or not operators or not methods:
        print(f"sffscan study: unknown operator or method {', '.join(bad) or '(none given)'}; "
              f"operators: {', '.join(OPERATOR_CHOICES)}; methods: {', '.join(METHODS)}",
              file=sys.stderr)
        return EXIT_BAD_INPUT
    if any(k < 3 or k % 2 == 0 for k in args.windows):
        print(f"sffscan study: --windows must be odd integers >= 3, got {args.windows}",
              file=sys.stderr)
        return EXIT_BAD_INPUT
    try:
        if args.imdata is not None:
            stack = read_imdata(Path(args.imdata))
        else:
            stack = chapter3_stack(noise=args.noise)
        rows = run_study(stack, operators=operators, windows=args.windows, methods=methods,
                         median_size=args.median_size)
    except ValueError as err:
        print(f"sffscan study: {err}", file=sys.stderr)
        return EXIT_BAD_INPUT
    paths = write_outputs(rows, Path(args.output), title=stack.name)
    best = min(rows, key=lambda r: r.rmse_um)
    print(f"best: {best.operator.upper()} k={best.window} {best.method}: RMSE "
          f"{best.rmse_um:.1f} µm, CORR {best.corr:.4f}, PSNR {best.psnr_db:.1f} dB")
    print("wrote " + ", ".join(str(p) for p in paths))
    return EXIT_OK


def register(sub: Any) -> None:
    p = sub.add_parser("study", help="operators x windows x depth methods on a stack with a "
                       "known truth: table (CSV, JSON) and plot (PNG)",
                       description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    src = p.add_mutually_exclusive_group(required=True)
    src.add_argument("--imdata", metavar="MAT", help="toolbox-format imdata.mat (images beside)")
    src.add_argument("--chapter3", action="store_true", help="the thesis' chapter-3 simulation")
    p.add_argument("--noise", type=float, default=0.0,
                   help="--chapter3: variance of the added Gaussian noise (thesis: 0.005)")
    p.add_argument("--operators", default="glvm,tenv,lapm,teng,lape,sfrq",
                   help="comma-separated operators (default glvm,tenv,lapm,teng,lape,sfrq)")
    p.add_argument("--windows", type=_int_list, default=[3, 5, 7, 9, 11, 13],
                   help="comma-separated odd window sizes (default 3,5,7,9,11,13)")
    p.add_argument("--methods", default=",".join(METHODS),
                   help=f"comma-separated depth methods (default {','.join(METHODS)})")
    p.add_argument("--median-size", type=int, default=11,
                   help="median filter of SPC, wcentroid and adaptive, odd, px (default 11)")
    p.add_argument("-o", "--output", default="sffscan-study", help="output folder")
    p.set_defaults(func=cmd_study)
