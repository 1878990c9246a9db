"""Screenshot of a mosaic opened in neuroglancer, a standard OME-Zarr web viewer.

Serves the mosaic's folder from a local HTTP server (with the CORS headers a browser
wants), starts neuroglancer's own viewer server (the ``neuroglancer`` Python package, which
bundles the web client; not a project dependency: ``pip install neuroglancer``) on the
mosaic's OME-Zarr (NGFF 0.5, Zarr v3) image, opens it in headless Chromium (Debian packages
``chromium`` and ``chromium-driver``; WebGL through SwiftShader), and saves a PNG.
Neuroglancer reads the ``multiscales`` metadata itself: it picks the pyramid level that
suits the zoom and shows the µm axes. Usage::

    sffscan demo --passes 2 -o demo.zarr
    python docs/ngff_screenshot.py demo.zarr [--out docs/ngff-neuroglancer.png]

Exits 1 if no image was written; prints the browser console and the files the viewer
fetched (which pyramid levels it read).
"""

from __future__ import annotations

import argparse
import functools
import http.server
import sys
import tempfile
import threading
import urllib.parse
from pathlib import Path

import numpy as np
import zarr

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE))

from viewer_screenshot import shoot  # noqa: E402 - the docs folder's WebDriver helper

FLAGS = ["--use-angle=swiftshader", "--enable-unsafe-swiftshader", "--ignore-gpu-blocklist"]


class Handler(http.server.SimpleHTTPRequestHandler):
    """The mosaic's folder as static files, with CORS; records the paths served."""

    def __init__(self, *args: object, data: Path, served: list[str], **kw: object) -> None:
        self.served = served
        super().__init__(*args, directory=str(data), **kw)  # type: ignore[arg-type]

    def end_headers(self) -> None:
        self.send_header("Access-Control-Allow-Origin", "*")
        super().end_headers()

    def log_message(self, format: str, *args: object) -> None:  # noqa: A002 - stdlib name
        if args and str(args[1]) == "200":
            self.served.append(str(args[0]).split()[1])


def viewer_state(url: str, mosaic: zarr.Group, *, size: tuple[int, int]) -> dict[str, object]:
    """Neuroglancer state: the height image, jet colormap over its 1-99 % range, the whole
    mosaic in view."""
    ome = mosaic.attrs["ome"]["multiscales"][0]  # type: ignore[index]
    top = ome["datasets"][-1]
    h = np.asarray(mosaic[top["path"]][...])  # the top level: small
    lo, hi = (float(v) for v in np.nanpercentile(h, [1, 99]))
    base = ome["datasets"][0]["coordinateTransformations"]
    sy, sx = base[0]["scale"]
    ty, tx = base[1]["translation"]
    rows, cols = mosaic[ome["datasets"][0]["path"]].shape  # type: ignore[union-attr]
    centre = [tx + cols * sx / 2, ty + rows * sy / 2]
    zoom = 1.05 * max(cols * sx / size[0], rows * sy / size[1])  # µm per screen pixel
    shader = ("#uicontrol invlerp normalized\n"
              "void main() { float v = getDataValue();\n"
              "  if (isnan(v)) { emitRGB(vec3(0.0)); return; }\n"
              "  emitRGB(colormapJet(normalized())); }")
    return {
        "dimensions": {"x": [1e-6, "m"], "y": [1e-6, "m"]},
        "position": centre,
        "crossSectionScale": zoom,
        "layout": "xy",
        "showAxisLines": False,
        "layers": [{"type": "image", "name": f"height (µm, {lo:.0f}..{hi:.0f})",
                    "source": f"zarr3://{url}", "shader": shader,
                    "shaderControls": {"normalized": {"range": [lo, hi]}}}],
        "selectedLayer": {"visible": False}, "statistics": {"visible": False},
    }


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("mosaic", type=Path, help="an sffscan mosaic (Zarr v3 group)")
    ap.add_argument("--out", type=Path, default=HERE / "ngff-neuroglancer.png")
    ap.add_argument("--wait-s", type=float, default=40.0,
                    help="seconds the page gets to load before the screenshot")
    ap.add_argument("--size", default="1600,600", help="window size W,H, px")
    args = ap.parse_args()
    try:
        import neuroglancer
    except ImportError:
        raise SystemExit("neuroglancer is not installed (pip install neuroglancer): its "
                         "package holds the web client this script serves") from None
    mosaic = zarr.open_group(str(args.mosaic), mode="r")
    size = tuple(int(v) for v in args.size.split(","))
    served: list[str] = []
    handler = functools.partial(Handler, data=args.mosaic.resolve().parent, served=served)
    server = http.server.ThreadingHTTPServer(("127.0.0.1", 0), handler)
    threading.Thread(target=server.serve_forever, daemon=True).start()
    port = server.server_address[1]
    url = f"http://127.0.0.1:{port}/{urllib.parse.quote(args.mosaic.resolve().name)}/"
    neuroglancer.set_server_bind_address("127.0.0.1")
    viewer = neuroglancer.Viewer()
    viewer.set_state(neuroglancer.ViewerState(viewer_state(url, mosaic,
                                                           size=(size[0], size[1]))))
    page = viewer.get_viewer_url()
    try:
        with tempfile.TemporaryDirectory(prefix="sffscan-ng-") as profile:
            console = shoot(page, out=args.out, size=args.size, wait_s=args.wait_s,
                            profile=Path(profile), extra=FLAGS)
    finally:
        server.shutdown()
    for line in console:
        print("console:", line)
    levels = sorted({p.lstrip("/").rsplit("/c/", 1)[0] for p in served if "/c/" in p})
    print(f"arrays whose chunks the viewer read: {', '.join(levels) or 'none'}")
    if not args.out.exists() or args.out.stat().st_size == 0:
        return 1
    print(f"wrote {args.out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
