"""Import a folder of TIFF/PNG/JPEG/FITS frames (8 or 16 bit) as an image-level recording.

``import_images(folder, out, camera=None)`` reads the folder's ``recording.yaml`` sidecar (see
:mod:`rollingstar.logs.importers.sidecar`; optional when ``camera`` is given), writes every image as a
``foxglove.RawImage`` on ``/camera/image`` at its frame time ``t0``, the sidecar's gyro CSV on
``/gyro`` and its truth CSV on ``/truth/attitude``, and declares the sensor model (metadata
``scenario``, with the reference catalogue: epoch from the observation time, depth from the
camera's field, :mod:`rollingstar.logs.importers.observation`) so that ``rollingstar run`` works
on the result like on a simulated recording.
Images are read with Pillow (8-bit ``L``, 16-bit ``I;16``; colour images are converted to
luminance with a warning); FITS files with astropy, floating-point pixels as 16-bit counts
(:func:`read_image`). Pixel values are stored as ADC counts: unchanged, except that counts a
camera wrote left-justified in 16-bit words are shifted down to its ``bit_depth``
(:func:`_value_shift`).
"""
from __future__ import annotations

import fnmatch
import re
from datetime import datetime, timedelta, timezone
from pathlib import Path

import numpy as np
import yaml
from PIL import Image

from rollingstar.config import to_yaml
from rollingstar.logs.importers.common import (
    TIME_COLUMNS,
    UNIX_TIME_COLUMNS,
    ImportDataError,
    WarningLog,
    check_non_decreasing,
    float_column,
    import_metadata,
    output_path,
    read_csv,
    time_column,
    warn,
)
from rollingstar.logs.importers.fits_images import fits_header, fits_holds_image, fits_observation, read_fits
from rollingstar.logs.importers.observation import (
    Observation,
    catalog_for,
    exif_observation,
    from_unix_ns,
    unix_looking,
)
from rollingstar.logs.importers.sidecar import (
    DEFAULT_FRAME_RATE_HZ,
    FITS_SUFFIXES,
    IMAGE_SUFFIXES,
    CameraSpec,
    RecordingSidecar,
    load_camera,
    load_sidecar,
    scenario_for,
)
from rollingstar.logs.records import AttitudeSamplesRecord, GyroSamplesRecord
from rollingstar.logs.topics import TOPIC_GYRO, TOPIC_IMAGE, TOPIC_TRUTH_ATTITUDE
from rollingstar.logs.writer import RECORDING, LogWriter
from rollingstar.outputs import safe_output
from rollingstar.progress import progress_bar
from rollingstar.sensors.conventions import NS_PER_S

SIDECAR_NAMES = ("recording.yaml", "recording.yml")

_MODES_16 = ("I;16", "I;16L", "I;16B", "I;16N")
_COLOUR_MODES = ("RGB", "RGBA", "P", "LA", "CMYK", "YCbCr", "PA", "La")
_LAST_NUMBER = re.compile(r"(.*?)(\d+)(\D*)")  # a file name split around its last run of digits


def read_image(path: str | Path, log=warn) -> np.ndarray:
    """One image file as a (H, W) uint8 or uint16 array of raw values.

    8-bit greyscale stays uint8, 16-bit greyscale (``I;16*``, or ``I`` within 0..65535) becomes
    uint16; RGB(A) and palette images are converted to 8-bit luminance (ITU-R 601-2, Pillow's
    ``convert("L")``) with a warning. FITS files (:mod:`~rollingstar.logs.importers.fits_images`)
    give integers like the 16-bit files. Floating-point pixels (32-bit float TIFF, FITS ``BITPIX
    -32``) become uint16: values 0..1 are normalised (1.0 is 65535), values up to 65535 are counts
    (rounded to integers). Multi-page files, NaN/inf and other values raise ImportDataError.
    ``log``: where the colour conversion's warning goes (an import's :class:`WarningLog` keeps it).
    """
    path = Path(path)
    arr = read_fits(path) if path.suffix.lower() in FITS_SUFFIXES else _read_pillow(path, log)
    if arr.size == 0:
        raise ImportDataError(f"{path}: the image has no pixels ({arr.shape[-1]}x{arr.shape[0]} px)")
    if arr.dtype == np.uint8:
        return np.ascontiguousarray(arr)
    if arr.dtype.kind == "f":
        return _float_to_uint16(arr, path)
    if arr.dtype.kind in "ui" and (arr.min() < 0 or arr.max() > 65535):
        raise ImportDataError(f"{path}: pixel values {arr.min()}..{arr.max()} do not fit 16 bits (expected 0..65535)")
    if arr.dtype.kind not in "ui":
        raise ImportDataError(f"{path}: pixel type {arr.dtype} not supported (expected 8- or 16-bit integers)")
    return np.ascontiguousarray(arr, dtype=np.uint16)


