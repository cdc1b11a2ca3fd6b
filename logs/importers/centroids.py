"""Import a centroid table (CSV: frame, time, x, y, flux, ...) as a centroid-level recording.

One row per star detection. Required columns: ``frame`` (integer, non-decreasing, the rows of one
frame contiguous), ``t_ns`` (integer ns) or ``time_s`` (seconds), or ``t_unix_ns``/``time_unix_s``
for times stated to be Unix time, the frame's time ``t0`` (exposure
start of row 0: the same on every row of a frame and strictly increasing from frame to frame),
``x``, ``y`` (px, column and row, pixel centres at integers with (0, 0) the first pixel), ``flux``
(ADU above background; an empty cell means unknown). Optional: ``sigma_px``, ``snr``, ``peak``
(floats, empty = unknown), ``npix`` (integer), ``saturated`` (1/0, true/false), ``catalog_id``
(integer, -1 or empty = unidentified) with ``ra_deg``, ``dec_deg`` (ICRS direction of the
identified star) and ``magnitude``; ``cov_xx, cov_xy, cov_yy`` (the 2 x 2 position covariance,
px^2, all three or none; a row's cells all empty = unknown, else positive definite). Other
columns are ignored with a warning.

Each star's ``t_ns`` is the mid-exposure of its own row and ``row_time_ns`` its row's exposure
start (:class:`~rollingstar.sensors.timing.DetectorTiming` of the camera's shutter), as for simulated
centroids. Frames whose stars all carry a catalogue id are treated as already identified by
``rollingstar run``.
"""
from __future__ import annotations

from datetime import datetime
from pathlib import Path

import numpy as np
import yaml
from pydantic import ValidationError

from rollingstar.config import format_validation_error, to_yaml
from rollingstar.logs.importers.common import (
    TIME_COLUMNS,
    UNIX_TIME_COLUMNS,
    ImportDataError,
    WarningLog,
    bool_column,
    check_non_decreasing,
    float_column,
    import_metadata,
    int_column,
    output_path,
    read_csv,
    time_column,
)
from rollingstar.logs.importers.identified import check_identified
from rollingstar.logs.importers.observation import (
    NO_OBSERVATION,
    Observation,
    catalog_for,
    from_unix_ns,
    mean_per_frame,
    unix_looking,
)
from rollingstar.logs.importers.sidecar import CameraSpec, ObservationSpec, load_camera, scenario_for
from rollingstar.logs.records import arrays_to_stars
from rollingstar.logs.topics import TOPIC_CENTROIDS
from rollingstar.logs.writer import RECORDING, LogWriter
from rollingstar.outputs import safe_output
from rollingstar.sensors.build import build_timing
from rollingstar.sensors.conventions import radec_to_unit
from rollingstar.sensors.scenario import MAX_TIME_MS

FAST_FRAME_MS = 1.0  # frames closer than this (median) with no shutter stated get a warning: a 1 kHz star camera is rare
REQUIRED = ("frame", "x", "y", "flux")
COVARIANCE = ("cov_xx", "cov_xy", "cov_yy")
OPTIONAL = ("sigma_px", "snr", "peak", "npix", "saturated", "catalog_id", "ra_deg", "dec_deg", "magnitude", *COVARIANCE)


