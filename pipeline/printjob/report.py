"""A self-contained HTML report of a print job: summary, tables and figures per layer.

``write_report(job)`` writes ``JOB/report.html``: the manifest (printer, G-code hash,
layers, tolerances), a table of every layer of the G-code (verdict per layer and object;
layers without a verdict are marked *not done*), and per done layer its objects'
statistics (p95 |deviation|, RMS, area out of tolerance, missing and excess material,
largest defect) and its deviation map in a diverging colour map: the tolerance band
(|deviation| <= tolerance) neutral grey, material missing in blues and excess in reds,
saturated at ``limit_um``; pixels without a measurement in dark slate; the objects'
outlines (``EXCLUDE_OBJECT_DEFINE`` polygons, else the convex hull of their extrusion up to
the layer) drawn on it. Figures are PNGs made with OpenCV and inlined as base64, the CSS is
inline: the file needs nothing else to open.
"""

from __future__ import annotations

import base64
import datetime as _dt
import html
from pathlib import Path
from typing import Any

import numpy as np
from sffscan.pipeline.printjob.deviation import LayerVerdict, ObjectVerdict
from sffscan.pipeline.printjob.jobstore import JobError, JobStore

__all__ = ["NEUTRAL_RGB", "NODATA_RGB", "deviation_colours", "layer_deviation",
           "write_report"]

NEUTRAL_RGB = (224, 224, 224)  # the tolerance band
NODATA_RGB = (47, 62, 70)  # no measurement (NaN)
# ColorBrewer RdBu stops beyond the tolerance: light -> saturated, (R, G, B)
_EXCESS = np.array([(253, 219, 199), (244, 165, 130), (214, 96, 77), (178, 24, 43),
                    (103, 0, 31)], dtype=np.float64)
_MISSING = np.array([(209, 229, 240), (146, 197, 222), (67, 147, 195), (33, 102, 172),
                     (5, 48, 97)], dtype=np.float64)
_VERDICT_RGB = {"pass": "#1a9850", "warn": "#e08a00", "fail": "#d73027",
                "unknown": "#6b7b86", "not done": "#b0b0b0"}
_FIG_PX = 420  # longest side of a deviation figure, px


def deviation_colours(deviation_um: np.ndarray, *, tolerance_um: float,
                      limit_um: float) -> np.ndarray:
    """Diverging colours of a deviation map, the tolerance band neutral.

    Parameters
    ----------
    deviation_um : (rows, columns) array_like of float
        Measured - expected height, µm; NaN where not measured.
    tolerance_um : float, keyword-only
        |deviation| <= this is :data:`NEUTRAL_RGB`, µm (> 0).
    limit_um : float, keyword-only
        |deviation| >= this takes the saturated end colour, µm (> ``tolerance_um``).

    Returns
    -------
    (rows, columns, 3) uint8
        RGB. Excess (deviation > tolerance) from light to dark red, missing material
        (deviation < -tolerance) from light to dark blue, NaN :data:`NODATA_RGB`.
    """
    if not (tolerance_um > 0 and limit_um > tolerance_um):
        raise ValueError(f"need 0 < tolerance_um < limit_um, got tolerance_um={tolerance_um}, "
                         f"limit_um={limit_um}")
    d = np.asarray(deviation_um, dtype=np.float64)
    out = np.empty(d.shape + (3,), dtype=np.uint8)
    out[...] = NEUTRAL_RGB
    a = np.abs(d)
    with np.errstate(invalid="ignore"):
        t = np.clip((a - tolerance_um) / (limit_um - tolerance_um), 0.0, 1.0)
        pos = d > tolerance_um
        neg = d < -tolerance_um
    stops = np.linspace(0.0, 1.0, len(_EXCESS))
    for mask, ramp in ((pos, _EXCESS), (neg, _MISSING)):
        if mask.any():
            tt = t[mask]
            out[mask] = np.stack([np.interp(tt, stops, ramp[:, c]) for c in range(3)],
                                 axis=-1).round().astype(np.uint8)
    out[np.isnan(d)] = NODATA_RGB
    return out


