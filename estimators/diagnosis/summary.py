"""The paragraph a diagnosis report leads with: what differs, how big, how sure, what improved on
held-out data, what the data cannot tell apart, what is left, and what this recording cannot test.

Built from the report's JSON object (:func:`.algorithm.as_json`) alone, so that the console, the
HTML report and a user reading ``result.json`` see the same words.
"""
from __future__ import annotations


def paragraph(result: dict) -> str:
    """One paragraph summarising ``result`` (a :func:`.algorithm.as_json` object)."""
    parts = [_noise_estimated(result), _what_differs(result), _heldout(result), _overstated(result), *_ambiguous(result), _unexplained(result), _isolated(result),
             _reference(result), _untestable(result), result.get("reference_available") or ""]
    return " ".join(p for p in parts if p)


def _noise_estimated(r: dict) -> str:
    if not r["noise"]["source"].startswith("estimated"):
        return ""
    return (f"The recording states no centroid noise: {r['noise']['sigma_px_median']:.3g} px was estimated from the "
            "residual scatter (MAD), so every chi-square and BIC below is measured against that estimate, not a "
            "stated noise.")


def _overstated(r: dict) -> str:
    o = r.get("noise_overstated")
    if not o:
        return ""
    return (f"The stated noise is larger than this recording's residuals: the final model leaves chi2 {o['chi2']:.3g} "
            f"over {o['dof']} dof on every star it kept (p = {o['p']:.2g}), as if the noise were {o['factor']:.2f} x the "
            "stated, so the tests here are less sensitive than the right noise would make them.")


def _what_differs(r: dict) -> str:
    if not r["mismatch"]:
        return "No mismatch: the simulation explains this recording within its noise."
    found = []
    proj = r.get("projection")
    if proj and proj["named"] != proj["declared"]:
        found.append(f"the lens projection is {proj['named']}, not the declared {proj['declared']}")
    elif proj and proj.get("refocused"):
        focal = proj["candidates"][proj["named"]]["focal_px"]
        found.append(f"the focal length is {focal:.1f} px, not the declared {proj['declared_focal_px']:.1f} px")
    noise = r.get("noise_check")
    if noise and noise.get("applied"):
        found.append(f"the centroid noise is {noise['factor']:.2f} +- {noise['factor_sigma']:.2f} x the stated "
                     f"(white: not library physics)")
    found += [_effect(e) for e in r["effects"]]
    desc = r["unexplained_systematic"].get("description")
    if desc and desc.get("correction"):
        found.append(f"outside the library, {desc['text']} (written to the updated scenario as an empirical correction)")
    ref = r.get("attitude_reference") or {}
    chosen = {m["name"] for m in ref.get("model", [])}
    for c in ref.get("model", []):
        alt = [a["candidates"][1] for a in ref.get("ambiguous", [])
               if a["candidates"][0] == c["name"] and a["candidates"][1] not in chosen]
        found.append(f"{c['name']}" + (f" (or {' or '.join(alt)}, which the reference cannot tell from it)" if alt else "")
                     + f", which the stars alone do not show, seen against the reference attitude ({_values(c['params'])}; "
                     "written to the updated scenario)")
    if not found:
        return "The simulation misses this recording, and no library effect explains it."
    return "What differs: " + "; ".join(found) + "."


def _effect(e: dict) -> str:
    values = []
    for name, p in e["params"].items():
        sig = p["sigma"]
        z = abs(p["value"]) / sig if sig and sig > 0 else None
        values.append(f"{name} = {p['value']:.4g} +- {sig:.2g}" + (f" {p['unit']}" if p["unit"] not in ("", "1") else "") + (f" ({z:.0f} sigma)" if z is not None and z >= 1 else ""))
    sure = e["confidence"] + (f", because: {', '.join(e['tentative_because'])}" if e.get("tentative_because") else "")
    return f"{e['name']} ({', '.join(values)}; {sure})"


def _heldout(r: dict) -> str:
    before, after = r.get("heldout_rms_before_px"), r.get("heldout_rms_after_px")
    if before is None or after is None:
        return "No held-out data to check the fit on."
    split = r["split"]
    noise = r["noise"]["sigma_px_median"]
    where = (f"{split['heldout_frames']} frames the fit never saw" if split["unit"] == "frames"
             else "stars of each frame the fit never saw")
    text = (f"On the {split['heldout_observations']} held-out stars ({where}), "
            f"RMS per axis {before:.3g} -> {after:.3g} px against a noise of {noise:.3g} px")
    cb, ca = r.get("heldout_chi2_dof_before"), r.get("heldout_chi2_dof_after")
    if cb is not None and ca is not None:
        text += f", chi2/dof {cb:.3g} -> {ca:.3g}"
    if r.get("rejected_on_heldout"):
        text += f" (no held-out improvement: {', '.join(r['rejected_on_heldout'])} not named)"
    return text + "."


MAX_PAIRS = 3  # ambiguous pairs spelled out in the paragraph (the report lists them all)


