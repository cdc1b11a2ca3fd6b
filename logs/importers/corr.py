"""Import astrometry.net ``corr`` tables (+ ``log.json``) as a centroid-level, already-identified recording.

Input: a folder holding one astrometry.net ``*.fits`` corr table and a ``log.json`` (field of
view, image size, pointing centre), or a folder of such folders (searched recursively). Output:
one recording with one frame per corr table, in sorted folder order, ``t0_k = k * 1 s`` (the
log.json times are local wall-clock strings with no zone, kept in the metadata only).
Each frame's ``/camera/centroids`` message holds the matched stars: ``x = field_x - 1``,
``y = field_y - 1`` (astrometry.net uses FITS pixel coordinates, first pixel centre at 1; checked
on the creusot images, where intensity centroids sit 1.0 px below ``field_x, field_y``),
``catalog_id = index_id`` (the star's id in the astrometry.net index, not a HIP number),
``ref_icrs`` the unit vector of ``(index_ra, index_dec)`` (fu2022 eq 1), ``flux = FLUX``.
Since every star is identified, ``rollingstar run`` skips identifier stages on these frames and
an attitude solver (``quest``) solves each image directly.

Camera: a pinhole with its principal point at the image centre and the focal length in pixels
``f = hypot(W, H) / fov`` (``fov`` in radians): log.json's ``fov_deg`` is astrometry.net's
diagonal field at its central pixel scale (``fov = diagonal_px * scale``), not ``2 atan``. On
the eleven 16 mm creusot scenes (``16mm_checker_2``) the focal length fitted to the star pairs'
angles differs from this rule by 0.001-0.24 %, and from the ``2 atan`` reading by 0.58-0.82 %
(``pytest tests/logs/test_importers.py -k linear_diagonal``).
All frames of one recording share the camera: image sizes must be equal and the fields of view
within 1 % of each other (the median is used); otherwise import the sub-folders separately.
"""
from __future__ import annotations

import json
import math
import os
import re
import warnings
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any, Callable

import numpy as np
import yaml
from pydantic import ConfigDict, Field, ValidationError
from scipy.spatial.transform import Rotation

from rollingstar.config import NoBooleanNumbers, format_validation_error, to_yaml
from rollingstar.logs.importers.common import (
    ImportDataError,
    ImportDataWarning,
    WarningLog,
    import_metadata,
    output_path,
)
from rollingstar.logs.importers.corr_checks import (
    check_centre,
    check_positions,
    check_scale,
    residual_of,
    unique_rows,
)
from rollingstar.logs.importers.identified import check_identified
from rollingstar.logs.importers.images import read_image
from rollingstar.logs.importers.observation import NO_OBSERVATION, catalog_for, mean_per_frame
from rollingstar.logs.importers.sidecar import (
    NOMINAL_PIXEL_SIZE_UM,
    CameraSpec,
    ObservationSpec,
    scenario_for,
)
from rollingstar.logs.reader import LogReader
from rollingstar.logs.records import arrays_to_stars
from rollingstar.logs.topics import TOPIC_CENTROIDS, TOPIC_EST_ATTITUDE
from rollingstar.logs.writer import RECORDING, LogWriter
from rollingstar.outputs import safe_output
from rollingstar.sensors.build import build_timing
from rollingstar.sensors.conventions import quat_from_fields, radec_roll_from_attitude, radec_to_unit
from rollingstar.sensors.scenario import AttitudeConfig

FRAME_SPACING_NS = 1_000_000_000
FOV_TOLERANCE = 0.01
"""Largest relative spread of log.json fields of view within one recording (one camera)."""
REQUIRED_COLUMNS = ("field_x", "field_y", "index_ra", "index_dec")
TABLE_SUFFIXES = (".fits", ".fit", ".fts", ".corr")  # astrometry.net's solve-field names its table <image>.corr
IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg", ".tif", ".tiff")  # the solved image beside a corr table (its FITS is the table)
STAR_CONTRAST = 5.0  # robust sigmas above the background at the median star for an image to be the solved one
EPOCH_REASON = ("the scenario default: log.json's dates are not read (local wall-clock time of no stated zone, "
                "day and month order not stated), and the stars carry astrometry.net's catalogue directions")


class _Size(NoBooleanNumbers):
    model_config = ConfigDict(extra="allow")
    x: int = Field(gt=0, description="image width, px")
    y: int = Field(gt=0, description="image height, px")


