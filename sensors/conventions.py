"""The project's conventions, one helper per conversion (see docs/conventions.md).

- Times are integer nanoseconds (``int`` / ``np.int64``).
- A frame's timestamp is the start of exposure of row 0; row ``r`` starts exposing at
  ``t0 + r * line_delay``.
- Quaternions in arrays are scalar-last ``(x, y, z, w)`` as in scipy. An *attitude* quaternion is
  the rotation that takes camera-frame vectors to ICRS vectors (the camera's orientation in ICRS,
  as in ``foxglove.PoseInFrame``): ``v_icrs = R.apply(w_cam)``. The seeds' attitude matrix ``A``
  (``w = A v``, he2021b eq 3) is therefore ``R.as_matrix().T``.
- Camera frame: +z is the boresight; +x points towards decreasing column and +y towards
  decreasing row (the OpenCV camera frame turned 180 deg about the boresight). Pixel
  ``(x, y) = (column, row)``, pixel centres at integer coordinates. The direction of pixel (x, y)
  is he2021b eq (2): ``w ~ [-(x - cx) p, -(y - cy) p, f]``.
- Attitude errors are the rotation from truth to estimate expressed in the camera (body) frame,
  per axis in arcseconds: x, y cross-boresight, z about the boresight.
"""
from __future__ import annotations

import numpy as np
from scipy.spatial.transform import Rotation

# Unit constants. Nanoseconds become seconds as ``t_ns / NS_PER_S`` (correctly rounded; the
# simulator's form) or ``t_ns * S_PER_NS`` (the estimators' form): the two can differ in the last
# bit, so a module's results depend on the form it uses.
NS_PER_S = 1_000_000_000
S_PER_NS = 1e-9
S_PER_HOUR = 3600.0
DEG_TO_RAD = np.pi / 180.0
RAD_TO_ARCSEC = 180.0 / np.pi * 3600.0
ARCSEC_TO_RAD = 1.0 / RAD_TO_ARCSEC  # equal to DEG_TO_RAD / 3600 in every bit
#: The camera frame's axes in words (docs/conventions.md, "camera frame"): what x, y and z mean in
#: every table of attitude and rate errors.
CAMERA_AXES = {"x": "camera x: cross-boresight, towards decreasing column",
               "y": "camera y: cross-boresight, towards decreasing row",
               "z": "camera z: the boresight (errors about it are roll)"}


def seconds_to_ns(seconds) -> np.ndarray | int:
    """Seconds (float) to integer nanoseconds, rounded to the nearest ns."""
    out = np.rint(np.asarray(seconds, dtype=float) * NS_PER_S).astype(np.int64)
    return int(out) if out.ndim == 0 else out


def pixel_to_foxglove(x, y):
    """Pixel ``(x, y)`` (pixel centres at integers) to Foxglove image-annotation coordinates.

    Foxglove's ``ImageAnnotations`` points have their origin at the top-left corner of the
    top-left pixel, so the centre of pixel (0, 0) is (0.5, 0.5) there. Scalars or arrays.
    """
    return np.asarray(x, dtype=float) + 0.5, np.asarray(y, dtype=float) + 0.5


def radec_to_unit(ra_rad, dec_rad) -> np.ndarray:
    """Right ascension / declination (rad) to ICRS unit vectors ``[cos a cos d, sin a cos d, sin d]``.

    This is fu2022 eq (1); he2021a/he2021b eq (1) misprint the second component.
    """
    ra = np.asarray(ra_rad, dtype=float)
    dec = np.asarray(dec_rad, dtype=float)
    cd = np.cos(dec)
    return np.stack([np.cos(ra) * cd, np.sin(ra) * cd, np.sin(dec)], axis=-1)


def unit_to_radec(unit) -> tuple[np.ndarray, np.ndarray]:
    """ICRS unit vectors to (ra, dec) in radians, ra in [0, 2 pi)."""
    u = np.asarray(unit, dtype=float)
    ra = np.mod(np.arctan2(u[..., 1], u[..., 0]), 2 * np.pi)
    dec = np.arcsin(np.clip(u[..., 2] / np.linalg.norm(u, axis=-1), -1.0, 1.0))
    return ra, dec


def attitude_from_radec_roll(ra_deg: float, dec_deg: float, roll_deg: float = 0.0) -> Rotation:
    """Camera-to-ICRS attitude whose boresight (+z) points at (ra, dec).

    With roll 0 the camera's -y axis points towards celestial north where defined (north images
    below the principal point, at increasing row); roll rotates the camera about its boresight by
    ``roll_deg`` (right-handed): ``R(ra, dec, roll) = R(ra, dec, 0) * Rz(roll)``.
    """
    ra, dec, roll = np.radians([ra_deg, dec_deg, roll_deg])
    z = radec_to_unit(ra, dec)
    north = np.array([0.0, 0.0, 1.0])
    if abs(z @ north) > 1.0 - 1e-12:  # at a pole pick any perpendicular reference
        north = np.array([1.0, 0.0, 0.0])
    up = north - (north @ z) * z
    up /= np.linalg.norm(up)
    y = -up
    x = np.cross(y, z)
    base = Rotation.from_matrix(np.column_stack([x, y, z]))
    return base * Rotation.from_rotvec([0.0, 0.0, roll])


def radec_roll_from_attitude(attitude: Rotation) -> tuple[float, float, float]:
    """Inverse of :func:`attitude_from_radec_roll` (degrees)."""
    z = attitude.apply([0.0, 0.0, 1.0])
    ra, dec = unit_to_radec(z)
    base = attitude_from_radec_roll(np.degrees(ra), np.degrees(dec), 0.0)
    roll = (base.inv() * attitude).as_rotvec()[2]
    return float(np.degrees(ra)), float(np.degrees(dec)), float(np.degrees(roll))


def attitude_error_body_arcsec(truth: Rotation, estimate: Rotation) -> np.ndarray:
    """Rotation from truth to estimate in the camera frame, per axis, arcsec; shape (..., 3).

    ``dR = truth^-1 * estimate`` so that ``estimate = truth * dR``; returns ``rotvec(dR)``.
    """
    return (truth.inv() * estimate).as_rotvec() * RAD_TO_ARCSEC


def attitude_from_opencv(attitude_opencv: Rotation) -> Rotation:
    """Our camera-to-ICRS attitude of a camera whose attitude is stated in the OpenCV camera frame
    (+x towards increasing column, +y towards increasing row): ``R = R_opencv * Rz(180 deg)``
    (docs/conventions.md)."""
    return attitude_opencv * Rotation.from_rotvec([0.0, 0.0, np.pi])


def quat_to_fields(q_xyzw) -> dict[str, float]:
    """Scalar-last array quaternion to the named fields used in logs."""
    x, y, z, w = (float(v) for v in np.asarray(q_xyzw, dtype=float))
    return {"x": x, "y": y, "z": z, "w": w}


def quat_from_fields(fields: dict) -> np.ndarray:
    """Named log fields ``{x, y, z, w}`` to a scalar-last array quaternion."""
    return np.array([fields["x"], fields["y"], fields["z"], fields["w"]], dtype=float)
