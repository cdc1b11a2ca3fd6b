"""``rollingstar diagnose`` on recordings written by the outsider of ``tests/test_outside_writer.py``
(the plain ``mcap`` package and the documents alone): what the diagnosis says about data nobody
here made. In their own file so that the test runner can put them beside the writer's own tests
on the other worker."""
from __future__ import annotations

import json
import subprocess
import sys

import numpy as np
import pytest

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


def _rewritten(src, dst, record_edit, time_edit=lambda t: t) -> None:
    """The outside recording rewritten by an outsider's own converter (plain mcap reader and writer,
    the metadata kept): ``record_edit(topic, record)`` on every JSON record, ``time_edit`` on log times."""
    from mcap.reader import make_reader
    from mcap.writer import Writer

    with open(src, "rb") as f, open(dst, "wb") as g:
        reader = make_reader(f)
        w = Writer(g)
        w.start(profile="rollingstar", library="outside")
        for meta in reader.iter_metadata():
            w.add_metadata(meta.name, meta.metadata)
        channels = {}
        for schema, channel, message in reader.iter_messages():
            if channel.id not in channels:
                sid = w.register_schema(schema.name, schema.encoding, schema.data)
                channels[channel.id] = w.register_channel(channel.topic, channel.message_encoding, sid)
            record = record_edit(channel.topic, json.loads(message.data))
            w.add_message(channels[channel.id], time_edit(message.log_time), json.dumps(record).encode(),
                          time_edit(message.publish_time))
        w.finish()


