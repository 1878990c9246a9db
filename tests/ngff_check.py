"""Opens a mosaic with the OME-Zarr tools of the NGFF community and prints what they see.

Run in its own environment (``tests/ngff-requirements.txt``: the ``ome-zarr`` reader and
the ``ome-zarr-models`` package pin versions of pydantic that the project does not use), by
``tests/pipeline/mosaic/test_mosaic_ngff.py``: ``python tests/ngff_check.py MOSAIC`` prints one
JSON object.
"""

from __future__ import annotations

import json
import sys


def main(path: str) -> None:
    import dask.array as da
    import zarr
    from ome_zarr.io import parse_url
    from ome_zarr.reader import Multiscales, Reader
    from ome_zarr_models.v05.image import Image

    location = parse_url(path)
    if location is None:
        raise SystemExit(f"{path}: ome-zarr finds no Zarr group")
    nodes = list(Reader(location)())
    images = [n for n in nodes if n.load(Multiscales) is not None]
    first = images[0] if images else None
    # the published NGFF models: raises if the metadata or the arrays do not conform
    model = Image.from_zarr(zarr.open_group(path, mode="r"))
    ms = model.ome_attributes.multiscales
    print(json.dumps({
        "nodes": len(nodes),
        "image_nodes": len(images),
        "levels": len(first.data) if first else 0,
        "shapes": [list(d.shape) for d in first.data] if first else [],
        "axes": first.metadata.get("axes") if first else None,
        "transforms": first.metadata.get("coordinateTransformations") if first else None,
        "level1_nanmean": float(da.nanmean(first.data[1]).compute()) if first else None,
        "model_multiscales": [m.name for m in ms],
        "model_levels": [len(m.datasets) for m in ms],
        "ome_zarr_version": __import__("ome_zarr").__version__,
        "ome_zarr_models_version": __import__("ome_zarr_models").__version__,
    }))


if __name__ == "__main__":
    main(sys.argv[1])
