"""Metrology: calibration, comparison with a reference, areal parameters and accuracy
against a known surface."""