def _times_in_microseconds(src, dst) -> None:
    """What an outsider whose clock counts microseconds writes: every log time and time field / 1000."""
    def us(v):
        return [us(x) for x in v] if isinstance(v, list) else v // 1000

    _rewritten(src, dst, lambda topic, r: {k: (us(v) if k.endswith("_ns") else v) for k, v in r.items()},
               lambda t: t // 1000)


def test_an_outside_recording_with_times_in_microseconds_is_refused_not_diagnosed(tmp_path):
    """Frames 100 us apart on a camera whose shutter needs 50 ms between frames: the times are in
    another unit. Both commands that read the frames refuse it naming the spacing and the unit,
    instead of a verdict on residuals that are not numbers."""
    ns, us_ = tmp_path / "ns.mcap", tmp_path / "us.mcap"
    write_centroid_recording(ns, 4, sigma_px=0.1, seed=5)
    _times_in_microseconds(ns, us_)
    for args in (("diagnose", "--recording", us_, "-o", tmp_path / "d", "-q"),
                 ("run", "baseline", us_, "-o", tmp_path / "out.mcap", "-q")):
        proc = subprocess.run([sys.executable, "-m", "rollingstar.cli", *map(str, args)], capture_output=True, text=True)
        assert proc.returncode == 2 and "Traceback" not in proc.stderr, proc.stderr
        assert "ns after the previous frame" in proc.stderr and "nanoseconds" in proc.stderr, proc.stderr


def test_a_reference_attitude_in_another_convention_is_refused_naming_it(tmp_path):
    """The outsider's /truth/attitude written with the quaternion's scalar first: used as a reference
    of 1 arcsec it would be 1e12 chi-square off; the diagnosis names the convention instead."""
    ok, wxyz = tmp_path / "ok.mcap", tmp_path / "wxyz.mcap"
    write_centroid_recording(ok, 6, sigma_px=0.1, seed=5)

    def scalar_first(topic, r):
        if topic != "/truth/attitude":
            return r
        return {**r, "qx": r["qw"], "qy": r["qx"], "qz": r["qy"], "qw": r["qz"]}

    _rewritten(ok, wxyz, scalar_first)
    args = ("diagnose", "--recording", wxyz, "-o", tmp_path / "d", "-q", "--reference-attitude-arcsec", "1")
    proc = subprocess.run([sys.executable, "-m", "rollingstar.cli", *map(str, args)], capture_output=True, text=True)
    assert proc.returncode == 2 and "Traceback" not in proc.stderr, proc.stderr
    assert "misses the attitude the stars give" in proc.stderr and "scalar first" in proc.stderr, proc.stderr
    assert cli("diagnose", "--recording", ok, "-o", tmp_path / "d2", "-q", "--reference-attitude-arcsec", "1")



@pytest.mark.parametrize("theta, convention", [((0.99, 0.96), "counted from 1"), ((0.52, 0.47), "corner"),
                                               ((0.80, 0.96), None), ((3.0, 1.0), None)])
def test_a_principal_point_at_a_pixel_origin_convention_is_tentative_and_says_so(theta, convention):
    """A recording whose pixels count from 1 (or from the first pixel's corner) shows a principal
    point shifted by exactly that: named, the report says so and keeps it tentative; a shift
    that is not a convention's value is not doubted for it."""
    from types import SimpleNamespace

    from rollingstar.estimators.diagnosis.library import library
    from rollingstar.estimators.diagnosis.verifying import effect_row

    naming = SimpleNamespace(correlations={}, delta_bic={}, delta_bic_method={}, selection={"inclusion": {}},
                             pooled_inclusion={})
    row = effect_row(library()["principal_point"], np.array(theta), np.array([0.02, 0.02]), naming,
                     SimpleNamespace(stability=[]), unexplained=False, confirms=True)
    doubts = " ".join(row["tentative_because"])
    if convention is None:
        assert row["confidence"] == "confident" and "pixel-origin" not in doubts
    else:
        assert row["confidence"] == "tentative" and convention in doubts and "docs/conventions.md" in doubts


@pytest.mark.parametrize("convert, reading", [
    (lambda w: np.degrees(w), "in deg/s"),
    (lambda w: w * np.array([-1.0, -1.0, 1.0]), "about the OpenCV camera axes"),
])
def test_a_gyro_in_another_convention_is_refused_naming_it(tmp_path, convert, reading):
    """The outsider's /gyro rewritten in degrees per second, or about the OpenCV camera axes: the
    diagnosis would otherwise name a noise factor or a gyro bias of twice the rate; it names the
    reading that fits the frames' own rates instead."""
    ok, bad = tmp_path / "ok.mcap", tmp_path / "bad.mcap"
    write_centroid_recording(ok, 8, sigma_px=0.1, seed=5)

    def rates(topic, r):
        if topic != "/gyro":
            return r
        w = convert(np.column_stack([r["x"], r["y"], r["z"]]))
        return {**r, "x": w[:, 0].tolist(), "y": w[:, 1].tolist(), "z": w[:, 2].tolist()}

    _rewritten(ok, bad, rates)
    args = ("diagnose", "--recording", bad, "-o", tmp_path / "d", "-q")
    proc = subprocess.run([sys.executable, "-m", "rollingstar.cli", *map(str, args)], capture_output=True, text=True)
    assert proc.returncode == 2 and "Traceback" not in proc.stderr, proc.stderr
    assert "/gyro rates miss those the frames' attitudes show" in proc.stderr and reading in proc.stderr, proc.stderr


def test_a_gyro_whose_times_are_in_microseconds_is_refused(tmp_path):
    ok, bad = tmp_path / "ok.mcap", tmp_path / "bad.mcap"
    write_centroid_recording(ok, 6, sigma_px=0.1, seed=5)
    _rewritten(ok, bad, lambda topic, r: {**r, "t_ns": [t // 1000 for t in r["t_ns"]]} if topic == "/gyro" else r)
    args = ("diagnose", "--recording", bad, "-o", tmp_path / "d", "-q")
    proc = subprocess.run([sys.executable, "-m", "rollingstar.cli", *map(str, args)], capture_output=True, text=True)
    assert proc.returncode == 2 and "no frame falls within the gyro's samples" in proc.stderr, proc.stderr


def test_a_burst_of_frames_closer_than_a_default_exposure_is_run(tmp_path):
    """A camera file without a shutter (the sensor model's exposure is then a default, 100 ms) and
    one pair of frames 40 ms apart among frames 200 ms apart: not a unit error, so `run` runs."""
    from rollingstar.sensors.camera import PinholeCamera
    from rollingstar.sensors.conventions import attitude_from_radec_roll, unit_to_radec

    w, h, f_mm, pix_um = 1280, 1024, 25.0, 5.3
    cam = PinholeCamera(f_mm * 1e-3, pix_um * 1e-6, w, h)
    rng = np.random.default_rng(0)
    x, y = rng.uniform(20, w - 20, 25), rng.uniform(20, h - 20, 25)
    ra, dec = (np.degrees(a) for a in unit_to_radec(attitude_from_radec_roll(80.0, 20.0, 10.0).apply(cam.unproject(x, y))))
    rows = ["frame,t_ns,x,y,flux,catalog_id,ra_deg,dec_deg"]
    for k, ms in enumerate([0, 200, 400, 440, 640, 840]):
        rows += [f"{k},{1_000_000_000 + ms * 1_000_000},{x[i] + rng.normal(0, .05):.4f},{y[i] + rng.normal(0, .05):.4f},"
                 f"100,{i + 1},{ra[i]:.8f},{dec[i]:.8f}" for i in range(25)]
    (tmp_path / "c.csv").write_text("\n".join(rows) + "\n")
    (tmp_path / "cam.yaml").write_text(f"width_px: {w}\nheight_px: {h}\nfocal_length_mm: {f_mm}\npixel_size_um: {pix_um}\n")
    cli("import", "centroids", tmp_path / "c.csv", "--camera", tmp_path / "cam.yaml", "-o", tmp_path / "r.mcap")
    assert "6 frames: 6 valid" in cli("run", "baseline", tmp_path / "r.mcap", "-o", tmp_path / "o.mcap", "-q").stdout
