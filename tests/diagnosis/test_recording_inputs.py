"""``rollingstar diagnose`` on what a recording carries besides its stars.

- A ``frame`` field that repeats (a frame counter that wraps, as the log format allows: frames are
  ordered by time): every frame must still be diagnosed, each with its own attitude, in time
  order, the same stars and the same fit as with distinct numbers.
- A reference attitude (``/truth/attitude``): the report says how to use it when no accuracy was
  given for it.
"""
from __future__ import annotations

import numpy as np

from rollingstar.pipelines.diagnose import DiagnoseOptions, diagnose_recording
from tests.reliability.helpers import rewrite

WRAP = 4  # the counter: 0, 1, 2, 3, 0, 1, ...


def _wrapped(src, dst) -> None:
    """A copy of the recording ``src`` with every frame number taken modulo ``WRAP``."""
    def edit(messages):
        return [type(m)(m.topic, m.log_time_ns, m.schema_name, {**m.data, "frame": int(m.data["frame"]) % WRAP})
                if isinstance(m.data, dict) and "frame" in m.data else m for m in messages]

    rewrite(src, dst, edit)


def test_a_wrapping_frame_counter_diagnoses_every_frame_as_distinct_numbers_do(tmp_path, small_recording):
    wrapped = tmp_path / "wrapped.mcap"
    _wrapped(small_recording, wrapped)
    options = DiagnoseOptions(seed=0, n_boot=10, resimulate=False)
    plain, d_plain = diagnose_recording(small_recording, options=options)
    wrap, d_wrap = diagnose_recording(wrapped, options=options)
    assert wrap["split"]["frames"] == plain["split"]["frames"] == 20
    o1, o2 = d_plain.location.data.obs, d_wrap.location.data.obs
    np.testing.assert_array_equal(o2.t0_ns, o1.t0_ns)  # in time order, none lost
    np.testing.assert_array_equal(o2.frame_index, o1.frame_index % WRAP)  # reported by the recording's numbers
    np.testing.assert_allclose(d_wrap.location.nuisance.attitude.as_quat(), d_plain.location.nuisance.attitude.as_quat(),
                               atol=1e-12)
    assert [e["name"] for e in wrap["effects"]] == [e["name"] for e in plain["effects"]]


def test_a_recording_with_a_reference_attitude_says_how_to_use_it(small_recording):
    """Effects the attitude absorbs are untestable from the stars alone; when the recording carries
    /truth/attitude and no accuracy was given for it, the report says how to test them against it,
    and with the accuracy it tests them instead of saying so."""
    options = DiagnoseOptions(seed=0, n_boot=10, resimulate=False)
    res, _ = diagnose_recording(small_recording, options=options)
    absorbed = [a["name"] for a in res["absorbed_by_attitude"]]
    assert absorbed and "--reference-attitude-arcsec" in res["reference_available"]
    assert all(name in res["reference_available"] for name in absorbed)
    assert res["reference_available"] in res["summary"]
    with_ref, _ = diagnose_recording(small_recording, options=DiagnoseOptions(seed=0, n_boot=10, resimulate=False,
                                                                                reference_sigma_arcsec=1.0))
    assert with_ref["reference_available"] is None and with_ref["attitude_reference"] is not None


def test_a_free_reference_mount_without_a_reference_is_refused(small_recording):
    """``--reference-mount-free`` fits the misalignment of a reference: without the reference's
    accuracy there is none to fit, and the run says so (exit 2 from the CLI) instead of ignoring it."""
    from typer.testing import CliRunner

    from rollingstar.cli import app

    res = CliRunner().invoke(app, ["diagnose", "--recording", str(small_recording), "--reference-mount-free", "--json",
                                   "-q"])
    assert res.exit_code == 2 and "--reference-attitude-arcsec" in res.output, res.output
    assert "Traceback" not in res.output


def test_no_verdict_is_given_on_residuals_that_are_not_numbers():
    from pathlib import Path

    import pytest

    from rollingstar.errors import UserError
    from rollingstar.pipelines.diagnose import _refuse_non_finite

    finite = {"train_rms_before_px": 0.1, "train_rms_after_px": 0.1, "heldout_rms_before_px": 0.2,
              "heldout_rms_after_px": None}
    _refuse_non_finite(finite, Path("r.mcap"))  # None (no held-out data) is no number to refuse
    with pytest.raises(UserError, match=r"r.mcap: the model given cannot place .*heldout_rms_before_px = nan"):
        _refuse_non_finite({**finite, "heldout_rms_before_px": float("nan")}, Path("r.mcap"))