def _read_pillow(path: Path, log=warn) -> np.ndarray:
    """A TIFF, PNG or JPEG file's pixels as Pillow decodes them (greyscale; colour converted to luminance)."""
    try:
        with Image.open(path) as im:
            if getattr(im, "n_frames", 1) > 1:
                raise ImportDataError(f"{path}: has {im.n_frames} pages/frames; one image per file is expected")
            mode = im.mode
            if mode in ("L", "1") or mode in _MODES_16:
                return np.asarray(im.convert("L") if mode == "1" else im)
            if mode in ("I", "F"):
                return np.asarray(im)
            if mode in _COLOUR_MODES:
                log(f"{path}: colour image (mode {mode}) converted to 8-bit luminance; "
                     "star trackers normally record raw greyscale")
                return np.asarray(im.convert("L"))
            raise ImportDataError(f"{path}: image mode {mode!r} not supported (expected 8- or 16-bit greyscale)")
    except ImportDataError:
        raise
    except Exception as exc:  # Pillow raises many types for unreadable files
        raise _unreadable(path, exc) from None


def _unreadable(path: Path, exc: Exception) -> ImportDataError:
    """The error for an image file Pillow cannot open or decode."""
    if isinstance(exc, FileNotFoundError):
        return ImportDataError(f"{path}: image file not found")
    what = "empty file (0 bytes)" if path.is_file() and path.stat().st_size == 0 else f"{type(exc).__name__}: {exc}"
    return ImportDataError(f"{path}: cannot read image ({what}); expected a TIFF, PNG, JPEG or FITS image")


def _float_to_uint16(arr: np.ndarray, path: Path) -> np.ndarray:
    """Floating-point pixels as uint16: 0..1 scaled to 0..65535 (normalised), 0..65535 rounded (counts)."""
    bad = ~np.isfinite(arr)
    if bad.any():
        row, col = np.argwhere(bad)[0]
        raise ImportDataError(f"{path}: {int(bad.sum())} pixels are NaN or infinite (the first at row {row}, "
                              f"column {col}); expected finite values (0..1 normalised, or 0..65535)")
    lo, hi = float(arr.min()), float(arr.max())
    if lo < 0.0 or hi > 65535.0:
        raise ImportDataError(f"{path}: floating-point pixel values {lo:g}..{hi:g}; expected 0..1 (normalised) "
                              "or 0..65535 (counts)")
    scale = 65535.0 if hi <= 1.0 else 1.0
    return np.rint(arr * scale).astype(np.uint16)


def _image_header(path: Path) -> tuple[int, int, int, str]:
    """(width, height, bits, mode) without decoding the pixels; bits is that of :func:`read_image`'s
    array, mode Pillow's (``FITS`` for a FITS file)."""
    if path.suffix.lower() in FITS_SUFFIXES:
        return (*fits_header(path), "FITS")
    try:
        with Image.open(path) as im:
            bits = 16 if (im.mode in _MODES_16 or im.mode in ("I", "F")) else 8
            return im.size[0], im.size[1], bits, im.mode
    except Exception as exc:
        raise _unreadable(path, exc) from None