class _Centre(NoBooleanNumbers):
    model_config = ConfigDict(extra="allow")
    ra_degrees: float = Field(ge=-360, le=360)
    dec_degrees: float = Field(ge=-90, le=90)


class LogJson(NoBooleanNumbers):
    """The fields of a creusot/astrometry.net ``log.json`` that the importer uses (others are kept)."""

    model_config = ConfigDict(extra="allow", allow_inf_nan=False)
    fov_deg: float = Field(gt=0, lt=180, description="diagonal field of view at the central pixel scale, deg")
    image_size: _Size
    center: _Centre
    timestamp: Any = None  # kept in the metadata as given, whatever its form (not read: EPOCH_REASON)


# field path -> regex for the salvage of a malformed file: each must match exactly once.
_SALVAGE = {
    "fov_deg": r'"fov_deg"\s*:\s*(-?[0-9.eE+-]+)',
    "image_size.x": r'"image_size"\s*:\s*\{[^{}]*?"x"\s*:\s*(-?[0-9.eE+-]+)',
    "image_size.y": r'"image_size"\s*:\s*\{[^{}]*?"y"\s*:\s*(-?[0-9.eE+-]+)',
    "center.ra_degrees": r'"ra_degrees"\s*:\s*(-?[0-9.eE+-]+)',
    "center.dec_degrees": r'"dec_degrees"\s*:\s*(-?[0-9.eE+-]+)',
    "timestamp.date": r'"date"\s*:\s*"([^"]*)"',
    "timestamp.time": r'"time"\s*:\s*"([^"]*)"',
}


def _set(d: dict, path: str, value) -> None:
    head, _, tail = path.partition(".")
    if tail:
        _set(d.setdefault(head, {}), tail, value)
    else:
        d[head] = value


def _repair_commas(text: str) -> tuple[dict | None, list[str]]:
    """Insert the ',' the JSON decoder asks for, as long as that is the only problem (at most 20)."""
    notes = []
    for _ in range(20):
        try:
            return json.loads(text), notes
        except json.JSONDecodeError as exc:
            if exc.msg != "Expecting ',' delimiter":
                return None, notes
            notes.append(f"line {exc.lineno}, column {exc.colno}: missing ',' inserted")
            text = text[:exc.pos] + "," + text[exc.pos:]
    return None, notes


def _pairs(path: Path, log: WarningLog):
    """A ``json.loads`` object hook that says when a key is given twice (the last value is taken)."""
    def hook(pairs: list) -> dict:
        keys = [k for k, _ in pairs]
        twice = sorted({k for k in keys if keys.count(k) > 1})
        if twice:
            log(f"{path}: key(s) {', '.join(map(repr, twice))} given more than once in one object; the last value is used")
        return dict(pairs)
    return hook


def read_log_json(path: str | Path, log: WarningLog | None = None) -> LogJson:
    """Parse a log.json; recover a malformed file where that is unambiguous, else fail naming the field.

    Recovery, in order: (1) valid JSON; (2) only missing commas between members (each inserted
    where the decoder expects one, reported with its line and column); (3) field by field: a
    field is recovered when its ``"key": value`` pattern occurs exactly once. A required field
    that cannot be recovered raises ImportDataError naming the file and the field.
    """
    path = Path(path)
    log = log or WarningLog()
    try:
        text = path.read_text(encoding="utf-8-sig")
    except FileNotFoundError:
        raise ImportDataError(f"{path}: log.json not found") from None
    except UnicodeDecodeError as exc:  # an editor's legacy encoding: every byte is a Latin-1 character
        text = path.read_bytes().decode("latin-1")
        log(f"{path}: not UTF-8 (byte {exc.start}); read as Latin-1")
    data = None
    try:
        data = json.loads(text, object_pairs_hook=_pairs(path, log))
    except json.JSONDecodeError as exc:
        first_error = f"line {exc.lineno}, column {exc.colno}: {exc.msg}"
        data, notes = _repair_commas(text)
        if data is not None:
            log(f"{path}: not valid JSON ({first_error}); recovered: {'; '.join(notes)}")
        else:
            data, recovered, problems = {}, [], []
            for field, pattern in _SALVAGE.items():
                found = re.findall(pattern, text)
                if len(found) == 1:
                    value = found[0]
                    if not field.startswith("timestamp"):
                        try:
                            value = float(value)
                        except ValueError:
                            problems.append(f"{field}: {value!r} is not a number")
                            continue
                        if field.startswith("image_size"):
                            if value != int(value):
                                problems.append(f"{field}: {value!r} is not an integer")
                                continue
                            value = int(value)
                    _set(data, field, value)
                    recovered.append(field)
                elif not field.startswith("timestamp"):
                    problems.append(f"{field}: {'not found' if not found else f'found {len(found)} times'}")
            if problems:
                raise ImportDataError(f"{path}: not valid JSON ({first_error}) and cannot be recovered: "
                                      + "; ".join(problems))
            log(f"{path}: not valid JSON ({first_error}); recovered field by field: {', '.join(recovered)}")
    if not isinstance(data, dict):
        raise ImportDataError(f"{path}: expected a JSON object at the top level, got {type(data).__name__}")
    try:
        return LogJson.model_validate(data)
    except ValidationError as err:
        raise ImportDataError(format_validation_error(str(path), err)) from None


