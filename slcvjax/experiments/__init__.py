"""Experiments on the model: noise sweeps, experiment and sensor design, catadioptric cameras from images."""
