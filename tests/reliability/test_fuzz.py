"""Property-based fuzzing (hypothesis) of the MCAP reader, the importers and the config loader.

Invariant: bad bytes or text never escape as anything but our errors (LogFormatError, UserError
subclasses such as ConfigError / ImportDataError); what is returned is valid. CI runs a small
budget; the long run is

    ROLLINGSTAR_FUZZ_EXAMPLES=5000 .venv/bin/python -m pytest -q tests/reliability/test_fuzz.py
"""
from __future__ import annotations

import os
import warnings

import numpy as np
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from rollingstar.config import parse_yaml, validate
from rollingstar.errors import UserError
from rollingstar.logs.errors import LogFormatError
from rollingstar.logs.importers import CameraSpec, import_centroids
from rollingstar.logs.importers.sidecar import load_camera, load_sidecar
from rollingstar.logs.reader import STANDARD_SCHEMAS, LogReader
from rollingstar.logs.records import TOPIC_RECORDS
from rollingstar.logs.replay import image_from_raw
from rollingstar.pipelines.config import PipelineConfig
from rollingstar.sensors.scenario import ScenarioConfig, scenario_from_yaml

from ..logs.helpers import write_recording
from .helpers import SCENARIO

EXAMPLES = int(os.environ.get("ROLLINGSTAR_FUZZ_EXAMPLES", "40"))
FUZZ = settings(max_examples=EXAMPLES, deadline=None, derandomize="ROLLINGSTAR_FUZZ_EXAMPLES" not in os.environ,
                suppress_health_check=[HealthCheck.function_scoped_fixture, HealthCheck.too_slow])


_LOG: list[bytes] = []


def _log_bytes(tmp_path) -> bytes:
    """A small valid log with every topic and several chunks (made once; not a fixture, so that
    hypothesis does not print its 60 kB in a failure report)."""
    if not _LOG:
        path = tmp_path / "small.mcap"
        write_recording(path, n_frames=4, chunk_size=1024, image_shape=(6, 8))
        _LOG.append(path.read_bytes())
    return _LOG[0]


def _read_all(path):
    """Every message of a (possibly damaged) log, each checked; None when refused with LogFormatError."""
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        try:
            reader = LogReader(path)
            msgs = list(reader.messages())
            reader.summary_info()
        except LogFormatError:
            return None
    last = -1
    for m in msgs:
        assert m.log_time_ns >= last  # log-time order
        last = m.log_time_ns
        if m.topic in TOPIC_RECORDS:  # validated record of the format's schema
            assert m.record is not None and m.schema_name == STANDARD_SCHEMAS[m.topic]
        if m.topic == "/camera/image":
            try:
                img = image_from_raw(m)
            except LogFormatError:
                continue
            assert img.ndim == 2
    return msgs


# positions as a fraction of the file length, drawn on a uniform grid (hypothesis' floats favour a
# few "nice" values such as 0, 0.5 and 1, which left most of a file's bytes unvisited)
position = st.integers(0, 2**20).map(lambda v: v / 2**20)
mutation = st.one_of(
    st.tuples(st.just("flip"), position, st.integers(1, 255)),
    st.tuples(st.just("cut"), position, st.just(0)),
    st.tuples(st.just("insert"), position, st.integers(0, 255)),
    st.tuples(st.just("zero"), position, st.integers(1, 64)),
)


def _mutate(data: bytes, mutations) -> bytes:
    data = bytearray(data)
    for kind, where, value in mutations:
        i = int(where * max(len(data) - 1, 0))
        if kind == "flip" and data:
            data[i] ^= value
        elif kind == "cut":
            del data[i:]
        elif kind == "insert":
            data[i:i] = bytes([value])
        elif kind == "zero":
            data[i:i + value] = bytes(len(data[i:i + value]))
    return bytes(data)


@FUZZ
@given(mutations=st.lists(mutation, min_size=1, max_size=4))
def test_reader_on_mutated_logs(tmp_path, mutations):
    path = tmp_path / "m.mcap"
    path.write_bytes(_mutate(_log_bytes(tmp_path), mutations))
    _read_all(path)