@dataclass(frozen=True)
class CorrFrame:
    """One corr table, ready to write."""

    folder: Path
    fits: Path
    log_json: Path
    meta: LogJson
    x: np.ndarray
    y: np.ndarray
    ref_icrs: np.ndarray
    catalog_id: np.ndarray
    flux: np.ndarray
    residual_px: np.ndarray  # (n, 2) field - index position, NaN when index_x/y are absent
    cov: np.ndarray | None = None  # (n, 2, 2) px^2 of the stars measured again (NaN: a table position)


def find_corr_folders(root: str | Path) -> list[Path]:
    """``root`` if it holds a ``*.fits``, else every folder below it that does, in sorted order."""
    root = Path(root)
    if not root.is_dir():
        raise ImportDataError(f"{root}: not a directory (expected a folder with an astrometry.net corr "
                              "*.fits table and a log.json, or a folder of such folders)")
    folders = _table_folders(root)
    if _fits_in(root):
        below = [f for f in folders if f != root]
        if below:
            warnings.warn(ImportDataWarning(f"{root}: holds a corr table, so it is read as one image; the {len(below)} "
                                            f"folder(s) below it that hold tables ({below[0].relative_to(root)}, ...) "
                                            "are not read: import them separately"), stacklevel=2)
        return [root]
    if not folders:
        raise ImportDataError(f"{root}: no astrometry.net corr table (*.fits) in it or below it")
    return folders


def _table_folders(root: Path) -> list[Path]:
    """Every folder at or below ``root`` that holds a FITS or corr file, sorted; linked folders followed once."""
    folders, seen = [], set()
    for here, dirs, files in os.walk(root, followlinks=True):  # a folder linked in is read like any other
        real = os.path.realpath(here)
        if real in seen:  # a link back up the tree, or a second link to one folder
            dirs.clear()
            continue
        seen.add(real)
        if any(Path(f).suffix.lower() in TABLE_SUFFIXES and Path(here, f).is_file() for f in files):
            folders.append(Path(here))
    return sorted(folders, key=lambda p: p.relative_to(root).as_posix())


def _fits_in(folder: Path) -> list[Path]:
    return sorted(p for p in folder.iterdir() if p.is_file() and p.suffix.lower() in TABLE_SUFFIXES)


def _corr_table_in(folder: Path) -> Path:
    """The folder's corr table: its one FITS file, or, among several (a solve's whole output: wcs,
    rdls, axy, the image), the one whose binary table has the corr columns."""
    files = _fits_in(folder)
    if len(files) == 1:
        return files[0]
    tables = [p for p in files if _has_corr_columns(p)]
    if len(tables) == 1:
        return tables[0]
    which = "none has" if not tables else f"{len(tables)} have ({', '.join(p.name for p in tables)})"
    raise ImportDataError(f"{folder}: holds {len(files)} FITS files ({', '.join(p.name for p in files)}) and {which} "
                          f"a binary table with the corr columns {', '.join(REQUIRED_COLUMNS)}; expected one corr table "
                          "per folder")


def _has_corr_columns(path: Path) -> bool:
    """Whether the first binary table of the FITS file ``path`` has the corr columns (False when unreadable)."""
    from astropy.io import fits

    try:
        with fits.open(path, memmap=False) as hdul:
            table = next((h for h in hdul if isinstance(h, fits.BinTableHDU)), None)
            names = set() if table is None else {n.lower() for n in table.columns.names}
    except Exception:  # noqa: BLE001 - any unreadable file is simply not the table (the others say why)
        return False
    return set(REQUIRED_COLUMNS) <= names


