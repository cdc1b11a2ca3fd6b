"""Step 1, locate: where the simulation as given misses the recording.

Before any fit, a share of the data is held out (:func:`split_heldout`). The attitudes and rates
are then fitted under the simulation model as given; observations far beyond the noise (a wrong
star match, not physics) are dropped and the fit repeated; with a gyro, attitude increments of
consecutive training frames become a second residual channel. The result: chi-square per dof
against the recording's noise and residual structure by covariate, channel, field region and time
span (:mod:`.residuals`), and the linear problem of the candidates' signatures at the model as
given (:mod:`.signatures`), from which the next step names effects.
"""
from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np
from scipy.spatial import cKDTree
from scipy.spatial.transform import Rotation

from rollingstar.errors import UserError
from rollingstar.estimators.diagnosis import gyro_channel, residuals
from rollingstar.estimators.diagnosis.gyro_channel import GyroChannel, GyroData
from rollingstar.estimators.diagnosis.inputs import DiagnoseOptions, SensorModel
from rollingstar.estimators.diagnosis.library import Candidate
from rollingstar.estimators.diagnosis.observations import (
    Nuisance,
    Observations,
    Prediction,
    fit_nuisance,
    whitened_residuals,
)
from rollingstar.estimators.diagnosis.selection import LinearProblem
from rollingstar.estimators.diagnosis.signatures import linear_problem

MIN_STARS_PER_FRAME = 4  # an attitude from fewer stars says little: frames keep at least this many
OUTLIER_SIGMA = 30.0  # far beyond noise, below the identifier's refine gate: a wrong match, not physics
GATE_ROUNDS = 4  # attitude refits of the gross-outlier gate (:func:`gross_outliers`)
MIN_TRAINING_STARS = 10  # fewer training stars left after the outlier gate: nothing to diagnose
# Times the median miss of the gate that replaces OUTLIER_SIGMA when that one would leave fewer than
# MIN_TRAINING_STARS, or reject more than MAX_GROSS_FRACTION of the stars (wrong identifications are a
# minority of a verified identification): many stars beyond a gate meant for them say the model is far
# off (a lens far from the one declared, against stars measured to a few hundredths of a pixel),
# not that most identifications are wrong; a wrong one still misses by many times the typical star.
# Only for a model off by at most ROBUST_GATE_MAX_MISS of the image diagonal at the median star
# (8 px on 808 x 608, the distortion a lens's corners commonly show): beyond it the model is too far
# for the fits to start from, and the diagnosis says what to state closer
ROBUST_GATE = 5.0
MAX_GROSS_FRACTION = 0.25
ROBUST_GATE_MAX_MISS = 0.008
LOCATED_STRUCTURE_ROWS = 12  # covariate x channel tests reported (strongest first)


@dataclass(frozen=True, eq=False)
class Dataset:
    """The observations as every fit uses them: held-out split made, gross outliers removed, and
    with a gyro the increment channel of the training frames attached (``obs.channel``)."""

    obs: Observations  # ``obs.heldout`` marks the held-out observations
    unit: str  # what was held out: "frames" (>= 4 frames) or "stars" (within frames)
    frame_has_train: np.ndarray  # (F,) frames with at least one training star
    att_mask: np.ndarray  # observations the attitudes are fitted to: training stars, and held-out frames' own
    n_rejected: int  # gross outliers dropped
    channel_heldout: GyroChannel | None  # the increment channel of the pairs touching a held-out frame
    gate_sigmas: float = OUTLIER_SIGMA  # the gross-outlier gate used (Mahalanobis sigmas)
    gate_trimmed: bool = False  # the gate started from the least-trimmed-squares attitudes (:func:`trimmed_gate`)

    @property
    def train(self) -> np.ndarray:
        return ~self.obs.heldout

    @property
    def heldout(self) -> np.ndarray:
        return self.obs.heldout

    @property
    def n_train_frames(self) -> int:
        return int(self.frame_has_train.sum())

    @property
    def n_heldout_frames(self) -> int:
        return int((~self.frame_has_train).sum())

    @property
    def heldout_frames_fitted(self) -> int:
        """Attitudes fitted to held-out data alone (3 dof each): the held-out frames, when whole frames are held out."""
        return self.n_heldout_frames if self.unit == "frames" else 0

    @property
    def n_residuals(self) -> int:
        """Rows of the training residual: x and y of every training star, and the gyro increment rows."""
        return 2 * int(self.train.sum()) + (self.obs.channel.rows if self.obs.channel is not None else 0)

    def blocks(self) -> np.ndarray:
        """Bootstrap block of every residual row: its frame (its star, when stars are held out); gyro rows by pair."""
        chan = self.obs.channel
        blocks_all = self.obs.frame if self.unit == "frames" else np.arange(self.obs.n)
        train = self.train
        return np.concatenate([blocks_all[train], blocks_all[train], np.repeat(chan.pairs, 3) if chan is not None else []])