def _png_b64(rgb: np.ndarray) -> str:
    import cv2

    ok, buf = cv2.imencode(".png", np.ascontiguousarray(rgb[..., ::-1]))
    if not ok:
        raise RuntimeError("cv2.imencode failed to encode a PNG")
    return base64.b64encode(buf.tobytes()).decode("ascii")


def _outlines_mm(store: JobStore, layer: int) -> dict[str, np.ndarray]:
    """Each object's outline, printer mm: its EXCLUDE_OBJECT polygon, else the convex hull
    of its extrusion on layers <= ``layer``."""
    import cv2

    prog = store.program
    out: dict[str, np.ndarray] = {}
    for i, name in enumerate(prog.objects):
        if name in prog.outlines and len(prog.outlines[name]) >= 3:
            out[name] = np.asarray(prog.outlines[name], dtype=np.float64)
            continue
        m = (prog.object_id == i) & (prog.layer <= layer)
        if not m.any():
            continue
        pts = np.concatenate([prog.start[m], prog.end[m]]).astype(np.float32)
        out[name] = cv2.convexHull(pts).reshape(-1, 2).astype(np.float64)
    return out


def layer_deviation(store: JobStore, layer: int
                    ) -> tuple[np.ndarray, dict[str, np.ndarray]] | None:
    """A layer's stored deviation map and its objects' outlines in its pixel coordinates.

    Returns
    -------
    (deviation, outlines) or None
        ``deviation`` (rows, columns) float32, µm (NaN not measured); ``outlines`` object
        name -> (K, 2) float64 (column, row) pixel coordinates, pixel centres at integers.
        None when the layer has no deviation map.
    """
    import zarr

    path = store.deviation_path(layer)
    if not path.exists():
        return None
    arr = zarr.open_array(str(path), mode="r")
    dev = np.asarray(arr[...], dtype=np.float32)
    origin = arr.attrs["origin_um"]
    assert isinstance(origin, list)
    ox, oy = float(origin[0]), float(origin[1])  # type: ignore[arg-type]
    p = float(arr.attrs["pixel_um"])  # type: ignore[arg-type]
    mapping = store.manifest.mapping
    outlines = {}
    for name, poly_mm in _outlines_mm(store, layer).items():
        xy = mapping.apply(poly_mm)
        outlines[name] = np.stack([(xy[:, 0] - ox) / p, (xy[:, 1] - oy) / p], axis=-1)
    return dev, outlines


def _figure(store: JobStore, layer: int, *, limit_um: float) -> str | None:
    """Base64 PNG of a layer's deviation map with the objects' outlines, or None."""
    import cv2

    got = layer_deviation(store, layer)
    if got is None:
        return None
    dev, outlines = got
    rgb = deviation_colours(dev, tolerance_um=store.manifest.tolerances.tolerance_um,
                            limit_um=limit_um)
    scale = _FIG_PX / max(dev.shape)
    size = (max(1, round(dev.shape[1] * scale)), max(1, round(dev.shape[0] * scale)))
    interp = cv2.INTER_AREA if scale < 1 else cv2.INTER_NEAREST
    img = np.ascontiguousarray(cv2.resize(rgb, size, interpolation=interp))
    for name, px in outlines.items():
        pts = np.round((px + 0.5) * scale - 0.5).astype(np.int32).reshape(-1, 1, 2)
        cv2.polylines(img, [pts], isClosed=True, color=(20, 20, 20), thickness=1,
                      lineType=cv2.LINE_AA)
        label = Path(name).stem.encode("ascii", "replace").decode("ascii")
        x0, y0 = int(pts[:, 0, 0].min()), int(pts[:, 0, 1].min())
        cv2.putText(img, label, (max(2, x0), max(12, y0 - 4)), cv2.FONT_HERSHEY_SIMPLEX, 0.4,
                    (20, 20, 20), 1, cv2.LINE_AA)
    return _png_b64(img)


