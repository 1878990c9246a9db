"""The JSON Schemas of sffscan's formats (``*.v1.json``), shipped as package data.

Generated from the typed models by ``sffscan schemas``; ``sffscan schemas --check``
compares this packaged copy with the models (:mod:`sffscan.pipeline.formats.schema_gen`).
"""
