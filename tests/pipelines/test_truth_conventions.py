"""``rollingstar evaluate`` on a run whose ``/truth/attitude`` was written in another tool's
convention (docs/conventions.md states ours: camera-to-ICRS, our camera frame, named quaternion
fields). The errors are reported against the truth as written, and a warning names the reading
under which the estimates agree with it; a truth in our convention gets no warning."""
from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation
from typer.testing import CliRunner

from rollingstar.cli import app
from rollingstar.pipelines.evaluate import evaluate_log
from tests.reliability.helpers import rewrite


def _with_truth(src, dst, rewrite_q) -> None:
    """A copy of the run ``src`` whose ``/truth/attitude`` quaternions (scalar-last rows) pass through
    ``rewrite_q``, written back into the named fields."""
    def edit(messages):
        out = []
        for m in messages:
            if m.topic == "/truth/attitude":
                q = rewrite_q(np.column_stack([m.data[k] for k in ("qx", "qy", "qz", "qw")]))
                data = {**m.data, **{k: q[:, i].tolist() for i, k in enumerate(("qx", "qy", "qz", "qw"))}}
                m = type(m)(m.topic, m.log_time_ns, m.schema_name, data)
            out.append(m)
        return out

    rewrite(src, dst, edit)


def _opencv(q):  # our attitude R = R_opencv * Rz(180 deg), so R_opencv = R * Rz(180 deg)^-1
    return (Rotation.from_quat(q) * Rotation.from_rotvec([0.0, 0.0, -np.pi])).as_quat()


WRITTEN = {
    "inverse": (lambda q: Rotation.from_quat(q).inv().as_quat(), "ICRS-to-camera rotation (the inverse"),
    "opencv": (_opencv, "in the OpenCV camera frame"),
    "scalar first": (lambda q: np.roll(q, 1, axis=1), "scalar first"),
    "inverse, OpenCV frame": (lambda q: Rotation.from_quat(_opencv(q)).inv().as_quat(),
                              "ICRS-to-camera rotation in the OpenCV camera frame"),
}


@pytest.mark.parametrize("name", list(WRITTEN))
def test_a_truth_written_in_another_convention_is_named(tmp_path, small_output, name):
    rewrite, words = WRITTEN[name]
    out = tmp_path / "run.mcap"
    _with_truth(small_output, out, rewrite)
    m = evaluate_log(out)
    assert max(m["attitude_error_arcsec"][f"{a}_rmse"] for a in "xyz") > 3600.0  # against the truth as written
    assert words in m.get("truth_convention", ""), m.get("truth_convention")
    res = CliRunner().invoke(app, ["evaluate", str(out)])
    assert res.exit_code == 0 and "warning" in res.output and words.split()[0] in " ".join(res.output.split())


def test_a_truth_in_our_convention_gets_no_warning(tmp_path, small_output):
    out = tmp_path / "run.mcap"
    _with_truth(small_output, out, lambda q: q)
    m = evaluate_log(out)
    assert "truth_convention" not in m
    assert max(m["attitude_error_arcsec"][f"{a}_rmse"] for a in "xyz") < 60.0
