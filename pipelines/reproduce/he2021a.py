"""Reproduction of he2021a (He et al., Acta Photonica Sinica 50(3), 2021), section 3.

Sensor: Table 1 (``configs/scenarios/he2021a.yaml``: f = 24.09 mm, 5.5 um pixels, 1024 x 1024,
line delay 43.9 us, exposure 44.9 ms, frame period eq (5) 89.85 ms), real Hipparcos sky (Hp <= 6)
around (ra, dec) = (83.8, -5.4) deg. Pipeline ``configs/pipelines/he2021a.yaml`` (tracking, kf-cv
with Q = 1e-4 px^2/s^4, time-domain to the middle row's exposure start, QUEST); the "before"
branch is the same frame's identified raw centroids (correction ``none``).

Experiments (each trial = one simulator seed ``seed * 1000 + trial``; noise differs, sky the same):

- Figs 6-7 (filter): centroid level, centroid noise variance R (px^2) = the filter's ``r``,
  1 deg/s about camera x (Fig 6) and y (Fig 7), 100 frames. Error of each filtered star against
  the simulator truth at the star's ``t_ns``; velocity against the true image velocity there
  (central difference of the truth, +-0.5 ms). Reported: RMS per axis over stars whose track is
  >= 50 frames old ("after 50 frames").
- Fig 10 (smear centroid): image level (our PSF sigma 1 px, see the scenario), CoG centroids,
  rates about x. "Before": raw centroid vs the truth at the time it claims (mid-exposure of its
  row). "After": eqs (12)-(16) with the filtered velocity (``x' = x_f - v t_e / 2``) vs the truth
  at the exposure start of the star's row (the time ``x'`` refers to). RMS radial error, tracks
  >= 10 frames old.
- Fig 12 (star-pair distance): centroid level, rates 0-3 deg/s about x and y, R = 0.05 and 0.1.
  Pair distance of two identified stars minus the true distance at the pair's common time (mean
  of the two claimed times), as ``pipelines.evaluate``. "After": pairs of corrected stars whose
  tracks are >= 10 frames old. Two statistics: RMS over all pair-frames ("per frame", noise
  included), and RMS over pairs of each pair's mean error over its frames ("systematic": the
  paper's figure, linear in rate before correction, reads as this).
- Figs 14-15 (attitude): the same runs, QUEST on five stars per frame (the five brightest with a
  filtered velocity, the same catalogue stars before and after), error per axis vs truth at the
  estimate's time; RMS over frames 10-99 (arcsec).
"""
from __future__ import annotations

import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from estimators.corrections.time_domain import TimeDomainCorrection
from estimators.data import FrameData, StarTable
from estimators.filters.kf_cv import KfCvFilter
from pipelines import build
from pipelines.config import load_pipeline, load_scenario
from pipelines.reproduce import Row, paper_values
from pipelines.runner import build_stages
from pipelines.simulate import build_simulator
from pipelines.truth import true_positions
from sensors.conventions import attitude_error_body_arcsec

ROOT = Path(__file__).resolve().parents[2]
SCENARIO = ROOT / "configs" / "scenarios" / "he2021a.yaml"
PIPELINE = ROOT / "configs" / "pipelines" / "he2021a.yaml"
AGE_CONVERGED = 50  # "after 50 frames" (Figs 6-7)
AGE_MIN = 10  # tracks younger than this are excluded from the pair / smear statistics
N_ATT_STARS = 5  # "five stars" for the QUEST part
VEL_H_NS = 500_000


@dataclass
class RunRecord:
    """Per-frame measurements of one simulated run (concatenated arrays)."""

    age: list = field(default_factory=list)  # track age per filtered star
    pos_err: list = field(default_factory=list)  # (m, 2) filtered - truth at t_ns
    vel_err: list = field(default_factory=list)  # (m, 2)
    smear_before: list = field(default_factory=list)  # radial, raw vs truth at t_ns
    smear_after: list = field(default_factory=list)  # radial, eqs 12-16 vs truth at row start
    pair_before: list = field(default_factory=list)  # (err, pair_key)
    pair_after: list = field(default_factory=list)
    att_before: list = field(default_factory=list)  # (3,) arcsec
    att_after: list = field(default_factory=list)
    frame_pos: list = field(default_factory=list)  # (frame, track age, |err x|, |err y|, |ev x|, |ev y|) of one star


