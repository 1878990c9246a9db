"""Height-uncertainty models against the held-out coverage bar (issue 24: 90-98 % of
|error| <= 2 sigma on every held-out family), leave one family out.

    python bench/bench_uncertainty_models.py     # writes bench/results/uncertainty_models.md
    python bench/bench_uncertainty_models.py --seeds 6 --out bench/results/uncertainty_models_6.md

For every stack of the synthetic families (:mod:`sffscan.stages.sim.families`, the study's
ten and the ten crossed from them, seeds 0 .. 2S - 1, 64 px, GLVM 9) and pertuz-simu02
(../shared/datasets/pertuz-simu02, BSD-3-Clause, read in place), the default depth's
per-pixel errors and the uncertainty's terms
(:func:`sffscan.stages.depth_study.uncertainty_sample`). Each model's constants are fitted
by :func:`sffscan.stages.uncertainty_fit.fit_uncertainty` on the training seeds (0 .. S - 1;
``--seeds S``, default 3) of the other families and scored on the held-out seeds (S .. 2S - 1)
of the family; pertuz-simu02 with
the constants fitted on every family. Twice: over the study's ten families, and over all
twenty.

Models (each stated before it was scored; add one as a function of the pixels' terms):

- ``shipped``: ``sqrt((a scatter)^2 + (r relief)^2 + (m excess)^2 + b^2 + c^2)``, one
  (a, r, c) (:mod:`sffscan.stages.depth_uncertainty`); the table must reproduce
  docs/depth-study.md (with the relief since 2026-12-04, night: the ``relief`` model below;
  ``b``, in every model here, SPC's departure where the stack took SPC and, since later
  that night, the size of the curves' centroid pull where it took the fallback:
  :func:`sffscan.stages.depth_choice.fallback_bias`);
- ``scatter only``: the shipped model before the relief joined it,
  ``sqrt((a scatter)^2 + (m excess)^2 + b^2 + c^2)``, one (a, c) (``m``:
  :data:`~sffscan.stages.depth_uncertainty.MIX_SCALE`, 1/2 until 2026-12-05, 1 since);
- ``per estimator``: the shipped model, its constants fitted apart on the pixels whose depth
  is SPC's (``shape_select`` gave their stack SPC) and on the others: ``c`` is the
  estimator's sub-level bias (2026-12-03: not kept, 9 of 21 sets in band against 14).

The models below add one term to ``scatter only`` (they were stated before the relief
joined the shipped model), ``b`` fitted with ``a`` and ``c``:

- ``curve noise``: the shipped terms and the noise that each pixel's own focus curve puts
  on a 3-point peak, ``sqrt((a scatter)^2 + (excess / 2)^2 + (b nu)^2 + c^2)``, (a, b, c)
  fitted by the same pinball loss: ``nu = s_f / (sqrt(2) |D|)`` levels, the first-order
  spread of ``(f[-1] - f[+1]) / (2 D)`` for independent noise ``s_f`` on each level, ``D``
  the curve's second difference at its argmax (the argmax kept one level off the ends),
  ``s_f`` the median absolute deviation of the curve's second differences over its levels
  / (0.6745 sqrt 6) (a second difference of white noise has variance 6 s^2); ``nu`` at most
  N levels. Nothing in it is tuned but (a, b, c) (stated 2026-12-03, before its first run).
- ``plane scatter``: the shipped form (with the relief since it joined) with another
  scatter: the depth's RMS over the focus window (k x k px) about the mean of its 5 x 5
  median over ``2k + 1`` px square (the value at the centre of that square's least-squares
  plane), instead of about the 5 x 5 median itself. Errors that are smooth over a few pixels
  (neighbours share most of the focus window) follow a 5 x 5 median and hide from its
  scatter, so ``a`` had to be ~4; a plane over the square that the excess width already
  looks at follows a slope, not a bump or an edge. (a, c) fitted as shipped (stated
  2026-12-03, before its first run: no new constant; an ``a`` near 1 was the hope).
- ``pull floor``: the shipped terms and ``b |pull|`` in quadrature, ``pull`` the stack's
  centroid pull (:func:`sffscan.stages.depth_statistics.pull_statistics`, levels; 0 where no
  curve is judged): a lopsided curve (a thin lens' blur) biases every centroid-like
  estimate toward its longer tail by about the pull, a bias no scatter shows, and the
  floor ``c`` alone must then cover the lopsided stacks and over-cover the even ones.
  (a, b, c) fitted as ``curve noise`` (stated 2026-12-03, before its first run; a block of
  a scan has this pull already: ``shape_select`` computes it).
- ``disagreement``: the shipped terms and ``b g`` in quadrature, ``g`` the 5 x 5 median of
  ``|SPC - adaptive_centroid|`` (levels), the two estimators ``shape_select`` chooses
  between, whichever it took: where they disagree one of them errs, and a stack given the
  wrong one (held-out seeds show a few) has no other sign of it. (a, b, c) fitted as
  ``curve noise`` (stated 2026-12-03, before its first run; a block of a scan has SPC's
  sums already, the fallback would cost its reduction again).
- ``relief``: (now shipped) the shipped terms and ``b r`` in quadrature, ``r`` the depth's
  local relief: the RMS over the focus window (k x k px) of the depth minus its own k x k
  box mean. The scatter is taken about a 5 x 5 median, which follows errors that are smooth
  over a few pixels (neighbours share most of the focus window), so ``a`` had to be ~4 and
  could not tell a rough map from a smooth one at the window's scale; the box mean leaves a
  plane alone (a slope has no relief) and leaves a bump, an edge or a smooth error of the
  window's size in ``r``. Found (2026-12-04, night) in a script that scored it with six
  training and six held-out seeds (17 of 21 sets in band against 11); its first run on seeds
  3..5 was this bench's (10 of 11 and 13 of 21 against 10 and 12); then shipped, so it is
  the ``shipped`` column.

Not a test: nothing here asserts.
"""

