"""The documents' camera frame, pixel origin and attitude agree with the code.

Each test reads a statement from docs/conventions.md (the one place they are defined), from the
"Conventions" of docs/log-format.md, or from any document that states a camera axis, turns it into
numbers and compares it with :class:`~rollingstar.sensors.camera.PinholeCamera` and
:func:`~rollingstar.sensors.conventions.attitude_from_radec_roll`. The expected answers come from
the documents' text, never from a copy of them in this file.
"""
from __future__ import annotations

import ast
import re
from pathlib import Path

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from rollingstar.sensors.camera import PinholeCamera
from rollingstar.sensors.conventions import attitude_from_opencv, attitude_from_radec_roll, radec_to_unit

ROOT = Path(__file__).resolve().parents[1]
CONVENTIONS = ROOT / "docs" / "conventions.md"
LOG_FORMAT = ROOT / "docs" / "log-format.md"
CAMERA = PinholeCamera(focal_length_m=24e-3, pixel_size_m=5.5e-6, width=1024, height=768, cx=530.0, cy=370.0)


def _flat(text: str) -> str:
    """Markdown as one line of plain words: no line breaks, code quotes or emphasis (``*word*``,
    ``**words**``; a ``*`` between spaces is a product and stays)."""
    text = re.sub(r"\*\*([^*]+)\*\*", r"\1", text.replace("`", ""))
    return re.sub(r"\s+", " ", re.sub(r"\*(\w[^*\s]*)\*", r"\1", text))


def _table(column: int = 1) -> dict[str, str]:
    """conventions.md's table: quantity -> convention (``column`` 1) or helper (2), code quotes kept."""
    rows = {}
    for line in CONVENTIONS.read_text().splitlines():
        cells = [c.strip() for c in line.strip().strip("|").split("|")]
        if line.startswith("|") and len(cells) == 3 and not set(cells[0]) <= {"-"}:
            rows[cells[0]] = cells[column]
    return rows


def _log_format_bullet(name: str) -> str:
    """The ``- **name**...`` bullet of log-format.md's Conventions, flattened."""
    text = LOG_FORMAT.read_text()
    match = re.search(rf"^- \*\*{re.escape(name)}\*\*(.*?)(?=^- \*\*|^## )", text, re.S | re.M)
    assert match, f"log-format.md: no '{name}' bullet under Conventions"
    return match.group(0)


def _expression(text: str, names: dict[str, float]):
    """Evaluate a formula as the documents write it (``-(x - cx) p``: a product by juxtaposition;
    ``^`` a power; a name ``names`` maps to a function, followed by ``(``, a call)."""
    tokens = re.findall(r"[A-Za-z_]\w*|\d+(?:\.\d*)?|\*\*|\S", text.replace("^", "**"))
    out = []
    for prev, tok in zip([None, *tokens], tokens):
        operand_end = prev is not None and (prev == ")" or re.fullmatch(r"\w+(?:\.\d*)?", prev))
        operand_end = operand_end and not (tok == "(" and callable(names.get(prev)))  # a function call
        if operand_end and (tok == "(" or re.fullmatch(r"\w+(?:\.\d*)?", tok)):
            out.append("*")
        out.append(tok)
    code = " ".join(out)
    unknown = {n.id for n in ast.walk(ast.parse(code, mode="eval")) if isinstance(n, ast.Name)} - set(names)
    assert not unknown, f"formula {text!r} uses {unknown}, not defined by the document"
    return eval(compile(code, "<doc>", "eval"), {"__builtins__": {}}, dict(names))  # noqa: S307


def _direction_tilted(axis: str, sign: int) -> np.ndarray:
    """A camera-frame direction 1 deg from the boresight towards ``sign`` times ``axis``."""
    w = np.array([0.0, 0.0, 1.0])
    w["xyz".index(axis)] = sign * np.tan(np.radians(1.0))
    return w


def _image_motion(w: np.ndarray) -> tuple[float, float]:
    x, y, _ = CAMERA.project(w)
    return float(x - CAMERA.cx), float(y - CAMERA.cy)


