"""Locate a mismatch: chi-square against the recording's noise and residual structure by covariate.

Residuals ``r_i = (x_i - x_model, y_i - y_model)`` after the per-frame attitude refit are
normalised by the recording's centroid sigma. Under the model they are N(0, 1) per axis, so

- ``chi2 / dof`` with ``dof = 2 n - 3 F`` (three attitude angles per frame) is 1 within
  ``sqrt(2 / dof)``;
- for a covariate ``c`` (field position, row, image speed, magnitude, pixel phase, time, ...) the
  residuals binned in quantiles of ``c`` have weighted bin means ``m_b`` with variance ``1 / W_b``;
  ``sum_b W_b (m_b - m)^2`` is chi-square with ``B - 1`` dof when the residual does not depend on
  ``c``. Its p-value, as a one-sided normal z, ranks where the mismatch concentrates;
- the per-frame mean residual has lag-1 autocorrelation ``rho`` with ``rho sqrt(F) ~ N(0, 1)``
  (whiteness over time).
"""
from __future__ import annotations

import numpy as np
from scipy import stats

from rollingstar.estimators.diagnosis.observations import whitened_residuals
from rollingstar.sensors.conventions import S_PER_NS

N_BINS = 8
GRID = 3
STRUCTURE_Z = 4.0  # 36 covariate x channel tests: the largest null z rarely exceeds 3.5


def z_from_sf(p: np.ndarray | float) -> np.ndarray | float:
    """One-sided normal z of an upper-tail probability (capped at 40 for p below 1e-300)."""
    return np.minimum(stats.norm.isf(np.clip(p, 1e-300, 1.0)), 40.0)


def normalised(obs, pred) -> np.ndarray:
    """Residuals in units of their sigma (whitened by their 2 x 2 covariance when the stars carry one), (n, 2)."""
    return whitened_residuals(obs, pred)


def chi2_stats(obs, pred, mask, n_params: int) -> dict:
    """Chi-square, dof, chi2/dof, its z against 1 (:func:`chi2_z`) and the RMS residual (px) over ``mask``."""
    r = normalised(obs, pred)[mask]
    chi2 = float(np.sum(r**2))
    dof = max(int(2 * r.shape[0] - n_params), 1)
    rms = float(np.sqrt(np.mean((obs.x[mask] - pred.x[mask]) ** 2 + (obs.y[mask] - pred.y[mask]) ** 2) / 2)) if r.size else float("nan")
    return {"chi2": chi2, "dof": dof, "chi2_dof": chi2 / dof, "z": chi2_z(chi2, dof, obs.noise_sigma_ln), "rms_px": rms}


def chi2_z(chi2: float, dof: int, scale_sigma_ln: float = 0.0) -> float:
    """One-sided z of ``chi2`` against ``dof``. When the noise scale was measured (standard error
    ``scale_sigma_ln`` of its log), a chi-square of ``dof`` terms is off by ``2 scale_sigma_ln dof``
    (1 sigma) on top of its own ``sqrt(2 dof)``: the z is then the smaller of the exact one and
    the normal approximation with both spreads."""
    z = float(z_from_sf(stats.chi2.sf(chi2, dof)))
    if scale_sigma_ln > 0.0:
        z = min(z, (chi2 - dof) / float(np.sqrt(2.0 * dof + (2.0 * scale_sigma_ln * dof) ** 2)))
    return z


def covariates(obs, pred, camera) -> dict[str, np.ndarray]:
    """The covariates residual structure is tested against (per observation)."""
    rx, ry = pred.x - camera.cx, pred.y - camera.cy
    return {
        "field_x": pred.x,
        "field_y": pred.y,
        "field_radius": np.hypot(rx, ry),
        "row (exposure time)": obs.y,
        "image_speed": np.hypot(pred.vx, pred.vy),
        "magnitude": obs.magnitude,
        "pixel_phase_x": obs.x - np.round(obs.x),
        "pixel_phase_y": obs.y - np.round(obs.y),
        "time": (obs.t_ns - obs.t_ns.min()).astype(float) * S_PER_NS if obs.n else np.zeros(0),
    }


def channels(obs, pred, camera) -> dict[str, np.ndarray]:
    """Residual channels: x, y, and radial/tangential about the principal point (normalised)."""
    r = normalised(obs, pred)
    dx, dy = pred.x - camera.cx, pred.y - camera.cy
    rad = np.hypot(dx, dy)
    ex, ey = np.where(rad > 0, dx / np.where(rad > 0, rad, 1), 1.0), np.where(rad > 0, dy / np.where(rad > 0, rad, 1), 0.0)
    return {"x": r[:, 0], "y": r[:, 1], "radial": r[:, 0] * ex + r[:, 1] * ey, "tangential": -r[:, 0] * ey + r[:, 1] * ex}