def _ambiguous(r: dict) -> list[str]:
    named = {e["name"] for e in r["effects"]}
    pairs = sorted(r["ambiguous"], key=lambda a: abs(a["delta_bic_swap"]))
    out = []
    for a in pairs[:MAX_PAIRS]:
        first, second = a["candidates"]
        swap = a["delta_bic_swap"]
        if {first, second} <= named:
            how = "both are named and trade off against each other"
        elif swap >= 0:
            how = f"swapping them costs {swap:.3g} BIC"
        else:
            how = f"the linearised fit prefers the other by {-swap:.3g} BIC"
        out.append(f"Cannot tell {first} from {second} here ({how}); to separate them: {a['separating_experiment']}.")
    if len(pairs) > MAX_PAIRS:
        out.append(f"{len(pairs) - MAX_PAIRS} more pairs cannot be told apart (listed in the report).")
    return out


def _unexplained(r: dict) -> str:
    u = r["unexplained_systematic"]
    if not u["present"]:
        return ""
    desc = u.get("description")
    if desc and desc.get("correction"):  # described and corrected (in what differs); anything still left
        left = u.get("left_after_correction") or []
        return ("Still left after the correction: " + ", ".join(f"{e['basis']} (z = {e['z']:.1f})" for e in left) + ".") if left else ""
    if desc:
        return f"Left unexplained (outside the library): {desc['text']}."
    return "Left unexplained (outside the library): " + ", ".join(f"{e['basis']} (z = {e['z']:.1f})" for e in u["evidence"]) + "."


def _isolated(r: dict) -> str:
    stars = r.get("isolated_misfits") or []
    if not stars:
        return ""
    where = "; ".join(f"frame {s['frame']}, catalogue {s['catalog_id']} at ({s['x']:.0f}, {s['y']:.0f}), "
                      f"{s['sigmas']:.0f} sigma" for s in stars)
    return (f"{len(stars)} star{'s' if len(stars) > 1 else ''} alone off the model ({where}): a local defect "
            f"(a detector edge, a blend, a hot pixel), not a systematic; left out of the held-out test.")


def _reference(r: dict) -> str:
    ref = r.get("attitude_reference")
    if not ref:
        return ""
    tested = [c for c in ref["candidates"] if c["tested"]]
    head = (f"Against the recording's reference attitude ({ref['sigma_arcsec']:g} arcsec per axis, {ref['frames']} frames, "
            f"chi2 {ref['chi2']:.3g} over {ref['dof']} dof " + ("with only its misalignment fitted)" if ref.get("mount")
                                                                 else "without an effect)"))
    mount = ref.get("mount")
    tail = (" The reference's misalignment, fitted: " + ", ".join(
        f"{v:.3g} +- {sg:.2g}" for v, sg in zip(mount["rotation_arcsec"], mount["sigma_arcsec"]))
        + " arcsec about the camera's x, y, z.") if mount else ""
    if not tested:
        return head + ", no effect the attitude absorbs is seen." + tail
    found = "; ".join(f"{c['name']} ({_values(c['params'])}, delta BIC {c['delta_bic']:.3g})" for c in tested)
    names = [c["name"] for c in ref["model"]]
    joint = (f"Fitted together, {', '.join(names[:-1])} and {names[-1]} leave" if len(names) > 1
             else f"{names[0]} leaves")
    amb = "".join(f" It cannot tell {a['candidates'][0]} from {a['candidates'][1]} ("
                  + (f"swap delta BIC {a['delta_bic_swap']:.3g}; " if a["delta_bic_swap"] is not None else "")
                  + f"separate them with: {a['separating_experiment']})." for a in ref.get("ambiguous", []))
    return f"{head}: each alone, {found}. {joint} chi2 {ref['chi2_after']:.3g} over {ref['dof_after']} dof.{amb}{tail}"


def _values(params: dict) -> str:
    return ", ".join(f"{k} = {p['value']:.4g} +- {p['sigma']:.2g}" + (f" {p['unit']}" if p["unit"] not in ("", "1") else "")
                     for k, p in params.items())


def _untestable(r: dict) -> str:
    ref = r.get("attitude_reference") or {}
    tested = {c["name"] for c in ref.get("candidates", []) if c["tested"]}
    mounted = {c["name"] for c in ref.get("candidates", []) if not c["determined"] or c["like_the_mount"]} \
        if ref.get("mount") else set()
    rows = [f"{a['name']} (" + ("a constant rotation, which the reference's fitted misalignment takes up; separate "
                                "them with a reference aligned with the camera" if a["name"] in mounted
                                else a["separating_experiment"]) + ")"
            for a in r.get("absorbed_by_attitude", []) if a["name"] not in tested]
    rows += [f"{a['name']} ({a['reason']})" for a in r.get("not_testable", [])]
    if not rows:
        return ""
    return "Not testable in this recording: " + "; ".join(rows) + "."
