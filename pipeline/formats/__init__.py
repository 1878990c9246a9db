"""File and wire formats: raw-stream recordings, the zmq transport, exports (PLY, x3p,
TIFF) and the JSON Schemas generated from the typed models."""
