"""FITS image files for the image importer (:mod:`rollingstar.logs.importers.images`), read with astropy.

A camera's FITS file holds its frame in the primary HDU or, behind an empty primary HDU, in the
first image extension (tile-compressed ``.fits.fz`` images included). astropy applies ``BZERO``
and ``BSCALE``: the unsigned 16-bit pixels that cameras store as ``int16`` with ``BZERO = 32768``
read as ``uint16``, and scaled integers read as floats. Leading axes of length 1 (a cube of one
plane, ``NAXIS3 = 1``) are dropped. Rows come in the order the file stores them: row 0 is the
first row of the data array (the row FITS viewers draw at the bottom).

A FITS file that holds only tables (an astrometry.net ``corr.fits`` beside the images) has no
image: :func:`fits_holds_image` tells the importer to leave it out.
"""
from __future__ import annotations

import math
import re
import warnings
from datetime import datetime, timezone
from pathlib import Path

import numpy as np

from rollingstar.logs.importers.common import ImportDataError
from rollingstar.logs.importers.observation import NO_OBSERVATION, Observation
from rollingstar.logs.importers.sidecar import EPOCH_YEARS

# astropy warns about a short file when it opens it; the header check below reports it as an error instead
_TRUNCATED_WARNING = "File may have been truncated"


def _fits():
    from astropy.io import fits  # here, not at the top: astropy takes ~0.3 s to import and only FITS files need it

    return fits


def _open(path: Path):
    fits = _fits()
    try:
        with warnings.catch_warnings():
            warnings.filterwarnings("ignore", message=_TRUNCATED_WARNING)
            return fits.open(path, memmap=False, lazy_load_hdus=False)
    except FileNotFoundError:
        raise ImportDataError(f"{path}: image file not found") from None
    except Exception as exc:  # astropy raises OSError, ValueError, ... for files that are not FITS
        what = "empty file (0 bytes)" if path.stat().st_size == 0 else f"{type(exc).__name__}: {exc}"
        raise ImportDataError(f"{path}: cannot read FITS file ({what}); expected a FITS image") from None


def _image_index(hdul) -> int | None:
    """Index of the first HDU holding an image of two or more axes, else None."""
    for index, hdu in enumerate(hdul):
        if hdu.is_image and hdu.header.get("NAXIS", 0) >= 2:
            return index
    return None


def _image_shape(hdul, index: int, path: Path) -> tuple[int, int]:
    """(height, width) of the image in HDU ``index``; extra axes must have length 1."""
    header = hdul[index].header
    axes = [int(header[f"NAXIS{i}"]) for i in range(1, int(header["NAXIS"]) + 1)]
    planes = math.prod(axes[2:])
    if planes != 1:
        raise ImportDataError(f"{path}: HDU {index} holds {planes} planes (NAXIS = {len(axes)}, axes {axes}); "
                              "one image per file is expected")
    return axes[1], axes[0]


def _check_complete(hdul, index: int, path: Path) -> None:
    """The file holds all the pixels its header declares (checked before any pixel is read)."""
    hdu = hdul[index]
    fits = _fits()
    if not isinstance(hdu, (fits.PrimaryHDU, fits.ImageHDU)):  # tile-compressed: stored size is not the image's
        return
    info = hdul.fileinfo(index)
    h, w = _image_shape(hdul, index, path)
    need = h * w * abs(int(hdu.header["BITPIX"])) // 8
    size = path.stat().st_size
    if info["datLoc"] + need > size:
        raise ImportDataError(f"{path}: truncated: the header declares a {w}x{h} px image (BITPIX "
                              f"{hdu.header['BITPIX']}, {need} bytes) but the file holds {size} bytes")


def fits_holds_image(path: str | Path) -> bool:
    """Whether the FITS file holds an image (True for files astropy cannot read: the reader reports them)."""
    try:
        with _open(Path(path)) as hdul:
            return _image_index(hdul) is not None
    except ImportDataError:
        return True


def fits_header(path: str | Path) -> tuple[int, int, int]:
    """(width, height, bits) of the file's image without reading its pixels; bits: 8 for BITPIX 8, else 16."""
    path = Path(path)
    with _open(path) as hdul:
        index = _checked_index(hdul, path)
        h, w = _image_shape(hdul, index, path)
        return w, h, 8 if int(hdul[index].header["BITPIX"]) == 8 else 16


def read_fits(path: str | Path) -> np.ndarray:
    """The file's image as a (H, W) array in native byte order, scaled by BZERO/BSCALE."""
    path = Path(path)
    with _open(path) as hdul:
        index = _checked_index(hdul, path)
        shape = _image_shape(hdul, index, path)
        try:
            data = hdul[index].data
        except Exception as exc:  # a damaged data unit or compressed tile
            raise ImportDataError(f"{path}: cannot read the FITS image ({type(exc).__name__}: {exc})") from None
        return np.asarray(data.reshape(shape), dtype=data.dtype.newbyteorder("="))


def _checked_index(hdul, path: Path) -> int:
    index = _image_index(hdul)
    if index is None:
        raise ImportDataError(f"{path}: holds no image (its HDUs are tables or empty); expected a FITS image "
                              "in the primary HDU or an image extension")
    _check_complete(hdul, index, path)
    return index


