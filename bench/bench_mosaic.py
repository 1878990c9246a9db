"""CPU per frame of the mosaic stage alone, this tree against another (issue 28).

    python bench/bench_mosaic.py                          # this tree only
    python bench/bench_mosaic.py --against /tmp/old       # and another checkout, interleaved

The default scan of ``bench_pipeline.py`` (1280 x 1024, N = 50, k = 9, the default depth
method, registration on) runs once over the bench's frame bank (``--frames`` distinct
simulated frames) in threads, and the depth blocks that reach its mosaic stage are kept
(``.npy`` files and their headers as JSON in a temporary folder). Then, in every round,
each tree replays the same blocks into a new mosaic (its own
:class:`~sffscan.pipeline.mosaic.stage.MosaicStage` and writer, a fresh Zarr folder under
``--dir``, made before the clock starts) in a fresh process that imports only that tree:
the blocks, end of the pass, final status, pyramid flush and consolidated metadata, as a
scan's mosaic stage does them.
Trees alternate (the other first in even rounds), so the machine's load hits both alike.

Reported per tree: the process's CPU time (every thread: Zarr's event loop included) over
the replay, per frame of the capture (median and range of the rounds), and the wall time;
every round checks that the two trees' mosaics hold the same values (level 0 and the
pyramid, each array, NaN equal to NaN). ``--dir`` matters: the cost of creating a chunk's
file depends on the file system (on this VM's ext4 ~0.8 ms of kernel CPU per new file,
on tmpfs ~0.03 ms). Not a test: nothing here asserts; it writes
``bench/results/mosaic_results.json`` and ``.md``.
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

HERE = Path(__file__).resolve().parent
ROOT = HERE.parent


def capture(frames: int, out: Path) -> int:
    """Run the bench scan once and keep its mosaic stage's depth blocks under ``out``."""
    sys.path.insert(0, str(HERE))
    import numpy as np
    from bench_pipeline import bench_config, frame_bank, load_bank, replay_frames
    from sffscan.pipeline.config_groups import Method
    from sffscan.pipeline.mosaic.stage import MosaicStage
    from sffscan.pipeline.wiring import run_scan

    cfg = bench_config(method=Method.model_fields["depth_method"].default)
    images = load_bank(cfg, frame_bank(Path(tempfile.gettempdir()) / "sffscan-bench", frames),
                       frames)
    kept: list[Any] = []
    original = MosaicStage.process

    def keep(self: MosaicStage, item: Any) -> Any:
        kept.append(item)  # the blocks of the threaded scan are not reused after the stage
        return original(self, item)

    MosaicStage.process = keep  # type: ignore[method-assign]
    try:
        with tempfile.TemporaryDirectory() as tmp:
            run_scan(cfg, frames=replay_frames(cfg, images), output=Path(tmp) / "m.zarr",
                     progress=False)
    finally:
        MosaicStage.process = original  # type: ignore[method-assign]
    for i, b in enumerate(kept):
        arrays = {"height_um": b.height_um, "texture": b.texture, "confidence": b.confidence}
        if b.uncertainty_um is not None:
            arrays["uncertainty_um"] = b.uncertainty_um
        np.savez(out / f"block{i:05d}.npz", **arrays)
        (out / f"block{i:05d}.json").write_text(b.header.model_dump_json())
    (out / "config.json").write_text(cfg.model_dump_json())
    return len(kept)


def commit_of(tree: Path) -> str:
    """The tree's git commit (short; "+ changes" where its code differs from it: sffscan/,
    pipeline/, stages/, schemas/), or "not a git checkout"."""
    head = subprocess.run(["git", "-C", str(tree), "rev-parse", "--short", "HEAD"],
                          capture_output=True, text=True, check=False)
    if head.returncode != 0:
        return "not a git checkout"
    dirty = subprocess.run(["git", "-C", str(tree), "diff", "--quiet", "HEAD", "--",
                            "sffscan", "pipeline", "stages", "schemas"],
                           check=False).returncode != 0
    return head.stdout.strip() + (" + changes" if dirty else "")


def package_of(tree: Path, farm: Path) -> Path:
    """A folder holding ``sffscan`` as ``tree``'s layout maps it (pyproject's package-dir):
    links to the tree's ``sffscan/`` files and its ``pipeline``, ``stages``, ``schemas``."""
    pkg = farm / "sffscan"
    pkg.mkdir(parents=True)
    for f in (tree / "sffscan").iterdir():
        (pkg / f.name).symlink_to(f)
    for sub in ("pipeline", "stages", "schemas"):
        (pkg / sub).symlink_to(tree / sub)
    return farm


REPLAY = r"""
import json, resource, sys, time
from pathlib import Path
import numpy as np
import zarr
blocks_dir, mosaic, frames = Path(sys.argv[1]), Path(sys.argv[2]), int(sys.argv[3])
from sffscan.pipeline.config import ScanConfig
from sffscan.pipeline.mosaic.stage import MosaicStage
from sffscan.pipeline.wiring import open_writer
from sffscan.stages.messages import DepthBlock, DepthBlockHeader
import sffscan
cfg = ScanConfig.model_validate_json((blocks_dir / "config.json").read_text())
blocks = []
for p in sorted(blocks_dir.glob("block*.npz")):
    a = np.load(p)
    h = DepthBlockHeader.model_validate_json(p.with_suffix(".json").read_text())
    blocks.append(DepthBlock(h, a["height_um"], a["texture"], a["confidence"],
                             a["uncertainty_um"] if "uncertainty_um" in a else None))
stage = MosaicStage(open_writer(cfg, path=mosaic))
ru0, w0 = resource.getrusage(resource.RUSAGE_SELF), time.perf_counter()
for b in blocks:
    for _ in stage.process(b):
        pass
for _ in stage.finish():
    pass
stage.close(failed=False)
ru1, w1 = resource.getrusage(resource.RUSAGE_SELF), time.perf_counter()
cpu = ru1.ru_utime + ru1.ru_stime - ru0.ru_utime - ru0.ru_stime
sysc = ru1.ru_stime - ru0.ru_stime
print(json.dumps({"cpu_ms": 1e3 * cpu / frames, "sys_ms": 1e3 * sysc / frames,
                  "user_ms": 1e3 * (cpu - sysc) / frames,
                  "wall_ms": 1e3 * (w1 - w0) / frames, "package": sffscan.__file__}))
"""