def _code_axis_words(axis: str, sign: int = 1) -> str:
    """What the code does: 'increasing'/'decreasing' column/row where ``sign * axis`` images."""
    dx, dy = _image_motion(_direction_tilted(axis, sign))
    along, d = ("column", dx) if abs(dx) > abs(dy) else ("row", dy)
    return f"{'increasing' if d > 0 else 'decreasing'} {along}"


def test_pixel_direction_formula_is_the_cameras():
    formula = re.search(r"w ~ \[(.*?)\]", _table()["pixel direction"])
    assert formula, "conventions.md: pixel direction row has no 'w ~ [...]' formula"
    components = [c.strip() for c in formula.group(1).split(",")]
    rng = np.random.default_rng(0)
    x, y = rng.uniform(-0.5, CAMERA.width - 0.5, 50), rng.uniform(-0.5, CAMERA.height - 0.5, 50)
    names = {"x": x, "y": y, "cx": CAMERA.cx, "cy": CAMERA.cy, "p": CAMERA.pixel_size_m, "f": CAMERA.focal_length_m}
    w = np.stack([np.broadcast_to(_expression(c, names), x.shape) for c in components], axis=-1)
    np.testing.assert_allclose(w / np.linalg.norm(w, axis=-1, keepdims=True), CAMERA.unproject(x, y), atol=1e-15)


@pytest.mark.parametrize("where", ["conventions.md", "log-format.md"])
def test_image_of_a_camera_vector_is_the_cameras(where):
    text = _table()["pixel direction"] if where == "conventions.md" else _flat(_log_format_bullet("Camera frame"))
    pairs = dict(re.findall(r"\b([xy]) = (c[xy] - [^,`;]*?w_[xy] / w_z)", text.replace("`", "")))
    assert set(pairs) == {"x", "y"}, f"{where}: the image x = ..., y = ... of a camera vector is not stated"
    w = np.random.default_rng(1).normal([0, 0, 1], [0.05, 0.05, 0.0], (40, 3))
    names = {"cx": CAMERA.cx, "cy": CAMERA.cy, "w_x": w[:, 0], "w_y": w[:, 1], "w_z": w[:, 2],
             "f": CAMERA.focal_length_m, "p": CAMERA.pixel_size_m, "f_px": CAMERA.focal_px}
    x, y, _ = CAMERA.project(w)
    np.testing.assert_allclose(_expression(pairs["x"], names), x, atol=1e-9)
    np.testing.assert_allclose(_expression(pairs["y"], names), y, atol=1e-9)


def test_the_camera_frame_row_says_where_each_axis_images():
    row = _flat(_table()["camera frame"])
    for axis in "xy":
        stated = re.search(rf"\+{axis} (?:points )?towards (\w+ (?:column|row))", row)
        assert stated, f"conventions.md: camera frame row does not say where +{axis} points"
        assert stated.group(1) == _code_axis_words(axis), (axis, stated.group(1))
    right = re.search(r"a star imaged right of the principal point \(larger column\) has a (\w+) camera x", row)
    below = re.search(r"a star imaged below it \(larger row\) a (\w+) camera y", row)
    assert right and below, "conventions.md: camera frame row lost its star examples"
    w_right, w_below = CAMERA.unproject(CAMERA.cx + 10.0, CAMERA.cy), CAMERA.unproject(CAMERA.cx, CAMERA.cy + 10.0)
    assert {"negative": -1, "positive": 1}[right.group(1)] == np.sign(w_right[0])
    assert {"negative": -1, "positive": 1}[below.group(1)] == np.sign(w_below[1])