def _json_in(folder: Path) -> Path:
    if (folder / "log.json").is_file():
        return folder / "log.json"
    found = sorted(p for p in folder.iterdir() if p.is_file() and p.suffix.lower() == ".json")
    if len(found) != 1:
        what = "none" if not found else ", ".join(p.name for p in found)
        raise ImportDataError(f"{folder}: needs a log.json (field of view, image size, pointing centre); "
                              f"found {what}")
    return found[0]


def read_corr_table(path: str | Path, log: WarningLog | None = None) -> dict[str, np.ndarray]:
    """The columns of an astrometry.net corr table (first binary-table HDU), as float/int arrays.

    Required: ``field_x, field_y, index_ra, index_dec``; optional: ``index_id, FLUX, index_x,
    index_y, match_weight``. Rows with a non-finite required value, or a catalogue direction that is
    none on the sky (``|index_dec| > 90`` or ``|index_ra| > 360`` deg), are dropped with a warning.
    """
    from astropy.io import fits  # here, not at the top: astropy takes ~0.3 s to import and only FITS tables need it

    path = Path(path)
    log = log or WarningLog()
    try:
        with fits.open(path, memmap=False) as hdul:
            table = next((h for h in hdul if isinstance(h, fits.BinTableHDU)), None)
            if table is None:
                raise ImportDataError(f"{path}: no binary table HDU (expected an astrometry.net corr table)")
            names = {n.lower(): n for n in table.columns.names}
            missing = [c for c in REQUIRED_COLUMNS if c not in names]
            if missing:
                raise ImportDataError(f"{path}: missing column(s) {', '.join(missing)} (found "
                                      f"{', '.join(table.columns.names)}; an astrometry.net corr table has "
                                      f"{', '.join(REQUIRED_COLUMNS)})")
            data = table.data
            complex_ = [n for n in table.columns.names if np.iscomplexobj(data[n])]
            if complex_:
                raise ImportDataError(f"{path}: column(s) {', '.join(complex_)} hold complex numbers; an "
                                      "astrometry.net corr table has real ones")
            cols = {c: np.asarray(data[names[c]], dtype=float) for c in REQUIRED_COLUMNS}
            for c in ("index_x", "index_y", "flux", "match_weight"):
                if c in names:
                    cols[c] = np.asarray(data[names[c]], dtype=float)
            if "index_id" in names:
                cols["index_id"] = np.asarray(data[names["index_id"]], dtype=np.int64)
    except ImportDataError:
        raise
    except FileNotFoundError:
        raise ImportDataError(f"{path}: corr table not found") from None
    except ValueError as exc:  # e.g. a column of vectors, which numpy cannot make one number per row of
        raise ImportDataError(f"{path}: a column is not one number per star ({exc}); an astrometry.net corr "
                              "table has scalar columns") from None
    except Exception as exc:  # astropy raises OSError/ValueError/TypeError for damaged files
        raise ImportDataError(f"{path}: cannot read FITS table ({type(exc).__name__}: {exc})") from None
    shaped = [c for c, v in cols.items() if v.ndim != 1]
    if shaped:
        raise ImportDataError(f"{path}: column(s) {', '.join(shaped)} hold {cols[shaped[0]].shape[1:]} values per "
                              "star; an astrometry.net corr table has one number per star in each column")
    finite = np.all([np.isfinite(cols[c]) for c in REQUIRED_COLUMNS], axis=0)
    cols = _drop_rows(cols, finite, f"a non-finite {'/'.join(REQUIRED_COLUMNS)}", path, log)
    on_sky = (np.abs(cols["index_ra"]) <= 360.0) & (np.abs(cols["index_dec"]) <= 90.0)
    return _drop_rows(cols, on_sky, "index_ra outside [-360, 360] deg or index_dec outside [-90, 90] deg", path, log)


def _drop_rows(cols: dict[str, np.ndarray], keep: np.ndarray, what: str, path: Path, log: WarningLog
               ) -> dict[str, np.ndarray]:
    """The rows of ``cols`` where ``keep``; the others are a damaged table's, dropped with a warning."""
    if keep.all():
        return cols
    rows = np.flatnonzero(~keep)
    log(f"{path}: {rows.size} row(s) with {what} dropped (rows {', '.join(map(str, rows[:10]))})")
    return {k: v[keep] for k, v in cols.items()}


