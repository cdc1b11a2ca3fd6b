"""The diagnosis as four steps on a recording's observations (docs/diagnosis.md for the method).

:func:`diagnose` chains them; each returns a typed result the next one reads:

1. :func:`.locating.locate` -> :class:`.locating.Location`: hold out data, fit the simulation as
   given, reject gross outliers, measure where it misses;
2. :func:`.naming.name_effects` -> :class:`.naming.Naming`: stepwise selection of library effects,
   refined nonlinearly, bootstrap and alias checks;
3. :func:`.modelling.model_effects` -> :class:`.modelling.EffectModel`: joint refit of the named
   effects, stability, what is left unexplained;
4. :func:`.verifying.verify` -> :class:`.verifying.Verification`: the fit before and after on
   training and held-out data, re-simulation, the claims and the verdict.

Around them: the lens is fitted first (:mod:`.projection`: the projection on wide fields; the focal
length and ``k1`` on a narrow field the model as given misses by far); the steps run
in rounds of model-aware outlier rejection; and the recording's noise is measured against the
stated one (:mod:`.noise`) on the named model's residuals: when it is off, every sigma is scaled
by the measured factor and the steps run again, so white noise the simulation understates is
reported as a noise-model mismatch instead of being fitted as physics.

:func:`as_json` is the report of a :class:`Diagnosis` as one JSON-able dict
(``rollingstar diagnose --json``).
"""
from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np
from scipy.spatial.transform import Rotation
from threadpoolctl import threadpool_limits

from rollingstar.config import validate
from rollingstar.estimators.diagnosis import summary
from rollingstar.estimators.diagnosis.describe import Description, describe, refine
from rollingstar.estimators.diagnosis.gyro_channel import GyroData
from rollingstar.estimators.diagnosis.inputs import DiagnoseOptions, SensorModel, sensor_model, sequence_moves
from rollingstar.estimators.diagnosis.library import Candidate, library
from rollingstar.estimators.diagnosis.locating import Location, check_parity, locate, with_noise
from rollingstar.estimators.diagnosis.modelling import (
    EffectModel,
    known_noise,
    model_effects,
    updated_scenario,
    with_stability,
)
from rollingstar.estimators.diagnosis.naming import Naming, name_effects
from rollingstar.estimators.diagnosis.noise import NoiseCheck, combined, overstated, scaled
from rollingstar.estimators.diagnosis.noise import measure as measure_noise
from rollingstar.estimators.diagnosis.observations import Observations, fit_nuisance, star_chi2
from rollingstar.estimators.diagnosis.projection import (
    ProjectionChoice,
    choose_projection,
    fitted_camera,
    with_projection,
)
from rollingstar.estimators.diagnosis.reference import ReferenceCheck, reference_check
from rollingstar.estimators.diagnosis.signatures import candidate_signatures
from rollingstar.estimators.diagnosis.verifying import Verification, chi2_dof, rms_px, verify
from rollingstar.sensors.scenario import ScenarioConfig

#: Rounds of model-aware outlier rejection: the model as given, then the model each round named
MAX_OUTLIER_ROUNDS = 3
#: Rounds with an empirical correction in the model: its size is a linear estimate at the model as
#: given (the rates the attitudes imply still carry part of the shape), so what the corrected model
#: as given leaves of the same shape is added to it and the physics named again
MAX_CORRECTION_ROUNDS = 3


