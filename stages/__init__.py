"""The chain's stages, one per module (frame source, camera source, speed shift,
registration, focus measure, focus volume and depth, mosaic) and its sinks (recorder,
live view); :mod:`.sim` is the simulator and :mod:`.fields` the camera-standing-still
tools."""
