"""he2021a time-domain correction (section 2.2, eqs 12-18): every star moved to one reference time.

Input: stars with (filtered) positions ``x, y`` referring to ``t_ns`` (for a raw or kf-cv-filtered
centroid, the mid-exposure of its own row, ``t0 + y dt_line + t_e / 2``) and image velocities
``vx, vy`` (px/s, from the ``kf-cv`` filter). Two steps, both constant-velocity extrapolations:

1. Smear ("distortion") centroid correction, eqs (12)-(16): the star is exposed for
   ``t_i = (h_i - 1) dt_line + t_e`` (eq 12, ``h_i`` the rows the spot covers); its centroid is the
   mid-exposure position, so the exposure-start position is ``x' = x - vx t_i / 2``,
   ``y' = y - vy t_i / 2`` (eqs 13-16).
2. Reference-row correction, eqs (17)-(18): from the exposure start of the star's row to the
   exposure start of row ``k_s``: ``x_C = x' - vx (row - k_s) dt_line`` (same for y).

``variant="exact"`` (default) composes the two steps with the time each position really refers to:
a centroid at ``t_ns`` moved to ``t_ref = t0 + k_s dt_line`` (``DetectorTiming.row_start_ns``) is
``x_C = x - vx (t_ns - t_ref)``, ``y_C = y - vy (t_ns - t_ref)``. This is eqs (12)-(18) with
``h_i = 1`` (the spot's extra rows do not delay the centroid's time: the convention's mid-exposure
of the centroid row already is the time of a rolling-shutter centroid) and with the star's row
time in eq (17) taken from the measured centroid row rather than the smear-corrected ``y'``.
Every corrected star then refers to ``t_ref`` exactly: ``t_ns = t_ref``.

``variant="paper"`` evaluates eqs (12)-(18) literally (``h_i = spot_rows``, ``y'`` in eq 17).
Under the constant-velocity model the result is then the star's position at
``t_ns - t_i / 2 - (y' - k_s) dt_line = t_ref - (h_i - 1) dt_line / 2 + (y - y') dt_line``, which
differs from star to star by a few microseconds (``y - y' = vy t_i / 2``); ``t_ns`` is set to that
per-star time, rounded to the ns, so that downstream stages and the evaluation know it.

Stars without a finite velocity (``vx`` or ``vy`` NaN, e.g. a track's first frame) are left
unchanged, keep their own ``t_ns``, and the frame gets flag ``"time_domain_no_velocity:<n>"``.
``row_time_ns`` is left as measured (the exposure start of the star's measured centroid row) and
``sigma_px`` and the 2 x 2 covariance ``cov_*`` unchanged (velocity uncertainty times the
extrapolation interval is not added).
"""
from __future__ import annotations

from typing import Literal

import numpy as np
from pydantic import BaseModel, ConfigDict, Field

from rollingstar.estimators.corrections.base import Correction
from rollingstar.estimators.data import FrameData
from rollingstar.sensors.conventions import NS_PER_S, S_PER_NS


def reference_time_ns(timing, t0_ns: int, reference_row: float | None = None) -> int:
    """Exposure start of row ``k_s`` (default the middle row ``(rows - 1) / 2``) of the frame at ``t0_ns``."""
    k_s = (timing.rows - 1) / 2.0 if reference_row is None else float(reference_row)
    return int(timing.row_start_ns(t0_ns, k_s))


def time_domain_correct(x, y, vx, vy, t_ns, t0_ns: int, timing, reference_row: float | None = None,
                        variant: str = "exact", spot_rows: float = 5.0):
    """Vectorised eqs (12)-(18). Returns ``(x_c, y_c, t_c_ns, ok)``; rows with ``ok`` False (no finite
    velocity) are returned unchanged with their own ``t_ns``."""
    x = np.asarray(x, dtype=float)
    y = np.asarray(y, dtype=float)
    vx = np.asarray(vx, dtype=float)
    vy = np.asarray(vy, dtype=float)
    t_ns = np.asarray(t_ns, dtype=np.int64)
    ok = np.isfinite(vx) & np.isfinite(vy)
    k_s = (timing.rows - 1) / 2.0 if reference_row is None else float(reference_row)
    t_ref = reference_time_ns(timing, t0_ns, k_s)
    ld_s = timing.effective_line_delay_ns * S_PER_NS
    if variant == "exact":
        tau_ns = t_ns - np.int64(t_ref)  # eqs (12)-(18) with h_i = 1: mid-exposure -> t_ref
        tau = tau_ns.astype(float) * S_PER_NS
        t_new = np.full(t_ns.shape, t_ref, dtype=np.int64)
    elif variant == "paper":
        t_i = (spot_rows - 1.0) * ld_s + timing.exposure_ns * S_PER_NS  # eq (12)
        y_prime = y - 0.5 * vy * t_i  # eqs (13)-(14), (16)
        tau = 0.5 * t_i + (y_prime - k_s) * ld_s  # eqs (15)-(18): total extrapolation interval
        t_new = t_ns - np.rint(np.where(ok, tau, 0.0) * NS_PER_S).astype(np.int64)
    else:
        raise ValueError(f"variant must be 'exact' or 'paper', got {variant!r}")
    xc = np.where(ok, x - vx * tau, x)
    yc = np.where(ok, y - vy * tau, y)
    return xc, yc, np.where(ok, t_new, t_ns), ok


class TimeDomainParams(BaseModel):
    model_config = ConfigDict(extra="forbid")

    reference_row: float | None = Field(
        default=None, description="Row k_s whose exposure start is the common time (eq 17); None: the middle row (rows - 1) / 2.")
    variant: Literal["exact", "paper"] = Field(
        default="exact", description="'exact': move each star from its own t_ns to t_ref; 'paper': eqs (12)-(18) literally.")
    spot_rows: float = Field(default=5.0, ge=1.0, description="h_i of eq (12) for variant 'paper' (the seed's 5 x 5 spot).")


class TimeDomainCorrection(Correction):
    """he2021a time-domain correction of every star to the exposure start of row ``k_s`` (eqs 12-18).

    Needs ``vx, vy`` (px/s) from a star-motion filter (``kf-cv``) upstream. See the module docstring
    for the two variants and exactly which time the corrected positions refer to (``t_ns``):
    ``variant="exact"``: ``t_ref = t0 + round(k_s * line_delay)`` for every corrected star.
    Stars without velocity are left unchanged (own ``t_ns``) and the frame is flagged
    ``"time_domain_no_velocity:<n>"``.
    """

    name = "time-domain"
    Params = TimeDomainParams
    needs = frozenset({"velocities"})

    def process(self, frame: FrameData) -> FrameData:
        stars = frame.stars
        if stars is None or stars.n == 0:
            return frame.evolve()
        p = self.params
        xc, yc, tc, ok = time_domain_correct(stars.x, stars.y, stars.vx, stars.vy, stars.t_ns, frame.t0_ns,
                                             self.context.timing, p.reference_row, p.variant, p.spot_rows)
        flags = frame.flags + ((f"time_domain_no_velocity:{int((~ok).sum())}",) if not ok.all() else ())
        return frame.evolve(stars=stars.with_columns(x=xc, y=yc, t_ns=tc), flags=flags)
