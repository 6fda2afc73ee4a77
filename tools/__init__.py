"""Benchmarks, the scene simulator and the viewer. Not imported by the packages."""