@dataclass(frozen=True, eq=False)
class Diagnosis:
    """The result of every step of one diagnosis."""

    sensor: SensorModel
    location: Location
    naming: Naming
    model: EffectModel
    verification: Verification
    projection: ProjectionChoice | None = None  # the lens projection's choice (None: not searched, narrow field)
    outlier_rounds: tuple = ()  # per round: the gate's model and the stars it rejected (model-aware outliers)
    noise: NoiseCheck | None = None  # the recording's noise against the stated (None: too few repeated stars)
    description: Description | None = None  # the shape of an unexplained systematic (None: none left, or none found)
    uncorrected_evidence: tuple = ()  # the systematic's evidence before its empirical correction joined the model
    as_given: dict | None = None  # with a correction: the model as given without it, on the final stars (:func:`_as_given`)
    reference: ReferenceCheck | None = None  # the absorbed effects tested against a reference attitude
    carries_reference: bool = False  # the recording has a reference attitude (used or not)

    @property
    def obs(self) -> Observations:
        """The observations as fitted (held-out split made, outliers removed)."""
        return self.location.data.obs

    def updated_scenario(self) -> ScenarioConfig:
        """The input scenario with the named effects enabled at their fitted parameters (and, when
        the diagnosis measured them, the noise, an empirical correction and the effects the attitude
        absorbs that the reference attitude showed)."""
        v = self.verification
        chosen, thetas = list(v.named), list(v.thetas)
        if self.reference is not None:
            chosen += [c for c, _ in self.reference.model]
            thetas += [t for _, t in self.reference.model]
        out = updated_scenario(self.sensor.scenario, chosen, thetas)
        if self.noise is not None and self.noise.applied and self.sensor.scenario.level == "centroid":
            sigma = self.noise.stated_sigma_px * self.noise.factor  # the stated noise may be the recording's
            out = out.model_copy(update={"noise": out.noise.model_copy(update={"centroid_sigma_px": sigma})})
        return out

    @property
    def corrected(self) -> bool:
        """Whether an empirical correction of a shape outside the library is part of the model."""
        return self.description is not None and self.description.correction is not None


#: The phases :func:`diagnose` reports to its ``on_phase`` callback, in order.
PHASES = ("projection", "effects named", "noise", "shape outside the library", "corrections", "reference attitude")


def diagnose(observations: Observations, attitudes: Rotation, scenario: ScenarioConfig, gyro: GyroData | None = None,
             options: DiagnoseOptions = DiagnoseOptions(), exclude_effects=(),
             reference: tuple[Rotation, np.ndarray] | None = None, on_phase=None,
             carries_reference: bool = False) -> Diagnosis:
    """Diagnose a recording's identified stars (with a first attitude per frame) against ``scenario``.

    ``gyro``: the recording's gyro samples (a second residual channel); ``exclude_effects``:
    library effects not to test; ``reference``: a reference attitude per frame (at its reference
    time) and the frames it covers, of accuracy ``options.reference_sigma_arcsec``. BLAS runs single-threaded here: the matrices are small (thousands
    x tens) and a threaded BLAS on a busy machine was measured 16x slower on them (80 ms vs 5 ms for
    a 1078 x 32 SVD on 2 loaded cores). ``on_phase(name)`` is called after each of the ``PHASES``
    (a progress display), whether or not the recording needed it. ``carries_reference``: the
    recording has a reference attitude; without ``reference`` the report says how to use it.
    """
    done = on_phase or (lambda name: None)
    with threadpool_limits(limits=1, user_api="blas"):
        sensor = sensor_model(scenario)
        moves = sensor.moving or sequence_moves(observations, attitudes, sensor.camera, sensor.timing)
        sensor = replace(sensor, moving=moves)
        observations = with_noise(observations, attitudes, sensor)
        check_parity(observations, sensor)
        choice = choose_projection(observations, attitudes, sensor, options)
        if choice is not None and choice.restated:
            sensor = sensor_model(with_projection(scenario, choice), moves)
        done(PHASES[0])
        cands: dict[str, Candidate] = library(exclude=exclude_effects)
        # the stability refits change only the final model's report (each effect's confidence):
        # the rounds run without them, and the model reported gets them once, at the end
        per_round = replace(options, stability=False)
        steps = _outlier_rounds(observations, attitudes, sensor, cands, gyro, per_round, choice)
        done(PHASES[1])
        data, noise = steps[0].data, None
        if known_noise(data):  # a noise estimated from the residuals has nothing to be measured against
            noise = measure_noise(data.obs, steps[2].prediction, data.train, data.att_mask, sensor.camera)
        if noise is not None and noise.applied:
            steps = _outlier_rounds(scaled(observations, noise), attitudes, sensor, cands, gyro, per_round, choice)
        obs_used = scaled(observations, noise) if noise is not None and noise.applied else observations
        done(PHASES[2])
        shape = _describe(steps[0], steps[2], steps[3], sensor) if steps[3].unexplained else None
        done(PHASES[3])
        evidence, given, before = tuple(steps[3].evidence), sensor_model(sensor.scenario, moves), None
        if shape is not None and shape.correction is not None:
            sensor, steps, shape = _corrected(shape, given.scenario, obs_used, attitudes, cands, gyro, per_round,
                                              given.moving, choice)
            steps, noise = _noise_again(noise, steps, observations, attitudes, sensor, cands, gyro, per_round, choice)
            before = _as_given(steps[0], given)
        if options.stability:
            steps = _with_stability(steps, sensor, cands, options)
        done(PHASES[4])
        check = None
        if reference is not None and options.reference_sigma_arcsec is not None:
            check = reference_check(steps[0].data, steps[2], cands, list(steps[1].problem.absorbed), *reference,
                                    options.reference_sigma_arcsec, options.min_delta_bic,
                                    {e.kind: dict(e.params) for e in sensor.scenario.effects},
                                    options.reference_mount_free)
        done(PHASES[5])
    return Diagnosis(sensor, *steps[:4], choice, steps[4], noise, shape, evidence, before, check, carries_reference)