def _opencv_rule() -> tuple[float, np.ndarray, np.ndarray]:
    """(angle of ``R = R_opencv * Rz(angle)``, its scalar-last quaternion, rate signs) from the table."""
    row = _table()["OpenCV camera frame to ours"].replace("`", "")
    angle = re.search(r"R = R_opencv \* Rz\((\d+) deg\)", row)
    quat = re.search(r"q = q_opencv \* \(([^)]*)\)", row)
    rates = re.search(r"\(wx, wy, wz\) = \(([^)]*)\)_opencv", row)
    assert angle and quat and rates, "conventions.md: the OpenCV row lost its attitude, quaternion or rate rule"
    signs = np.array([-1.0 if c.strip().startswith("-") else 1.0 for c in rates.group(1).split(",")])
    return np.radians(float(angle.group(1))), np.array([float(v) for v in quat.group(1).split(",")]), signs


def test_opencv_rule_maps_the_opencv_pinhole_onto_ours():
    """An OpenCV camera (x = cx + f X/Z, y = cy + f Y/Z) with attitude R_opencv images every star
    where PinholeCamera images it with the attitude the rule gives; its body rate maps likewise."""
    angle, quat, signs = _opencv_rule()
    fix = Rotation.from_rotvec([0.0, 0.0, angle])
    np.testing.assert_allclose(Rotation.from_quat(quat).as_matrix(), fix.as_matrix(), atol=1e-12)
    r_cv = Rotation.from_rotvec([0.3, -0.2, 1.1]) * attitude_from_radec_roll(40.0, 20.0, 0.0)
    stars = radec_to_unit(np.radians(40.0 + np.array([0.5, -1.0, 2.0])), np.radians(20.0 + np.array([1.0, -2.0, 0.3])))
    w_cv = r_cv.inv().apply(stars)
    x_cv = CAMERA.cx + CAMERA.focal_px * w_cv[:, 0] / w_cv[:, 2]
    y_cv = CAMERA.cy + CAMERA.focal_px * w_cv[:, 1] / w_cv[:, 2]
    x, y, _ = CAMERA.project((r_cv * fix).inv().apply(stars))
    np.testing.assert_allclose(np.c_[x, y], np.c_[x_cv, y_cv], atol=1e-9)
    omega_cv, dt = np.array([0.01, -0.02, 0.03]), 0.5  # R(t + dt) = R(t) Exp(omega dt), both frames
    later = (r_cv * Rotation.from_rotvec(omega_cv * dt)) * fix
    ours = (r_cv * fix) * Rotation.from_rotvec(signs * omega_cv * dt)
    assert (later.inv() * ours).magnitude() < 1e-12
    helper = re.match(r"`(\w+)`", _table(column=2)["OpenCV camera frame to ours"])
    assert helper and helper.group(1) == "attitude_from_opencv", "conventions.md: the OpenCV row names its helper"
    assert (attitude_from_opencv(r_cv).inv() * (r_cv * fix)).magnitude() < 1e-12


def test_roll_row_is_attitude_from_radec_roll():
    row = _flat(_table()["boresight and roll"])
    assert re.search(r"R\(ra, dec, roll\) = R\(ra, dec, 0\) \* Rz\(roll\)", row), row
    for ra, dec, roll in [(83.8, -5.4, 30.0), (200.0, 60.0, -75.0), (10.0, -80.0, 170.0)]:
        composed = attitude_from_radec_roll(ra, dec, 0.0) * Rotation.from_rotvec([0.0, 0.0, np.radians(roll)])
        assert (composed.inv() * attitude_from_radec_roll(ra, dec, roll)).magnitude() < 1e-12
        np.testing.assert_allclose(attitude_from_radec_roll(ra, dec, roll).apply([0, 0, 1]),
                                   radec_to_unit(np.radians(ra), np.radians(dec)), atol=1e-12)
    north = re.search(r"north images (below|above) the principal point \((\w+ row)\)", row)
    east = re.search(r"east to its (right|left) \((\w+ column)\)", row)
    assert north and east, "conventions.md: roll row does not say where north and east image"
    r0 = attitude_from_radec_roll(83.8, -5.4, 0.0)
    dx_n, dy_n = _image_motion(r0.inv().apply(radec_to_unit(np.radians(83.8), np.radians(-5.0))))
    dx_e, dy_e = _image_motion(r0.inv().apply(radec_to_unit(np.radians(84.2), np.radians(-5.4))))
    assert abs(dx_n) < 1e-6 and north.group(2) == ("increasing row" if dy_n > 0 else "decreasing row")
    assert north.group(1) == ("below" if dy_n > 0 else "above")
    assert abs(dy_e) < 0.1 and east.group(2) == ("increasing column" if dx_e > 0 else "decreasing column")
    assert east.group(1) == ("right" if dx_e > 0 else "left")
    assert "-y axis points to celestial north" in row and np.sign(dy_n) == np.sign(_image_motion([0, -0.01, 1])[1])