@dataclass(frozen=True, eq=False)
class Location:
    """What the Locate step found: the data, the fit of the model as given, and where it misses."""

    data: Dataset
    nuisance: Nuisance  # attitudes and rates fitted under the model as given
    prediction: Prediction
    residuals: dict  # :func:`.residuals.locate` (chi-square, structure by covariate/channel, regions, time spans)
    gyro_chi2: float | None  # chi-square of the gyro increment rows under the model as given
    problem: LinearProblem  # every testable candidate's signature at the model as given
    untestable: list[dict]  # ``{"name", "reason"}`` of the candidates that cannot be tested

    def summary(self) -> dict:
        """The reported part of :attr:`residuals`: no private keys, the strongest structure rows only."""
        located = {k: v for k, v in self.residuals.items() if not k.startswith("_")}
        located["structure"] = located["structure"][:LOCATED_STRUCTURE_ROWS]
        return located


def locate(obs: Observations, attitudes: Rotation, sensor: SensorModel, cands: dict[str, Candidate],
           gyro: GyroData | None, options: DiagnoseOptions, gate: SensorModel | None = None) -> Location:
    """Hold out data, fit the model as given, reject gross outliers, measure where it misses.

    ``gate``: the model whose misses decide what is a gross outlier (default: the model as given);
    the diagnosis passes the model it named, so that stars the named physics explains are kept."""
    data, nuis0, pred0 = prepare_data(obs, attitudes, sensor, gyro, options, gate)
    obs = data.obs
    gyro_chi2 = None if obs.channel is None else float(np.sum(gyro_channel.channel_rows(obs, pred0) ** 2))
    located = residuals.locate(obs, pred0, sensor.camera, data.train, 3 * data.n_train_frames)
    problem, untestable = linear_problem(obs, pred0, cands, sensor.effects, data.train, data.blocks())
    return Location(data, nuis0, pred0, located, gyro_chi2, problem, untestable)