def _corrected(shape: Description, given: ScenarioConfig, obs: Observations, attitudes: Rotation,
               cands: dict[str, Candidate], gyro: GyroData | None, options: DiagnoseOptions, moving: bool,
               lens: ProjectionChoice | None):
    """The diagnosis with ``shape``'s empirical correction in the model as given: the physics is
    named again (an effect that only absorbed part of the shape drops), and what the corrected
    model still leaves of the same shape, with the named effects free, is added to the correction
    (:data:`MAX_CORRECTION_ROUNDS`). Returns the sensor model, the last round's steps and the
    shape that round ran with; ``moving``: the motion flag of the sensor model (:func:`sequence_moves`);
    ``lens``: the projection search's fit (:func:`_outlier_rounds`)."""
    for k in range(MAX_CORRECTION_ROUNDS):
        sensor = sensor_model(with_correction(given, shape), moving)
        steps = _outlier_rounds(obs, attitudes, sensor, cands, gyro, options, lens)
        if k == MAX_CORRECTION_ROUNDS - 1:
            break
        data, model, verification = steps[0].data, steps[2], steps[3]
        named = _named_rows(data, model, data.train) if verification.named and model.chosen else None
        refined = refine(shape, data.obs, model.prediction, data.train, named)
        if refined is None:  # nothing of the same shape left: the correction stands
            break
        shape = refined
    return sensor, steps, shape


def _with_stability(steps: tuple, sensor: SensorModel, cands: dict[str, Candidate], options: DiagnoseOptions) -> tuple:
    """The steps of the final round with the model's stability rows, verified again with them."""
    location, naming, model, _, rounds = steps
    model = with_stability(location.data, model, sensor)
    return location, naming, model, verify(location, naming, model, sensor, cands, options), rounds


def _noise_again(noise: NoiseCheck | None, steps: tuple, observations: Observations, attitudes: Rotation,
                 sensor: SensorModel, cands: dict[str, Candidate], gyro: GyroData | None, options: DiagnoseOptions,
                 lens: ProjectionChoice | None):
    """The noise measured once more on the corrected model (a shape left in the first residual
    moves stars between frames too); the last round runs again when the factor it used changes."""
    if noise is None:
        return steps, noise
    data = steps[0].data
    again = measure_noise(data.obs, steps[2].prediction, data.train, data.att_mask, sensor.camera)
    if again is None:
        return steps, noise
    total = combined(noise, again)
    if total.applied == noise.applied and not again.applied:  # the factor the rounds used stands
        return steps, noise if noise.applied else total
    obs = scaled(observations, total) if total.applied else observations
    return _outlier_rounds(obs, attitudes, sensor, cands, gyro, options, lens), total


