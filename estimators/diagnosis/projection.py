"""Which lens projection a recording's stars follow, before any effect is named.

A lens's projection (:data:`rollingstar.sensors.camera.PROJECTIONS`: the image radius of a
direction ``theta`` from the boresight, ``r = f rho(theta)``) is not a small perturbation of
another: a 100 deg fisheye declared as a pinhole misses its corner stars by hundreds of pixels,
beyond the outlier gate and beyond what the library's distortion terms can bend. So the
projection is chosen first, as a discrete model choice, and the effects are then named relative
to it.

Every projection is fitted to the training stars (the held-out split of
:func:`~rollingstar.estimators.diagnosis.locating.split_heldout`, so held-out data stays unseen):
its focal length (from the one that images the declared camera's nominal field edge at the same
pixel, free by a factor 0.7-1.4), a radial term ``k1``, and every frame's attitude by variable
projection (each frame's rate held at the one the declared model's attitudes give: a projection
changes where stars image, not how the frame turns); the best one and the declared one are then
fitted again with the rates free. Fitting ``k1`` for every candidate, the
declared projection included, means a projection must explain what a third-order distortion of
the declared one cannot: over a narrow field the projections differ by a ``theta^3`` term a ``k1``
absorbs, and none is named (:func:`distinguishable` skips the search when no projection could
be). The best projection replaces the declared one when its chi-square (same parameter count, so
the BIC difference) is lower by ``NAMING_DELTA``; the scenario the rest of the diagnosis works
from then declares it with the focal length fitted with it (a nominal field through the wrong
projection is off by more than the library's focal-length effect reaches), and the library names
the distortion, and any focal-length error left, relative to it.

Over a narrow field the projections cannot be told apart, but the lens can still be far from the
model as given: a ``log.json`` field of view that is the lens's nominal one, not its own, or a
strong distortion. When the model as given leaves more than ``LENS_FIT_FRACTION`` of the stars
beyond the gross-outlier gate, the declared projection's focal length and ``k1`` are fitted the
same way (no other projection is tried). In either case the fit is the first round's outlier
gate, and a focal length off the declared one by more than ``REFOCUS_FRACTION`` is declared in the
scenario the effects are named against, and stated in the verdict: the library's focal-length
effect is a tolerance, bounded at 10 %, not a search.
"""
from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np
from scipy.optimize import least_squares
from scipy.spatial.transform import Rotation

from rollingstar.estimators.diagnosis.inputs import DiagnoseOptions, SensorModel
from rollingstar.estimators.diagnosis.locating import (
    GATE_ROUNDS,
    MAX_GROSS_FRACTION,
    MIN_TRAINING_STARS,
    attitude_mask,
    beyond_gate,
    gross_outliers,
    split_heldout,
    trimmed_gate,
)
from rollingstar.estimators.diagnosis.observations import (
    Nuisance,
    Observations,
    fit_attitudes,
    fit_nuisance,
    whitened_residuals,
)
from rollingstar.sensors.camera import PROJECTIONS, projection_rho, projection_theta
from rollingstar.sensors.scenario import ScenarioConfig

NAMING_DELTA = 10.0  # chi-square a projection must gain over the declared one (the library's BIC margin)
FOCAL_RANGE = (0.7, 1.4)  # the focal length's freedom around the nominal field's
SEPARATION_SIGMAS = 1.0  # a projection this far (in noise sigmas) from every focal and k1 change of the declared is searched
LENS_FIT_FRACTION = 0.1  # stars beyond the gate of the model as given above which a narrow field's lens is fitted too
REFOCUS_FRACTION = 0.05  # a focal length off the declared one by more than this is declared (the library's reaches 10 %)