def _colour_bar(*, tolerance_um: float, limit_um: float) -> str:
    """HTML colour bar (an inline PNG strip) with labels in µm."""
    x = np.linspace(-limit_um * 1.05, limit_um * 1.05, 420)
    strip = deviation_colours(np.repeat(x[None, :], 14, axis=0), tolerance_um=tolerance_um,
                              limit_um=limit_um)
    mid = (limit_um + tolerance_um) / 2
    ticks = [-limit_um, -mid, -tolerance_um, tolerance_um, mid, limit_um]
    labels = "".join(
        f'<span style="left:{(t + limit_um * 1.05) / (2.1 * limit_um) * 100:.2f}%">'
        f"{t:+.0f} µm</span>".replace("-", "−") for t in ticks)
    nodata = "#{:02x}{:02x}{:02x}".format(*NODATA_RGB)
    return (f'<div class="cbar"><img alt="colour bar" src="data:image/png;base64,'
            f'{_png_b64(strip)}"><div class="ticks">{labels}</div>'
            f'<div class="cap">Mosaic pixels: x to the right, y down; outlines from the '
            f'G-code. Measured − expected height: blue missing material, red '
            f"excess, grey within ±{tolerance_um:.0f} µm, "
            f'<span class="sw" style="background:{nodata}"></span> no measurement</div></div>')


def _badge(verdict: str) -> str:
    return (f'<span class="badge" style="background:{_VERDICT_RGB.get(verdict, "#888")}">'
            f"{html.escape(verdict)}</span>")


def _num(x: float | None, fmt: str = "{:.0f}") -> str:
    return "–" if x is None else fmt.format(x)


def _object_row(o: ObjectVerdict) -> str:
    where = ("–" if o.defect_xy_mm is None else
             f"({o.defect_xy_mm[0]:.1f}, {o.defect_xy_mm[1]:.1f}) mm, "
             f"{o.defect_area_mm2:.2f} mm²")
    cells = [html.escape(o.name), _badge(o.verdict), _num(o.p95_abs_um), _num(o.rms_um),
             f"{o.area_out_mm2:.2f}", f"{o.missing_mm2:.2f}", f"{o.excess_mm2:.2f}",
             f"{100 * o.unknown_fraction:.1f} %", where]
    return "<tr>" + "".join(f"<td>{c}</td>" for c in cells) + "</tr>"


def _layer_section(store: JobStore, v: LayerVerdict, n: int, *, limit_um: float,
                   cbar: str) -> str:
    k = v.layer
    head = (f'<section class="layer" id="layer-{k:04d}"><h3>Layer {k + 1}/{n} '
            f"(index {k}) · z {v.z_mm:.2f} mm {_badge(v.verdict)}</h3>")
    if v.reason:
        head += f'<p class="reason">{html.escape(v.reason)}</p>'
    rows = "".join(_object_row(o) for o in v.objects)
    table = ("<table><tr><th>object</th><th>verdict</th><th>p95 |dev| µm</th>"
             "<th>RMS µm</th><th>out of tol. mm²</th><th>missing mm²</th>"
             "<th>excess mm²</th><th>unknown</th><th>largest defect (printer)</th></tr>"
             f"{rows}</table>")
    fig = _figure(store, k, limit_um=limit_um)
    figure = (f'<figure><img alt="deviation map of layer {k}" '
              f'src="data:image/png;base64,{fig}">{cbar}</figure>' if fig is not None else
              '<p class="nofig">no deviation map (the scan gave no comparable mosaic)</p>')
    return head + f'<div class="row">{figure}<div>{table}</div></div></section>'