from __future__ import annotations

import argparse
import dataclasses
import math
import sys
import time
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

import cv2
import numpy as np
from scipy.optimize import minimize
from sffscan.stages.depth import DEFAULT_METHOD, depth_from_focus
from sffscan.stages.depth_statistics import pull_statistics
from sffscan.stages.depth_study import uncertainty_sample
from sffscan.stages.depth_uncertainty import MIX_SCALE
from sffscan.stages.sim.families import family_names
from sffscan.stages.uncertainty_fit import COVERAGE_TARGET, fit_uncertainty, uncertainty_coverage

ROOT = Path(__file__).resolve().parents[1]
OUT = ROOT / "bench" / "results" / "uncertainty_models.md"
BAND = (0.90, 0.98)


@dataclasses.dataclass
class Stack:
    """One stack's scored pixels: the default depth's terms and which took SPC."""

    scores: Any  # sffscan.stages.depth_study's per-stack scores
    spc: np.ndarray  # bool, the scored pixels whose depth is SPC's
    nu: np.ndarray  # the scored pixels' 3-point peak noise from their own curve, levels
    plane: np.ndarray  # the scored pixels' ``plane scatter`` (module docstring), levels
    pull: float  # the stack's centroid pull (``pull floor``, module docstring), levels
    disagree: np.ndarray  # the scored pixels' ``disagreement`` (module docstring), levels


def peak_noise(volume: np.ndarray) -> np.ndarray:
    """``nu`` of the ``curve noise`` model (module docstring), (H, W) levels, of a
    (N, H, W) focus volume."""
    n = volume.shape[0]
    v = volume.astype(np.float64)
    d2 = v[:-2] - 2.0 * v[1:-1] + v[2:]  # (N - 2, H, W): level i + 1's second difference
    s_f = np.median(np.abs(d2 - np.median(d2, axis=0)), axis=0) / (0.6745 * np.sqrt(6.0))
    i = np.clip(v.argmax(axis=0), 1, n - 2)
    d = np.abs(np.take_along_axis(d2, (i - 1)[None], axis=0)[0])
    with np.errstate(divide="ignore", invalid="ignore"):
        nu = s_f / (np.sqrt(2.0) * d)
    return np.where(np.isfinite(nu), np.minimum(nu, n), float(n))


def plane_scatter(depth: np.ndarray, *, window: int = 9) -> np.ndarray:
    """The ``plane scatter`` of a depth map (module docstring), (H, W) levels."""
    d = np.ascontiguousarray(np.nan_to_num(depth), dtype=np.float32)
    k = 2 * window + 1
    r = d - cv2.blur(cv2.medianBlur(d, 5), (k, k), borderType=cv2.BORDER_REPLICATE)
    return np.sqrt(np.maximum(cv2.blur(r * r, (window, window),
                                       borderType=cv2.BORDER_REPLICATE), 0.0))