def _read_frame(folder: Path, log: WarningLog) -> CorrFrame:
    fits_files = [_corr_table_in(folder)]
    json_path = _json_in(folder)
    meta = read_log_json(json_path, log)
    cols = unique_rows(read_corr_table(fits_files[0], log), fits_files[0], log)
    check_positions(cols, fits_files[0])
    n = cols["field_x"].size
    if n < 2:
        log(f"{fits_files[0]}: {n} matched star(s); an attitude needs at least 2, so this frame gets no estimate")
    x, y = cols["field_x"] - 1.0, cols["field_y"] - 1.0  # FITS 1-based pixel centres -> ours (0-based)
    w, h = meta.image_size.x, meta.image_size.y
    outside = (x < -0.5) | (y < -0.5) | (x > w - 0.5) | (y > h - 0.5)
    if outside.any():  # a damaged table: a star the image cannot hold is no measurement
        log(f"{fits_files[0]}: {int(outside.sum())} star(s) outside the {w}x{h} image of {json_path.name} dropped "
            f"(rows {', '.join(map(str, np.flatnonzero(outside)[:10]))})")
        cols = {k: v[~outside] for k, v in cols.items()}
        x, y, n = x[~outside], y[~outside], int((~outside).sum())
    ids = cols.get("index_id", np.arange(n, dtype=np.int64))
    if (ids < 0).any():
        raise ImportDataError(f"{fits_files[0]}: index_id has negative values; catalogue ids must be >= 0")
    resid = residual_of(cols, fits_files[0], math.hypot(w, h), log)
    ref = np.asarray(radec_to_unit(np.radians(cols["index_ra"]), np.radians(cols["index_dec"]))).reshape(n, 3)
    check_scale(x, y, ref, focal_px_from_fov(meta.fov_deg, w, h), fits_files[0], meta.fov_deg)
    check_identified(x, y, ref, focal_px_from_fov(meta.fov_deg, w, h), (w - 1) / 2.0, (h - 1) / 2.0, str(fits_files[0]))
    centre = radec_to_unit(math.radians(meta.center.ra_degrees), math.radians(meta.center.dec_degrees))
    check_centre(ref, np.asarray(centre), meta.fov_deg, str(json_path), log)
    return CorrFrame(folder, fits_files[0], json_path, meta, x, y, ref, ids, cols.get("flux", np.full(n, np.nan)), resid)


def focal_px_from_fov(fov_deg: float, width: int, height: int) -> float:
    """Focal length (px) from astrometry.net's diagonal field: ``hypot(W, H) / radians(fov)``."""
    return math.hypot(width, height) / math.radians(fov_deg)


def camera_for(frames: list[CorrFrame], root: Path) -> tuple[CameraSpec, float]:
    """The one pinhole camera of a recording (median field of view); (camera, fov_deg)."""
    sizes = {(f.meta.image_size.x, f.meta.image_size.y) for f in frames}
    if len(sizes) > 1:
        by = {}
        for f in frames:
            by.setdefault((f.meta.image_size.x, f.meta.image_size.y), f.log_json)
        listing = "; ".join(f"{w}x{h} in {p}" for (w, h), p in by.items())
        raise ImportDataError(f"{root}: the folders have different image sizes ({listing}); one recording has one "
                              "camera: import the sub-folders separately")
    fovs = np.array([f.meta.fov_deg for f in frames])
    if fovs.max() / fovs.min() - 1.0 > FOV_TOLERANCE:
        lo, hi = frames[int(fovs.argmin())], frames[int(fovs.argmax())]
        raise ImportDataError(f"{root}: fields of view differ by more than {FOV_TOLERANCE:.0%} "
                              f"({lo.meta.fov_deg} deg in {lo.log_json}, {hi.meta.fov_deg} deg in {hi.log_json}); "
                              "one recording has one camera: import the sub-folders separately")
    fov = float(np.median(fovs))
    (w, h), = sizes
    f_px = focal_px_from_fov(fov, w, h)
    cam = CameraSpec(name=f"astrometry.net {root.name}",
                     description=f"pinhole from log.json: fov {fov} deg (diagonal, linear scale), {w}x{h} px",
                     width_px=w, height_px=h, focal_length_mm=f_px * NOMINAL_PIXEL_SIZE_UM * 1e-3,
                     pixel_size_um=NOMINAL_PIXEL_SIZE_UM)
    return cam, fov