def read_centroid_table(path: str | Path, camera: CameraSpec, log: WarningLog | None = None) -> dict[str, np.ndarray]:
    """Validated columns of a centroid CSV (see module docstring), with ``lines``, the file line of
    each row (for messages); errors name file, line and column."""
    log = log or WarningLog()
    table = read_csv(path, required=REQUIRED, optional=OPTIONAL, one_of=[TIME_COLUMNS + UNIX_TIME_COLUMNS], log=log)
    if table.n == 0:
        raise ImportDataError(f"{table.path}: no data rows after the header")
    frame = int_column(table, "frame")
    bad = np.flatnonzero(frame < 0)
    if bad.size:
        raise ImportDataError(f"{table.where(int(bad[0]), 'frame')}: {frame[bad[0]]} is negative; frames are 0-based")
    check_non_decreasing(table, frame, "frame")
    t, tname, starts = _frame_times(table, frame)
    _check_frame_spacing(table, frame, t, starts, tname, camera, log)
    cols: dict[str, np.ndarray] = {"frame": frame, "t0_ns": t, "time_column": np.asarray(tname),
                                   "lines": table.lines,
                                   "x": float_column(table, "x"), "y": float_column(table, "y"),
                                   "flux": float_column(table, "flux", required=False)}
    w, h = camera.width_px, camera.height_px
    for name, size in (("x", w), ("y", h)):
        out = np.flatnonzero((cols[name] < -0.5) | (cols[name] > size - 0.5))
        if out.size:
            i = int(out[0])
            raise ImportDataError(f"{table.where(i, name)}: {cols[name][i]} is outside the detector "
                                  f"[-0.5, {size - 0.5}] of the {w}x{h} camera")
    _check_repeated_stars(table, frame, cols["x"], cols["y"])
    flux = cols["flux"][np.isfinite(cols["flux"])]
    if flux.size and not (flux > 0).any():
        log(f"{table.path}: column 'flux' holds no positive value; identifiers rank stars by flux (brightest "
            "first), so every star is equal to them: a column of magnitudes, or a background-subtracted sum gone wrong?")
    for name in ("sigma_px", "snr", "peak", "magnitude"):
        if name in table.columns:
            cols[name] = float_column(table, name, required=False)
    bad_sigma = np.flatnonzero(cols["sigma_px"] <= 0) if "sigma_px" in cols else []
    if len(bad_sigma):
        i = int(bad_sigma[0])
        raise ImportDataError(f"{table.where(i, 'sigma_px')}: {cols['sigma_px'][i]}; a position uncertainty is "
                              "> 0 px (leave the cell empty when it is unknown)")
    cols.update(_covariance_columns(table))
    if "cov_xx" in cols:  # a star's stated covariance also states its sigma (sqrt(trace / 2)) where no sigma_px does
        from_cov = np.sqrt(0.5 * (cols["cov_xx"] + cols["cov_yy"]))
        cols["sigma_px"] = np.where(np.isfinite(cols["sigma_px"]), cols["sigma_px"], from_cov) if "sigma_px" in cols \
            else from_cov
    if "npix" in table.columns:
        cols["npix"] = int_column(table, "npix", default=0)
    if "saturated" in table.columns:
        cols["saturated"] = bool_column(table, "saturated")
    cols.update(_catalogue_columns(table))
    return cols


def _frame_times(table, frame: np.ndarray) -> tuple[np.ndarray, str, np.ndarray]:
    """The time column (ns), its name and each frame's first row: the time is the frame's t0, equal
    within a frame and strictly increasing between frames."""
    t, tname = time_column(table)
    new = np.r_[True, frame[1:] != frame[:-1]]
    same = np.flatnonzero(~new & np.r_[False, t[1:] != t[:-1]])
    if same.size:
        i = int(same[0])
        raise ImportDataError(f"{table.where(i, tname)}: {t[i]} differs from {t[i - 1]} on line "
                              f"{int(table.lines[i - 1])} of the same frame {frame[i]}; the time column is the "
                              "frame time t0 (exposure start of row 0), one value per frame")
    starts = np.flatnonzero(new)
    for a, b in zip(starts[:-1], starts[1:]):
        if t[b] <= t[a]:
            raise ImportDataError(f"{table.where(int(b), tname)}: frame {frame[b]} at {t[b]} ns is not after frame "
                                  f"{frame[a]} at {t[a]} ns (line {int(table.lines[a])}); frame times must increase "
                                  "strictly")
    return t, tname, starts