@dataclass(frozen=True)
class ProjectionChoice:
    """The projections' fits: chi-square, focal length (px) and ``k1`` each, the declared one and
    the one named (the declared one when no other wins by ``NAMING_DELTA``)."""

    declared: str
    named: str
    chi2: dict
    focal_px: dict
    k1: dict
    dof: int
    heldout_rms_px: dict  # held-out RMS per axis under the declared and the named projection (their fits)
    beyond_gate: int = 0  # stars every projection was fitted without (beyond the gross-outlier gate of the best)
    declared_focal_px: float = float("nan")
    searched: bool = True  # False: a narrow field, only the declared projection's focal length and k1 fitted
    trimmed_start: bool = False  # the search started again from a trimmed fit's gate (:func:`choose_projection`)

    @property
    def renamed(self) -> bool:
        return self.named != self.declared

    @property
    def refocused(self) -> bool:
        """Whether the declared projection stays but its fitted focal length is off the declared one
        by more than ``REFOCUS_FRACTION``: a nominal field that far off is stated in the scenario the
        effects are named against (the library's focal-length effect is a tolerance, bounded at
        10 %). A renamed projection always brings its own focal length (:attr:`restated`)."""
        ratio = self.focal_px[self.named] / self.declared_focal_px
        return bool(not self.renamed and np.isfinite(ratio) and abs(ratio - 1.0) > REFOCUS_FRACTION)

    @property
    def restated(self) -> bool:
        """Whether the scenario the diagnosis works from declares this fit's projection and focal length."""
        return self.renamed or self.refocused

    @property
    def delta_chi2(self) -> float:
        """How much better the named projection fits than the declared one."""
        return float(self.chi2[self.declared] - self.chi2[self.named])

    def as_json(self) -> dict:
        return {"declared": self.declared, "named": self.named, "delta_chi2": self.delta_chi2, "dof": self.dof,
                "heldout_rms_px": self.heldout_rms_px, "beyond_gate": self.beyond_gate, "searched": self.searched,
                "trimmed_start": self.trimmed_start,
                "declared_focal_px": self.declared_focal_px, "refocused": self.refocused,
                "candidates": {p: {"chi2_dof": self.chi2[p] / max(self.dof, 1), "focal_px": self.focal_px[p],
                                   "k1": self.k1[p]} for p in self.chi2}}

    def sentence(self) -> str:
        if not self.renamed:
            if not self.refocused:
                return ""
            f = self.focal_px[self.named]
            return (f"focal length {f:.1f} px, not the declared {self.declared_focal_px:.1f} px "
                    f"({100.0 * (f / self.declared_focal_px - 1.0):+.1f} %: the declared field is off; fitted with k1 "
                    f"before any effect; held-out RMS {self.heldout_rms_px[self.named]:.3g} px)")
        return (f"lens projection: {self.named}, not the declared {self.declared}, focal length "
                f"{self.focal_px[self.named]:.1f} px (training chi2/dof {self.chi2[self.declared] / max(self.dof, 1):.3g} "
                f"-> {self.chi2[self.named] / max(self.dof, 1):.3g}, focal length and k1 fitted for each; held-out RMS "
                f"{self.heldout_rms_px[self.declared]:.3g} -> {self.heldout_rms_px[self.named]:.3g} px)")


def nominal_focal_px(camera, projection: str) -> float:
    """The focal length (px) with which ``projection`` images the direction at the declared camera's
    field edge (half the detector's width) at that same pixel."""
    edge_px = 0.5 * camera.width
    theta = float(projection_theta(edge_px / camera.focal_px, camera.projection))
    return edge_px / float(projection_rho(theta, projection)[0])


def distinguishable(camera, sigma_px: float) -> bool:
    """Whether any other projection differs from ``camera``'s, over its field (out to the detector's
    corners), by more than ``SEPARATION_SIGMAS`` of the stars' noise after the best focal-length and
    ``k1`` change of the declared one: the radial curves compared directly (linear least squares on
    ``r``, ``r^3``), no stars needed. Over a narrow field none does, and no search is made."""
    corner = float(np.hypot(max(camera.cx + 0.5, camera.width - 0.5 - camera.cx),
                            max(camera.cy + 0.5, camera.height - 0.5 - camera.cy)))
    theta_max = float(projection_theta(corner / camera.focal_px, camera.projection))
    if not np.isfinite(theta_max):
        return True
    theta = np.linspace(0.0, theta_max, 64)
    rho_declared = projection_rho(theta, camera.projection)[0]
    basis = np.column_stack([rho_declared, rho_declared**3])
    for projection in PROJECTIONS:
        if projection == camera.projection:
            continue
        r = nominal_focal_px(camera, projection) * projection_rho(theta, projection)[0] / camera.focal_px
        if not np.all(np.isfinite(r)):
            return True
        coef, *_ = np.linalg.lstsq(basis, r, rcond=None)
        if np.max(np.abs(basis @ coef - r)) * camera.focal_px > SEPARATION_SIGMAS * sigma_px:
            return True
    return False