def stack_terms(volume: np.ndarray, truth_levels: np.ndarray, mask: np.ndarray) -> Stack:
    sc = uncertainty_sample(volume, truth_levels, mask)  # the default's errors, d - truth
    default = depth_from_focus(volume, method=DEFAULT_METHOD, median_size=11, spread_size=9)[0]
    maps = [depth_from_focus(volume, method=m, median_size=11, spread_size=9)[0]
            for m in ("spc", "adaptive_centroid")]
    # the default's depth is SPC's where its error is SPC's (the same subtraction: exact)
    spc, other = ((d - truth_levels)[mask] for d in maps)
    pull = pull_statistics(volume, np.argmax(volume, axis=0), mask)[0]
    gap = np.ascontiguousarray(np.abs(np.nan_to_num(maps[0] - maps[1])), dtype=np.float32)
    return Stack(sc, (sc.error == spc) & (sc.error != other), peak_noise(volume)[mask],
                 plane_scatter(default)[mask], 0.0 if math.isnan(pull) else pull,
                 cv2.medianBlur(gap, 5)[mask])


def subset(st: Stack, sel: np.ndarray) -> Any:
    sc = st.scores
    return dataclasses.replace(sc, count=int(sel.sum()), error=sc.error[sel],
                               scatter=sc.scatter[sel], relief=sc.relief[sel],
                               excess=sc.excess[sel], bias=sc.bias[sel])


Model = Callable[[Sequence[Sequence[Stack]], Sequence[Stack]], float]
"""(training groups, one per family; held-out stacks) -> the held-out coverage."""


def shipped(train: Sequence[Sequence[Stack]], held: Sequence[Stack]) -> float:
    fit = fit_uncertainty([[s.scores for s in g] for g in train])
    return uncertainty_coverage([s.scores for s in held], fit)


def per_estimator(train: Sequence[Sequence[Stack]], held: Sequence[Stack]) -> float:
    hit = total = 0.0
    for takes_spc in (True, False):
        def pick(s: Stack, flag: bool = takes_spc) -> np.ndarray:
            return s.spc if flag else ~s.spc

        groups = [[subset(s, pick(s)) for s in g if pick(s).any()] for g in train]
        groups = [g for g in groups if g]
        held_part = [subset(s, pick(s)) for s in held if pick(s).any()]
        if not held_part:
            continue
        if not groups:  # no training pixel of this estimator: the shipped fit
            groups = [[s.scores for s in g] for g in train]
        n = sum(h.count for h in held_part)
        hit += uncertainty_coverage(held_part, fit_uncertainty(groups)) * n
        total += n
    return hit / total


def with_term(term: Callable[[Stack], np.ndarray]) -> Model:
    """``scatter only``'s terms and ``b term`` in quadrature, (a, b, c) fitted by the shipped
    quantile fit (the pinball loss of :func:`fit_uncertainty`, families weighted equally)."""

    def model(train: Sequence[Sequence[Stack]], held: Sequence[Stack]) -> float:
        def terms(g: Sequence[Stack]) -> tuple[np.ndarray, ...]:
            e = np.abs(np.concatenate([s.scores.error for s in g])).astype(np.float64)
            sc = np.concatenate([s.scores.scatter for s in g]).astype(np.float64)
            x = MIX_SCALE * np.concatenate([s.scores.excess for s in g]).astype(np.float64)
            b = np.concatenate([s.scores.bias for s in g]).astype(np.float64)  # SPC's bias
            t = np.concatenate([np.broadcast_to(term(s), s.scores.error.shape) for s in g])
            return e, sc * sc, x * x + b * b, t.astype(np.float64) ** 2

        data = [terms(g) for g in train]
        logs = [np.log(e + 1e-3) for e, *_ in data]
        tau = COVERAGE_TARGET

        def loss(p: np.ndarray) -> float:
            a2, b2, c2 = np.exp(2.0 * p)
            total = 0.0
            for le, (_, s2, x2, n2) in zip(logs, data, strict=True):
                r = le - np.log(2.0 * np.sqrt(a2 * s2 + x2 + b2 * n2 + c2) + 1e-3)
                total += float(np.mean(np.maximum(tau * r, (tau - 1.0) * r)))
            return total / len(data)

        bounds = [(math.log(0.1), math.log(100.0)), (math.log(1e-3), math.log(100.0)),
                  (math.log(1e-4), math.log(10.0))]
        best = min((minimize(loss, np.log([a0, b0, c0]), method="Nelder-Mead", bounds=bounds,
                             options={"xatol": 1e-3, "fatol": 1e-9})
                    for a0 in (1.0, 4.0) for b0 in (0.1, 1.0) for c0 in (0.01, 0.1)),
                   key=lambda r: float(r.fun))
        a, b, c = np.exp(best.x)
        e, s2, x2, n2 = terms(held)
        return float(np.mean(e <= 2.0 * np.sqrt(a * a * s2 + x2 + b * b * n2 + c * c)))

    return model