def _catalogue_columns(table) -> dict[str, np.ndarray]:
    """``catalog_id`` and ``ref_icrs`` (unit ICRS vectors from ``ra_deg``, ``dec_deg``) when the
    table identifies its stars; empty when it has no ``catalog_id``."""
    has_id = "catalog_id" in table.columns
    has_dir = ("ra_deg" in table.columns, "dec_deg" in table.columns)
    if any(has_dir) and not (all(has_dir) and has_id):
        raise ImportDataError(f"{table.path}: ra_deg and dec_deg go together, with catalog_id")
    if not has_id:
        return {}
    ids = int_column(table, "catalog_id", default=-1)
    if (ids < -1).any():
        i = int(np.flatnonzero(ids < -1)[0])
        raise ImportDataError(f"{table.where(i, 'catalog_id')}: {ids[i]}; ids are >= 0, or -1 for unidentified")
    ref = np.full((table.n, 3), np.nan)
    if all(has_dir):
        ra = float_column(table, "ra_deg", required=False)
        dec = float_column(table, "dec_deg", required=False)
        known = np.isfinite(ra) & np.isfinite(dec)
        need = np.flatnonzero((ids >= 0) & ~known)
        if need.size:
            i = int(need[0])
            raise ImportDataError(f"{table.where(i, 'ra_deg')}: identified star (catalog_id {ids[i]}) without "
                                  "ra_deg/dec_deg")
        badd = np.flatnonzero(known & (np.abs(dec) > 90))
        if badd.size:
            i = int(badd[0])
            raise ImportDataError(f"{table.where(i, 'dec_deg')}: {dec[i]} is not in [-90, 90]")
        sel = (ids >= 0) & known
        ref[sel] = radec_to_unit(np.radians(ra[sel]), np.radians(dec[sel]))
    elif (ids >= 0).any():
        raise ImportDataError(f"{table.path}: catalog_id given without ra_deg, dec_deg: the catalogue "
                              "direction of an identified star is needed")
    return {"catalog_id": ids, "ref_icrs": ref}


def import_centroids(csv: str | Path, out: str | Path, camera: CameraSpec | str | Path,
                     observation_time: datetime | str | None = None, catalog: dict | None = None) -> Path:
    """Import the centroid table ``csv`` into the recording ``out`` with ``camera``; returns ``out``.

    ``observation_time`` (ISO 8601 with its zone) and ``catalog`` (``{epoch_year, magnitude_limit}``)
    play the part of the image sidecar's keys of those names; without them the observation time
    comes from a Unix-time column (``t_unix_ns``, ``time_unix_s``), the catalogue depth from the
    camera's field and the detections per frame (:mod:`rollingstar.logs.importers.observation`).
    """
    csv = Path(csv)
    out = output_path(out)
    if camera is None:
        raise ImportDataError(f"{csv}: a camera is needed (--camera camera.yaml)")
    cam = camera if isinstance(camera, CameraSpec) else load_camera(camera)
    spec = _observation_spec(observation_time, catalog)
    log = WarningLog()
    cols = read_centroid_table(csv, cam, log)
    frame = cols["frame"]
    starts = np.flatnonzero(np.r_[True, frame[1:] != frame[:-1]])
    ends = np.r_[starts[1:], frame.size]
    counts = ends - starts
    lonely = np.flatnonzero(counts < 2)
    if lonely.size:
        first = int(starts[lonely[0]])
        log(f"{csv}: {lonely.size} of {counts.size} frames hold a single star (the first: frame {frame[first]}, "
            f"line {int(cols['lines'][first])}); an attitude needs at least 2 stars, so those frames get no estimate")
    if "catalog_id" in cols:
        _check_identification(cols, starts, ends, cam, csv)
    t0s = cols["t0_ns"][starts]
    period = float(np.median(np.diff(t0s))) * 1e-6 if t0s.size > 1 else None
    column = str(cols.pop("time_column"))
    cols.pop("lines")
    observation = (Observation(spec.observation_time, "observation_time") if spec.observation_time is not None
                   else from_unix_ns(int(t0s[0]), column, str(csv)) if column in UNIX_TIME_COLUMNS else NO_OBSERVATION)
    catalog_cfg, catalog_details = catalog_for(
        cam, spec, observation, log, source=str(csv), detections_per_frame=mean_per_frame(ends - starts),
        unix_hint=unix_looking(t0s) if observation.time is None else None)
    scenario = scenario_for(cam, name=f"import:{csv.stem}", description=f"centroids imported from {csv}",
                            level="centroid", frames=starts.size, frame_period_ms=period, catalog=catalog_cfg)
    timing = build_timing(scenario)
    details = {"frames": int(starts.size), "stars": int(frame.size), "camera": cam.model_dump(mode="json"),
               "focal_px": cam.focal_px, "time_column": column, "catalog": catalog_details,
               "columns": sorted(k for k in cols if k not in ("t0_ns",))}
    metadata = {"scenario": {"yaml": to_yaml(scenario)},
                "sensor": {"yaml": yaml.safe_dump(cam.model_dump(mode="json"), sort_keys=False)},
                "import": import_metadata("centroids", csv, details, log)}
    star_cols = [k for k in ("flux", "sigma_px", "snr", "peak", "npix", "saturated", "catalog_id", "ref_icrs",
                             "magnitude", *COVARIANCE) if k in cols]
    inputs = [csv, *([camera] if isinstance(camera, (str, Path)) else [])]
    with safe_output(out, inputs, replaces=RECORDING) as tmp, LogWriter(tmp, kind="import", metadata=metadata) as writer:
        for a, b in zip(starts, ends):
            t0 = int(cols["t0_ns"][a])
            y = cols["y"][a:b]
            writer.write_json(TOPIC_CENTROIDS, arrays_to_stars(
                int(frame[a]), t0, x=cols["x"][a:b], y=y, t_ns=timing.row_mid_exposure_ns(t0, y),
                row_time_ns=timing.row_start_ns(t0, y), **{k: cols[k][a:b] for k in star_cols}), t0)
    return out