CAMERA = CameraSpec(width_px=640, height_px=480, focal_length_mm=25.0, pixel_size_um=5.5,
                    shutter={"mode": "rolling", "exposure_ms": 10.0, "line_delay_us": 20.0})
cell = st.one_of(st.floats(allow_nan=True, allow_infinity=True).map(repr), st.integers(-5, 10**12).map(str),
                 st.sampled_from(["", "nan", "inf", "-inf", "x", "true", "1e400", "\"", "#"]),
                 st.text(max_size=6))
HEADERS = ["frame", "time_s", "t_ns", "x", "y", "flux", "sigma_px", "saturated", "catalog_id", "ra_deg", "dec_deg"]


@FUZZ
@given(header=st.lists(st.sampled_from(HEADERS), min_size=1, max_size=8, unique=True),
       rows=st.lists(st.lists(cell, min_size=0, max_size=9), max_size=6))
def test_centroid_csv_importer(tmp_path, header, rows):
    csv = tmp_path / "c.csv"
    csv.write_text("\n".join([",".join(header)] + [",".join(r).replace("\n", " ") for r in rows]) + "\n")
    out = tmp_path / "r.mcap"
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        try:
            import_centroids(csv, out, CAMERA)
        except UserError:
            return
    msgs = _read_all(out)
    assert msgs is not None
    for m in msgs:
        if m.topic == "/camera/centroids":
            x = np.array([np.nan if v is None else v for v in m.data["x"]], dtype=float)
            assert np.all(np.isnan(x) | np.isfinite(x))


yaml_text = st.one_of(
    st.text(max_size=200),
    st.lists(st.tuples(st.sampled_from(["width_px", "height_px", "focal_length_mm", "pixel_size_um", "fov_deg",
                                        "shutter", "bit_depth", "name", "timestamps", "frame_rate_hz", "camera", "x"]),
                       st.one_of(st.integers(-3, 5000).map(str), st.floats().map(repr), st.just("[1, 2]"),
                                 st.just("{mode: rolling}"), st.just("~"), st.just("{"), st.text(max_size=5))),
             max_size=6).map(lambda kv: "\n".join(f"{k}: {v}" for k, v in kv)),
)


@FUZZ
@given(text=yaml_text)
def test_sidecar_and_camera_yaml(tmp_path, text):
    p = tmp_path / "side.yaml"
    p.write_text(text)
    for load in (load_camera, load_sidecar):
        try:
            load(p)
        except UserError as exc:
            assert str(p) in str(exc)


SCENARIO_TEXT = SCENARIO.read_text()


@FUZZ
@given(cut=st.floats(0, 1), edits=st.lists(st.tuples(st.floats(0, 1), st.text(max_size=4)), max_size=3),
       pipeline=st.text(max_size=80))
def test_config_loader(cut, edits, pipeline):
    text = SCENARIO_TEXT[: max(1, int(cut * len(SCENARIO_TEXT)))] if cut < 0.95 else SCENARIO_TEXT
    for where, insert in edits:
        i = int(where * len(text))
        text = text[:i] + insert + text[i + 1:]
    for model, source in ((ScenarioConfig, text), (PipelineConfig, pipeline)):
        try:
            validate(model, parse_yaml(source, "<fuzz>"), "<fuzz>")
        except UserError as exc:  # ConfigError: names the source
            assert "<fuzz>" in str(exc)


_IMAGES: dict[str, bytes] = {}


def _image_bytes(suffix: str) -> bytes:
    """A valid 16-bit 40 x 30 frame as PNG or TIFF bytes (made once per format)."""
    if suffix not in _IMAGES:
        import io

        from PIL import Image

        img = np.random.default_rng(1).integers(0, 4096, (30, 40)).astype(np.uint16)
        buf = io.BytesIO()
        Image.fromarray(img).save(buf, format={".png": "PNG", ".tiff": "TIFF"}[suffix])
        _IMAGES[suffix] = buf.getvalue()
    return _IMAGES[suffix]


