"""The third-party example in docs/log-format.md writes a file rollingstar reads."""
import re
import warnings
from pathlib import Path

import numpy as np

from rollingstar.logs import LogReader, iter_frames, stars_to_arrays

DOC = Path(__file__).resolve().parents[2] / "docs" / "log-format.md"


def _example_code() -> str:
    text = DOC.read_text()
    match = re.search(r"<!-- example: centroid-recording -->\s*```python\n(.*?)```", text, re.S)
    assert match, "example block missing from docs/log-format.md"
    return match.group(1)


def test_documented_example_writes_a_valid_recording(tmp_path, monkeypatch):
    code = _example_code()
    assert "rollingstar" not in re.findall(r"^(?:from|import) (\w+)", code, re.M)
    assert set(re.findall(r"^(?:from|import) (\w+)", code, re.M)) <= {"json", "datetime", "mcap"}
    monkeypatch.chdir(tmp_path)
    exec(compile(code, str(DOC), "exec"), {})
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        reader = LogReader(tmp_path / "centroids.mcap")
        frames = list(iter_frames(reader, "/camera/centroids", ["/gyro"]))
    assert reader.metadata()["rollingstar"]["kind"] == "import"
    assert len(frames) == 3 and all(len(f.side["/gyro"]) == 1 for f in frames)
    stars = stars_to_arrays(frames[0].frame.data)
    assert np.isnan(stars["flux"][2]) and stars["t_ns"].dtype == np.int64


def test_documented_example_runs_through_the_pipeline(tmp_path, monkeypatch):
    """The example's recording carries the sensor model `rollingstar run` needs: the command runs
    on it and says what became of each frame (three unidentifiable stars: no estimate, flagged)."""
    import subprocess
    import sys

    monkeypatch.chdir(tmp_path)
    exec(compile(_example_code(), str(DOC), "exec"), {})
    proc = subprocess.run([sys.executable, "-m", "rollingstar.cli", "run", "baseline", "centroids.mcap", "-o", "out.mcap",
                           "-q"], capture_output=True, text=True, cwd=tmp_path)
    assert proc.returncode == 0, proc.stderr
    assert "3 frames" in proc.stdout and "Traceback" not in proc.stderr