def _scenario(level: str, rate_xyz, r: float, seed: int, frames: int):
    cfg = load_scenario(SCENARIO)
    return cfg.model_copy(update={
        "level": level, "seed": seed, "frames": frames,
        "noise": cfg.noise.model_copy(update={"centroid_sigma_px": float(np.sqrt(r))}),
        "motion": cfg.motion.model_copy(update={"rate_deg_s": tuple(float(v) for v in rate_xyz)})})


def _stages(r: float, level: str):
    pipe = load_pipeline(PIPELINE)
    stages = build_stages(pipe, str(PIPELINE))
    out = []
    for st, cfg in zip(stages, pipe.stages):
        if isinstance(st, KfCvFilter):
            st = KfCvFilter(**{**cfg.params, "r": r})
        if st.role == "centroider" and level == "centroid":
            continue
        out.append(st)
    return out


def _truth_xy(cam, motion, unit, t_ns):
    t = np.asarray(t_ns, dtype=np.int64)
    return np.column_stack(true_positions(cam, [], motion.attitude(t), unit, t))


def _pairs(stars: StarTable, cam, motion, ok):
    idx = np.flatnonzero(ok)
    if idx.size < 2:
        return np.zeros(0), np.zeros((0, 2), dtype=np.int64)
    i, j = np.triu_indices(idx.size, k=1)
    a, b = idx[i], idx[j]
    tc = (stars.t_ns[a] + stars.t_ns[b]) // 2
    pa = _truth_xy(cam, motion, stars.ref_icrs[a], tc)
    pb = _truth_xy(cam, motion, stars.ref_icrs[b], tc)
    d_true = np.hypot(*(pa - pb).T)
    d_meas = np.hypot(stars.x[a] - stars.x[b], stars.y[a] - stars.y[b])
    keys = np.column_stack([stars.catalog_id[a], stars.catalog_id[b]])
    return d_meas - d_true, keys


def _quest(quest, frame, stars):
    out = quest.process(frame.evolve(stars=stars, attitudes=()))
    est = out.attitudes[-1]
    return est if est.valid else None


