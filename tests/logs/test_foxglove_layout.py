"""The shipped Foxglove layout against a real run output, read with the plain ``mcap`` package: every
topic it names is there with the documented schema, every plot path resolves to a number, and the
attitude errors it plots are evaluate's."""
import json
import re
from pathlib import Path

import numpy as np
import pytest
from mcap.reader import make_reader

from rollingstar.pipelines.config import load_pipeline
from rollingstar.pipelines.evaluate import evaluate_log
from rollingstar.pipelines.runner import run_pipeline
from rollingstar.pipelines.simulate import simulate_to_log
from rollingstar.sensors.scenario import load_scenario

ROOT = Path(__file__).resolve().parents[2]
LAYOUT = ROOT / "configs" / "foxglove" / "run.json"
# the schema each panel's topic must carry (docs/foxglove.md)
SCHEMAS = {"/camera/image": "foxglove.RawImage", "/estimate/spots": "foxglove.ImageAnnotations",
           "/estimate/pose": "foxglove.PoseInFrame", "/estimate/attitude_error": "rollingstar.AttitudeError",
           "/estimate/rate": "rollingstar.RateEstimate", "/truth/attitude": "rollingstar.AttitudeSamples",
           "/estimate/frame": "rollingstar.FrameStatus"}


@pytest.fixture(scope="module")
def output(tmp_path_factory) -> Path:
    tmp = tmp_path_factory.mktemp("foxglove")
    cfg = load_scenario(ROOT / "configs" / "scenarios" / "he2021a.yaml")
    simulate_to_log(cfg, tmp / "rec.mcap", frames=6, show_progress=False)
    run_pipeline(tmp / "rec.mcap", load_pipeline(ROOT / "configs" / "pipelines" / "high_dynamic.yaml"),
                 tmp / "out.mcap", show_progress=False, with_images=True)
    return tmp / "out.mcap"


def _layout_topics(layout: dict) -> tuple[set[str], list[str]]:
    """Topics the panels subscribe to, and the plot message paths."""
    topics, paths = set(), []
    for panel_id, cfg in layout["configById"].items():
        kind = panel_id.split("!")[0]
        if kind == "Image":
            topics.add(cfg["imageMode"]["imageTopic"])
            topics |= set(cfg["imageMode"].get("annotations", {}))
        elif kind == "3D":
            topics |= set(cfg["topics"])
        elif kind == "Plot":
            for p in cfg["paths"]:
                paths.append(p["value"])
                topics.add(p["value"].split(".", 1)[0])
    return topics, paths


def _resolve(record: dict, path: str):
    """A Foxglove message path's value in a JSON record: ``a.b``, ``a[0]``."""
    value = record
    for name, index in re.findall(r"([A-Za-z_][A-Za-z0-9_]*)(?:\[(\d+)\])?", path):
        value = value[name]
        if index:
            value = value[int(index)]
    return value


def _read(path: Path):
    with open(path, "rb") as f:
        for schema, channel, message in make_reader(f).iter_messages():
            yield schema.name, channel.topic, message.data


def test_every_layout_topic_is_in_a_run_output_with_its_schema(output):
    layout = json.loads(LAYOUT.read_text())
    topics, paths = _layout_topics(layout)
    seen = {}
    for schema, topic, _ in _read(output):
        seen.setdefault(topic, schema)
    for topic in topics:
        assert seen.get(topic) == SCHEMAS[topic], (topic, seen.get(topic))
    panels = set(layout["configById"])
    leaves = set(re.findall(r'"([A-Za-z0-9]+![A-Za-z0-9-]+)"', json.dumps(layout["layout"])))
    assert leaves == panels  # every configured panel is placed, and nothing else


def test_every_plot_path_resolves_to_numbers(output):
    _, paths = _layout_topics(json.loads(LAYOUT.read_text()))
    records: dict[str, list[dict]] = {}
    for schema, topic, data in _read(output):
        if schema.startswith("rollingstar."):
            records.setdefault(topic, []).append(json.loads(data))
    for path in paths:
        topic, field = path.split(".", 1)
        values = [_resolve(r, field) for r in records[topic]]
        assert values and all(isinstance(v, (int, float)) and np.isfinite(v) for v in values), path


def test_the_plotted_attitude_errors_are_evaluates(output):
    errors = np.array([[r[f"{a}_arcsec"] for a in "xyz"] for schema, topic, data in _read(output)
                       if topic == "/estimate/attitude_error" for r in [json.loads(data)]])
    series = evaluate_log(output, series=True)["series"]["attitude_error_arcsec"]
    assert errors.shape == series.shape and errors.shape[0] >= 5
    np.testing.assert_allclose(errors, series, atol=1e-6)


def test_overlays_fall_on_the_image(output):
    from foxglove_schemas_protobuf.ImageAnnotations_pb2 import ImageAnnotations
    from foxglove_schemas_protobuf.RawImage_pb2 import RawImage

    images, spots = [], []
    for schema, topic, data in _read(output):
        if topic == "/camera/image":
            images.append(RawImage.FromString(data))
        elif topic == "/estimate/spots":
            spots.append(ImageAnnotations.FromString(data))
    assert len(images) == len(spots) == 6
    for img, ann in zip(images, spots):
        pts = [c.position for c in ann.circles]
        assert pts and all(0 <= p.x <= img.width and 0 <= p.y <= img.height for p in pts)
        assert any(t.text not in ("", "?") for t in ann.texts)  # identified stars carry their catalogue id


def test_preview_draws_the_layout_from_the_output(output, tmp_path):
    import subprocess
    import sys

    proc = subprocess.run([sys.executable, "-m", "rollingstar.cli", "preview", str(output), "-o",
                           str(tmp_path / "p.png")], capture_output=True, text=True, timeout=300)
    assert proc.returncode == 0, proc.stderr
    assert (tmp_path / "p.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    proc = subprocess.run([sys.executable, "-m", "rollingstar.cli", "preview", str(output), "-o", str(output)],
                          capture_output=True, text=True, timeout=300)
    assert proc.returncode == 2 and "input" in proc.stderr  # the log itself is never overwritten


def test_the_sinks_truth_buffer_interpolates_as_evaluate_does_in_any_message_order():
    """Samples added out of time order and past the buffer's first capacity give the same truth as
    the evaluation's trajectory (Slerp over all samples)."""
    from scipy.spatial.transform import Rotation

    from rollingstar.pipelines.sink import _TruthAttitude
    from rollingstar.pipelines.truth import TruthTrajectory

    rng = np.random.default_rng(2)
    t = np.arange(0, 300) * 5_000_000
    q = Rotation.from_rotvec(np.cumsum(rng.normal(0, 1e-3, (t.size, 3)), axis=0)).as_quat()
    buf = _TruthAttitude()
    chunks = np.array_split(np.arange(t.size), 30)
    for k in rng.permutation(len(chunks)):  # messages out of order
        i = chunks[k]
        buf.add({"t_ns": t[i].tolist(), "qx": q[i, 0], "qy": q[i, 1], "qz": q[i, 2], "qw": q[i, 3]})
    when = rng.integers(t[0], t[-1], 200)
    got, covered = buf.at(when)
    want = TruthTrajectory(t, q, np.zeros((t.size, 3))).attitude(when)
    assert covered.all()
    assert np.degrees((got.inv() * want).magnitude()).max() * 3600 < 1e-6  # arcsec
    _, outside = buf.at(np.array([t[-1] + 1]))
    assert not outside.any()
