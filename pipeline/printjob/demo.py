"""The embedded print job: a sliced plate printed in the simulator, scanned every layer.

The plate (``data/``): four objects (8 x 8 mm box, 8 mm cylinder, 6 x 8 mm box, 6 mm
cylinder, 4 mm high) sliced by PrusaSlicer 2.5.0 (Debian bookworm's package) into 20
layers of 0.2 mm; the STL files, the slicer's settings (``demo_plate_prusaslicer.ini``)
and the command (``data/SLICING.md``) are kept beside the G-code.

The simulated scanner (25 µm/px, 384 x 384 px frames, 30 focus levels of 200 µm, 150
frames/s, 15 mm/s, 3 passes) covers the 23 x 25 mm around the plate; the world's height is
the G-code's beads (:class:`~sffscan.stages.sim.print_world.PrintWorld`), with the
defects :func:`demo_defects` injects.
"""

from __future__ import annotations

from collections.abc import Callable, Iterable
from importlib.resources import files
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np
from sffscan.pipeline.config import ScanConfig, config_from_dict
from sffscan.pipeline.printjob.deviation import LayerVerdict, Tolerances
from sffscan.pipeline.printjob.expected import PrinterMapping
from sffscan.pipeline.printjob.gcode import GcodeProgram
from sffscan.pipeline.printjob.jobstore import JobStore
from sffscan.pipeline.printjob.layer import LayerRunner

if TYPE_CHECKING:
    from sffscan.pipeline.printjob.live_view import JobLiveView

__all__ = ["DEMO_MAPPING", "demo_config", "demo_defects", "demo_gcode", "demo_models",
           "run_simulated_print"]

#: The demo's printer -> world mapping: the plate (printer 90.7 .. 109.3 mm) lies at world
#: 2.2 .. 20.8 mm.
DEMO_MAPPING = PrinterMapping(offset_um=(-88500.0, -88500.0))


def demo_gcode() -> Path:
    """The shipped G-code (PrusaSlicer 2.5.0, four objects, 20 layers)."""
    return Path(str(files("sffscan.pipeline.printjob") / "data" / "demo_plate.gcode"))


def demo_models() -> list[Path]:
    """The shipped STL models of the demo plate's objects."""
    d = files("sffscan.pipeline.printjob") / "data"
    return [Path(str(d / n)) for n in ("box_a.stl", "cylinder_b.stl", "box_c.stl",
                                       "cylinder_d.stl")]


def demo_config(*, pixel_um: float = 25.0, frame_px: tuple[int, int] = (384, 384),
                x_mm: tuple[float, float] = (0.5, 22.5), y_start_mm: float = 0.0,
                passes: int = 3, speed_mm_s: float = 15.0, seed: int = 0,
                **sections: dict[str, Any]) -> ScanConfig:
    """The simulated scan of one layer of the demo plate.

    Parameters
    ----------
    pixel_um : float, keyword-only
        Object-side pixel, µm/px; the defocus blur per µm is the thesis optics' (0.034
        µm of blur sigma per µm of defocus), in px.
    frame_px : (int, int), keyword-only
        Frame width (along the motion) and height, px.
    x_mm, y_start_mm, passes : keyword-only
        The strip covered: x range, first row, passes, mm.
    speed_mm_s : float, keyword-only
        Scan speed, mm/s.
    seed : int, keyword-only
        Sensor noise seed.
    **sections : dict
        Further fields per table (``processing={"execution": "threads"}``...).
    """
    data: dict[str, Any] = {
        "source": {"kind": "sim", "seed": seed},
        "optics": {"pixel_um": pixel_um, "width_px": frame_px[0], "height_px": frame_px[1],
                   "n_levels": 30, "z_min_um": -600.0, "z_step_um": 200.0,
                   "psf_c_px_per_um": 0.034 / pixel_um},
        "motion": {"x_start_mm": x_mm[0], "x_end_mm": x_mm[1], "y_start_mm": y_start_mm,
                   "passes": passes, "speed_mm_s": speed_mm_s},
        "processing": {"execution": "threads"},
    }
    for name, table in sections.items():
        data.setdefault(name, {}).update(table)
    return config_from_dict(data, origin="job demo")


