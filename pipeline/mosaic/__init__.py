"""The mosaic format: completed depth blocks, stitched in world coordinates into a Zarr v3
group (format ``sffscan-mosaic``, version 3; schema in ``schemas/mosaic_attrs.v1.json``).

Modules:

- :mod:`~sffscan.pipeline.mosaic.layout`: the arrays (``height``, ``texture``,
  ``confidence``, ``weight``, ``uncertainty``), their fill values, units and codecs;
- :mod:`~sffscan.pipeline.mosaic.attrs`: the group's attributes (the typed model the schema
  is generated from);
- :mod:`~sffscan.pipeline.mosaic.ngff`: the OME-Zarr (NGFF 0.5) metadata (attribute
  ``ome``), so OME-Zarr readers and viewers open the group;
- :mod:`~sffscan.pipeline.mosaic.pyramid`: ``pyramid/<k>/<name>``, k = 1 .. L-1 (L >= 4),
  level k the 2^k x 2^k reduction of level 0, kept current while the scan runs through a
  write-back cache of upper-level chunks (a level-k chunk is written when the band writes
  leave it, or after at most 5 s, and at the end); the chunks not yet written are journaled
  (``pyramid_stale``) and recomputed on resume;
- :mod:`~sffscan.pipeline.mosaic.writer`: the writer, its journal and resume;
- :mod:`~sffscan.pipeline.mosaic.reader`: attributes, levels, tile states and the lazy
  xarray Dataset (:func:`sffscan.open_mosaic`);
- :mod:`~sffscan.pipeline.mosaic.stage`: the pipeline stage that feeds the writer.

The computation (blending by weight, gathering blocks into bands, the pyramid's reduction)
is :mod:`sffscan.stages.mosaic`.

``y``, ``x`` and ``pyramid/<k>/y``, ``pyramid/<k>/x`` (version 3) are float64 µm centres of
each level's rows and columns, so ``xarray.open_zarr`` gets µm coordinates; the metadata
is consolidated when the writer sets the final status (a resume drops it first). Version 1
mosaics (no pyramid, no ``ome``) and version 2 (no coordinate arrays, not consolidated) are
still read and resumed as they are.

Pixel (row, col) of the arrays is world pixel (origin_px[1] + row, origin_px[0] + col);
world pixel (x, y) has its centre at (x, y) * pixel_um µm. All passes of a plate land in
the one mosaic; where passes overlap, height and texture are the weighted mean with
weight = max(confidence, 1e-3) over valid pixels; ``valid_pixels`` counts the finite
heights of the mosaic (a pixel seen by two passes counts once). Blocks are gathered in
memory per chunk-wide column band and written when the motion has left the band, so each
chunk is written once per pass and memory stays bounded.
"""