def _png_bits_per_channel(path: Path) -> int | None:
    """The bit depth a PNG file's header (IHDR) states, None for another file: Pillow decodes 16-bit
    colour PNGs to 8 bits per channel without saying so."""
    with open(path, "rb") as f:
        head = f.read(26)
    return head[24] if len(head) == 26 and head.startswith(b"\x89PNG\r\n\x1a\n") and head[12:16] == b"IHDR" else None


def find_sidecar(folder: Path) -> Path | None:
    for name in SIDECAR_NAMES:
        if (folder / name).is_file():
            return folder / name
    return None


def _name_order(name: str) -> tuple:
    """Sort key of image file names: by name, with the last number in it compared by value, so that
    frames numbered without leading zeros keep their order (frame_9 before frame_10)."""
    m = _LAST_NUMBER.fullmatch(name)
    return (m[1], int(m[2]), m[3], name) if m else (name, -1, "", name)


def _without_fits_tables(folder: Path, names: list[str], log: WarningLog) -> list[str]:
    """``names`` less the FITS files that hold no image (tables, such as an astrometry.net corr.fits)."""
    tables = [n for n in names if n.lower().endswith(FITS_SUFFIXES) and not fits_holds_image(folder / n)]
    if tables:
        log(f"{folder}: {', '.join(tables[:5])}{' ...' if len(tables) > 5 else ''}: FITS file(s) holding no "
            "image (tables); not imported")
    return [n for n in names if n not in tables]


def _list_files(folder: Path, spec: str | list[str] | None, source: str, log: WarningLog) -> list[Path]:
    if isinstance(spec, list):
        files = [folder / f for f in spec]
        missing = [str(f) for f in files if not f.is_file()]
        if missing:
            raise ImportDataError(f"{source}: files: {', '.join(missing)} not found")
        return files
    def wanted(name: str) -> bool:
        return name.lower().endswith(IMAGE_SUFFIXES) if spec is None else fnmatch.fnmatch(name, spec)

    entries = sorted(folder.iterdir(), key=lambda p: _name_order(p.name))
    odd = [p.name for p in entries if wanted(p.name) and not p.is_file()]
    if odd:
        raise ImportDataError(f"{folder}: {', '.join(odd[:5])} match the image files but are not readable regular "
                              "files (a folder, a pipe, or a symbolic link that loops or points nowhere); remove "
                              "them or list the files in the sidecar's files:")
    chosen = [p.name for p in entries if wanted(p.name)]
    if spec is None:
        chosen = _without_fits_tables(folder, chosen, log)
    if not chosen:
        what = (f"no image files ({', '.join('*' + s for s in IMAGE_SUFFIXES)})" if spec is None
                else f"no files match files: {spec!r}")
        raise ImportDataError(f"{folder}: {what}")
    return [folder / n for n in chosen]


