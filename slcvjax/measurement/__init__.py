"""Measurement with a calibrated sensor: 3D laser points and pipe circles with their uncertainty."""