def _bbox(program: GcodeProgram, name: str) -> tuple[float, float, float, float]:
    k = program.objects.index(name)
    sel = program.object_id == k
    pts = np.concatenate([program.start[sel], program.end[sel]])
    return (float(pts[:, 0].min()), float(pts[:, 1].min()), float(pts[:, 0].max()),
            float(pts[:, 1].max()))


def demo_defects(program: GcodeProgram) -> tuple[Any, ...]:
    """13 defects of 5 kinds on the demo plate, one new defect per object and layer at
    most: gaps and blobs early, then a lifted corner, a missing object and a layer shift
    (which persist). Positions are inside each object's extent (printer mm)."""
    from sffscan.stages.sim.print_world import PrintDefect

    objs = program.objects
    if len(objs) < 4:
        raise ValueError(f"demo_defects needs 4 objects, the G-code has {len(objs)}")

    def at(name: str, fx: float, fy: float) -> tuple[float, float]:
        x0, y0, x1, y1 = _bbox(program, name)
        return (x0 + fx * (x1 - x0), y0 + fy * (y1 - y0))

    a, b, c, d = objs[:4]
    return (
        PrintDefect("blob", 2, a, at(a, 0.3, 0.6), size_mm=0.8, height_um=400.0),
        PrintDefect("gap", 3, b, at(b, 0.6, 0.4), size_mm=2.0),
        PrintDefect("blob", 4, c, at(c, 0.5, 0.3), size_mm=0.8, height_um=400.0),
        PrintDefect("gap", 5, d, at(d, 0.4, 0.5), size_mm=2.0),
        PrintDefect("gap", 6, a, at(a, 0.7, 0.3), size_mm=2.0),
        PrintDefect("blob", 7, b, at(b, 0.4, 0.7), size_mm=0.8, height_um=400.0),
        PrintDefect("gap", 8, c, at(c, 0.5, 0.7), size_mm=2.0),
        PrintDefect("blob", 9, d, at(d, 0.6, 0.4), size_mm=0.8, height_um=400.0),
        PrintDefect("lifted_corner", 10, a, at(a, 0.0, 0.0), size_mm=3.0, height_um=600.0),
        PrintDefect("missing_object", 12, b),
        PrintDefect("gap", 13, c, at(c, 0.4, 0.4), size_mm=2.0),
        PrintDefect("blob", 14, d, at(d, 0.5, 0.5), size_mm=0.8, height_um=400.0),
        PrintDefect("layer_shift", 16, d, shift_mm=(1.0, 0.0)),
    )


