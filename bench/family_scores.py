"""The held-out stacks the depth benches score (bench_level_warp.py, bench_window_choice.py):
each synthetic family's stack of a seed and pertuz-simu02, as focus volumes with their truth
in levels and the pixels scored, and a process pool that scores them all.

64 px stacks, GLVM 9, the focus window's reach left out of the scored pixels, as the study
(:mod:`sffscan.stages.depth_study`) scores them; pertuz-simu02 in its ROI.
"""

from __future__ import annotations

import argparse
import os
import platform
import sys
from collections.abc import Callable
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path
from typing import Any

import numpy as np
from sffscan.stages.focus_measure import focus_measure
from sffscan.stages.sim.families import BLUR_MODELS, CROSSED_FAMILIES, FAMILIES, family_stack

WINDOW = 9
"""The focus measure's window (GLVM), px."""

NAMES = [f.name for f in (*FAMILIES, *CROSSED_FAMILIES)]
"""The twenty families, in the study's order."""

PERTUZ = "pertuz-simu02"

ROOT = Path(__file__).resolve().parents[1]

Volume = tuple[np.ndarray, np.ndarray, np.ndarray]


def family_volume(name: str, seed: int, blur_model: str = "gather") -> Volume:
    """A family's stack of ``seed`` (rendered with ``blur_model``,
    :data:`sffscan.stages.sim.families.BLUR_MODELS`): its focus volume, truth (levels) and
    scored pixels."""
    st = family_stack(name, seed, blur_model=blur_model)  # type: ignore[arg-type]
    vol = focus_measure(st.images, operator="glvm", window=WINDOW)
    m = WINDOW // 2
    mask = np.zeros(st.truth_um.shape, bool)
    mask[m:-m, m:-m] = True
    truth = (st.truth_um - st.focus_um[0]) / (st.focus_um[1] - st.focus_um[0])
    return vol, truth, mask


def pertuz_volume(path: str) -> Volume:
    """pertuz-simu02 (its ``imdata.mat``): focus volume, truth (levels), ROI."""
    from sffscan.pipeline.cli.study_stacks import read_imdata

    st = read_imdata(Path(path))
    vol = focus_measure(st.images, operator="glvm", window=WINDOW)
    step = float(st.focus_um[1] - st.focus_um[0])
    truth = (st.truth_um - st.focus_um[0]) / step
    return vol, truth, st.mask & np.isfinite(truth)


def _job(score: Callable[[np.ndarray, np.ndarray, np.ndarray], Any], name: str,
         seed: int, imdata: str, blur_model: str = "gather") -> tuple[str, int, Any]:
    vol = pertuz_volume(imdata) if name == PERTUZ else family_volume(name, seed, blur_model)
    return name, seed, score(*vol)


def score_stacks(score: Callable[[np.ndarray, np.ndarray, np.ndarray], Any],
                 seeds: range, *, imdata: str, jobs: int, blur_model: str = "gather"
                 ) -> dict[str, list[tuple[int, Any]]]:
    """``score(volume, truth, mask)`` (a module-level function: it goes to worker
    processes) of every family's stack of every seed (rendered with ``blur_model``), and of
    pertuz-simu02 where ``imdata`` is given (seed 0), in ``jobs`` processes; per family,
    ``(seed, score)`` in the order they finish. Progress on stderr."""
    tasks = [(n, s) for n in NAMES for s in seeds]
    if imdata:
        tasks.append((PERTUZ, 0))
    rows: dict[str, list[tuple[int, Any]]] = {}
    with ProcessPoolExecutor(max_workers=jobs) as pool:
        futures = [pool.submit(_job, score, n, s, imdata, blur_model) for n, s in tasks]
        for i, fut in enumerate(futures, 1):
            name, seed, result = fut.result()
            rows.setdefault(name, []).append((seed, result))
            print(f"\r{i}/{len(futures)} stacks", end="", file=sys.stderr, flush=True)
    print(file=sys.stderr)
    return rows


def bench_parser(doc: str, *, seeds: tuple[int, int], out: Path) -> argparse.ArgumentParser:
    """The benches' common options: ``--seeds FROM TO``, ``--imdata``, ``--jobs``, ``--out``,
    ``--blur-model``."""
    p = argparse.ArgumentParser(description=doc.split("\n\n")[0])
    p.add_argument("--seeds", nargs=2, type=int, metavar=("FROM", "TO"), default=seeds,
                   help=f"seeds FROM .. TO - 1 (default {seeds[0]} {seeds[1]})")
    p.add_argument("--imdata", default=str(ROOT.parent / "shared" / "datasets"
                                           / "pertuz-simu02" / "imdata.mat"),
                   help="pertuz-simu02's imdata.mat ('' to leave it out)")
    p.add_argument("--jobs", type=int, default=os.cpu_count() or 1, help="processes")
    p.add_argument("--out", type=Path, default=out, help=f"the table (default {out})")
    p.add_argument("--blur-model", choices=BLUR_MODELS, default="gather",
                   help="how the families' stacks apply a blur that varies over the image "
                        "(sffscan.stages.sim.families.BLUR_MODELS; default gather, the "
                        "study's)")
    return p


def machine() -> str:
    """This machine in a few words, for a table's header."""
    return (f"{platform.processor() or platform.machine()}, {os.cpu_count()} cores, "
            f"Python {platform.python_version()}")


def write_table(path: Path, text: str) -> None:
    """Write a bench's table (its folder made) and print it."""
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(text, encoding="utf-8")
    print(text)
