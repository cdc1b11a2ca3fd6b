"""Detector timing: global or rolling shutter, the exact exposure window of every row.

Convention: a frame's timestamp ``t0`` is the start of exposure of row 0. In rolling-shutter mode
row ``r`` (which may be fractional: a star's centroid row) starts exposing at
``t0 + r * line_delay`` and exposes for ``exposure``; in global-shutter mode every row exposes over
``[t0, t0 + exposure]``. The default frame period is he2021a eq (5): ``t_f = t_e + N * dt``.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

import numpy as np


@dataclass(frozen=True)
class DetectorTiming:
    """Exposure timing of a detector with ``rows`` rows; all durations integer nanoseconds."""

    mode: Literal["rolling", "global"]
    exposure_ns: int
    line_delay_ns: int
    rows: int
    frame_period_ns: int | None = None
    start_ns: int = 0

    def __post_init__(self):
        if self.mode not in ("rolling", "global"):
            raise ValueError(f"shutter mode must be 'rolling' or 'global', got {self.mode!r}")
        if self.exposure_ns <= 0:
            raise ValueError(f"exposure must be positive, got {self.exposure_ns} ns")
        if self.line_delay_ns < 0:
            raise ValueError(f"line delay must be >= 0, got {self.line_delay_ns} ns")
        if self.frame_period_ns is None:
            object.__setattr__(self, "frame_period_ns", int(self.exposure_ns + self.rows * self.line_delay_ns))

    @property
    def effective_line_delay_ns(self) -> int:
        """Delay between the exposure starts of adjacent rows: 0 for a global shutter."""
        return self.line_delay_ns if self.mode == "rolling" else 0

    def frame_start_ns(self, k) -> np.ndarray | int:
        """Timestamp (row-0 exposure start) of frame ``k``."""
        out = self.start_ns + np.asarray(k, dtype=np.int64) * np.int64(self.frame_period_ns)
        return int(out) if out.ndim == 0 else out

    def row_start_ns(self, t0_ns: int, rows) -> np.ndarray:
        """Exposure start of (possibly fractional) ``rows``: ``t0 + round(r * line_delay)``."""
        r = np.asarray(rows, dtype=float)
        return np.int64(t0_ns) + np.rint(r * self.effective_line_delay_ns).astype(np.int64)

    def row_window_ns(self, t0_ns: int, rows) -> tuple[np.ndarray, np.ndarray]:
        """Exact exposure window ``[start, end)`` of each row, integer ns."""
        start = self.row_start_ns(t0_ns, rows)
        return start, start + np.int64(self.exposure_ns)

    def row_mid_exposure_ns(self, t0_ns: int, rows) -> np.ndarray:
        """Mid-exposure time of each row: the time a static-PSF centroid refers to."""
        return self.row_start_ns(t0_ns, rows) + np.int64(self.exposure_ns // 2)

    def frame_reference_ns(self, t0_ns: int) -> int:
        """Mid-exposure of the middle row: the frame's single representative time."""
        return int(self.row_mid_exposure_ns(t0_ns, (self.rows - 1) / 2.0))

    def frame_end_ns(self, t0_ns: int) -> int:
        """End of exposure of the last row."""
        return int(self.row_window_ns(t0_ns, self.rows - 1)[1])