def run_simulated_print(job: str | Path, *, gcode: str | Path | None = None,
                        models: list[Path] | None = None, defects: tuple[Any, ...] = (),
                        config: ScanConfig | None = None,
                        mapping: PrinterMapping = DEMO_MAPPING,
                        tolerances: Tolerances | None = None, layers: list[int] | None = None,
                        seed: int = 0, record: bool = False,
                        on_layer: Callable[[int, LayerVerdict, dict[str, float]], None]
                        | None = None,
                        view: Callable[[JobStore], JobLiveView] | None = None
                        ) -> list[LayerVerdict]:
    """Print a G-code in the simulator layer by layer, scanning and judging every layer.

    Parameters
    ----------
    job : path-like
        Job folder (created; or resumed if it holds a manifest: done layers are skipped).
    gcode, models : keyword-only
        The print and its models; default the shipped demo plate.
    defects : tuple of PrintDefect, keyword-only
        Defects injected into the simulated print.
    config : ScanConfig, keyword-only
        Scan of one layer; default :func:`demo_config`.
    mapping : PrinterMapping, keyword-only
        Printer -> world (= mosaic) coordinates.
    tolerances : Tolerances, keyword-only
        Verdict tolerances.
    layers : list of int, keyword-only
        Layers to print and scan (default all).
    seed : int, keyword-only
        World texture and bead jitter seed.
    record : bool, keyword-only
        Keep each layer's raw recording in the job (larger, slower).
    on_layer : callable, keyword-only
        Called ``on_layer(layer, verdict, timings)`` after each layer (timings: ``scan_s``,
        ``verdict_s`` after the scan, ``frames``).
    view : callable, keyword-only
        ``store -> JobLiveView``: the live view, shown each layer's scan as it runs and its
        deviation and verdict as they come (:mod:`~.live_view`); closed at the end.

    Returns
    -------
    list of LayerVerdict
    """

    from sffscan.stages.sim.print_world import PrintWorld

    gcode = Path(gcode) if gcode is not None else demo_gcode()
    models = models if models is not None else (demo_models() if gcode == demo_gcode() else [])
    cfg = config or demo_config()
    jp = Path(job)
    if (jp / "manifest.json").is_file():
        store = JobStore.open(jp)
    else:
        store = JobStore.create(jp, gcode=gcode, models=tuple(models), printer="sim",
                                config=cfg, mapping=mapping,
                                tolerances=tolerances or Tolerances())
    program = store.program
    o = cfg.optics
    world = PrintWorld(program, store.manifest.mapping, o.pixel_um,
                       _world_extent(program, store.manifest.mapping), defects=defects,
                       seed=seed)
    runner = LayerRunner(store)
    done = set(store.done_layers())
    live = view(store) if view is not None else None
    try:
        return _print_layers(store, runner, world, cfg, done, record, live, on_layer,
                             layers if layers is not None else range(program.n_layers))
    finally:
        if live is not None:
            live.close()


def _print_layers(store: JobStore, runner: LayerRunner, world: Any, cfg: ScanConfig,
                  done: set[int], record: bool, live: JobLiveView | None,
                  on_layer: Callable[[int, LayerVerdict, dict[str, float]], None] | None,
                  layers: Iterable[int]) -> list[LayerVerdict]:
    import time

    program = store.program
    out: list[LayerVerdict] = []
    for k in layers:
        if k in done:
            out.append(store.read_verdict(k))
            continue
        runner.begin(k, float(program.layer_z_mm[k]))
        runner.prepare(k)  # a service does this while the layer is scanned
        w = world.at_layer(k)
        t0 = time.perf_counter()
        sinks = () if live is None else (live.scan_sink(cfg, k),)
        try:
            report = runner.scan(k, config=cfg, world=w, record=record, sinks=sinks)
        except Exception as err:  # a failed scan is recorded as unknown, the job goes on
            v = runner.fail(k, f"the scan failed: {err}")
            out.append(v)
            if live is not None:
                live.layer_done(k)
            if on_layer:
                on_layer(k, v, {"scan_s": time.perf_counter() - t0})
            continue
        t1 = time.perf_counter()
        v = runner.analyse(k)
        t2 = time.perf_counter()
        out.append(v)
        if live is not None:
            live.layer_done(k)
        if on_layer:
            on_layer(k, v, {"scan_s": t1 - t0, "verdict_s": t2 - t1,
                            "frames": float(report.frames)})
    return out


def _world_extent(program: GcodeProgram, mapping: PrinterMapping
                  ) -> tuple[float, float, float, float]:
    e = program.extent_mm()
    c = mapping.apply(np.array([[e[0], e[1]], [e[2], e[3]], [e[0], e[3]], [e[2], e[1]]]))
    lo, hi = c.min(0) - 4000.0, c.max(0) + 4000.0  # room for layer shifts and blobs
    return (float(lo[0]), float(lo[1]), float(hi[0]), float(hi[1]))
