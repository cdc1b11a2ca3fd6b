"""The mirror check of the diagnosis (``locating.mirrored_fraction`` / ``check_parity``) on star
fields built here: a mirror image turns (nearly) every local star triangle over; a lens far from
the declared one, stars beyond 90 deg of a fisheye declared as a pinhole, a frame of a few stars
with two identities swapped, or two detections on one catalogue direction do not make a mirror."""
from __future__ import annotations

import numpy as np
import pytest

from rollingstar.errors import UserError
from rollingstar.estimators.diagnosis.locating import PARITY_MIN_TRIANGLES, check_parity, mirrored_fraction
from rollingstar.estimators.diagnosis.observations import Observations
from rollingstar.sensors.camera import PinholeCamera
from rollingstar.sensors.conventions import attitude_from_radec_roll


def observations(x, y, u, frames=None) -> Observations:
    """Identified stars at pixels ``(x, y)`` with catalogue directions ``u`` (one frame unless ``frames``)."""
    n = len(x)
    frame = np.zeros(n, dtype=int) if frames is None else np.asarray(frames)
    f = int(frame.max()) + 1
    return Observations(frame=frame, x=np.asarray(x, float), y=np.asarray(y, float), sigma=np.full(n, 0.1),
                        t_ns=np.zeros(n, dtype=np.int64), u_icrs=np.asarray(u, float), magnitude=np.full(n, 5.0),
                        catalog_id=np.arange(n), flux=np.ones(n), frame_index=np.arange(f),
                        t0_ns=np.arange(f, dtype=np.int64), t_ref_ns=np.arange(f, dtype=np.int64))


def field(camera, n=60, seed=0, off_axis_deg=(0.0, 0.0)):
    """``n`` stars imaged by ``camera`` at random pixels (between the off-axis angles given, when
    given), with their sky directions through an arbitrary attitude."""
    rng = np.random.default_rng(seed)
    R = attitude_from_radec_roll(40.0, -20.0, 30.0)
    if off_axis_deg != (0.0, 0.0):
        theta = np.radians(rng.uniform(*off_axis_deg, n))
        phi = rng.uniform(0, 2 * np.pi, n)
        w = np.column_stack([np.sin(theta) * np.cos(phi), np.sin(theta) * np.sin(phi), np.cos(theta)])
        x, y, ok = camera.project(w)
        assert ok.all()
    else:
        x, y = rng.uniform(0, camera.width - 1, n), rng.uniform(0, camera.height - 1, n)
        w = camera.unproject(x, y)
    return x, y, R.apply(w / np.linalg.norm(w, axis=1, keepdims=True))


PINHOLE = PinholeCamera(2400 * 5e-6, 5e-6, 1024, 1024)


def test_a_mirror_turns_every_triangle_over_and_is_refused():
    x, y, u = field(PINHOLE)
    flipped, judged = mirrored_fraction(observations(x, y, u), PINHOLE)
    assert flipped == 0 and judged >= PARITY_MIN_TRIANGLES
    flipped, judged = mirrored_fraction(observations(1023 - x, y, u), PINHOLE)
    assert flipped == judged >= PARITY_MIN_TRIANGLES
    from types import SimpleNamespace

    with pytest.raises(UserError, match="mirror image"):
        check_parity(observations(x, 1023 - y, u), SimpleNamespace(camera=PINHOLE))


@pytest.mark.parametrize("projection, focal_factor", [("equidistant", 1.0), ("equidistant", 0.5), ("equisolid", 0.5)])
def test_stars_beyond_90_deg_of_a_fisheye_declared_as_a_pinhole_are_no_mirror(projection, focal_factor):
    """A 220 deg fisheye's stars 95-108 deg off its axis, unprojected through a pinhole (of the same
    or half its focal length): a triangle spanning the field can turn over, a local one does not."""
    lens = PinholeCamera(300 * 5e-6, 5e-6, 1400, 1400, projection=projection)
    x, y, u = field(lens, n=80, seed=2, off_axis_deg=(95.0, 108.0))
    declared = PinholeCamera(focal_factor * 300 * 5e-6, 5e-6, 1400, 1400)
    flipped, judged = mirrored_fraction(observations(x, y, u), declared)
    assert judged >= PARITY_MIN_TRIANGLES and flipped < 0.2 * judged, (flipped, judged)


def test_a_small_frame_with_two_identities_swapped_gives_no_verdict():
    """Four stars, two catalogue directions swapped: at most four distinct triangles, fewer than
    the check needs to call a mirror; three stars give one."""
    x, y, u = field(PINHOLE, n=4, seed=3)
    u = u[[1, 0, 2, 3]]
    assert mirrored_fraction(observations(x, y, u), PINHOLE)[1] <= 4 < PARITY_MIN_TRIANGLES
    assert mirrored_fraction(observations(x[:3], y[:3], u[:3]), PINHOLE)[1] == 1


def test_two_detections_on_one_catalogue_direction_are_not_judged():
    x, y, u = field(PINHOLE, n=12, seed=4)
    u[1], u[3] = u[0], u[2]  # two pairs of detections matched to one star each
    flipped, judged = mirrored_fraction(observations(x, y, u, frames=np.repeat([0, 1, 2], 4)), PINHOLE)
    assert flipped == 0, (flipped, judged)