def _frame_times(sidecar: RecordingSidecar, files: list[Path], base: Path, source: str,
                 log: WarningLog) -> tuple[np.ndarray, dict]:
    ts = sidecar.timestamps
    n = len(files)
    if ts.t0_ns is not None:
        if len(ts.t0_ns) != n:
            raise ImportDataError(f"{source}: timestamps.t0_ns has {len(ts.t0_ns)} entries for {n} image files")
        t0 = np.asarray(ts.t0_ns, dtype=np.int64)
        how = {"source": "t0_ns"}
    elif ts.csv is not None:
        table = read_csv(base / ts.csv, required=["file"], one_of=[TIME_COLUMNS + UNIX_TIME_COLUMNS], log=log)
        times, column = time_column(table)
        by_name = {}
        for i, name in enumerate(table.columns["file"]):
            if name in by_name:
                raise ImportDataError(f"{table.where(i, 'file')}: {name!r} listed twice")
            by_name[name] = times[i]
        missing = [f.name for f in files if f.name not in by_name]
        if missing:
            raise ImportDataError(f"{table.path}: no time for image(s) {', '.join(missing[:5])}"
                                  f"{' ...' if len(missing) > 5 else ''}")
        t0 = np.array([by_name[f.name] for f in files], dtype=np.int64)
        how = {"source": "csv", "csv": str(table.path), "column": column}
    elif ts.frame_rate_hz is None and (headers := _fits_header_times(files, log)) is not None:
        t0, how = headers, {"source": "fits_headers"}
    else:
        rate = ts.frame_rate_hz
        if rate is None:
            rate = DEFAULT_FRAME_RATE_HZ
            if n > 1:
                log(f"{source}: no frame times given (timestamps.frame_rate_hz, t0_ns or csv, or a time in every FITS "
                    f"header); assuming {rate:g} Hz from t = {ts.start_ns} ns, in file-name order")
        t0 = ts.start_ns + np.rint(np.arange(n) * NS_PER_S / rate).astype(np.int64)
        how = {"source": "frame_rate_hz", "frame_rate_hz": rate, "start_ns": ts.start_ns}
    step = np.diff(t0)
    if step.size and (step <= 0).any():
        i = int(np.flatnonzero(step <= 0)[0]) + 1
        raise ImportDataError(f"{source}: frame times must increase strictly in file order: "
                              f"{files[i].name} has t0 = {t0[i]} ns after {files[i - 1].name} at {t0[i - 1]} ns")
    return t0, how