def prepare_data(obs: Observations, attitudes: Rotation, sensor: SensorModel, gyro: GyroData | None,
                 options: DiagnoseOptions, gate: SensorModel | None = None) -> tuple[Dataset, Nuisance, Prediction]:
    """The held-out split, the first nuisance fit, outlier rejection (against ``gate``'s
    prediction, default the model as given) and the gyro channel.

    Returns the data, and the attitudes/rates and prediction of the model as given on it.
    """
    heldout, unit = split_heldout(obs, options.heldout_fraction, options.seed)
    obs = replace(obs, heldout=heldout)
    frame_has_train, att_mask = attitude_mask(obs)
    fit = (sensor.camera, sensor.timing, sensor.effects)
    obs = with_noise(obs, attitudes, sensor)
    nuis0, pred0 = fit_nuisance(obs, attitudes, *fit, att_mask, sensor.moving)
    # gross outliers (misidentified stars: the tracking refine gate is 2 px = 40 sigma at 0.05 px),
    # against the named model's misses when one is given
    model = sensor if gate is None else gate
    far, gate_sigmas, gate_trimmed = _gate(obs, attitudes, model, att_mask, pred0 if gate is None else None)
    n_rejected = int(far.sum())
    if np.count_nonzero(~obs.heldout) < MIN_TRAINING_STARS:
        raise UserError(f"only {np.count_nonzero(~obs.heldout)} of the {obs.n} identified stars are left for training "
                        f"after holding out {obs.n - np.count_nonzero(~obs.heldout)} to check the fit; at least "
                        f"{MIN_TRAINING_STARS} are needed: diagnose a recording with more stars or frames")
    if np.count_nonzero(~far & ~obs.heldout) < MIN_TRAINING_STARS:
        miss = float(np.nanmedian(np.hypot(obs.x - pred0.x, obs.y - pred0.y)))
        raise UserError(f"the simulation as given misses {n_rejected} of the {obs.n} identified stars by more than "
                        f"{gate_sigmas:.3g} sigma (median miss {miss:.3g} px), leaving fewer than {MIN_TRAINING_STARS} "
                        f"training stars to diagnose: its sensor model is far from the recording's (lens projection, "
                        f"focal length, distortion or principal point), or so many of the identifications are wrong "
                        f"that not even the half of each frame's stars it misses least place its attitude; state the "
                        f"sensor closer in the scenario, or check the identification")
    if n_rejected:
        obs = obs.take(~far)
        frame_has_train, att_mask = attitude_mask(obs)
        nuis0, pred0 = fit_nuisance(obs, attitudes, *fit, att_mask, sensor.moving)
    # second channel: attitude increments of consecutive training frames against the gyro
    gyro = gyro if unit == "frames" else None
    chan = gyro_channel.build_channel(gyro, obs, pred0, frame_has_train, att_mask)
    chan_out = gyro_channel.build_channel(gyro, obs, pred0, frame_has_train, att_mask, heldout=True)
    if chan is not None:
        obs = replace(obs, channel=chan)
        nuis0, pred0 = fit_nuisance(obs, nuis0, *fit, att_mask, sensor.moving)
    return Dataset(obs, unit, frame_has_train, att_mask, n_rejected, chan_out, gate_sigmas, gate_trimmed), nuis0, pred0


def _gate(obs: Observations, attitudes, model: SensorModel, att_mask: np.ndarray,
          pred: Prediction | None) -> tuple[np.ndarray, float, bool]:
    """The gross outliers of ``model``, the gate (sigmas) that found them and whether it started from
    the trimmed fit.

    The gates of :func:`_gates_from` the attitudes fitted to every star. When they leave too few
    training stars, those attitudes were too far off to start from (a few wrong identifications
    hundreds of pixels off, on a lens the model as given also misses): the same gates from the
    least-trimmed-squares attitudes (:func:`trimmed_gate`)."""
    far, gate_sigmas = _gates_from(obs, attitudes, model, att_mask, pred)
    if _enough(obs, far):
        return far, gate_sigmas, False
    return (*trimmed_gate(obs, attitudes, model, att_mask), True)


def trimmed_gate(obs: Observations, attitudes, model: SensorModel, att_mask: np.ndarray) -> tuple[np.ndarray, float]:
    """The gross outliers of ``model`` and the gate (sigmas) that found them (:func:`_gates_from`),
    starting from the least-trimmed-squares attitudes (:func:`trimmed_prediction`)."""
    return _gates_from(obs, attitudes, model, att_mask, trimmed_prediction(obs, attitudes, model, att_mask))


