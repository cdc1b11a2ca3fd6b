"""The embedded default scenario `make demo` runs: simulate, run the baseline, evaluate."""
from __future__ import annotations

DEMO_SCENARIO_YAML = """
# Embedded demo: the he2021b Table 1 sensor (24.09 mm, 1024 x 1024, 5.5 um, 50 ms exposure,
# 49 us line delay) turning at 0.5 deg/s about the camera x axis over real Hipparcos stars.
name: demo-he2021b-0.5dps
level: centroid
sensor: {focal_length_mm: 24.09, pixel_size_um: 5.5, width_px: 1024, height_px: 1024}
shutter: {mode: rolling, exposure_ms: 50.0, line_delay_us: 49.0}
catalog: {source: hipparcos, magnitude_limit: 6.0, epoch_year: 2025.0}
motion:
  initial_attitude: {ra_deg: 83.8, dec_deg: -5.4, roll_deg: 0.0}
  rate_deg_s: [0.5, 0.0, 0.0]
noise: {centroid_sigma_px: 0.05}
frames: 100
seed: 1
"""

DEMO_PIPELINE_YAML = """
name: baseline
stages:
  - {kind: lost-in-space, params: {start_from_prior: true, track_min_matches: 2, tracking: {gate_px: 10.0}}}
  - {kind: none}
  - {kind: quest}
"""
