"""A depth method chosen per stack by how rough each candidate's map is (issue 24; measured,
not the default).

    python bench/bench_roughness_choice.py --seeds 6 12 --seeds 12 18
        # writes bench/results/roughness_choice.md (under a minute a seed range, 2 cores)

The default's per-stack tests (:mod:`sffscan.stages.depth_choice`; SPC's,
:mod:`sffscan.stages.depth_spc`) weigh SPC and the peak
methods by noise predicted from each curve's second differences along the levels, which
assumes noise independent from level to level; where it is not (a thin lens' noisy slope,
a 12-bit flat plate), the choice goes wrong (docs/depth-method-log.md). This measures each
candidate's noise where it shows as the map's roughness across the image instead: the
second difference of a depth map at a spacing ``D`` beyond the focus window,
``z(p - D) - 2 z(p) + z(p + D)``, along rows and columns, has the mean square
``(D2 T)^2 + 6 sigma^2`` where the errors are independent at that spacing, and the
surface's part ``D2 T`` is the same for every candidate. A candidate's predicted mean
squared error is its roughness ``mean((D2 z)^2) / 6`` plus its bias squared: the fallback's
centroid pull where it takes the centroid, ``wcentroid``'s median 9-level centroid minus
the 3-point Gaussian, SPC's departure from the 3-point Gaussian (the curves' maxima taken
as the unbiased reference, as the departure test takes them). No constant is fitted.

Candidates: ``adaptive_centroid`` (the default's fallback), ``wcentroid`` and SPC (in its
range; the fallback elsewhere). Variants scored against the shipped default:

* ``rough``: the smallest predicted error, from the whole map's second differences;
* ``rough-gated``: from a lattice of sites ``D`` apart (about independent), leaving the
  default's own choice only where another candidate is better by more than 2 standard
  errors of the paired site differences (a conventional level, not tuned);
* ``rough-peaks``: ``rough-gated`` between the two peak methods only, where the default
  does not take SPC (SPC's choice left as it is).

64 px stacks of the twenty crossed families, GLVM 9, as the study scores them; pooled RMSE
over each seed range, each variant's ratio to the best fixed method
(:data:`sffscan.stages.depth.DEPTH_METHODS`). Not a test: nothing here asserts.
"""

from __future__ import annotations

import argparse
import math
import time
from pathlib import Path

import numpy as np
from sffscan.stages import depth_choice as dc
from sffscan.stages import depth_spc as dspc
from sffscan.stages import depth_statistics as ds
from sffscan.stages.curve_shape import curve_width
from sffscan.stages.depth import DEPTH_METHODS, depth_from_focus, first_argmax
from sffscan.stages.depth_peak import three_point_offset, windowed_centroid
from sffscan.stages.sim.families import family_names

ROOT = Path(__file__).resolve().parents[1]
OUT = ROOT / "bench" / "results" / "roughness_choice.md"
SPACING = 10
"""Site spacing D, px: beyond the GLVM window of 9 px, so errors D apart are about
independent."""
VARIANTS = ("shape_select", "rough", "rough-gated", "rough-peaks")


def peak_biases(vol: np.ndarray, argmax: np.ndarray) -> tuple[float, float]:
    """Medians over the curves (argmax 4 levels or more from both ends) of the 5-level and
    the 9-level baseline-free centroid minus the 3-point Gaussian about the argmax."""
    n = vol.shape[0]
    am = np.asarray(argmax).astype(np.intp)
    ok = (am >= 4) & (am <= n - 5)
    v = np.ascontiguousarray(vol, np.float32)
    g3 = am + three_point_offset(v, am, log=True)
    c5 = windowed_centroid(v, am, half_window=2)
    c9 = windowed_centroid(v, am, half_window=4)
    if not ok.any():
        return math.nan, math.nan
    return float(np.median((c5 - g3)[ok])), float(np.median((c9 - g3)[ok]))


def second_differences(z: np.ndarray, mask: np.ndarray, *, lattice: bool) -> np.ndarray:
    """``(D2 z)^2 / 6`` along rows and columns over the scored pixels: at every pixel, or at
    the sites of a lattice ``SPACING`` apart."""
    d = SPACING
    inner = z.astype(np.float64)[mask.any(axis=1)][:, mask.any(axis=0)]
    if lattice:
        g = inner[::d, ::d]
        a, b = g[:, :-2] - 2 * g[:, 1:-1] + g[:, 2:], g[:-2] - 2 * g[1:-1] + g[2:]
    else:
        a = inner[:, :-2 * d] - 2 * inner[:, d:-d] + inner[:, 2 * d:]
        b = inner[:-2 * d] - 2 * inner[d:-d] + inner[2 * d:]
    return np.concatenate([a.ravel(), b.ravel()]) ** 2 / 6.0


def gated(sites: dict[str, np.ndarray], bias: dict[str, float], start: str,
          keys: list[str]) -> str:
    """The candidate of ``keys`` better than ``start`` by the most, where by more than two
    standard errors of the paired site differences; else ``start``."""
    best, gain = start, 0.0
    for k in keys:
        if k == start:
            continue
        diff = sites[k] - sites[start]
        delta = float(diff.mean()) + bias[k] ** 2 - bias[start] ** 2
        se = float(diff.std(ddof=1)) / math.sqrt(diff.size)
        if delta + 2.0 * se < 0.0 and delta < gain:
            best, gain = k, delta
    return best