def choose_projection(obs: Observations, attitudes: Rotation, sensor: SensorModel,
                      options: DiagnoseOptions) -> ProjectionChoice | None:
    """Fit every projection to the training stars (module docstring) and name the best. When no
    projection is :func:`distinguishable` from the declared one over this camera's field, only the
    declared one is fitted (its focal length and ``k1``), and only when the model as given misses
    many stars beyond the gross-outlier gate (:func:`_misses_many`); None otherwise.

    Every projection is fitted to the same stars: those within the gross-outlier gate of the best
    fit (with its rates free), found as a fixed point (fit, gate every star on the best fit, fit
    again on the stars inside; at most ``GATE_ROUNDS`` refits). A misidentified star hundreds of
    pixels off would otherwise decide the search: its miss is about the same under every projection.
    The first fit has every star in it, and a few such stars among a few tens can pull it so far
    that most stars end beyond the gate; the search then starts again from the stars within the
    gate of a trimmed fit of the model as given (:func:`~.locating.trimmed_gate`)."""
    if obs.n == 0:
        return None
    searched = distinguishable(sensor.camera, float(np.median(obs.sigma)))
    if not searched and not _misses_many(obs, attitudes, sensor):
        return None
    candidates = PROJECTIONS if searched else (sensor.camera.projection,)
    heldout, _ = split_heldout(obs, options.heldout_fraction, options.seed)
    obs = replace(obs, heldout=heldout)
    _, att_mask = attitude_mask(obs)
    train = ~heldout
    declared = sensor.camera.projection
    fits, best, inside = _search(obs, attitudes, sensor, candidates, att_mask, np.ones(obs.n, dtype=bool))
    trimmed = False
    if _gross_fraction(obs, fits[best]) > MAX_GROSS_FRACTION:
        # the search from every star left more than a quarter of them beyond the gate: wrong identifications
        # far off pulled its first fit; the search again from the stars within the gate of the
        # model as given with the attitudes of a trimmed fit (when they leave enough training stars),
        # kept when it leaves fewer beyond the gate
        far, _ = trimmed_gate(obs, attitudes, sensor, att_mask)
        if np.count_nonzero(~far & train) >= MIN_TRAINING_STARS:
            again = _search(obs, attitudes, sensor, candidates, att_mask, ~far)
            if _gross_fraction(obs, again[0][again[1]]) < _gross_fraction(obs, fits[best]):
                (fits, best, inside), trimmed = again, True
    if declared != best:
        fits[declared] = _fit(obs, attitudes, sensor, declared, att_mask & inside, train & inside, inside)
    chi2 = {p: f.chi2 for p, f in fits.items()}
    named = best if (not np.isfinite(chi2[declared]) or chi2[declared] - chi2[best] >= NAMING_DELTA) else declared
    dof = int(2 * np.count_nonzero(train & inside) - 3 * obs.n_frames - 2)
    return ProjectionChoice(declared, named, chi2, {p: f.focal_px for p, f in fits.items()},
                            {p: f.k1 for p, f in fits.items()}, dof, {p: f.heldout_rms for p, f in fits.items()},
                            int(np.count_nonzero(~inside)), sensor.camera.focal_px, searched, trimmed)


def _search(obs: Observations, attitudes: Rotation, sensor: SensorModel, candidates, att_mask: np.ndarray,
            inside: np.ndarray) -> tuple[dict, str, np.ndarray]:
    """Every candidate projection fitted to the training stars ``inside`` the gate, the best one
    fitted again with its rates free, and the gate moved to the stars within ``OUTLIER_SIGMA`` of
    the best fit, until it keeps the same stars (at most ``GATE_ROUNDS`` refits). Returns the fits,
    the best one's name and the stars inside the gate."""
    train, declared = ~obs.heldout, sensor.camera.projection
    for round_ in range(GATE_ROUNDS + 1):
        # the frames' rates from the declared model's attitudes, held through the search: a projection
        # changes where stars image, not how the frame turns between frames (the attitudes are
        # refitted in every evaluation)
        start, _ = fit_nuisance(obs, attitudes, sensor.camera, sensor.timing, sensor.effects, att_mask & inside,
                                sensor.moving)
        fits = {p: _fit(obs, start, sensor, p, att_mask & inside, train & inside, inside) for p in candidates}
        finite = {p: f.chi2 for p, f in fits.items() if np.isfinite(f.chi2)}
        best = min(finite, key=finite.get) if finite else declared
        # the best fitted again with every frame's rate free (as the locate step fits them): the
        # rates of a wrong model bias the focal length by a few parts in 1e4
        fits[best] = _fit(obs, attitudes, sensor, best, att_mask & inside, train & inside, inside)
        if fits[best].prediction is None or round_ == GATE_ROUNDS:
            break
        again = ~beyond_gate(obs, fits[best].prediction)
        if np.array_equal(again, inside) or np.count_nonzero(again & train) < MIN_TRAINING_STARS:
            break
        inside = again
    return fits, best, inside