_CSS = """
body{font:14px/1.4 system-ui,sans-serif;margin:24px;color:#222;max-width:1400px}
h1{font-size:22px;margin:0 0 8px} h2{font-size:18px;margin:24px 0 8px}
h3{font-size:16px;margin:0 0 6px}
table{border-collapse:collapse;margin:4px 0}
td,th{border:1px solid #ccc;padding:2px 7px;text-align:left;vertical-align:top}
th{background:#f2f2f2;font-weight:600}
.badge{color:#fff;border-radius:3px;padding:0 6px;font-weight:600;font-size:12px}
.layer{border-top:2px solid #ddd;padding:10px 0}
.row{display:flex;gap:18px;flex-wrap:wrap;align-items:flex-start}
figure{margin:0} figure>img{display:block;border:1px solid #999;image-rendering:pixelated}
.cbar{position:relative;width:420px;margin-top:6px}
.cbar img{display:block;width:420px;height:14px;border:1px solid #999}
.ticks{position:relative;height:16px;font-size:11px}
.ticks span{position:absolute;transform:translateX(-50%);white-space:nowrap;padding-top:3px}
.ticks span::before{content:'';position:absolute;left:50%;top:0;height:3px;
  border-left:1px solid #333}
.cap{font-size:11px;color:#555;width:420px}
.sw{display:inline-block;width:10px;height:10px;border:1px solid #999;vertical-align:middle}
code{font-size:12px} .reason{color:#555;margin:2px 0}
"""


def _summary_table(man: Any, verdicts: dict[int, LayerVerdict], begun: set[int]) -> str:
    names = list(man.objects)
    head = "".join(f"<th>{html.escape(Path(n).stem)}</th>" for n in names)
    rows = []
    zs = man.layer_z_mm
    k = 0
    while k < len(zs):
        v = verdicts.get(k)
        if v is None:  # a run of layers without a verdict is one row
            j = k
            while j + 1 < len(zs) and j + 1 not in verdicts:
                j += 1
            run = range(k, j + 1)
            began = [i + 1 for i in run if i in begun]
            label = f"{k + 1}" if j == k else f"{k + 1}–{j + 1}"
            zr = f"{zs[k]:.2f}" if j == k else f"{zs[k]:.2f}–{zs[j]:.2f}"
            note = f" (layer {', '.join(map(str, began))} begun)" if began else ""
            cells = [label, zr, _badge("not done") + note] + ["" for _ in names]
            rows.append(f'<tr class="notdone" data-layers="{k}-{j}">'
                        + "".join(f"<td>{c}</td>" for c in cells) + "</tr>")
            k = j + 1
            continue
        per = {o.name: o.verdict for o in v.objects}
        cells = [f'<a href="#layer-{k:04d}">{k + 1}</a>', f"{zs[k]:.2f}", _badge(v.verdict)]
        cells += [_badge(per[n]) if n in per else "–" for n in names]
        rows.append(f'<tr data-layer="{k}">' + "".join(f"<td>{c}</td>" for c in cells)
                    + "</tr>")
        k += 1
    return (f"<table><tr><th>layer</th><th>z mm</th><th>verdict</th>{head}</tr>"
            + "".join(rows) + "</table>")