def choices(vol: np.ndarray, mask: np.ndarray) -> tuple[dict[str, np.ndarray], dict[str, str]]:
    """Every fixed method's map and each variant's, and what each variant took."""
    a = first_argmax(np.ascontiguousarray(vol, np.float32))
    width = curve_width(vol)
    ch = dc.stack_choice(vol, a, width, margin=9 // 2)  # as the depth judges (spread 9)
    sample, peak, _ = ds.stack_sample(vol, a, width)
    b5, b9 = peak_biases(sample, peak)
    centroid = ds.takes_centroid(ch.pull, noise=ch.noise)
    dep = dspc.spc_departure(sample, peak, centroid=False)[0]
    maps = {m: depth_from_focus(vol, method=m, median_size=11, spread_size=9, argmax=a)[0]
            for m in DEPTH_METHODS}
    fb = maps["adaptive_centroid"]
    cand = {"fb": fb, "wc": maps["wcentroid"],
            "spc": np.where(dspc.spc_in_range(maps["spc"], width, vol.shape[0]), maps["spc"], fb)}
    bias = {"fb": b5 if centroid else 0.0, "wc": b9, "spc": dep}
    bias = {k: (v if math.isfinite(v) else math.inf) for k, v in bias.items()}
    whole = {k: float(second_differences(z, mask, lattice=False).mean()) + bias[k] ** 2
             for k, z in cand.items()}
    sites = {k: second_differences(z, mask, lattice=True) for k, z in cand.items()}
    start = "spc" if ch.spc else "fb"
    took = {"shape_select": start, "rough": min(whole, key=whole.__getitem__),
            "rough-gated": gated(sites, bias, start, ["fb", "wc", "spc"]),
            "rough-peaks": start if ch.spc else gated(sites, bias, start, ["fb", "wc"])}
    out = dict(maps)
    for v in VARIANTS[1:]:
        out[v] = cand[took[v]]
    return out, took


def run(seeds: range) -> tuple[dict[str, dict[str, float]], list[str]]:
    """Each family's ratio of each variant's pooled RMSE to the best fixed method's."""
    from study_stacks import family_volume  # the bench folder's own helper

    table: dict[str, dict[str, float]] = {}
    lines: list[str] = []
    for fam in family_names(crossed=True):
        sse: dict[str, float] = {}
        for seed in seeds:
            vol, truth, mask = family_volume(fam, seed)
            maps, took = choices(vol, mask)
            for k, z in maps.items():
                sse[k] = sse.get(k, 0.0) + float(np.sum((z - truth)[mask] ** 2))
            lines.append(f"| {fam} | {seed} | {vol.shape[0]} | "
                         + " | ".join(took[v] for v in VARIANTS) + " |")
        best = min(sse[m] for m in DEPTH_METHODS)
        table[fam] = {v: math.sqrt(sse[v] / best) for v in VARIANTS}
        print(f"{fam:22s} seeds {seeds.start}..{seeds.stop - 1}: "
              + " ".join(f"{v} {r:.3f}" for v, r in table[fam].items()), flush=True)
    return table, lines


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--seeds", nargs=2, type=int, action="append", metavar=("FROM", "TO"),
                   help="a seed range FROM..TO-1 (repeatable; default 6 12)")
    p.add_argument("--out", type=Path, default=OUT)
    args = p.parse_args(argv)
    ranges = [range(a, b) for a, b in (args.seeds or [(6, 12)])]
    md = ["# A depth method chosen by its map's roughness (measured, not the default)", "",
          "`python bench/bench_roughness_choice.py "
          + " ".join(f"--seeds {r.start} {r.stop}" for r in ranges)
          + "`; what each variant is: the script's docstring. Each family's pooled RMSE "
          "over the seeds divided by the best fixed method's (1.000 = as good as the best "
          "fixed method; below 1 where a per-stack choice beats every fixed one).", ""]
    for r in ranges:
        t0 = time.perf_counter()
        table, lines = run(r)
        md += [f"## Seeds {r.start}..{r.stop - 1} ({time.perf_counter() - t0:.0f} s)", "",
               "| family | " + " | ".join(VARIANTS) + " |",
               "|---" * (len(VARIANTS) + 1) + "|"]
        md += [f"| {f} | " + " | ".join(f"{x:.3f}" for x in row.values()) + " |"
               for f, row in table.items()]
        md += ["| **worst** | " + " | ".join(f"**{max(row[v] for row in table.values()):.3f}**"
                                             for v in VARIANTS) + " |", "",
               "<details><summary>What each stack took (fb: the default's fallback, wc: "
               "wcentroid, spc: SPC in range)</summary>", "",
               "| family | seed | N | " + " | ".join(VARIANTS) + " |",
               "|---" * (len(VARIANTS) + 3) + "|", *lines, "", "</details>", ""]
    args.out.write_text("\n".join(md))
    print(f"wrote {args.out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
