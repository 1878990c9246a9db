"""The simulator: a textured world, the SFF camera over it, the continuous scanner and
calibration targets. A first-class sibling of the camera and replay sources."""