def plane(train: Sequence[Sequence[Stack]], held: Sequence[Stack]) -> float:
    def swap(s: Stack) -> Any:
        return dataclasses.replace(s.scores, scatter=s.plane)

    fit = fit_uncertainty([[swap(s) for s in g] for g in train])
    return uncertainty_coverage([swap(s) for s in held], fit)


MODELS: dict[str, Model] = {"shipped": shipped,
                            "scatter only": with_term(lambda s: np.zeros(1)),
                            "per estimator": per_estimator,
                            "curve noise": with_term(lambda s: s.nu),
                            "plane scatter": plane,
                            "pull floor": with_term(lambda s: np.array(abs(s.pull))),
                            "disagreement": with_term(lambda s: s.disagree)}


def table(names: list[str], stacks: dict[tuple[str, int], Stack], third: Stack, *,
          seeds: int) -> str:
    rows = {}
    for f in names:
        train = [[stacks[g, s] for s in range(seeds)] for g in names if g != f]
        held = [stacks[f, s] for s in range(seeds, 2 * seeds)]
        rows[f] = {m: fn(train, held) for m, fn in MODELS.items()}
    everyone = [[stacks[g, s] for s in range(seeds)] for g in names]
    rows["pertuz-simu02 (third party)"] = {m: fn(everyone, [third]) for m, fn in MODELS.items()}
    lines = ["| held out | " + " | ".join(MODELS) + " |",
             "|---|" + "---:|" * len(MODELS)]
    for name, r in rows.items():
        cells = [f"{v:.3f}" + ("" if BAND[0] <= v <= BAND[1] else " **out**")
                 for v in r.values()]
        lines.append(f"| {name} | " + " | ".join(cells) + " |")
    counts = [sum(BAND[0] <= r[m] <= BAND[1] for r in rows.values()) for m in MODELS]
    lines.append("| **in band** | " + " | ".join(f"**{c} of {len(rows)}**" for c in counts)
                 + " |")
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--out", type=Path, default=OUT)
    ap.add_argument("--seeds", type=int, default=3,
                    help="training seeds per family (0 .. S-1), as many held out (S .. 2S-1)")
    args = ap.parse_args(argv)
    sys.path.insert(0, str(ROOT / "bench"))
    from bench_pipeline import machine
    from study_stacks import family_volume, pertuz_volume

    t0 = time.perf_counter()
    stacks = {}
    for f in family_names(crossed=True):
        for s in range(2 * args.seeds):
            stacks[f, s] = stack_terms(*family_volume(f, s))
    third = stack_terms(*pertuz_volume())
    parts = [
        "# Height-uncertainty models, held out (leave one family out)", "",
        f"`python bench/bench_uncertainty_models.py` ({machine()}; "
        f"{time.strftime('%Y-%m-%d %H:%M')}; training seeds 0..{args.seeds - 1}, held out "
        f"{args.seeds}..{2 * args.seeds - 1}). Share of the held-out pixels with "
        f"|error| <= 2 sigma; the bar is {BAND[0]:.2f} .. {BAND[1]:.2f} on every family. "
        "Models: the script's docstring.", "",
        "## The study's ten families", "",
        table(family_names(), stacks, third, seeds=args.seeds), "",
        "## All twenty (the ten crossed from them too)", "",
        table(family_names(crossed=True), stacks, third, seeds=args.seeds), "",
        f"Whole run {time.perf_counter() - t0:.0f} s.", ""]
    args.out.write_text("\n".join(parts))
    print("\n".join(parts))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