def _check_identification(cols: dict, starts: np.ndarray, ends: np.ndarray, cam: CameraSpec, csv: Path) -> None:
    """Every frame's identified stars against their catalogue directions (:mod:`.identified`)."""
    cx, cy = cam.principal_point_px or ((cam.width_px - 1) / 2.0, (cam.height_px - 1) / 2.0)
    for a, b in zip(starts, ends):
        known = cols["catalog_id"][a:b] >= 0
        where = f"{csv}: frame {cols['frame'][a]} (line {int(cols['lines'][a])})"
        check_identified(cols["x"][a:b][known], cols["y"][a:b][known], cols["ref_icrs"][a:b][known], cam.focal_px,
                         cx, cy, where)


def _check_frame_spacing(table, frame: np.ndarray, t: np.ndarray, starts: np.ndarray, tname: str,
                         camera: CameraSpec, log: WarningLog) -> None:
    """Refuse frame times closer together than the camera can take frames.

    Every row's exposure (when the camera file states its shutter) and the readout of all rows of a
    rolling shutter fit between consecutive frame times. Times written in another unit than the
    column's name says (microseconds or milliseconds in ``t_ns``) come out hundreds of times too
    close and fail here, instead of being read as a very fast camera; nanoseconds in ``time_s`` come
    out more than the sensor model's hour apart. The median spacing must reach that minimum, as the
    sensor model requires; a single spacing may fall short by up to half of it (timestamp jitter of
    a camera that exposes for its whole frame period). A camera file without a shutter states no
    minimum: frames less than ``FAST_FRAME_MS`` apart (median) then get a warning, since
    microseconds written in ``t_ns`` look like such a camera.
    """
    if starts.size < 2:
        return
    sh = camera.shutter
    readout_ns = (camera.height_px - 1) * sh.line_delay_us * 1e3 if sh.mode == "rolling" else 0.0
    exposure_ns = sh.exposure_ms * 1e6 if "shutter" in camera.model_fields_set else 0.0
    need = max(readout_ns, exposure_ns)
    gaps = np.diff(t[starts])
    unit = "integer nanoseconds" if tname.endswith("_ns") else "seconds"
    if np.median(gaps) > MAX_TIME_MS * 1e6:
        raise ImportDataError(f"{table.where(int(starts[1]), tname)}: the frames are {np.median(gaps) * 1e-9:g} s "
                              f"apart (median), more than the sensor model's limit of one hour; the column {tname} "
                              f"is read as {unit}: check that the times are in that unit")
    if not need and np.median(gaps) < FAST_FRAME_MS * 1e6:
        log(f"{table.where(int(starts[1]), tname)}: the frames are {np.median(gaps) * 1e-6:g} ms apart (median), "
            f"faster than star cameras commonly run ({1e3 / FAST_FRAME_MS:g} Hz), and the camera file states no "
            f"shutter to check them against; the column {tname} is read as {unit}: if the times are in another "
            "unit, the rolling-shutter timing and every rate will be off by the same factor")
    bad = np.flatnonzero(gaps < (need if np.median(gaps) < need else need / 2))
    if not bad.size:
        return
    k = int(bad[0])
    a, b = int(starts[k]), int(starts[k + 1])
    what = (f"exposure (shutter.exposure_ms {sh.exposure_ms:g})" if exposure_ns >= readout_ns else
            f"readout ((height_px - 1) x shutter.line_delay_us = {readout_ns * 1e-6:g} ms)")
    raise ImportDataError(f"{table.where(b, tname)}: frame {frame[b]} is {gaps[k] * 1e-6:g} ms after frame "
                          f"{frame[a]} (line {int(table.lines[a])}), less than the camera's {what}; the column "
                          f"{tname} is read as {unit}: check that the times are in that unit")