def simulate_run(level: str, rate_xyz, r: float, seed: int, frames: int) -> RunRecord:
    """Simulate one run and apply the he2021a pipeline frame by frame (see the module docstring)."""
    cfg = _scenario(level, rate_xyz, r, seed, frames)
    sim = build_simulator(cfg)
    ctx = build.build_context(cfg, catalog=sim.catalog)
    stages = _stages(r, level)
    for s in stages:
        s.setup(ctx)
    cen = [s for s in stages if s.role == "centroider"]
    ident = next(s for s in stages if s.role == "identifier")
    kf = next(s for s in stages if s.role == "filter")
    td = next(s for s in stages if s.role == "correction")
    quest = next(s for s in stages if s.role == "attitude")
    cam, motion, timing = sim.camera, sim.motion, sim.timing
    rec = RunRecord()
    ages: dict[int, int] = {}
    tracked_star = None
    for k in range(frames):
        sf = sim.frame(k)
        if sf.image is not None:
            frame = FrameData(index=k, t0_ns=sf.t0_ns, image=sf.image)
            frame = cen[0].process(frame)
        else:
            c = sf.centroids
            frame = FrameData(index=k, t0_ns=sf.t0_ns, stars=StarTable.build(
                c["x"], c["y"], c["t_ns"], c["row_time_ns"], flux=c["flux"], sigma_px=np.full(len(c["x"]), np.sqrt(r))))
        frame = ident.process(frame)
        raw = frame.stars
        filt_frame = kf.process(frame)
        filt = filt_frame.stars
        corr_frame = td.process(filt_frame)
        corr = corr_frame.stars
        # track ages (frames since the track started; 0 = first sighting)
        ages = {int(c): ages.get(int(c), -1) + 1 for c in filt.catalog_id}
        age = np.array([ages[int(c)] for c in filt.catalog_id], dtype=int)
        has_v = np.isfinite(filt.vx) & np.isfinite(filt.vy)
        # filter accuracy (Figs 6-7)
        if has_v.any():
            unit = filt.ref_icrs[has_v]
            t = filt.t_ns[has_v]
            p = _truth_xy(cam, motion, unit, t)
            v = (_truth_xy(cam, motion, unit, t + VEL_H_NS) - _truth_xy(cam, motion, unit, t - VEL_H_NS)) / (2 * VEL_H_NS * 1e-9)
            pe = np.column_stack([filt.x[has_v], filt.y[has_v]]) - p
            ve = np.column_stack([filt.vx[has_v], filt.vy[has_v]]) - v
            rec.age.append(age[has_v])
            rec.pos_err.append(pe)
            rec.vel_err.append(ve)
            if tracked_star is None or tracked_star not in ages:
                older = filt.catalog_id[has_v]
                # follow the star that will stay longest: the one with the largest remaining path (ours: first listed)
                tracked_star = int(older[0])
            sel = np.flatnonzero(filt.catalog_id[has_v] == tracked_star)
            if sel.size:
                s0 = sel[0]
                rec.frame_pos.append((k, ages[tracked_star], *np.abs(pe[s0]), *np.abs(ve[s0])))
            # smear centroid (Fig 10): before = raw at its t_ns; after = eqs (12)-(16), refers to row start
            old = age[has_v] >= AGE_MIN
            if old.any():
                raw_ok = raw.take(np.flatnonzero(has_v)[old])
                pr = _truth_xy(cam, motion, raw_ok.ref_icrs, raw_ok.t_ns)
                rec.smear_before.append(np.hypot(raw_ok.x - pr[:, 0], raw_ok.y - pr[:, 1]))
                f_ok = filt.take(np.flatnonzero(has_v)[old])
                half_te = 0.5 * timing.exposure_ns * 1e-9  # eqs (12)-(16) with h_i = 1
                xs, ys = f_ok.x - f_ok.vx * half_te, f_ok.y - f_ok.vy * half_te
                ps = _truth_xy(cam, motion, f_ok.ref_icrs, f_ok.t_ns - timing.exposure_ns // 2)
                rec.smear_after.append(np.hypot(xs - ps[:, 0], ys - ps[:, 1]))
        # star-pair distance (Fig 12)
        if level == "centroid":
            e, keys = _pairs(raw, cam, motion, np.ones(raw.n, bool))
            rec.pair_before.append((e, keys))
            e, keys = _pairs(corr, cam, motion, has_v & (age >= AGE_MIN))
            rec.pair_after.append((e, keys))
            # attitude (Figs 14-15): the five brightest stars with a velocity, same stars before/after
            cand = np.flatnonzero(has_v)
            if cand.size >= N_ATT_STARS and k >= AGE_MIN:
                pick = cand[np.argsort(-filt.flux[cand], kind="stable")[:N_ATT_STARS]]
                for stars, out in ((raw.take(pick), rec.att_before), (corr.take(pick), rec.att_after)):
                    est = _quest(quest, frame, stars)
                    if est is not None:
                        truth = motion.attitude(np.array([est.t_ns], dtype=np.int64))
                        from scipy.spatial.transform import Rotation
                        out.append(attitude_error_body_arcsec(truth, Rotation.from_quat(est.q_xyzw[None]))[0])
        # advance the tracking prior with the corrected solution (as the runner does)
        est = _quest(quest, corr_frame, corr.take(np.flatnonzero(corr.identified)))
        ident.update_prior(corr_frame.evolve(attitudes=(est,) if est is not None else ()))
    return rec


def _cat(lst, width=None):
    if not lst:
        return np.zeros((0,) if width is None else (0, width))
    return np.concatenate(lst)


def _rms(a):
    a = np.asarray(a, dtype=float)
    a = a[np.isfinite(a)]
    return float(np.sqrt(np.mean(a**2))) if a.size else None


def _pair_stats(recs: list[RunRecord], attr: str):
    """(per-frame RMS, systematic RMS) of pair errors over runs; pairs keyed per run."""
    per_frame, systematic = [], []
    for ri, rec in enumerate(recs):
        errs = [e for e, _ in getattr(rec, attr)]
        keys = [k for _, k in getattr(rec, attr)]
        if not errs or not sum(len(e) for e in errs):
            continue
        e = np.concatenate(errs)
        k = np.concatenate(keys)
        per_frame.append(e)
        _, inv = np.unique(k, axis=0, return_inverse=True)
        inv = inv.reshape(-1)
        sums = np.bincount(inv, weights=e)
        cnt = np.bincount(inv)
        systematic.append(sums[cnt >= 5] / cnt[cnt >= 5])
    return _rms(_cat(per_frame)), _rms(_cat(systematic)), (np.concatenate(per_frame) if per_frame else np.zeros(0))


def _config(quick: bool) -> dict:
    if quick:
        return {"filter_trials": 2, "rates": [0.0, 3.0], "pair_trials": 2, "frames": 100,
                "image_rates": [3.0], "image_trials": 1, "image_frames": 20, "r_values": [0.05]}
    return {"filter_trials": 10, "rates": [0.0, 0.5, 1.0, 1.5, 2.0, 2.5, 3.0], "pair_trials": 5, "frames": 100,
            "image_rates": [0.0, 1.0, 2.0, 3.0], "image_trials": 1, "image_frames": 40, "r_values": [0.05, 0.1]}


def run(quick: bool, plots_dir: Path | None, seed: int) -> list[Row]:
    start = time.perf_counter()
    paper = paper_values("he2021a")
    cfg = _config(quick)
    rows: list[Row] = []
    plot_data: dict = {"filter": {}, "smear": {}, "pair": {}, "att": {}}

    # ---- Figs 6-7: filter at 1 deg/s about x and y, R = 0.05
    for axis, fig in ((0, "Fig 6"), (1, "Fig 7")):
        rate = [0.0, 0.0, 0.0]
        rate[axis] = 1.0
        n = cfg["filter_trials"]
        recs = [simulate_run("centroid", rate, 0.05, seed * 1000 + t, cfg["frames"]) for t in range(n)]
        age = _cat([_cat(r.age) for r in recs])
        pe = _cat([_cat(r.pos_err, 2) for r in recs], 2)
        ve = _cat([_cat(r.vel_err, 2) for r in recs], 2)
        conv = age >= AGE_CONVERGED
        name = "xy"[axis]
        cond = f"1 deg/s about {name}, R=0.05 px^2, track age >= {AGE_CONVERGED} frames"
        pv = paper["position_error_after_50_frames"]
        vv = paper["velocity_deviation_after_50_frames"]
        for ax in (0, 1):
            rows.append(Row(f"filtered position error {'xy'[ax]} (RMS)", cond, pv["value"], _rms(pe[conv, ax]), "px",
                            pv["source"], n, seed, f"{int(conv.sum())} star-frames"))
        for ax in (0, 1):
            rows.append(Row(f"filtered velocity deviation v{'xy'[ax]} (RMS)", cond, vv["value"], _rms(ve[conv, ax]), "px/s",
                            vv["source"], n, seed, "vs the true image velocity at the star's t_ns"))
        plot_data["filter"][name] = (age, pe, ve, recs[0].frame_pos)

    # ---- Fig 10: smear centroid, image level
    sm = paper["smear_centroid_error_before"], paper["smear_centroid_error_after"]
    for w in cfg["image_rates"]:
        recs = [simulate_run("image", [w, 0.0, 0.0], 0.05, seed * 1000 + 500 + t, cfg["image_frames"])
                for t in range(cfg["image_trials"])]
        b = _rms(_cat([_cat(r.smear_before) for r in recs]))
        a = _rms(_cat([_cat(r.smear_after) for r in recs]))
        cond = f"{w:g} deg/s about x, image level, {cfg['image_frames']} frames, track age >= {AGE_MIN}"
        rows.append(Row("smear centroid error before (RMS radial)", cond, sm[0]["value"], b, "px", sm[0]["source"],
                        cfg["image_trials"], seed, "raw CoG vs truth at its claimed time"))
        rows.append(Row("smear centroid error after eqs 12-16 (RMS radial)", cond, sm[1]["value"], a, "px", sm[1]["source"],
                        cfg["image_trials"], seed, "kf-cv + eqs 12-16 vs truth at the row's exposure start"))
        plot_data["smear"][w] = (b, a)

    # ---- Fig 12 and Figs 14-15: pair distance and attitude, centroid level
    pp = paper["pair_distance_error_after"]
    pa = paper["attitude_error_after"]
    for axis in (0, 1):
        for r in cfg["r_values"]:
            for w in cfg["rates"]:
                rate = [0.0, 0.0, 0.0]
                rate[axis] = w
                n = cfg["pair_trials"]
                recs = [simulate_run("centroid", rate, r, seed * 1000 + 100 + t, cfg["frames"]) for t in range(n)]
                bf, bs, _ = _pair_stats(recs, "pair_before")
                af, as_, _ = _pair_stats(recs, "pair_after")
                cond = f"{w:g} deg/s about {'xy'[axis]}, R={r:g} px^2"
                rows.append(Row("pair distance error before, per frame (RMS)", cond, None, bf, "px", pp["source"], n, seed))
                rows.append(Row("pair distance error before, systematic (RMS)", cond, None, bs, "px", pp["source"], n, seed,
                                "RMS over pairs of each pair's mean error"))
                rows.append(Row("pair distance error after, per frame (RMS)", cond, pp["value"], af, "px", pp["source"], n, seed,
                                f"track age >= {AGE_MIN}"))
                rows.append(Row("pair distance error after, systematic (RMS)", cond, pp["value"], as_, "px", pp["source"], n, seed,
                                f"track age >= {AGE_MIN}; RMS over pairs of each pair's mean error"))
                plot_data["pair"][(axis, r, w)] = (bf, bs, af, as_)
                if r == cfg["r_values"][0]:
                    ab = _cat([np.asarray(rr.att_before).reshape(-1, 3) for rr in recs], 3)
                    aa = _cat([np.asarray(rr.att_after).reshape(-1, 3) for rr in recs], 3)
                    for ax, label in enumerate(("x", "y", "z")):
                        rows.append(Row(f"attitude error {label} before (RMS, 5 stars)", cond, None, _rms(ab[:, ax]), "arcsec",
                                        pa["source"], n, seed))
                        rows.append(Row(f"attitude error {label} after (RMS, 5 stars)", cond, pa["value"], _rms(aa[:, ax]),
                                        "arcsec", pa["source"], n, seed, f"frames {AGE_MIN}-{cfg['frames'] - 1}"))
                    plot_data["att"][(axis, w)] = (np.sqrt(np.mean(ab**2, axis=0)) if len(ab) else np.full(3, np.nan),
                                                   np.sqrt(np.mean(aa**2, axis=0)) if len(aa) else np.full(3, np.nan))
    elapsed = time.perf_counter() - start
    rows.append(Row("run time", "quick" if quick else "full", None, elapsed, "s", "", None, seed))
    if plots_dir is not None:
        _plots(Path(plots_dir), plot_data, cfg)
    return rows


def _plots(d: Path, data: dict, cfg: dict) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    for name, fig_no in (("x", 6), ("y", 7)):
        if name not in data["filter"]:
            continue
        age, pe, ve, fp = data["filter"][name]
        ages = np.arange(1, age.max() + 1) if age.size else np.zeros(0, int)
        pos = [np.sqrt(np.mean(pe[age == a] ** 2, axis=0)) if np.any(age == a) else (np.nan, np.nan) for a in ages]
        vel = [np.sqrt(np.mean(ve[age == a] ** 2, axis=0)) if np.any(age == a) else (np.nan, np.nan) for a in ages]
        fig, axs = plt.subplots(1, 2, figsize=(10, 4))
        axs[0].plot(ages, np.array(pos))
        axs[0].axhline(0.1, ls="--", c="k", lw=0.8)
        axs[0].set(xlabel="track age (frames)", ylabel="RMS position error (px)", yscale="log",
                   title=f"Fig {fig_no}: 1 deg/s about {name}, R=0.05")
        axs[0].legend(["x", "y", "paper bound 0.1"])
        axs[1].plot(ages, np.array(vel))
        axs[1].axhline(0.02, ls="--", c="k", lw=0.8)
        axs[1].set(xlabel="track age (frames)", ylabel="RMS velocity deviation (px/s)", yscale="log")
        axs[1].legend(["vx", "vy", "paper bound 0.02"])
        fig.tight_layout()
        fig.savefig(d / f"he2021a_fig{fig_no}_filter_{name}.png", dpi=110)
        plt.close(fig)
    if data["smear"]:
        w = sorted(data["smear"])
        fig, ax = plt.subplots(figsize=(5, 4))
        ax.plot(w, [data["smear"][k][0] for k in w], "o-", label="before")
        ax.plot(w, [data["smear"][k][1] for k in w], "s-", label="after eqs 12-16")
        ax.axhline(0.06, ls="--", c="k", lw=0.8, label="paper after < 0.06")
        ax.set(xlabel="rate about x (deg/s)", ylabel="RMS centroid error (px)", title="Fig 10: smear centroid")
        ax.legend()
        fig.tight_layout()
        fig.savefig(d / "he2021a_fig10_smear.png", dpi=110)
        plt.close(fig)
    if data["pair"]:
        fig, axs = plt.subplots(1, 2, figsize=(10, 4), sharey=True)
        for axis in (0, 1):
            for r in cfg["r_values"]:
                w = [k[2] for k in data["pair"] if k[0] == axis and k[1] == r]
                vals = np.array([data["pair"][(axis, r, x)] for x in w], dtype=float)
                axs[axis].plot(w, vals[:, 1], "o-", label=f"before (syst.), R={r:g}")
                axs[axis].plot(w, vals[:, 2], "s-", label=f"after (per frame), R={r:g}")
                axs[axis].plot(w, vals[:, 3], "^-", label=f"after (syst.), R={r:g}")
            axs[axis].axhline(0.1, ls="--", c="k", lw=0.8)
            axs[axis].set(xlabel=f"rate about {'xy'[axis]} (deg/s)", ylabel="pair distance error RMS (px)", yscale="log",
                          title="Fig 12: star-pair distance")
            axs[axis].legend(fontsize=7)
        fig.tight_layout()
        fig.savefig(d / "he2021a_fig12_pairs.png", dpi=110)
        plt.close(fig)
    for axis, fig_no in ((0, 14), (1, 15)):
        w = sorted(k[1] for k in data["att"] if k[0] == axis)
        if not w:
            continue
        b = np.array([data["att"][(axis, x)][0] for x in w])
        a = np.array([data["att"][(axis, x)][1] for x in w])
        fig, ax = plt.subplots(figsize=(6, 4))
        for i, lab in enumerate("xyz"):
            ax.plot(w, b[:, i], "o--", label=f"{lab} before")
            ax.plot(w, a[:, i], "s-", label=f"{lab} after")
        ax.axhline(10, ls=":", c="k", lw=0.8)
        ax.set(xlabel=f"rate about {'xy'[axis]} (deg/s)", ylabel="RMS attitude error (arcsec)",
               title=f"Fig {fig_no}: QUEST, 5 stars")
        ax.legend(fontsize=7)
        fig.tight_layout()
        fig.savefig(d / f"he2021a_fig{fig_no}_attitude_{'xy'[axis]}.png", dpi=110)
        plt.close(fig)