def _gross_fraction(obs: Observations, fit) -> float:
    """The share of the stars beyond the gross-outlier gate of ``fit`` (1 for a failed fit)."""
    return 1.0 if fit.prediction is None else float(beyond_gate(obs, fit.prediction).mean())


def _misses_many(obs: Observations, attitudes: Rotation, sensor: SensorModel) -> bool:
    """Whether the model as given leaves more than ``LENS_FIT_FRACTION`` of the stars beyond the
    gross-outlier gate (:func:`~.locating.gross_outliers`): a lens further off than its
    tolerances (a nominal field of view that is not the lens's, a strong distortion), which the
    gate would otherwise take for misidentifications."""
    far = gross_outliers(obs, attitudes, sensor, np.ones(obs.n, dtype=bool))
    return bool(np.count_nonzero(far) > LENS_FIT_FRACTION * obs.n)


@dataclass(frozen=True)
class _Fit:
    chi2: float
    focal_px: float
    k1: float
    heldout_rms: float
    prediction: object  # every star's, with the attitudes fitted to the stars the fit used


_FAILED = _Fit(np.inf, np.nan, np.nan, np.nan, None)


def _fit(obs, start, sensor: SensorModel, projection: str, att_mask, train, inside) -> _Fit:
    """Chi-square, focal length and k1 of ``projection`` fitted to the ``train`` stars with every
    frame's attitude (fitted to ``att_mask``), the held-out RMS per axis with them (the held-out
    frames' attitudes fitted to their own stars, the nuisance; only stars ``inside`` the gate) and
    every star's prediction. ``start``: a :class:`Nuisance` whose rates are
    held (the search), or bare attitudes, whose rates are fitted too (the final fits)."""

    def nuisance_fit(camera, mask):
        if isinstance(start, Nuisance):
            return fit_attitudes(obs, start, camera, sensor.timing, sensor.effects, mask)
        return fit_nuisance(obs, start, camera, sensor.timing, sensor.effects, mask, sensor.moving)

    cam0 = sensor.camera
    f0 = nominal_focal_px(cam0, projection)
    if not np.isfinite(f0) or f0 <= 0:
        return _FAILED

    def camera(p):
        return replace(cam0, projection=projection, focal_length_m=f0 * np.exp(p[0]) * cam0.pixel_size_m, k1=p[1])

    def residuals(p):
        _, pred = nuisance_fit(camera(p), att_mask)
        r = whitened_residuals(obs, pred)[train].ravel()
        return np.where(np.isfinite(r), r, 1e3)  # a star the model cannot image: a large, finite miss

    lo, hi = np.log(FOCAL_RANGE[0]), np.log(FOCAL_RANGE[1])
    try:
        sol = least_squares(residuals, x0=[0.0, 0.0], bounds=([lo, -1.0], [hi, 1.0]), x_scale=[0.01, 0.01],
                            max_nfev=40)
    except (ValueError, np.linalg.LinAlgError):
        return _FAILED
    _, pred = nuisance_fit(camera(sol.x), att_mask)
    out = obs.heldout & inside
    miss = np.concatenate([obs.x[out] - pred.x[out], obs.y[out] - pred.y[out]])
    heldout_rms = float(np.sqrt(np.nanmean(miss**2))) if out.any() else float("nan")
    return _Fit(float(2.0 * sol.cost), float(f0 * np.exp(sol.x[0])), float(sol.x[1]), heldout_rms, pred)


def fitted_camera(camera, choice: ProjectionChoice):
    """``camera`` with the named projection and the focal length and ``k1`` fitted with it, or None
    when that fit failed (no finite focal length or ``k1``)."""
    if not (np.isfinite(choice.focal_px[choice.named]) and np.isfinite(choice.k1[choice.named])):
        return None
    focal_m = choice.focal_px[choice.named] * camera.pixel_size_m
    return replace(camera, projection=choice.named, focal_length_m=focal_m, k1=choice.k1[choice.named])


def with_projection(scenario: ScenarioConfig, choice: ProjectionChoice) -> ScenarioConfig:
    """``scenario`` declaring the named projection with the focal length fitted with it."""
    focal_mm = choice.focal_px[choice.named] * scenario.sensor.pixel_size_um * 1e-3
    sensor = scenario.sensor.model_copy(update={"projection": choice.named, "focal_length_mm": focal_mm})
    return scenario.model_copy(update={"sensor": sensor})