def _check_repeated_stars(table, frame: np.ndarray, x: np.ndarray, y: np.ndarray) -> None:
    """Refuse two rows of one frame at the same position: one detection written twice would count
    as two stars (double weight, and two stars for the identifier to match)."""
    if frame.size < 2:
        return
    order = np.lexsort((y, x, frame))
    same = np.flatnonzero((np.diff(frame[order]) == 0) & (np.diff(x[order]) == 0) & (np.diff(y[order]) == 0))
    if not same.size:
        return
    pairs = np.sort(np.stack([order[same], order[same + 1]], axis=1), axis=1)
    i, j = (int(v) for v in pairs[np.argmin(pairs[:, 1])])  # the repeat that comes first in the file
    raise ImportDataError(f"{table.where(j, 'x')}: the star at ({x[j]:g}, {y[j]:g}) repeats line "
                          f"{int(table.lines[i])} of the same frame {frame[j]}; each row is one detection "
                          "(remove the repeated row)")


def _observation_spec(observation_time, catalog) -> ObservationSpec:
    """The ``observation_time`` and ``catalog`` arguments, checked as the sidecar keys of those names."""
    try:
        return ObservationSpec.model_validate({"observation_time": observation_time, "catalog": catalog or {}})
    except ValidationError as err:
        raise ImportDataError(format_validation_error("import_centroids", err)) from None


def _covariance_columns(table) -> dict[str, np.ndarray]:
    """The optional ``cov_xx, cov_xy, cov_yy`` columns (px^2): all three or none, each row either
    all empty (unknown) or a positive-definite 2 x 2 matrix; errors name line and column."""
    present = [c for c in COVARIANCE if c in table.columns]
    if not present:
        return {}
    if len(present) < 3:
        raise ImportDataError(f"{table.path}: {', '.join(present)} without {', '.join(c for c in COVARIANCE if c not in present)}"
                              "; the position covariance needs cov_xx, cov_xy and cov_yy")
    xx, xy, yy = (float_column(table, c, required=False) for c in COVARIANCE)
    known = np.isfinite(np.stack([xx, xy, yy]))
    partial = np.flatnonzero(known.any(axis=0) & ~known.all(axis=0))
    if partial.size:
        i = int(partial[0])
        raise ImportDataError(f"{table.where(i, COVARIANCE[int(np.argmin(known[:, i]))])}: empty while the row's other "
                              "covariance cells are given; fill all three or leave all three empty")
    with np.errstate(invalid="ignore"):
        bad = np.flatnonzero(known.all(axis=0) & ~((xx > 0) & (yy > 0) & (xx * yy - xy * xy > 0)))
    if bad.size:
        i = int(bad[0])
        raise ImportDataError(f"{table.where(i, 'cov_xx')}: [[{xx[i]}, {xy[i]}], [{xy[i]}, {yy[i]}]] is not a "
                              "position covariance (positive definite, px^2)")
    return dict(zip(COVARIANCE, (xx, xy, yy)))
