"""``rollingstar diagnose`` on recordings written by the outsider of ``tests/test_outside_writer.py``
(the plain ``mcap`` package and the documents alone): what the diagnosis says about data nobody
here made. In their own file so that the test runner can put them beside the writer's own tests
on the other worker."""
from __future__ import annotations

import json

import numpy as np

from tests.test_outside_writer import cli, write_centroid_recording, write_image_folder


def test_diagnosis_of_an_outside_recording_measures_its_noise_and_locates_a_stitch(tmp_path):
    """A recording whose sensor has a 0.3 px stitch in y across column 512 (the halves of the
    detector offset) and whose centroid noise is 1.5x the stated ``sigma_px``, written by the
    outsider: ``rollingstar diagnose`` against the model the recording declares names no library
    physics for either, measures the noise factor and describes the stitch where it is. The
    recording's scenario declares no motion although the camera turns: the diagnosis finds the
    motion in the frames themselves (``inputs.sequence_moves``): fitted as a still sensor, the
    frames' rolling-shutter skew would look like library physics."""
    def stitched_and_noisier(record, rng):
        x = np.asarray(record["x"])
        y = np.asarray(record["y"]) + np.where(x >= 512.0, 0.3, 0.0)
        n = len(x)
        extra = 0.1 * np.sqrt(1.5**2 - 1.0)  # noise 1.5x the stated 0.1 px
        return {**record, "x": (x + rng.normal(0, extra, n)).tolist(), "y": (y + rng.normal(0, extra, n)).tolist()}

    recording = tmp_path / "stitched.mcap"
    write_centroid_recording(recording, 30, sigma_px=0.1, seed=5, edit=stitched_and_noisier)
    proc = cli("diagnose", "--recording", recording, "--json", "-q")
    assert proc.returncode == 0, proc.stderr
    result = json.loads(proc.stdout)
    print(result["summary"])
    assert result["effects"] == [], result["summary"]
    noise = result["noise_check"]
    assert noise["applied"] and abs(noise["factor"] - 1.5) < 4 * noise["factor_sigma"], noise
    shape = result["unexplained_systematic"]["description"]
    assert shape is not None and (shape["shape"], shape["axis"], shape["coordinate"]) == ("step", "y", "column"), shape
    low, high = shape["between_px"]  # the step lies between two stars' columns: 512 must be in that gap
    assert low - 1 <= 511.5 <= high + 1, shape
    assert abs(shape["coefficients_px"][0] - 0.3) < 4 * shape["sigmas_px"][0], shape


def test_diagnosis_of_the_outside_image_folder_finds_no_mismatch(tmp_path):
    """The outsider's rendered frames (its own Gaussian renderer, OpenCV camera frame, a sidecar)
    imported and diagnosed against the model they declare: nothing named and nothing left
    unexplained. A star the renderer cut at the detector's edge sits 13 sigma off in one held-out
    frame: it is reported as an isolated misfit, not taken for a systematic."""
    folder, meta = tmp_path / "frames", tmp_path / "meta"
    folder.mkdir()
    meta.mkdir()
    write_image_folder(folder, meta, 12, seed=5)
    recording = tmp_path / "outside_images.mcap"
    assert cli("import", "images", folder, "--sidecar", meta / "recording.yaml", "-o", recording).returncode == 0
    proc = cli("diagnose", "--recording", recording, "--json", "-q")
    assert proc.returncode == 0, proc.stderr
    result = json.loads(proc.stdout)
    print(result["summary"])
    assert result["effects"] == [] and not result["unexplained_systematic"]["present"], result["summary"]
    assert not result["mismatch"]
    assert len(result["isolated_misfits"]) <= 2