def _gates_from(obs: Observations, attitudes, model: SensorModel, att_mask: np.ndarray,
                pred: Prediction | None) -> tuple[np.ndarray, float]:
    """The ``OUTLIER_SIGMA`` gate from ``pred`` (None: ``model``'s fit to every star); when it leaves
    too few training stars or rejects too many, :func:`_robust_gate`'s."""
    if pred is None:
        _, pred = fit_nuisance(obs, attitudes, model.camera, model.timing, model.effects, att_mask, model.moving)
    far = gross_outliers(obs, attitudes, model, att_mask, pred)
    if _enough(obs, far) and far.mean() <= MAX_GROSS_FRACTION:
        return far, OUTLIER_SIGMA
    gate_sigmas = _robust_gate(obs, attitudes, model, att_mask, pred)
    return gross_outliers(obs, attitudes, model, att_mask, pred, gate_sigmas), gate_sigmas


def _enough(obs: Observations, far: np.ndarray) -> bool:
    """Whether at least ``MIN_TRAINING_STARS`` training stars are left outside ``far``."""
    return np.count_nonzero(~far & ~obs.heldout) >= MIN_TRAINING_STARS


TRIM_FRACTION = 0.5  # of each frame's stars, the share the trimmed attitude fit keeps
TRIM_ROUNDS = 10  # C-steps of the trimmed fit at most (they stop when the stars kept repeat)


def trimmed_prediction(obs: Observations, attitudes, model: SensorModel, att_mask: np.ndarray) -> Prediction:
    """``model``'s prediction with each frame's attitude fitted to the half of its stars it misses
    least: least trimmed squares by C-steps (Rousseeuw and Van Driessen 2006; fit, keep the half
    with the smallest misses, refit, until the stars kept repeat). A wrong identification hundreds
    of pixels off pulls a fit to every star by tens of pixels; it cannot pull this one while wrong
    stars are fewer than half of a frame's."""
    fit = (model.camera, model.timing, model.effects)
    _, pred = fit_nuisance(obs, attitudes, *fit, att_mask, model.moving)
    keep = att_mask
    for _ in range(TRIM_ROUNDS):
        miss = np.where(att_mask, miss_sigmas(obs, pred), np.inf)
        again = att_mask & _least_per_frame(obs.frame, obs.n_frames, miss, TRIM_FRACTION)
        if np.array_equal(again, keep):
            break
        keep = again
        _, pred = fit_nuisance(obs, attitudes, *fit, keep, model.moving)
    return pred


def _least_per_frame(frame: np.ndarray, n_frames: int, value: np.ndarray, fraction: float) -> np.ndarray:
    """Per frame, the ``fraction`` of its observations with a finite ``value`` that have the smallest
    (at least ``MIN_STARS_PER_FRAME``, or all it has); an infinite value marks one left out."""
    order = np.lexsort((value, frame))  # by frame, then by value
    count = np.bincount(frame, minlength=n_frames)
    first = np.concatenate([[0], np.cumsum(count)[:-1]])
    rank = np.empty(frame.size, dtype=np.int64)
    rank[order] = np.arange(frame.size) - first[frame[order]]
    finite = np.bincount(frame, weights=np.isfinite(value), minlength=n_frames)
    n_keep = np.maximum(np.ceil(fraction * finite), np.minimum(MIN_STARS_PER_FRAME, finite))
    return rank < n_keep[frame]


def _robust_gate(obs: Observations, attitudes, model: SensorModel, att_mask: np.ndarray,
                 pred: Prediction | None = None) -> float:
    """``ROBUST_GATE`` times the median miss (sigmas) of ``model`` with every star in the attitude
    fit, never below ``OUTLIER_SIGMA``; ``OUTLIER_SIGMA`` when the median miss exceeds
    ``ROBUST_GATE_MAX_MISS`` of the image diagonal."""
    if pred is None:  # ``model``'s prediction with every star in the attitude fit, when not already made
        _, pred = fit_nuisance(obs, attitudes, model.camera, model.timing, model.effects, att_mask, model.moving)
    diagonal = float(np.hypot(model.camera.width, model.camera.height))
    if np.median(np.hypot(obs.x - pred.x, obs.y - pred.y)) > ROBUST_GATE_MAX_MISS * diagonal:
        return OUTLIER_SIGMA
    return max(OUTLIER_SIGMA, ROBUST_GATE * float(np.median(miss_sigmas(obs, pred))))