def _image_for(folder: Path) -> str | None:
    """The PNG the corr table was made from, when the folder makes it unambiguous."""
    pngs = _images_in(folder)
    if len(pngs) == 1:
        return pngs[0]
    exposed = [p for p in pngs if re.search(r"_\d+e_", p)]  # creusot naming: <scene>_<exposure>e_<gain>g.png
    return exposed[0] if len(exposed) == 1 else None


def _images_in(folder: Path) -> list[str]:
    return sorted(p.name for p in folder.iterdir() if p.suffix.lower() in IMAGE_SUFFIXES)


def solved_image(frame: CorrFrame, log: WarningLog) -> tuple[Path, np.ndarray] | None:
    """The image ``frame``'s table was made from, and its pixels: the folder's only image, or the
    one its naming singles out, or else the one whose pixels at the table's stars stand highest
    above its background (``STAR_CONTRAST`` robust sigmas at the median star, required of every
    choice: a dark frame or another scene is not the solved image). A file that is not a readable
    image of the table's size is passed over with a warning; None, with a warning, when no image
    qualifies."""
    names = _images_in(frame.folder)
    named = _image_for(frame.folder)
    best, best_score = None, -np.inf
    for name in [named] + [n for n in names if n != named] if named else names:
        path = frame.folder / name
        try:
            img = read_image(path)
        except ImportDataError as exc:  # another file of the folder: not the solved image
            log(f"{exc}; not used as the solved image")
            continue
        if img.shape != (frame.meta.image_size.y, frame.meta.image_size.x):
            log(f"{path}: {img.shape[1]}x{img.shape[0]} px, not the {frame.meta.image_size.x}x"
                f"{frame.meta.image_size.y} of {frame.log_json.name}; not the solved image")
            continue
        score = _star_contrast(img, frame.x, frame.y)
        if score > best_score:
            best, best_score = (path, img), score
        if name == named and score >= STAR_CONTRAST:  # the image the naming singles out shows the stars
            break
    if best is None or best_score < STAR_CONTRAST:
        why = "no image file" if not names else (f"no image shows stars at the table's positions (best: {best[0].name}, "
                                                 f"{best_score:.1f} sigma)" if best else "no image of the table's size")
        log(f"{frame.folder}: {why}; the table's own positions are kept")
        return None
    return best


def _star_contrast(img: np.ndarray, x: np.ndarray, y: np.ndarray) -> float:
    """The median over the stars of the brightest pixel within 1 px of each, above the image's
    median, in robust sigmas of the image (MAD)."""
    a = img.astype(float)
    med = float(np.median(a))
    scale = 1.4826 * float(np.median(np.abs(a - med))) or 1.0
    h, w = a.shape
    r, c = np.rint(y).astype(int), np.rint(x).astype(int)
    peaks = (np.max([a[np.clip(r + dr, 0, h - 1), np.clip(c + dc, 0, w - 1)] for dr in (-1, 0, 1) for dc in (-1, 0, 1)],
                    axis=0) if len(x) else np.zeros(1))
    return float((np.median(peaks) - med) / scale)


def remeasured_frame(frame: CorrFrame, remeasure: Callable, log: WarningLog) -> tuple[CorrFrame, dict]:
    """``frame`` with its stars measured again on its solved image by ``remeasure`` (``(image, x, y)
    ->`` :class:`~rollingstar.estimators.centroiders.remeasure.Remeasured`), and what was done."""
    found = solved_image(frame, log) if frame.x.size else None
    if found is None:
        return frame, {"image": None, "measured": 0}
    path, img = found
    r = remeasure(img, frame.x, frame.y)
    left = {str(k): int(v) for k, v in zip(*np.unique(r.reason[~r.measured], return_counts=True))}
    cov = np.where(r.measured[:, None, None], r.cov, np.nan)
    frame = replace(frame, x=r.x, y=r.y, cov=cov)
    return frame, {"image": path.name, "measured": int(r.measured.sum()), "kept_from_table": left,
                   "psf_sigma_px": r.psf_sigma_px, "psf_measured": bool(r.psf_measured)}