def test_pixel_row_spans_the_detector_contains():
    row = _table()["pixel"].replace("`", "")
    span = re.search(r"spans \[([^,]+), ([^\]]+)\] x \[([^,]+), ([^\]]+)\]", row)
    assert span and "(0, 0) is the centre of the first pixel" in row
    names = {"W": CAMERA.width, "H": CAMERA.height}
    x0, x1, y0, y1 = (float(_expression(span.group(i), names)) for i in range(1, 5))
    for x, y in [(x0, y0), (x1, y1), (x0, y1), (x1, y0)]:
        assert CAMERA.contains(x, y)
    for x, y in [(x0 - 1e-9, y0), (x1 + 1e-9, y0), (x0, y0 - 1e-9), (x0, y1 + 1e-9)]:
        assert not CAMERA.contains(x, y)
    assert x0 + 0.5 == 0.0 and y0 + 0.5 == 0.0  # so the first pixel [x0, x0 + 1] has its centre at 0


def test_log_format_camera_frame_agrees_and_links_to_conventions():
    bullet = _log_format_bullet("Camera frame")
    assert "(conventions.md)" in bullet and "(conventions.md)" in _log_format_bullet("Pixels")
    flat = _flat(bullet)
    for axis in "xy":
        stated = re.search(rf"\+{axis} (?:points )?towards (\w+ (?:column|row))", flat)
        assert stated and stated.group(1) == _code_axis_words(axis), (axis, flat)
    angle, quat, signs = _opencv_rule()
    quat_text = re.search(r"q = q_opencv \* \(([^)]*)\)", flat)
    rates_text = re.search(r"body rates \(([^)]*)\)", flat)
    assert quat_text and rates_text, flat
    np.testing.assert_array_equal([float(v) for v in quat_text.group(1).split(",")], quat)
    np.testing.assert_array_equal([-1.0 if c.strip().startswith("-") else 1.0 for c in rates_text.group(1).split(",")],
                                  signs)


AXIS_STATEMENT = re.compile(r"([+-])([xy]) (?:axis )?(?:is |points )?(?:along |towards )?(increasing|decreasing) (column|row)")
AXIS_IMAGE = re.compile(r"([+-])([xy]) (?:axis )?\(?(?:points )?(?:towards )?image (up|down|left|right)")
IMAGE_AXIS = re.compile(r"image (up|down|left|right),? \((?:camera )?([+-])([xy])\b")
OTHER_FRAMES = ("OpenCV", "opencv", "tetra3", "Foxglove", "FITS")


def _documents() -> list[Path]:
    docs = [*sorted((ROOT / "docs").rglob("*.md")), ROOT / "README.md", *sorted((ROOT / "configs").rglob("*.yaml"))]
    return docs + [*sorted((ROOT / "logs" / "importers").glob("*.py")), ROOT / "sensors" / "conventions.py",
                   ROOT / "sensors" / "camera.py", ROOT / "sensors" / "scenario.py", ROOT / "sensors" / "build.py"]