def _manifest_table(store: JobStore) -> str:
    man = store.manifest
    tol = man.tolerances
    zs = man.layer_z_mm
    items = [
        ("job", man.job_id), ("created (UTC)", man.created_utc),
        ("printer", man.printer or "not named"),
        ("G-code", f"{man.gcode_file} · sha256 <code>{man.gcode_sha256}</code>"),
        ("models", ", ".join(f"{html.escape(k)} <code>{h[:16]}…</code>"
                             for k, h in man.models.items()) or "none"),
        ("objects", ", ".join(html.escape(o) for o in man.objects) or "none"),
        ("layers", f"{len(zs)} (z {zs[0]:.2f}–{zs[-1]:.2f} mm)" if zs else "0"),
        ("tolerances", f"±{tol.tolerance_um:g} µm; blobs ≥ {tol.min_blob_mm2:g} mm²; warn "
         f"at {tol.warn_area_mm2:g} mm² out, fail at a blob ≥ {tol.fail_area_mm2:g} mm²; "
         f"edge band {tol.edge_band_um:g} µm; unknown above "
         f"{100 * tol.max_unknown_fraction:g} % of a footprint; confidence ≥ "
         f"{tol.min_confidence:g}; action on fail: {tol.action}"),
        ("printer → mosaic", f"offset ({man.mapping.offset_um[0]:.0f}, "
         f"{man.mapping.offset_um[1]:.0f}) µm, rotation {man.mapping.rotation_deg:g}°"),
        ("calibration", "stored" if man.calibration else "none stored"),
    ]
    return "<table>" + "".join(
        f"<tr><th>{html.escape(a)}</th><td>{b if a in ('G-code', 'models', 'objects', 'tolerances') else html.escape(str(b))}</td></tr>"  # noqa: E501
        for a, b in items) + "</table>"


def write_report(job_path: str | Path, out_html: str | Path | None = None, *,
                 limit_um: float | None = None) -> Path:
    """Write a self-contained HTML report of a print job.

    Parameters
    ----------
    job_path : path-like
        A job folder (:class:`~sffscan.pipeline.printjob.jobstore.JobStore`).
    out_html : path-like, optional
        Output file; default ``JOB/report.html``.
    limit_um : float, keyword-only, optional
        |deviation| at which the colour map saturates, µm; default 5 x the job's tolerance.

    Returns
    -------
    Path
        The HTML file written.

    Raises
    ------
    JobError
        ``job_path`` is not a job folder (the path is named), or a layer's verdict is
        unreadable.
    """
    jp = Path(job_path)
    try:
        store = JobStore.open(jp)
    except OSError as err:
        raise JobError(f"{jp}: not a readable job folder ({err})") from None
    man = store.manifest
    tol_um = man.tolerances.tolerance_um
    lim = 5.0 * tol_um if limit_um is None else float(limit_um)
    verdicts: dict[int, LayerVerdict] = {}
    for k in store.done_layers():
        try:
            verdicts[k] = store.read_verdict(k)
        except ValueError as err:
            raise JobError(f"{store.verdict_path(k)}: unreadable verdict: {err}") from None
    begun = set(store.begun_layers()) if (jp / "layers").is_dir() else set()
    n = len(man.layer_z_mm)
    cbar = _colour_bar(tolerance_um=tol_um, limit_um=lim)
    counts = {s: sum(v.verdict == s for v in verdicts.values())
              for s in ("pass", "warn", "fail", "unknown")}
    counts_html = ", ".join(f"{c} {_badge(s)}" for s, c in counts.items())
    sections = "".join(_layer_section(store, verdicts[k], n, limit_um=lim, cbar=cbar)
                       for k in sorted(verdicts))
    now = _dt.datetime.now(_dt.UTC).isoformat(timespec="seconds")
    doc = (
        '<!DOCTYPE html><html lang="en"><head><meta charset="utf-8">'
        f"<title>sffscan job {html.escape(man.job_id[:8])}</title><style>{_CSS}</style>"
        "</head><body>"
        f"<h1>sffscan print job {html.escape(jp.name)}</h1>"
        f"<p>{len(verdicts)} of {n} layers done: {counts_html}. Report written {now}.</p>"
        f"<h2>Job</h2>{_manifest_table(store)}"
        f"<h2>Layers</h2>{_summary_table(man, verdicts, begun)}"
        f"<h2>Deviation per layer</h2>{sections or '<p>No layer is done yet.</p>'}"
        "</body></html>\n")
    out = jp / "report.html" if out_html is None else Path(out_html)
    out.write_text(doc, encoding="utf-8")
    return out