def fits_observation(path: str | Path, log) -> Observation:
    """The observation time the file's header states, else none (``log``: a warning's sink).

    ``DATE-OBS`` (the start of the observation) in the image's HDU, else the primary HDU: ISO 8601
    (``2019-07-29T20:47:26.5``; a space for the ``T``, minutes without seconds and a zone, ``Z`` or
    ``+02:00``, are read too), or the pre-2000 form ``DD/MM/YY`` (years 1900-1999). A date without a
    time of day takes ``MJD-OBS`` when given, else ``TIME-OBS`` (or ``UT``), else midnight with a
    warning; ``MJD-OBS`` alone is read too. The time scale is ``TIMESYS`` (UTC by the standard's
    default) unless the time states a zone; a scale astropy cannot convert to UTC (``GPS``,
    ``LOCAL``) is read as UTC with a warning: GPS time differs from it by seconds, far below the
    53 min to which the catalogue epoch is rounded, and a local clock by its zone (at most 14 h,
    0.0016 yr)."""
    path = Path(path)
    try:
        with _open(path) as hdul:
            index = _image_index(hdul)
            headers = [hdul[index].header] if index not in (None, 0) else []
            headers.append(hdul[0].header)
            cards = {key: next((str(h[key]).strip() for h in headers if str(h.get(key, "")).strip()), "")
                     for key in ("DATE-OBS", "MJD-OBS", "TIME-OBS", "UT", "TIMESYS")}
    except ImportDataError:  # an unreadable file is reported by the image reader itself
        return NO_OBSERVATION
    if not cards["DATE-OBS"] and not cards["MJD-OBS"]:
        return NO_OBSERVATION
    when, what = _header_utc(cards, _time_scale(cards["TIMESYS"], path, log), path, log)
    if when is None:
        return NO_OBSERVATION
    if not EPOCH_YEARS[0] <= when.year <= EPOCH_YEARS[1]:
        log(f"{path}: {what} is outside the years {EPOCH_YEARS[0]:.0f}-{EPOCH_YEARS[1]:.0f}; not used")
        return NO_OBSERVATION
    return Observation(when, "fits")


_DATE_ONLY = re.compile(r"\d{4}-\d\d-\d\d")
_ZONE = re.compile(r"(Z|[+-]\d\d:?\d\d)$")


def _time_scale(timesys: str, path: Path, log) -> str:
    from astropy.time import Time  # here, not at the top, like astropy.io.fits

    scale = (timesys or "UTC").lower()
    if scale not in Time.SCALES or scale == "local":  # astropy keeps a local clock but cannot convert it
        log(f"{path}: TIMESYS {timesys} is not a time scale that converts to UTC; the header's time read as UTC")
        return "utc"
    return scale


def _header_utc(cards: dict[str, str], scale: str, path: Path, log) -> tuple[datetime | None, str]:
    """The UTC time of the header's cards (:func:`fits_observation`) and the cards it came from; None
    (with a warning) when they hold no time."""
    from astropy.time import Time

    text, mjd = cards["DATE-OBS"], cards["MJD-OBS"]
    date = _normalised(text)
    if not text or _DATE_ONLY.fullmatch(date):
        if mjd:
            try:
                return Time(float(mjd), format="mjd", scale=scale).utc.to_datetime(timezone=timezone.utc), f"MJD-OBS {mjd}"
            except ValueError:
                log(f"{path}: MJD-OBS {mjd!r} is not a modified Julian date; not used")
            if not text:
                return None, f"MJD-OBS {mjd}"
        clock = _normalised(cards["TIME-OBS"] or cards["UT"])
        if not clock:
            log(f"{path}: DATE-OBS {text} states no time of day (and no TIME-OBS); read as 00:00 (a day moves the "
                "catalogue epoch by 0.0027 yr, no Hipparcos star by more than 30 mas)")
        date = f"{date}T{clock or '00:00:00'}"
        text = f"{text} {cards['TIME-OBS'] or cards['UT']}".strip()
    try:
        if _ZONE.search(date):  # a civil time with its zone: the zone, not TIMESYS, says how far from UTC
            return datetime.fromisoformat(date).astimezone(timezone.utc), f"DATE-OBS {text}"
        return Time(date, format="isot", scale=scale).utc.to_datetime(timezone=timezone.utc), f"DATE-OBS {text}"
    except ValueError:
        log(f"{path}: DATE-OBS {text!r} is not a date and time (YYYY-MM-DDThh:mm:ss); not used")
        return None, f"DATE-OBS {text}"


def _normalised(text: str) -> str:
    """A header's date or time as ISO 8601 astropy and Python read: ``DD/MM/YY`` as 19YY-MM-DD,
    upper case, a space for the ``T``, seconds added to ``hh:mm``, a leap second (``:60``) read as
    the end of the second before it (neither Python nor the catalogue epoch needs it)."""
    old = re.fullmatch(r"(\d\d)/(\d\d)/(\d\d)", text)
    out = f"19{old[3]}-{old[2]}-{old[1]}" if old else text.strip().upper().replace(" ", "T", 1)
    out = re.sub(r"(T|^)(\d\d:\d\d)(?=$|Z|[+-])", r"\1\2:00", out)
    return re.sub(r"(\d\d:\d\d):60(\.\d*)?(?=$|Z|[+-])", r"\1:59.999999", out)