def replay(package: Path | None, blocks: Path, mosaic: Path, frames: int) -> dict[str, Any]:
    """One replay in a fresh process importing ``package``'s sffscan (this tree's if None)."""
    env = dict(os.environ)
    if package is not None:
        env["PYTHONPATH"] = os.pathsep.join([str(package), env.get("PYTHONPATH", "")])
    code = REPLAY if package is None else f"import sys; sys.path.insert(0, {str(package)!r})\n" \
        + REPLAY
    out = subprocess.run([sys.executable, "-c", code, str(blocks), str(mosaic), str(frames)],
                         check=True, capture_output=True, text=True, env=env)
    return dict(json.loads(out.stdout.strip().splitlines()[-1]))


def same_values(a: Path, b: Path) -> bool:
    """Whether two mosaics hold the same values in every array of every level."""
    import numpy as np
    import zarr

    ga, gb = zarr.open_group(str(a), mode="r"), zarr.open_group(str(b), mode="r")
    names = sorted(k for k, _ in ga.arrays())
    if names != sorted(k for k, _ in gb.arrays()):
        return False
    for name in names:
        x, y = np.asarray(zarr.open_array(str(Path(a) / name), mode="r")[...]), \
            np.asarray(zarr.open_array(str(Path(b) / name), mode="r")[...])
        if x.shape != y.shape or not np.array_equal(x, y, equal_nan=x.dtype.kind == "f"):
            return False
    for name, _ in ga.groups():
        if not same_values(Path(a) / name, Path(b) / name) or name not in dict(gb.groups()):
            return False
    return True


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--frames", type=int, default=600, help="frames of the captured scan")
    ap.add_argument("--rounds", type=int, default=5)
    ap.add_argument("--against", type=Path, help="another source tree")
    ap.add_argument("--dir", type=Path, default=Path(tempfile.gettempdir()),
                    help="where the mosaics are written (its file system counts)")
    ap.add_argument("--out", type=Path, default=HERE / "results" / "mosaic_results")
    args = ap.parse_args(argv)
    sys.path.insert(0, str(HERE))
    from bench_pipeline import machine

    t0 = time.perf_counter()
    with tempfile.TemporaryDirectory() as tmp:
        blocks = Path(tmp) / "blocks"
        blocks.mkdir()
        n_blocks = capture(args.frames, blocks)
        print(f"captured {n_blocks} blocks of {args.frames} frames", flush=True)
        trees: dict[str, Path | None] = {f"this tree ({commit_of(ROOT)})": None}
        if args.against is not None:
            trees[f"{args.against} ({commit_of(args.against)})"] = package_of(
                args.against.resolve(), Path(tmp) / "farm")
        runs: dict[str, list[dict[str, Any]]] = {k: [] for k in trees}
        identical = []
        for r in range(args.rounds):
            order = list(trees) if r % 2 else list(reversed(trees))
            paths = {}
            for name in order:
                m = Path(tempfile.mkdtemp(dir=args.dir)) / "m.zarr"
                runs[name].append(replay(trees[name], blocks, m, args.frames))
                paths[name] = m
                print(f"round {r} {name}: {runs[name][-1]['cpu_ms']:.3f} ms/frame "
                      f"({runs[name][-1]['package']})", flush=True)
            if len(paths) == 2:
                identical.append(same_values(*paths.values()))
            for m in paths.values():
                subprocess.run(["rm", "-rf", str(m.parent)], check=True)
    res = {"command": "python bench/bench_mosaic.py " + " ".join(argv or sys.argv[1:]),
           "machine": machine(), "frames": args.frames, "blocks": n_blocks,
           "dir": str(args.dir), "rounds": args.rounds, "runs": runs,
           "identical": identical, "seconds": time.perf_counter() - t0}
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.with_suffix(".json").write_text(json.dumps(res, indent=1))
    lines = [f"`{res['command']}`", "",
             f"machine: {res['machine']}; {args.frames} frames ({n_blocks} depth blocks) of the "
             f"default scan, replayed into the mosaic stage; mosaics under {args.dir}; "
             f"{args.rounds} rounds, trees alternating; per frame of the capture, median "
             "(min-max)", "",
             "| tree | process CPU ms/frame | user | kernel (sys) | wall ms/frame |",
             "|---|---:|---:|---:|---:|"]

    def cell(vals: list[float]) -> str:
        return f"{statistics.median(vals):.3f} ({min(vals):.3f}-{max(vals):.3f})"

    for name, rs in runs.items():
        lines.append(f"| {name} | {cell([x['cpu_ms'] for x in rs])} | "
                     f"{cell([x['user_ms'] for x in rs])} | {cell([x['sys_ms'] for x in rs])} | "
                     f"{cell([x['wall_ms'] for x in rs])} |")
    if identical:
        lines += ["", f"mosaics identical (every array and level) in {sum(identical)} of "
                  f"{len(identical)} rounds"]
    text = "\n".join(lines) + "\n"
    args.out.with_suffix(".md").write_text(text)
    print(text)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