def check_parity(obs: Observations, model: SensorModel) -> None:
    """Refuse a recording whose stars are a mirror image of the sky ``model`` draws: no projection,
    focal length or distortion turns one into the other, so every later fit would only report that
    it misses (:func:`mirrored_fraction`; at least ``PARITY_MIN_TRIANGLES`` triangles judged, and
    ``MIRRORED_FRACTION`` of them turned over)."""
    flipped, judged = mirrored_fraction(obs, model.camera)
    if judged < PARITY_MIN_TRIANGLES or flipped < MIRRORED_FRACTION * judged:
        return
    raise UserError(
        f"the recording's stars are a mirror image of the sky the simulation draws: {flipped} of {judged} triangles "
        f"of stars run round the other way than their catalogue stars (a rotation, a focal length or a distortion "
        f"keeps that order; only a mirror reverses it). The recording's pixel axes run the other way than "
        f"docs/conventions.md states ((x, y) = (column, row), row 0 the first row of the image data, the sky as seen "
        f"through the lens): flip one axis where the recording is made or imported (x -> W - 1 - x, or "
        f"y -> H - 1 - y; x and y swapped is the same mirror turned about the boresight)")


PARITY_MIN_TRIANGLES = 10  # fewer distinct triangles judged over the recording: no verdict
MIRRORED_FRACTION = 0.8  # a true recording's wrong stars turn some triangles over, never most of them


def mirrored_fraction(obs: Observations, camera) -> tuple[int, int]:
    """Of the local triangles of each frame's stars (each star with its two nearest neighbours in
    the image, every distinct triangle once), how many run round the other way than their
    catalogue stars, and how many were judged: ``(turned over, judged)``.

    The order round a triangle is the sign of ``det(w_i, w_j, w_k)`` of the camera directions and of
    ``det(u_i, u_j, u_k)`` of the catalogue directions. An attitude is a rotation, which keeps it; a
    focal length, a radial distortion or another projection maps a small neighbourhood of the image
    smoothly onto the sky without turning it over, which keeps it too, even far off the boresight
    (a triangle spanning the field of a wide lens declared as a pinhole would not); a mirror
    reverses it. Triangles thinner than a quarter of the frame's median, or degenerate (two stars
    on one catalogue direction), are not judged; frames with fewer than 3 stars have none."""
    w = camera.unproject(obs.x, obs.y).reshape(-1, 3)
    flipped = judged = 0
    for f in range(obs.n_frames):
        idx = np.flatnonzero((obs.frame == f) & np.all(np.isfinite(w), axis=1))
        if idx.size < 3:
            continue
        tri = idx[_local_triangles(obs.x[idx], obs.y[idx])]
        du, dw = np.linalg.det(obs.u_icrs[tri]), np.linalg.det(w[tri])
        judge = (np.abs(du) >= 0.25 * np.median(np.abs(du))) & (du != 0) & (dw != 0)
        flipped += int(np.count_nonzero(judge & (np.sign(du) != np.sign(dw))))
        judged += int(np.count_nonzero(judge))
    return flipped, judged


def _local_triangles(x: np.ndarray, y: np.ndarray) -> np.ndarray:
    """Each point with its two nearest neighbours, as index triples (m, 3), each distinct triangle once."""
    _, near = cKDTree(np.column_stack([x, y])).query(np.column_stack([x, y]), k=3)  # itself first
    return np.unique(np.sort(near, axis=1), axis=0)