def _as_given(location: Location, given: SensorModel) -> dict:
    """Training and held-out RMS and chi2/dof of the model as given, without the empirical
    correction, on the final round's stars (the "before" of a corrected diagnosis)."""
    data = location.data
    _, pred = fit_nuisance(data.obs, location.nuisance, given.camera, given.timing, given.effects, data.att_mask,
                           given.moving)
    return {"train_rms_px": rms_px(data.obs, pred, data.train), "heldout_rms_px": rms_px(data.obs, pred, data.heldout),
            "train_chi2_dof": chi2_dof(data.obs, pred, data.train, data.n_train_frames),
            "heldout_chi2_dof": chi2_dof(data.obs, pred, data.heldout, data.heldout_frames_fitted)}


def with_correction(scenario: ScenarioConfig, shape: Description) -> ScenarioConfig:
    """``scenario`` with the empirical correction of ``shape`` added to its effects."""
    data = scenario.model_dump(mode="json")
    data["effects"] = [*data["effects"], shape.correction]
    data["description"] = (data["description"] + "; " if data["description"] else "") + f"empirical correction: {shape.text}"
    return validate(ScenarioConfig, data, "<scenario with an empirical correction>")


def _describe(location: Location, model: EffectModel, verification: Verification, sensor: SensorModel) -> Description | None:
    """The shape of the systematic left (:mod:`.describe`): on the residual of the named model with
    the named effects free, or on the residual of the model as given (the named effects then only
    absorbed the shape), whichever leaves the lower held-out chi-square (the lower BIC without
    held-out data); the model as given alone when the named model was rejected on the held-out data.
    A shape of the model as given that becomes no correction (a catch-all basis) is not reported
    beside named effects: it would describe, as left unexplained, what they explain; what the named
    model leaves is reported instead (None when it leaves no significant shape)."""
    data = location.data
    as_given = describe(data.obs, location.prediction, data.train, sensor.camera)
    if not verification.named or not model.chosen:
        return as_given
    named = tuple(_named_rows(data, model, mask) for mask in (data.train, data.heldout))
    named = None if any(n is None for n in named) else named
    with_named = describe(data.obs, model.prediction, data.train, sensor.camera, named)
    k_named = sum(len(c.parameters) for c in model.chosen)
    options = [((d.heldout_chi2[1] if d.heldout_chi2 is not None else np.inf), d.bic(k), d)
               for d, k in ((as_given, 0), (with_named, k_named)) if d is not None]
    chosen = min(options, key=lambda o: o[:2])[2] if options else None
    if chosen is as_given and as_given is not None and as_given.correction is None:
        return with_named
    return chosen


def _named_rows(data, model: EffectModel, mask) -> np.ndarray | None:
    """The named effects' whitened, attitude-projected image rows on ``mask`` (N, q)."""
    groups, _, _ = candidate_signatures(data.obs, model.prediction, {c.name: c for c in model.chosen}, model.effects, mask)
    rows = 2 * int(mask.sum())  # image rows only (the gyro rows follow them)
    return np.concatenate([g[:rows] for g in groups.values()], axis=1) if groups else None