def import_corr(folder: str | Path, out: str | Path, remeasure: Callable | None = None) -> Path:
    """Import the corr table(s) under ``folder`` into the recording ``out``; returns ``out``.

    ``remeasure``: None keeps the table's positions; else a function ``(image, x, y) ->``
    :class:`~rollingstar.estimators.centroiders.remeasure.Remeasured` (the layer above passes
    :func:`~rollingstar.estimators.centroiders.remeasure.remeasure_stars`) that measures the stars
    again on each table's solved image (:func:`solved_image`); the stars it measured carry its
    covariances, the others keep the table's positions and the recording's centroid sigma, the
    table's own accuracy (the RMS per axis of ``field_xy - index_xy``) either way.

    Recoverable problems emit :class:`~rollingstar.logs.importers.common.ImportDataWarning` and are kept in
    the log's ``import.warnings`` metadata; the per-frame sources and log.json pointing centres
    are in ``import.details`` (see :func:`pointing_centres`).
    """
    root = Path(folder)
    out = output_path(out)
    log = WarningLog()
    frames = [_read_frame(f, log) for f in find_corr_folders(root)]
    remeasured = None
    if remeasure is not None:
        frames, remeasured = zip(*(remeasured_frame(f, remeasure, log) for f in frames))
    cam, fov = camera_for(frames, root)
    _same_tables(frames, log)
    sigma = _residual_rms([f.residual_px for f in frames])
    if sigma is not None and not (np.isfinite(sigma) and sigma < math.hypot(cam.width_px, cam.height_px)):
        log(f"{root}: field_xy - index_xy residuals of {sigma:.3g} px RMS are not a centroid noise (damaged "
            f"index_x/index_y?); the recording states no centroid noise")
        sigma = None
    if sigma is None:  # no table states its residual: no noise is assumed (`diagnose` estimates it)
        sigma = 0.0
    first = frames[0].meta.center
    prior = AttitudeConfig(ra_deg=first.ra_degrees, dec_deg=first.dec_degrees, roll_deg=0.0)
    catalog, catalog_details = catalog_for(cam, ObservationSpec(), NO_OBSERVATION, log, source=str(root),
                                           detections_per_frame=mean_per_frame([f.x.size for f in frames]),
                                           warn_default=False)
    catalog_details["epoch_reason"] = EPOCH_REASON
    scenario = scenario_for(cam, name=f"import:{root.name}", level="centroid", frames=len(frames),
                            description=f"astrometry.net corr tables imported from {root}",
                            centroid_sigma_px=sigma, initial_attitude=prior, frame_period_ms=FRAME_SPACING_NS * 1e-6,
                            catalog=catalog)
    timing = build_timing(scenario)
    details = {
        "focal_px": cam.focal_px, "fov_deg": fov, "fov_rule": "focal_px = hypot(W, H) / radians(fov_deg)",
        "centroid_sigma_px": sigma, "centroid_sigma_rule": "RMS per axis of field_xy - index_xy over all stars" if sigma
        else "none stated: no table gives field_xy - index_xy",
        "frame_spacing_ns": FRAME_SPACING_NS, "catalog": catalog_details,
        "positions": "astrometry.net's field_x, field_y" if remeasured is None else (
            "measured again on each table's image (rollingstar.estimators.centroiders.remeasure); "
            "stars it could not measure keep field_x, field_y"),
        "frames": [{
            "frame": k, "t0_ns": k * FRAME_SPACING_NS,
            "folder": f.folder.relative_to(root).as_posix() if f.folder != root else ".",
            "fits": f.fits.name, "log_json": f.log_json.name,
            "image": _image_for(f.folder) if remeasured is None else remeasured[k]["image"],
            "fov_deg": f.meta.fov_deg, "ra_deg": f.meta.center.ra_degrees, "dec_deg": f.meta.center.dec_degrees,
            "timestamp": f.meta.timestamp, "n_stars": int(f.x.size),
            "residual_rms_px": _finite_or_none(_residual_rms([f.residual_px])),
            **({} if remeasured is None else {"remeasured": remeasured[k]})} for k, f in enumerate(frames)],
    }
    metadata = {"scenario": {"yaml": to_yaml(scenario)},
                "sensor": {"yaml": yaml.safe_dump(cam.model_dump(mode="json"), sort_keys=False)},
                "import": import_metadata("corr", root, details, log)}
    with safe_output(out, [folder], replaces=RECORDING) as tmp, LogWriter(tmp, kind="import", metadata=metadata) as writer:
        for k, f in enumerate(frames):
            t0 = k * FRAME_SPACING_NS
            writer.write_json(TOPIC_CENTROIDS, arrays_to_stars(
                k, t0, x=f.x, y=f.y, t_ns=timing.row_mid_exposure_ns(t0, f.y), row_time_ns=timing.row_start_ns(t0, f.y),
                flux=f.flux, catalog_id=f.catalog_id, ref_icrs=f.ref_icrs, **_covariance_columns(f.cov)), t0)
    return out


