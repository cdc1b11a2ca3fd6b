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
import warnings
from pathlib import Path

import numpy as np

from rollingstar.logs.importers.common import ImportDataError

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
