"""The stack's confidence-weighted median (issue 26 item 4): the argsort form it replaced
against the sorted-keys form of :func:`sffscan.stages.fields.weighted_median.
confidence_weighted_median`, on the height map of the real PCB photographs
(``shared/datasets/focus-stack-pcb``, ``--grey``, 15 x 15), interleaved rounds; CPU and wall
seconds per configuration, and the reconstruction's for scale. Writes
``bench/weighted_median_results.md``.

    python bench/bench_weighted_median.py --rows 256 --rounds 2

Not a test: nothing here asserts (the equality of the two forms is tested in
tests/stages/fields/test_stack_images.py).
"""

from __future__ import annotations

import argparse
import glob
import os
import platform
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np
from sffscan.stages.fields.stack_io import read_image_stack
from sffscan.stages.fields.stationary import StackSettings, reconstruct_field
from sffscan.stages.fields.weighted_median import confidence_weighted_median

ROOT = Path(__file__).resolve().parents[1]
DATA = ROOT.parent / "shared" / "datasets" / "focus-stack-pcb"


def by_argsort(z: np.ndarray, w: np.ndarray, *, size: int, block_rows: int = 64) -> np.ndarray:
    """The filter as it was (argsort of the values, gathers of values and weights)."""
    valid = np.isfinite(z)
    wz = np.where(valid, np.maximum(w, 1e-3), 0.0).astype(np.float32)
    zz = np.where(valid, z, np.inf).astype(np.float32)
    r = size // 2
    zp, wp = np.pad(zz, r, mode="edge"), np.pad(wz, r, mode="edge")
    out = np.full(z.shape, np.nan, dtype=np.float32)
    for i0 in range(0, z.shape[0], block_rows):
        i1 = min(i0 + block_rows, z.shape[0])
        zs = np.lib.stride_tricks.sliding_window_view(zp[i0:i1 + 2 * r], (size, size))
        ws = np.lib.stride_tricks.sliding_window_view(wp[i0:i1 + 2 * r], (size, size))
        zs = zs.reshape(i1 - i0, z.shape[1], size * size)
        ws = ws.reshape(i1 - i0, z.shape[1], size * size)
        order = np.argsort(zs, axis=-1)
        zs = np.take_along_axis(zs, order, axis=-1)
        cum = np.cumsum(np.take_along_axis(ws, order, axis=-1), axis=-1, dtype=np.float64)
        k = np.count_nonzero(cum < 0.5 * cum[..., -1:], axis=-1)
        out[i0:i1] = np.where(valid[i0:i1],
                              np.take_along_axis(zs, k[..., None], axis=-1)[..., 0], np.nan)
    return out


def timed(f: Callable[[], object]) -> tuple[float, float]:
    c, t = time.process_time(), time.perf_counter()
    f()
    return time.process_time() - c, time.perf_counter() - t


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--rows", type=int, default=256, help="rows of the height map filtered")
    ap.add_argument("--rounds", type=int, default=2, help="interleaved rounds")
    ap.add_argument("--size", type=int, default=15, help="window, px")
    args = ap.parse_args()
    stack = read_image_stack(sorted(glob.glob(str(DATA / "pcb_*.JPG"))), grey=True)
    res = None

    def recon() -> None:
        nonlocal res
        res = reconstruct_field(stack, focus_heights_um=np.arange(len(stack), dtype=float),
                                settings=StackSettings(filter_size=1))

    rec_cpu, rec_wall = timed(recon)
    assert res is not None
    z, w = res.raw_height_um[:args.rows], res.confidence[:args.rows]
    forms: dict[str, Callable[[], object]] = {
        "argsort (before)": lambda: by_argsort(z, w, size=args.size),
        "sorted keys, 1 thread": lambda: confidence_weighted_median(z, w, size=args.size,
                                                                     threads=1),
        "sorted keys, default threads": lambda: confidence_weighted_median(z, w,
                                                                            size=args.size),
    }
    same = np.array_equal(by_argsort(z, w, size=args.size),
                          confidence_weighted_median(z, w, size=args.size), equal_nan=True)
    times: dict[str, list[tuple[float, float]]] = {k: [] for k in forms}
    for _ in range(args.rounds):
        for name, f in forms.items():
            times[name].append(timed(f))
    scale = stack.shape[1] / args.rows
    lines = [
        "# Weighted median of `sffscan stack` (bench/bench_weighted_median.py)",
        "",
        f"PCB photographs {stack.shape[0]} x {stack.shape[1]} x {stack.shape[2]} (--grey), "
        f"window {args.size} x {args.size}, the first {args.rows} rows of the height map; "
        f"{args.rounds} interleaved rounds, best of each; {os.cpu_count()} CPUs "
        f"({platform.machine()}), load average {os.getloadavg()[0]:.1f} at the end. "
        f"Forms equal bit for bit: {same}.",
        "",
        f"Reconstruction (filter 1) of the whole stack: CPU {rec_cpu:.1f} s, wall "
        f"{rec_wall:.1f} s.",
        "",
        "| form | CPU s | wall s | whole map, CPU s (x rows) | CPU / reconstruction |",
        "|---|---|---|---|---|",
    ]
    for name, ts in times.items():
        cpu = min(t[0] for t in ts)
        wall = min(t[1] for t in ts)
        lines.append(f"| {name} | {cpu:.2f} | {wall:.2f} | {cpu * scale:.1f} | "
                     f"{cpu * scale / rec_cpu:.1f} |")
    text = "\n".join(lines) + "\n"
    (ROOT / "bench" / "weighted_median_results.md").write_text(text, encoding="utf-8")
    print(text)


if __name__ == "__main__":
    main()