def _same_tables(frames: list[CorrFrame], log: WarningLog) -> None:
    """Warn about tables that list the same stars at the same positions (one image imported twice)."""
    seen: dict[bytes, CorrFrame] = {}
    for f in frames:
        key = b"".join(np.ascontiguousarray(a).tobytes() for a in (f.x, f.y, f.catalog_id))
        if f.x.size and key in seen:
            log(f"{f.fits}: the same stars at the same positions as {seen[key].fits}: one image imported twice counts "
                "its stars twice (its held-out copy is then no test); remove one of the folders")
        seen.setdefault(key, f)


def _covariance_columns(cov: np.ndarray | None) -> dict:
    """``cov_xx, cov_xy, cov_yy`` and ``sigma_px`` (``sqrt(trace / 2)``) of the stars measured again
    (NaN for the others, which take the recording's centroid sigma); {} when none was."""
    if cov is None:
        return {}
    return {"cov_xx": cov[:, 0, 0], "cov_xy": cov[:, 0, 1], "cov_yy": cov[:, 1, 1],
            "sigma_px": np.sqrt(0.5 * (cov[:, 0, 0] + cov[:, 1, 1]))}


def _finite_or_none(v: float | None) -> float | None:
    return v if v is not None and math.isfinite(v) else None


def _residual_rms(residuals: list[np.ndarray]) -> float | None:
    """RMS per axis of the finite ``(n, 2)`` residuals (None: none; inf: damaged ``index_xy``)."""
    resid = np.concatenate(residuals)
    resid = resid[np.isfinite(resid).all(axis=1)]
    with np.errstate(over="ignore"):  # damaged index_xy overflow to inf, refused by the caller
        return float(np.sqrt(np.mean(resid**2))) if resid.size else None


def pointing_centres(recording: str | Path) -> dict[int, dict]:
    """Frame index -> that frame's ``import.details.frames`` entry (folder, ra_deg, dec_deg, ...)."""
    meta = LogReader(recording).metadata().get("import", {})
    if meta.get("format") != "corr":
        raise ImportDataError(f"{recording}: not a recording made by `rollingstar import corr`")
    return {int(f["frame"]): f for f in json.loads(meta["details"])["frames"]}


def boresight_offsets(recording: str | Path, run_output: str | Path) -> list[dict]:
    """Per frame: the estimated boresight vs log.json's pointing centre (angle in degrees).

    ``run_output`` is the log ``rollingstar run`` wrote from ``recording``; the first valid
    ``/estimate/attitude`` of each frame is used. Frames without a valid estimate get
    ``offset_deg = None`` and the estimate's reason.
    """
    centres = pointing_centres(recording)
    estimates: dict[int, dict] = {}
    for msg in LogReader(run_output).messages(TOPIC_EST_ATTITUDE):
        d = msg.data
        if d["frame"] not in estimates or (d["valid"] and not estimates[d["frame"]]["valid"]):
            estimates[d["frame"]] = d
    rows = []
    for k, c in sorted(centres.items()):
        est = estimates.get(k)
        row = {"frame": k, "folder": c["folder"], "ra_deg": c["ra_deg"], "dec_deg": c["dec_deg"],
               "n_stars": c["n_stars"], "offset_deg": None, "reason": "no estimate" if est is None else est["reason"]}
        if est is not None and est["valid"]:
            R = Rotation.from_quat(quat_from_fields(est["q"]))
            ra, dec, roll = radec_roll_from_attitude(R)
            boresight = R.apply([0.0, 0.0, 1.0])
            centre = radec_to_unit(np.radians(c["ra_deg"]), np.radians(c["dec_deg"]))
            angle = math.degrees(math.atan2(np.linalg.norm(np.cross(boresight, centre)), float(boresight @ centre)))
            row.update(est_ra_deg=ra, est_dec_deg=dec, est_roll_deg=roll, offset_deg=angle, reason="")
        rows.append(row)
    return rows
