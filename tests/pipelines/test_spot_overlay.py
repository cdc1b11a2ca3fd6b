"""``/estimate/spots`` draws each circle where the star is in Foxglove's image coordinates.

Foxglove's ``ImageAnnotations`` put the origin at the top-left corner of the top-left pixel
(https://docs.foxglove.dev/docs/visualization/message-schemas/circle-annotation/). The spot below
is rendered in exactly those coordinates (pixel column ``i`` spans ``[i, i + 1)``), centroided,
written by the run's sink and read back with the plain ``mcap`` reader and protobuf decoding, so
the test does not go through the project's own pixel convention at all.
"""
from __future__ import annotations

import numpy as np
from mcap.reader import make_reader
from mcap_protobuf.decoder import DecoderFactory
from scipy.special import erf

from rollingstar.estimators.centroiders.cog import CogCentroider
from rollingstar.estimators.data import FrameData, SensorContext
from rollingstar.logs.writer import LogWriter
from rollingstar.pipelines.sink import write_frame
from rollingstar.sensors.camera import PinholeCamera
from rollingstar.sensors.conventions import pixel_to_foxglove
from rollingstar.sensors.timing import DetectorTiming

WIDTH, HEIGHT = 48, 40
SIGMA_PX = 1.3  # Gaussian PSF
FLUX = 60_000.0  # ADU: bright, so read noise moves the centroid by ~0.002 px
BACKGROUND, NOISE = 100.0, 2.0


def _pixel_integrals(n: int, centre: float) -> np.ndarray:
    """Fraction of a unit 1-D Gaussian at ``centre`` (corner coordinates) falling in each of ``n`` pixels."""
    edges = (np.arange(n + 1) - centre) / (np.sqrt(2.0) * SIGMA_PX)
    return 0.5 * np.diff(erf(edges))


def _render(u0: float | None, v0: float | None, rng) -> np.ndarray:
    """A uint16 image of one pixel-integrated Gaussian spot centred at ``(u0, v0)`` measured from the
    top-left corner of the top-left pixel (None: no spot), with background and read noise."""
    image = np.full((HEIGHT, WIDTH), BACKGROUND)
    if u0 is not None:
        image += FLUX * np.outer(_pixel_integrals(HEIGHT, v0), _pixel_integrals(WIDTH, u0))
    image += rng.normal(0.0, NOISE, image.shape)
    return np.clip(np.rint(image), 0, 65535).astype(np.uint16)


def _context() -> SensorContext:
    camera = PinholeCamera(focal_length_m=0.05, pixel_size_m=5e-6, width=WIDTH, height=HEIGHT)
    timing = DetectorTiming(mode="rolling", exposure_ns=10_000_000, line_delay_ns=20_000, rows=HEIGHT)
    return SensorContext(camera=camera, timing=timing, catalog=None)


def _overlays(path) -> list[tuple[int, object]]:
    """(log time, decoded message) of every ``/estimate/spots`` message of ``path``, read with the
    plain mcap reader."""
    with open(path, "rb") as f:
        reader = make_reader(f, decoder_factories=[DecoderFactory()])
        return [(m.log_time, msg) for _, _, m, msg in reader.iter_decoded_messages(topics=["/estimate/spots"])]


def _centroided_frames(spots, rng) -> list[FrameData]:
    cog = CogCentroider()
    cog.setup(_context())
    return [cog.process(FrameData(index=k, t0_ns=1_000_000_000 * (k + 1), image=_render(u, v, rng)))
            for k, (u, v) in enumerate(spots)]


def _write(tmp_path, frames: list[FrameData]):
    path = tmp_path / "out.mcap"
    with LogWriter(path, kind="run") as writer:
        for frame in frames:
            write_frame(writer, frame)
    return _overlays(path)


def test_circle_centre_is_the_true_centre_in_foxglove_coordinates(tmp_path):
    """Sub-pixel centres in all four quarters of a pixel: the circle lands within 0.02 px of the true
    centre measured from the image corner (the half-pixel shift between conventions is 0.5 px)."""
    rng = np.random.default_rng(7)
    spots = [(20.13, 17.71), (11.5, 25.5), (30.87, 9.02), (24.0, 20.0), (15.38, 12.94)]
    frames = _centroided_frames(spots, rng)
    overlays = _write(tmp_path, frames)
    assert len(overlays) == len(spots)
    for (u0, v0), frame, (log_time, overlay) in zip(spots, frames, overlays):
        assert frame.stars.n == 1 and len(overlay.circles) == 1
        circle = overlay.circles[0].position
        assert abs(circle.x - u0) < 0.02 and abs(circle.y - v0) < 0.02, (u0, v0, circle)
        # the centroid itself is in the project's convention (pixel centres at integers)
        assert abs(frame.stars.x[0] - (u0 - 0.5)) < 0.02 and abs(frame.stars.y[0] - (v0 - 0.5)) < 0.02
        stamp = overlay.circles[0].timestamp
        assert log_time == stamp.seconds * 1_000_000_000 + stamp.nanos == frame.t0_ns  # the image's timestamp
        assert [t.text for t in overlay.texts] == ["?"]  # unidentified spot


def test_pixel_to_foxglove_puts_pixel_centres_half_a_pixel_from_the_corner():
    x, y = pixel_to_foxglove(np.array([0.0, 47.0, -0.5]), np.array([0.0, 39.0, -0.5]))
    assert x.tolist() == [0.5, 47.5, 0.0] and y.tolist() == [0.5, 39.5, 0.0]


def test_a_frame_without_stars_writes_an_empty_overlay(tmp_path):
    """A spot, then a frame with no star detected, then one whose stage left no star table: each
    frame gets its own message, the empty ones with no circle and no text (Foxglove then clears
    the previous frame's circles instead of keeping them on screen)."""
    rng = np.random.default_rng(3)
    frames = _centroided_frames([(20.3, 17.6), (None, None)], rng)
    frames.append(FrameData(index=2, t0_ns=3_000_000_000, stars=None))
    assert frames[0].stars.n == 1 and frames[1].stars.n == 0
    overlays = _write(tmp_path, frames)
    assert [len(o.circles) for _, o in overlays] == [1, 0, 0]
    assert [len(o.texts) + len(o.points) for _, o in overlays] == [1, 0, 0]
    assert [t for t, _ in overlays] == [f.t0_ns for f in frames]