def _axis_claims(text: str):
    """(matched text, sign, axis, claimed image direction) of every camera-axis statement of ``text``
    that is not about another frame (a clause that names OpenCV, tetra3, Foxglove or FITS)."""
    words = {"up": "decreasing row", "down": "increasing row", "left": "decreasing column", "right": "increasing column"}
    for m in AXIS_STATEMENT.finditer(text):
        yield m, m.group(1), m.group(2), f"{m.group(3)} {m.group(4)}"
    for m in AXIS_IMAGE.finditer(text):
        yield m, m.group(1), m.group(2), words[m.group(3)]
    for m in IMAGE_AXIS.finditer(text):
        yield m, m.group(2), m.group(3), words[m.group(1)]


def test_every_document_that_states_a_camera_axis_agrees_with_the_code():
    """Statements like '+x points towards decreasing column', '-y (image up)' or 'image up (-y)'
    anywhere in the docs, README, configs and the sensor/importer docstrings, except where they
    describe another frame, match where the code images that axis; a Markdown document that states
    one links to conventions.md."""
    wrong, unlinked = [], []
    for path in _documents():
        text = _flat(path.read_text())
        found = False
        for m, sign, axis, claim in _axis_claims(text):
            clause = text[max(text.rfind(c, 0, m.start()) for c in ".;|") + 1:m.start()]
            if any(word in clause for word in OTHER_FRAMES):
                continue
            found = True
            if claim != _code_axis_words(axis, 1 if sign == "+" else -1):
                wrong.append(f"{path.relative_to(ROOT)}: '{m.group(0)}'")
        if found and path.suffix == ".md" and path != CONVENTIONS and "conventions.md" not in text \
                and "(#conventions)" not in text:
            unlinked.append(str(path.relative_to(ROOT)))
    assert not wrong, "axis statements that disagree with PinholeCamera:\n" + "\n".join(wrong)
    assert not unlinked, "documents that state a camera axis without linking docs/conventions.md: " + ", ".join(unlinked)


def test_the_axis_scan_finds_a_wrong_statement():
    """The scan above is not blind: the statements these documents used to make are caught."""
    old = ["+z is the boresight, +x is along increasing column and +y along increasing row",
           "the camera's -y axis (image up, decreasing row) points to celestial north",
           "zenith towards image up (-y); None in space"]
    for text in old:
        claims = list(_axis_claims(_flat(text)))
        assert claims and any(c != _code_axis_words(a, 1 if s == "+" else -1) for _, s, a, c in claims), text


def test_the_lens_projection_row_is_the_cameras():
    """Each projection's radius law and the distortion as conventions.md states them, evaluated
    from its text, against where the camera images directions up to 80 deg from the boresight."""
    from rollingstar.sensors.camera import PROJECTIONS

    text = _table()["lens projection"]
    laws = dict(re.findall(r"(\w+)(?: \(the pinhole\))? `r = ([^`]*)`", text))
    assert set(laws) == set(PROJECTIONS), f"conventions.md: projections stated {sorted(laws)}, the code's {PROJECTIONS}"
    distortion = re.search(r"`r' = ([^`]*)`", text)
    assert distortion, "conventions.md: the lens projection row states no distortion r' = ..."
    rng = np.random.default_rng(5)
    theta = rng.uniform(0.0, np.radians(80.0), 60)
    phi = rng.uniform(-np.pi, np.pi, 60)
    w = np.column_stack([np.sin(theta) * np.cos(phi), np.sin(theta) * np.sin(phi), np.cos(theta)])
    k = {"k1": -0.02, "k2": 0.001, "k3": -1e-5}
    for name, law in laws.items():
        cam = PinholeCamera(focal_length_m=4e-3, pixel_size_m=5e-6, width=808, height=608, projection=name, **k)
        names = {"f_px": cam.focal_px, "theta": theta, "tan": np.tan, "sin": np.sin, **k}
        r = _expression(law, names)
        r = _expression(distortion.group(1), {**names, "r": r})
        x, y, _ = cam.project(w)
        # along the pinhole's azimuth: a camera vector with positive x images at smaller columns
        np.testing.assert_allclose(x, cam.cx - r * np.cos(phi), atol=1e-6)
        np.testing.assert_allclose(y, cam.cy - r * np.sin(phi), atol=1e-6)
