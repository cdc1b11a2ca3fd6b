"""Physics of a star tracker: catalogue, optics, detector timing, motion, gyro, simulation, effects.

This package depends on nothing else in rollingstar; the other packages build on it.
"""