def _fits_header_times(files: list[Path], log: WarningLog) -> np.ndarray | None:
    """Every file's observation time from its FITS header (:func:`fits_observation`) as Unix
    nanoseconds (to the microsecond the header time is read to), or None unless every file is
    FITS and states a full time without a warning, and the times increase strictly in file order
    (headers that state whole seconds for a faster camera do not: a warning says so)."""
    if not all(f.suffix.lower() in FITS_SUFFIXES for f in files):
        return None
    times = []
    for f in files:
        said: list[str] = []
        when = fits_observation(f, said.append).time
        if when is None or said:
            return None
        times.append((when - _UNIX_EPOCH) // timedelta(microseconds=1) * 1000)
    t0 = np.asarray(times, dtype=np.int64)
    if t0.size > 1 and (np.diff(t0) <= 0).any():
        k = int(np.flatnonzero(np.diff(t0) <= 0)[0]) + 1
        log(f"{files[0].parent}: the FITS headers' times do not increase strictly in file order ({files[k].name} is "
            f"{(t0[k] - t0[k - 1]) * 1e-9:g} s after {files[k - 1].name}); they are not used as frame times")
        return None
    return t0


_UNIX_EPOCH = datetime(1970, 1, 1, tzinfo=timezone.utc)


def _read_gyro(path: Path, log: WarningLog) -> tuple[np.ndarray, np.ndarray]:
    table = read_csv(path, required=["wx", "wy", "wz"], one_of=[("t_ns", "time_s")], log=log)
    t, name = time_column(table)
    check_non_decreasing(table, t, name)
    w = np.column_stack([float_column(table, c) for c in ("wx", "wy", "wz")])
    return t, w


def _read_truth(path: Path, log: WarningLog) -> tuple[np.ndarray, np.ndarray, np.ndarray | None]:
    table = read_csv(path, required=["qx", "qy", "qz", "qw"], optional=["wx", "wy", "wz"],
                     one_of=[("t_ns", "time_s")], log=log)
    t, name = time_column(table)
    check_non_decreasing(table, t, name)
    q = np.column_stack([float_column(table, c) for c in ("qx", "qy", "qz", "qw")])
    norm = np.linalg.norm(q, axis=1)
    bad = np.flatnonzero(np.abs(norm - 1.0) > 1e-6)
    if bad.size:
        raise ImportDataError(f"{table.path}: line {int(table.lines[bad[0]])}: quaternion (qx, qy, qz, qw) has "
                              f"norm {norm[bad[0]]:.9g}; a unit camera-to-ICRS quaternion is expected (within 1e-6)")
    rates = [c in table.columns for c in ("wx", "wy", "wz")]
    if any(rates) and not all(rates):
        raise ImportDataError(f"{table.path}: give all of wx, wy, wz or none of them")
    w = np.column_stack([float_column(table, c) for c in ("wx", "wy", "wz")]) if all(rates) else None
    return t, q, w


def batches_by_frame(t: np.ndarray, t0: np.ndarray, join_tail: bool = True) -> list[np.ndarray]:
    """Split sample indices so that batch k holds the samples in ``(t0[k-1], t0[k]]``.

    Batch 0 holds every sample up to ``t0[0]``. With ``join_tail`` the samples after the last
    frame time join the last batch, so that a batch logged at its *first* sample (truth) still
    belongs to a frame; without it they form a batch of their own (gyro, logged at its *last*
    sample: samples after the last frame belong to no frame).
    """
    edges = np.searchsorted(t, t0, side="right")
    bounds = [0, *edges[:-1].tolist(), t.size] if join_tail else [0, *edges.tolist(), t.size]
    return [np.arange(a, b) for a, b in zip(bounds[:-1], bounds[1:]) if b > a]


def resolve_camera(camera: CameraSpec | str | Path | None, sidecar: RecordingSidecar | None,
                   sidecar_path: Path | None, log: WarningLog, folder: Path) -> CameraSpec:
    """The camera: ``camera`` (a CameraSpec or camera.yaml path) over the sidecar's; one is required."""
    side_cam = None
    if sidecar is not None:
        side_cam = sidecar.camera
        if sidecar.camera_file is not None:
            side_cam = load_camera(sidecar_path.parent / sidecar.camera_file)
    if camera is not None:
        cam = camera if isinstance(camera, CameraSpec) else load_camera(camera)
        if side_cam is not None:
            log(f"{sidecar_path}: camera overridden by the camera given on the command line")
        return cam
    if side_cam is None:
        where = f"{sidecar_path} has no camera" if sidecar_path else f"{folder} has no recording.yaml"
        raise ImportDataError(f"{where}: give the camera with --camera camera.yaml (or 'camera' or "
                              "'camera_file' in recording.yaml); see docs/log-format.md")
    return side_cam


def import_images(folder: str | Path, out: str | Path, camera: CameraSpec | str | Path | None = None,
                  sidecar: str | Path | None = None, show_progress: bool = False) -> Path:
    """Import the images of ``folder`` into the recording ``out``; returns ``out``.

    ``camera``: a :class:`CameraSpec` or the path of a camera.yaml; overrides the sidecar's camera.
    ``sidecar``: a recording.yaml kept elsewhere (e.g. for a read-only folder); default
    ``folder/recording.yaml`` when present. Paths inside a sidecar are relative to its own folder,
    except ``files``, which are relative to ``folder``. The declared catalogue's epoch and depth
    follow the observation time and the camera's field
    (:mod:`rollingstar.logs.importers.observation`).
    Imperfect but recoverable input emits :class:`~rollingstar.logs.importers.common.ImportDataWarning` (also
    kept in the log's ``import.warnings`` metadata); unusable input raises ImportDataError.
    """
    folder = Path(folder)
    if not folder.is_dir():
        raise ImportDataError(f"{folder}: not a directory (expected a folder of images)")
    out = output_path(out)
    log = WarningLog()
    sidecar_path = Path(sidecar) if sidecar is not None else find_sidecar(folder)
    if sidecar_path is not None and not sidecar_path.is_file():
        raise ImportDataError(f"{sidecar_path}: sidecar file not found")
    side = load_sidecar(sidecar_path) if sidecar_path else RecordingSidecar()
    base = sidecar_path.parent if sidecar_path else folder
    source = str(sidecar_path or folder)
    cam = resolve_camera(camera, side if sidecar_path else None, sidecar_path, log, folder)
    files = _list_files(folder, side.files, source, log)
    container_bits, bit_depth = _bit_depths(files, cam, folder, log)
    shift, shift_reason = _value_shift(files, container_bits, cam, log)
    t0, timing = _frame_times(side, files, base, source, log)
    gyro = _read_gyro(base / side.gyro_csv, log) if side.gyro_csv else None
    truth = _read_truth(base / side.truth_csv, log) if side.truth_csv else None
    observation = _observation(side, files, t0, timing, log)
    catalog, catalog_details = catalog_for(cam, side, observation, log, source=source,
                                           unix_hint=unix_looking(t0) if observation.time is None else None)
    period = float(np.median(np.diff(t0))) * 1e-6 if len(t0) > 1 else None
    scenario = scenario_for(cam, name=f"import:{folder.name}", description=f"images imported from {folder}",
                            level="image", frames=len(files), bit_depth=bit_depth,
                            initial_attitude=side.initial_attitude, frame_period_ms=period, catalog=catalog)
    details = {
        "files": [f.name for f in files], "t0_ns": t0.tolist(), "timestamps": timing,
        "container_bits": container_bits, "bit_depth": bit_depth, "value_shift_bits": shift,
        "value_shift_reason": shift_reason,
        "camera": cam.model_dump(mode="json"), "focal_px": cam.focal_px,
        "sidecar": str(sidecar_path) if sidecar_path else None,
        "gyro_csv": side.gyro_csv, "truth_csv": side.truth_csv, "catalog": catalog_details,
    }
    metadata = {"scenario": {"yaml": to_yaml(scenario)},
                "sensor": {"yaml": yaml.safe_dump(cam.model_dump(mode="json"), sort_keys=False)},
                "import": import_metadata("images", folder, details, log)}
    inputs = [folder, *(p for p in (sidecar_path, camera) if isinstance(p, (str, Path)))]
    with safe_output(out, inputs, replaces=RECORDING) as tmp, LogWriter(tmp, kind="import", metadata=metadata) as writer, \
            progress_bar(f"import {folder.name}", len(files), show_progress) as advance:
        _write_samples(writer, t0, gyro, truth)
        for f, t in zip(files, t0.tolist()):
            writer.write_image(TOPIC_IMAGE, _frame_pixels(f, container_bits, bit_depth, (shift, shift_reason),
                                                            cam.mirrored), t)
            advance()
    return out


def _said(message: str) -> None:
    """Nothing: for a warning the import has already given once for every image."""


def _frame_pixels(path: Path, container_bits: int, bit_depth: int, shift: tuple[int, str | None],
                  mirrored: bool) -> np.ndarray:
    """One file's pixels as the recording holds them: ADC counts, in the camera's unmirrored view
    (``shift``: the bits and reason :func:`_value_shift` gives)."""
    image = read_image(path, log=_said)  # a colour image was said once, by :func:`_bit_depths`
    if image.itemsize * 8 != container_bits:  # header and pixels disagree (e.g. mode "I")
        raise ImportDataError(f"{path}: decoded as {image.dtype}, expected {container_bits}-bit like the other images")
    if bit_depth < container_bits:
        image = _to_counts(image, bit_depth, *shift, path)
    if mirrored:
        image = np.ascontiguousarray(image[:, ::-1])
    return image


MIN_JUSTIFIED_PIXELS = 100
"""Non-zero pixels, all multiples of ``2^(16 - bit_depth)``, that show an image's counts are
left-justified when none exceeds ``2^bit_depth - 1`` (a dark image): right-justified counts with
noise in their low bits are all such multiples with a chance of ``2^-(16 - bit_depth)`` per pixel."""


def _value_shift(files: list[Path], container_bits: int, cam: CameraSpec, log: WarningLog) -> tuple[int, str | None]:
    """How many bits the files' values sit above the camera's ADC counts, and why: judged on the
    first image that decides it (:func:`_justification`; none decides: right-justified).

    A camera whose ``bit_depth`` is less than the 16-bit container writes its counts either
    right-justified (0 .. 2^bit_depth - 1) or left-justified (shifted up to the top of the word:
    multiples of 2^(16 - bit_depth), as many 10- to 14-bit cameras write). Left-justified counts
    are shifted down, so that the saturation level 2^bit_depth - 1 and the gain in e-/ADU refer to
    the camera's own counts.
    """
    if container_bits != 16 or cam.bit_depth == 16:
        return 0, None
    if cam.bit_depth is None:
        _hint_bit_depth(read_image(files[0]), files[0], log)
        return 0, None
    for path in files:
        left, why = _justification(read_image(path), cam.bit_depth)
        if left is not None:
            return (16 - cam.bit_depth if left else 0), f"{path.name}: {why}"
    why = f"no image tells (every one has fewer than {MIN_JUSTIFIED_PIXELS} non-zero pixels): read as right-justified"
    log(f"{files[0].parent}: {why}; if the camera writes its {cam.bit_depth}-bit counts left-justified in 16-bit words, "
        f"every count is {1 << (16 - cam.bit_depth)} times too large")
    return 0, why


def _justification(image: np.ndarray, bit_depth: int) -> tuple[bool | None, str]:
    """(True, why) for left-justified counts: a value exceeds ``2^bit_depth - 1``, or at least
    :data:`MIN_JUSTIFIED_PIXELS` non-zero values are all multiples of ``2^(16 - bit_depth)``;
    (False, why) when a value is not such a multiple; (None, "") when the image cannot tell (all
    zero, or too few non-zero pixels)."""
    top, step = (1 << bit_depth) - 1, 1 << (16 - bit_depth)
    if int(image.max()) > top:
        return True, f"values up to {int(image.max())} exceed {top}"
    if ((image & (step - 1)) != 0).any():
        return False, f"values up to {int(image.max())}, not all multiples of {step}"
    nonzero = int(np.count_nonzero(image))
    if nonzero >= MIN_JUSTIFIED_PIXELS:
        return True, f"all {nonzero} non-zero values are multiples of {step}"
    return None, ""


def _hint_bit_depth(image: np.ndarray, path: Path, log: WarningLog) -> None:
    """Warn when every value is a multiple of 4 or more: left-justified counts of a camera with fewer
    bits, whose saturated pixels never reach the 65535 assumed without a bit_depth."""
    ored = int(np.bitwise_or.reduce(image, axis=None))
    zeros = (ored & -ored).bit_length() - 1 if ored else 0
    if zeros >= 2:
        log(f"{path}: every pixel value is a multiple of {1 << zeros}, as when a {16 - zeros}-bit camera's counts "
            "fill the top bits of 16-bit words; the camera file states no bit_depth, so saturation is taken at "
            f"65535, which such values never reach: state bit_depth: {16 - zeros} to have saturated stars recognised")


def _to_counts(image: np.ndarray, bit_depth: int, shift: int, why: str | None, path: Path) -> np.ndarray:
    """``image`` as counts 0 .. 2^bit_depth - 1: shifted down ``shift`` bits (left-justified), else
    checked; ``why``: what decided the shift (:func:`_value_shift`), for the messages."""
    top = (1 << bit_depth) - 1
    if shift:
        # a saturated pixel may read all ones (65535) rather than the largest multiple
        odd = ((image & ((1 << shift) - 1)) != 0) & (image != np.iinfo(image.dtype).max)
        if odd.any():
            row, col = np.argwhere(odd)[0]
            raise ImportDataError(
                f"{path}: pixel value {image[row, col]} at row {row}, column {col} is not a multiple of {1 << shift}; "
                f"the counts of the camera's bit_depth {bit_depth} were judged left-justified in 16-bit words "
                f"({why}), so every image is expected to hold multiples of {1 << shift}")
        return image >> shift
    if int(image.max()) > top:
        raise ImportDataError(
            f"{path}: pixel values up to {image.max()} exceed {top}, the largest count of the camera's bit_depth "
            f"{bit_depth}; the counts were judged right-justified ({why}), so 0..{top} is expected (or counts "
            f"left-justified in 16-bit words, multiples of {1 << (16 - bit_depth)}, in every image), or a larger bit_depth")
    return image


def _bit_depths(files: list[Path], cam: CameraSpec, folder: Path, log: WarningLog) -> tuple[int, int]:
    """(container bits, ADC bit depth) of the images, which must all have the camera's size and one
    container; colour images (converted to luminance) are said once, in the import's warnings."""
    headers = [_image_header(f) for f in files]
    colour = [(f, hd[3]) for f, hd in zip(files, headers) if hd[3] in _COLOUR_MODES]
    if colour:
        deep = sum(_png_bits_per_channel(f) == 16 for f, _ in colour)
        lost = (f"; {deep} of them hold 16 bits per channel, of which Pillow keeps the top 8 (convert them to "
                "16-bit greyscale to keep the rest)") if deep else ""
        log(f"{folder}: {len(colour)} of the {len(files)} images are colour (the first {colour[0][0].name}, mode "
            f"{colour[0][1]}) and are converted to 8-bit luminance; star trackers normally record raw greyscale{lost}")
    for f, (w, h, _, _) in zip(files, headers):
        if (w, h) != (cam.width_px, cam.height_px):
            raise ImportDataError(f"{f}: image is {w}x{h} px but the camera says width_px {cam.width_px}, "
                                  f"height_px {cam.height_px}")
    bits = {b for _, _, b, _ in headers}
    if len(bits) > 1:
        first8 = next(f for f, hd in zip(files, headers) if hd[2] == 8)
        first16 = next(f for f, hd in zip(files, headers) if hd[2] == 16)
        raise ImportDataError(f"{folder}: mixes 8-bit ({first8.name}) and 16-bit ({first16.name}) images; "
                              "one recording has one bit depth")
    container_bits = bits.pop()
    bit_depth = cam.bit_depth if cam.bit_depth is not None else container_bits
    if bit_depth > container_bits:
        raise ImportDataError(f"camera bit_depth {bit_depth} exceeds the {container_bits}-bit images in {folder}")
    return container_bits, bit_depth


def _observation(side: RecordingSidecar, files: list[Path], t0: np.ndarray, timing: dict,
                 log: WarningLog) -> Observation:
    """The observation time: the sidecar's, else Unix-time frame times', else the first image's
    FITS ``DATE-OBS`` or EXIF time."""
    if side.observation_time is not None:
        return Observation(side.observation_time, "observation_time")
    if timing.get("column") in UNIX_TIME_COLUMNS:
        return from_unix_ns(int(t0[0]), timing["column"], timing["csv"])
    if files[0].suffix.lower() in FITS_SUFFIXES:
        return fits_observation(files[0], log)
    return exif_observation(files[0], log)


def _write_samples(writer: LogWriter, t0: np.ndarray, gyro, truth) -> None:
    """The truth and gyro samples, batched per frame (:func:`batches_by_frame`)."""
    if truth is not None:
        tt, q, w = truth
        for idx in batches_by_frame(tt, t0):
            writer.write_json(TOPIC_TRUTH_ATTITUDE, AttitudeSamplesRecord(
                t_ns=tt[idx].tolist(), qx=q[idx, 0].tolist(), qy=q[idx, 1].tolist(), qz=q[idx, 2].tolist(),
                qw=q[idx, 3].tolist(), **({} if w is None else dict(
                    wx=w[idx, 0].tolist(), wy=w[idx, 1].tolist(), wz=w[idx, 2].tolist()))))
    if gyro is not None:
        tg, wg = gyro
        for idx in batches_by_frame(tg, t0, join_tail=False):
            writer.write_json(TOPIC_GYRO, GyroSamplesRecord(
                t_ns=tg[idx].tolist(), x=wg[idx, 0].tolist(), y=wg[idx, 1].tolist(), z=wg[idx, 2].tolist()))