def binned_structure(value: np.ndarray, resid: np.ndarray, n_bins: int = N_BINS) -> dict:
    """Chi-square of quantile-bin means of unit-variance ``resid`` against ``value`` (module doc)."""
    ok = np.isfinite(value) & np.isfinite(resid)
    v, r = value[ok], resid[ok]
    if v.size < 2 * n_bins or np.ptp(v) == 0:
        return {"chi2": 0.0, "dof": 0, "z": 0.0, "bin_centres": [], "bin_means": [], "bin_sigma": []}
    edges = np.unique(np.quantile(v, np.linspace(0, 1, n_bins + 1)))
    if edges.size < 3:
        return {"chi2": 0.0, "dof": 0, "z": 0.0, "bin_centres": [], "bin_means": [], "bin_sigma": []}
    b = np.clip(np.searchsorted(edges, v, side="right") - 1, 0, edges.size - 2)
    nb = edges.size - 1
    cnt = np.bincount(b, minlength=nb).astype(float)
    sums = np.bincount(b, weights=r, minlength=nb)
    cen = np.bincount(b, weights=v, minlength=nb)
    good = cnt > 0
    means = sums[good] / cnt[good]
    mean_all = r.mean()
    chi2 = float(np.sum(cnt[good] * (means - mean_all) ** 2))
    dof = int(good.sum() - 1)
    z = float(z_from_sf(stats.chi2.sf(chi2, dof))) if dof > 0 else 0.0
    return {"chi2": chi2, "dof": dof, "z": z, "bin_centres": (cen[good] / cnt[good]).tolist(),
            "bin_means": means.tolist(), "bin_sigma": (1.0 / np.sqrt(cnt[good])).tolist()}


def whiteness(obs, resid: np.ndarray, mask) -> dict:
    """Lag-1 autocorrelation of the per-frame mean residual (x and y) and its z = rho sqrt(F)."""
    f = obs.n_frames
    out = {}
    for k, name in enumerate("xy"):
        cnt = np.bincount(obs.frame[mask], minlength=f)
        s = np.bincount(obs.frame[mask], weights=resid[mask, k], minlength=f)
        m = s[cnt > 0] / cnt[cnt > 0]
        if m.size < 3 or np.std(m) == 0:
            out[name] = {"lag1": 0.0, "z": 0.0}
            continue
        m = m - m.mean()
        rho = float(np.sum(m[1:] * m[:-1]) / np.sum(m * m))
        out[name] = {"lag1": rho, "z": float(rho * np.sqrt(m.size))}
    return out


def region_grid(obs, pred, camera, mask, grid: int = GRID) -> list[dict]:
    """Chi-square per dof (two axes per star) in a ``grid`` x ``grid`` partition of the detector."""
    r = normalised(obs, pred)[mask]
    gx = np.clip((pred.x[mask] + 0.5) / camera.width * grid, 0, grid - 1e-9).astype(int)
    gy = np.clip((pred.y[mask] + 0.5) / camera.height * grid, 0, grid - 1e-9).astype(int)
    cell = gy * grid + gx
    c2 = np.bincount(cell, weights=np.sum(r**2, axis=1), minlength=grid * grid)
    cnt = np.bincount(cell, minlength=grid * grid)
    return [{"col": int(i % grid), "row": int(i // grid), "n": int(cnt[i]),
             "chi2_per_axis": float(c2[i] / (2 * cnt[i])) if cnt[i] else None} for i in range(grid * grid)]


def time_spans(obs, pred, mask, n_spans: int = 5) -> list[dict]:
    """Chi-square per axis in ``n_spans`` equal spans of frames (where in time it concentrates)."""
    r = normalised(obs, pred)
    f = obs.n_frames
    span = np.minimum(obs.frame * n_spans // max(f, 1), n_spans - 1)
    c2 = np.bincount(span[mask], weights=np.sum(r[mask] ** 2, axis=1), minlength=n_spans)
    cnt = np.bincount(span[mask], minlength=n_spans)
    return [{"span": i, "frames": [int(i * f // n_spans), int(max((i + 1) * f // n_spans - 1, i * f // n_spans))],
             "n": int(cnt[i]), "chi2_per_axis": float(c2[i] / (2 * cnt[i])) if cnt[i] else None} for i in range(n_spans)]


def locate(obs, pred, camera, mask, n_params: int) -> dict:
    """Everything the Locate step reports (module doc): chi2, structure by covariate and channel."""
    covs = covariates(obs, pred, camera)
    chans = channels(obs, pred, camera)
    structure = []
    for cname, cval in covs.items():
        for chname, chval in chans.items():
            s = binned_structure(cval[mask], chval[mask])
            structure.append({"covariate": cname, "channel": chname, **s})
    structure.sort(key=lambda s: -s["z"])
    strongest = structure[0] if structure else None
    ch = chi2_stats(obs, pred, mask, n_params)
    per_axis = {name: float(np.mean(chans[name][mask] ** 2)) for name in ("x", "y")}
    grid = region_grid(obs, pred, camera, mask)
    worst = max((g for g in grid if g["chi2_per_axis"] is not None), key=lambda g: g["chi2_per_axis"], default=None)
    spans = time_spans(obs, pred, mask)
    worst_span = max((s for s in spans if s["chi2_per_axis"] is not None), key=lambda s: s["chi2_per_axis"], default=None)
    return {
        **ch,
        "strongest_covariate": None if strongest is None or strongest["z"] < STRUCTURE_Z else strongest["covariate"],
        "strongest_channel": None if strongest is None or strongest["z"] < STRUCTURE_Z else strongest["channel"],
        "strongest_z": 0.0 if strongest is None else strongest["z"],
        "chi2_per_axis": per_axis,
        "whiteness": whiteness(obs, normalised(obs, pred), mask),
        "worst_region": worst,
        "regions": grid,
        "worst_time_span": worst_span,
        "structure": [{k: s[k] for k in ("covariate", "channel", "chi2", "dof", "z")} for s in structure],
        "_structure_full": structure,
    }