def _outlier_rounds(observations: Observations, attitudes: Rotation, sensor: SensorModel, cands: dict[str, Candidate],
                    gyro: GyroData | None, options: DiagnoseOptions, lens: ProjectionChoice | None = None) -> tuple:
    """The four steps in rounds of model-aware outlier rejection: the gross-outlier gate of each
    round after the first is the model the previous round named (stars its physics explains come
    back); a fixed point when a round names what its gate held, or when its gate keeps the stars the
    round before named on (whose steps then stand; that gate is not listed). The first round's gate is the model
    as given, or, when the lens was fitted (``lens``, :mod:`.projection`), the model with the
    projection, focal length and ``k1`` of that fit (reported as the gate "lens fit"): a strong
    distortion the model as given leaves out moves corner stars beyond the gate, and they must not
    be lost before step 2 can name it. Returns the
    last round's (location, naming, model, verification) and each round's gate and rejected
    fraction."""
    gate_names, rounds, last = (), [], None
    lens_camera = None if lens is None else fitted_camera(sensor.camera, lens)
    gate = None if lens_camera is None else replace(sensor, camera=lens_camera)
    for _ in range(MAX_OUTLIER_ROUNDS):
        location = locate(observations, attitudes, sensor, cands, gyro, options, gate)
        if last is not None and _same_stars(location.data.obs, last[0].data.obs):
            # the named model's gate kept the stars the last round named on: the same steps again
            location, naming, model, verification = last
            break
        rejected = location.data.n_rejected
        rounds.append({"gate": list(gate_names) or (["lens fit"] if gate is not None else []),
                       "rejected": rejected, "fraction": rejected / max(observations.n, 1)})
        naming = name_effects(location, sensor, cands, options)
        model = model_effects(location.data, naming, sensor, options)
        verification = verify(location, naming, model, sensor, cands, options)
        last = (location, naming, model, verification)
        names = tuple(c.name for c in verification.named)
        if not rejected or not names or set(names) == set(gate_names):
            break
        gate_names = names
        gate = sensor_model(updated_scenario(sensor.scenario, verification.named, verification.thetas), sensor.moving)
    return location, naming, model, verification, tuple(rounds)


def _same_stars(a: Observations, b: Observations) -> bool:
    """True when two rounds kept the same stars of one recording, with the same held-out split."""
    return a.n == b.n and np.array_equal(a.x, b.x) and np.array_equal(a.y, b.y) and np.array_equal(a.heldout, b.heldout)


def _isolated(obs: Observations, pred, isolated: np.ndarray) -> list[dict]:
    """The held-out stars the final model misses alone, which the held-out test left out
    (``Verification.isolated``), with where they are and by how many sigma."""
    idx = np.flatnonzero(isolated)
    c = star_chi2(obs, pred)
    return [{"frame": int(obs.frame_index[obs.frame[i]]), "catalog_id": int(obs.catalog_id[i]), "x": float(obs.x[i]),
             "y": float(obs.y[i]), "sigmas": float(np.sqrt(c[i]))} for i in idx]


def _reference_available(d: Diagnosis) -> str | None:
    """How to test the absorbed effects against the recording's reference attitude, when it has one
    and the diagnosis did not use it (its accuracy is the user's to state, never assumed)."""
    absorbed = [a["name"] for a in d.verification.absorbed]
    if d.reference is not None or not d.carries_reference or not absorbed:
        return None
    return ("This recording carries a reference attitude (/truth/attitude): run again with "
            "--reference-attitude-arcsec S, its accuracy per axis, to test the effects the attitude absorbs "
            f"({', '.join(absorbed)}) against it.")