def gross_outliers(obs: Observations, attitudes, model: SensorModel, att_mask: np.ndarray,
                   pred: Prediction | None = None, gate_sigmas: float = OUTLIER_SIGMA) -> np.ndarray:
    """The stars ``model`` misses by more than ``gate_sigmas`` with every frame's attitude fitted
    without them: a fixed point of fitting the attitudes to the stars inside the gate and gating
    every star again (at most ``GATE_ROUNDS`` fits). A wrong identification pulls its frame's
    least-squares attitude, by tens of pixels when it is hundreds of pixels off, and a single gate
    on that fit rejects good stars with it (4 wrong stars among 40 can take half the good ones
    along); the refit without the far stars brings the good ones back. ``pred``: ``model``'s prediction with
    every star in the fit, when already computed."""
    fit = (model.camera, model.timing, model.effects)
    if pred is None:
        _, pred = fit_nuisance(obs, attitudes, *fit, att_mask, model.moving)
    far = miss_sigmas(obs, pred) > gate_sigmas
    for _ in range(GATE_ROUNDS):
        if not far.any():
            break
        _, pred = fit_nuisance(obs, attitudes, *fit, att_mask & ~far, model.moving)
        again = miss_sigmas(obs, pred) > gate_sigmas
        if np.array_equal(again, far):
            break
        far = again
    return far


def beyond_gate(obs: Observations, pred: Prediction) -> np.ndarray:
    """The stars further than ``OUTLIER_SIGMA`` from ``pred`` (:func:`miss_sigmas`)."""
    return miss_sigmas(obs, pred) > OUTLIER_SIGMA


def miss_sigmas(obs: Observations, pred: Prediction) -> np.ndarray:
    """Each star's distance from ``pred`` in sigmas (Mahalanobis under its 2 x 2 covariance)."""
    if obs.cov is None:
        return np.hypot(obs.x - pred.x, obs.y - pred.y) / obs.sigma
    return np.linalg.norm(whitened_residuals(obs, pred), axis=1)


def split_heldout(obs: Observations, fraction: float, seed: int) -> tuple[np.ndarray, str]:
    """Held-out mask decided before any fit: whole frames (>= 4 frames), else stars within frames."""
    rng = np.random.default_rng([seed, 7])
    if obs.n_frames >= 4:
        n_out = max(1, int(round(fraction * obs.n_frames)))
        out_frames = rng.choice(obs.n_frames, size=n_out, replace=False)
        return np.isin(obs.frame, out_frames), "frames"
    mask = np.zeros(obs.n, dtype=bool)
    perm = rng.permutation(obs.n)
    # per frame keep at least MIN_STARS_PER_FRAME training stars
    for k in range(obs.n_frames):
        idx = perm[obs.frame[perm] == k]
        n_out = min(int(round(fraction * idx.size)), max(idx.size - MIN_STARS_PER_FRAME, 0))
        mask[idx[:n_out]] = True
    return mask, "stars"


def attitude_mask(obs: Observations) -> tuple[np.ndarray, np.ndarray]:
    """Frames with training stars (F,), and the observations each frame's attitude is fitted to:
    its training stars, or a held-out frame's own stars (the attitude is a nuisance, fitted anyway)."""
    train = ~obs.heldout
    frame_has_train = np.bincount(obs.frame[train], minlength=obs.n_frames) > 0
    return frame_has_train, train | ~frame_has_train[obs.frame]


def with_noise(obs: Observations, attitudes, sensor: SensorModel) -> Observations:
    """``obs`` with a noise: as they are when they state one, else :func:`estimate_sigma` of the
    model's fit with every star weighted alike."""
    if obs.sigma_source != "estimated":
        return obs
    equal = replace(obs, sigma=np.ones(obs.n), cov=None)
    fit = fit_nuisance(equal, attitudes, sensor.camera, sensor.timing, sensor.effects, None, sensor.moving)
    return estimate_sigma(obs, fit[1])


def estimate_sigma(obs: Observations, pred: Prediction) -> Observations:
    """Observations without a known noise get the residual scatter of ``pred`` (MAD) as their sigma."""
    r = np.concatenate([obs.x - pred.x, obs.y - pred.y])
    s = 1.4826 * np.median(np.abs(r - np.median(r)))
    return replace(obs, sigma=np.where(np.isfinite(obs.sigma), obs.sigma, max(s, 1e-6)),
                   sigma_source="estimated from the residual scatter (MAD): the chi-square test is then uninformative")