IMAGE_SIDECAR = ("camera: {width_px: 40, height_px: 30, focal_length_mm: 10.0, pixel_size_um: 5.0,\n"
                 "         shutter: {mode: rolling, exposure_ms: 2.0, line_delay_us: 20.0}}\n"
                 "timestamps: {frame_rate_hz: 10.0}\n")


@FUZZ
@given(suffix=st.sampled_from([".png", ".tiff"]), mutations=st.lists(mutation, min_size=1, max_size=4))
def test_image_importer_on_damaged_files(tmp_path, suffix, mutations):
    """A damaged image file fails with an error naming it, or imports as a readable frame of the declared size."""
    from rollingstar.logs.importers import import_images

    folder = tmp_path / "imgs"
    folder.mkdir(exist_ok=True)
    for old in folder.iterdir():
        old.unlink()
    (folder / f"f00{suffix}").write_bytes(_image_bytes(suffix))
    (folder / f"f01{suffix}").write_bytes(_mutate(_image_bytes(suffix), mutations))
    (folder / "recording.yaml").write_text(IMAGE_SIDECAR)
    out = tmp_path / "r.mcap"
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        try:
            import_images(folder, out)
        except UserError as exc:
            assert "f01" in str(exc) or "recording.yaml" in str(exc), str(exc)
            return
    images = [image_from_raw(m) for m in _read_all(out) if m.topic == "/camera/image"]
    assert len(images) == 2 and all(img.shape == (30, 40) for img in images)


_CORR: dict[str, bytes] = {}


def _corr_files(tmp_path) -> tuple[bytes, str]:
    """A valid astrometry.net corr table and log.json (tests/logs/test_importers.write_corr)."""
    if not _CORR:
        from scipy.spatial.transform import Rotation

        from ..logs.test_importers import write_corr

        write_corr(tmp_path / "corr-template", Rotation.from_rotvec([0.3, -0.2, 1.0]), n=12)
        _CORR["fits"] = (tmp_path / "corr-template" / "corr.fits").read_bytes()
        _CORR["json"] = (tmp_path / "corr-template" / "log.json").read_text()
    return _CORR["fits"], _CORR["json"]


@FUZZ
@given(fits_mutations=st.lists(mutation, max_size=3),
       json_edits=st.lists(st.tuples(st.floats(0, 1), st.text(max_size=3)), max_size=2))
def test_corr_importer_on_damaged_tables(tmp_path, fits_mutations, json_edits):
    """Damaged corr FITS / log.json: an error naming the file, or one frame whose stars are finite and inside the image."""
    from rollingstar.logs.importers import import_corr

    fits_bytes, log_json = _corr_files(tmp_path)
    for where, insert in json_edits:
        i = int(where * len(log_json))
        log_json = log_json[:i] + insert + log_json[i + 1:]
    folder = tmp_path / "sky" / "scene"
    folder.mkdir(parents=True, exist_ok=True)
    (folder / "corr.fits").write_bytes(_mutate(fits_bytes, fits_mutations))
    (folder / "log.json").write_text(log_json)
    out = tmp_path / "r.mcap"
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        try:
            import_corr(tmp_path / "sky", out)
        except UserError as exc:
            assert "corr.fits" in str(exc) or "log.json" in str(exc) or "sky" in str(exc), str(exc)
            return
    msgs = _read_all(out)
    frames = [m for m in msgs if m.topic == "/camera/centroids"]
    assert len(frames) == 1  # (possibly without stars: damaged rows are dropped with a warning)
    sensor = scenario_from_yaml(LogReader(out).metadata()["scenario"]["yaml"]).sensor
    x, y = (np.array(frames[0].data[k], dtype=float) for k in ("x", "y"))
    assert np.isfinite(x).all() and np.isfinite(y).all()
    assert ((x >= -0.5) & (x <= sensor.width_px - 0.5) & (y >= -0.5) & (y <= sensor.height_px - 0.5)).all()
