"""Numerical safety and the on-disk caches: the layer every other builds on."""