def as_json(d: Diagnosis, recording: str, sim: str, pipeline: str) -> dict:
    """The report of ``d`` as one JSON-able dict; ``recording``, ``sim`` and ``pipeline`` name its inputs."""
    data, v, q = d.location.data, d.verification, d.verification.quality
    restated = d.projection is not None and d.projection.restated
    noise_off = d.noise is not None and d.noise.applied
    referenced = d.reference.tested if d.reference is not None else []
    out = {
        "recording": recording,
        "sim": sim,
        "pipeline": pipeline,
        "mismatch": v.mismatch or restated or noise_off or d.description is not None or bool(referenced),
        "verdict": _verdict(d.projection, d.noise, d.description, v.verdict, d.reference),
        "projection": d.projection.as_json() if d.projection is not None else None,
        "noise": {"sigma_px_median": float(np.median(data.obs.sigma)), "source": data.obs.sigma_source},
        "noise_check": d.noise.as_json() if d.noise is not None else None,
        "noise_overstated": (overstated(data.obs, d.model.prediction, data.train | data.heldout,
                                        data.n_train_frames + data.heldout_frames_fitted,
                                        sum(len(c.parameters) for c in d.model.chosen))
                             if d.noise is None and known_noise(data) else None),
        "rejected_outliers": data.n_rejected,
        "outlier_gate_sigmas": data.gate_sigmas,
        "outlier_gate_trimmed_start": data.gate_trimmed,
        "isolated_misfits": _isolated(data.obs, d.model.prediction, v.isolated),
        "outlier_rounds": list(d.outlier_rounds),
        "split": {"unit": data.unit, "frames": data.obs.n_frames, "train_frames": data.n_train_frames,
                  "heldout_frames": data.n_heldout_frames, "train_observations": int(data.train.sum()),
                  "heldout_observations": int(data.heldout.sum())},
        "located": d.location.summary(),
        "screen": d.naming.selection["screen"],
        "selection_steps": d.naming.selection["steps"],
        "selection_rounds": d.naming.rounds,
        "weak_candidates": v.weak,
        "effects": v.effects,
        "ambiguous": v.ambiguous,
        "absorbed_by_attitude": v.absorbed,
        "attitude_reference": d.reference.as_json() if d.reference is not None else None,
        "reference_available": _reference_available(d),
        "not_testable": d.location.untestable,
        "unexplained_systematic": {"present": v.unexplained or d.description is not None,
                                   "evidence": list(d.uncorrected_evidence) if d.corrected else v.evidence,
                                   "tests": d.model.leftover_tests,
                                   "description": d.description.as_json() if d.description is not None else None,
                                   "left_after_correction": v.evidence if d.corrected else None},
    }
    # "before" is the model as given; with an empirical correction, the model as given without it
    given = d.as_given if d.corrected and d.as_given is not None else {}
    for key, pair in (("train_rms", q.train_rms_px), ("heldout_rms", q.heldout_rms_px)):
        out[f"{key}_before_px"], out[f"{key}_after_px"] = given.get(f"{key}_px", pair.before), pair.after
    for key, pair in (("train_chi2_dof", q.train_chi2_dof), ("heldout_chi2_dof", q.heldout_chi2_dof)):
        out[f"{key}_before"], out[f"{key}_after"] = given.get(key, pair.before), pair.after
    out.update({
        "heldout_residual_distribution": q.heldout_distribution,
        "gyro_channel": q.gyro,
        "stability": d.model.stability,
        "refit_success": d.model.fit["success"],
        "resimulation": q.resimulation,
        "heldout_confirms": v.heldout_confirms,
        "rejected_on_heldout": v.rejected_on_heldout,
    })
    out["summary"] = summary.paragraph(out)
    return out


def _verdict(projection: ProjectionChoice | None, noise: NoiseCheck | None, description: Description | None,
             verdict: str, reference: ReferenceCheck | None = None) -> str:
    """The verdict, led by the lens projection or focal length when one replaced the declared one, by the noise
    factor when the recording's noise is not the stated one, and by a shape outside the library
    when one was described."""
    lead = []
    if projection is not None and projection.restated:
        lead.append(projection.sentence())
    if noise is not None and noise.applied:
        lead.append(noise.sentence())
    if description is not None:
        lead.append(f"outside the library: {description.text}" +
                    (" (written as an empirical correction)" if description.correction is not None else ""))
    if reference is not None and reference.model:
        lead.append("against the reference attitude: " + ", ".join(c.name for c, _ in reference.model))
    if not lead:
        return verdict
    rest = verdict.replace("no mismatch: the simulation explains", "with it the simulation explains", 1)
    return "; ".join([*lead, rest])
