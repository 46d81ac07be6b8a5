"""Drift found without a board (fusion.drift, fusion.drift_align).

Ground truth: the simulated inspection room rendered with a rig in which one sensor is
turned (``T_rig_s @ R(delta)``, the sensor's own frame) and checked against the unmoved
rig. On the simulator a single instant's pair measurement is within about 0.05 degrees of the
truth (0.1 about the optical axis); six instants over the pan give each camera's rotation
within 0.03 degrees (measured: 0.016 degrees about the thermal imager's axis), hence the
tolerances below: the issue's own 0.1 degrees for the refined rig, 0.05 for the rest.
"""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import pytest

from tests.drift_support import TIMES_S, render, run, turned
from trifuse.app.sources.sim.head import default_rig
from trifuse.calib.rig import Rig
from trifuse.calib.transforms import rotation_angle_deg
from trifuse.fusion.drift import (
    DRIFT_DEG,
    PAIR_FLOOR_DEG,
    DriftReport,
    PairEstimate,
    RefineRefused,
    SensorCheck,
    camera_pairs,
    combine,
    groups,
    refined_rig,
    solve_sensors,
    synchronous,
    verdict,
)
from trifuse.fusion.drift_align import PairProbe, PairRotation, work_image
from trifuse.fusion.mapping import TofGrid


@pytest.fixture(scope="module")
def rig() -> Rig:
    return default_rig()


@pytest.fixture(scope="module")
def true_frames(rig: Rig) -> list[tuple[float, dict]]:
    return render(rig, TIMES_S)


@pytest.fixture(scope="module")
def rolled_frames(rig: Rig) -> list[tuple[float, dict]]:
    """thermal_left turned 0.3 degrees about its optical axis (the hardest axis: a roll
    moves the picture's centre not at all)."""
    return render(turned(rig, "thermal_left", (0.0, 0.0, 0.3)), TIMES_S)


# -- one pair, one instant ------------------------------------------------------------------


def test_a_pair_measures_its_work_cameras_turn_in_the_rig_frame(rig: Rig) -> None:
    """thermal_left turned 0.3 degrees about its y axis, against ccd_left: theta (rig frame)
    is R_rig_thermal (0, 0.3, 0) within 0.05 degrees about x and y, 0.12 about the optical
    axis (one instant); with the true rig, 0 within the same."""
    grid = TofGrid(rig)
    probe = PairProbe(rig, "thermal_left", "ccd_left", grid)
    R = rig["thermal_left"].T_rig_sensor[:3, :3]
    for moved, expected in ((rig, np.zeros(3)), (turned(rig, "thermal_left", (0, 0.3, 0)), None)):
        ((_, fs),) = render(moved, (6.0,))
        points = grid.points(fs["tof"].distance_m, 0.05)
        r = probe.measure(
            work_image(rig["thermal_left"], fs["thermal_left"].image),
            work_image(rig["ccd_left"], fs["ccd_left"].image),
            points,
        )
        assert isinstance(r, PairRotation), r
        want = np.radians([0, 0.3, 0]) if expected is None else expected
        err = np.degrees(R.T @ r.theta - want)  # about the thermal imager's own axes
        assert np.abs(err[:2]).max() < 0.05 and abs(err[2]) < 0.12, err
        assert r.patches >= 20


# -- the check over several instants -------------------------------------------------------


def test_the_true_rig_is_ok_everywhere(rig: Rig, true_frames: list) -> None:
    report = run(rig, true_frames)
    assert report.instants == len(TIMES_S)
    for name in ("tof", "ccd_left", "ccd_right", "thermal_left", "thermal_right"):
        s = report.sensors[name]
        assert s.verdict == "ok", (name, s)
        assert s.angle_deg < 0.05, (name, s)
    assert not report.drifted


def test_a_rolled_thermal_imager_is_drifted_and_refined_within_a_tenth_of_a_degree(
    rig: Rig, rolled_frames: list
) -> None:
    report = run(rig, rolled_frames)
    assert report.drifted == ["thermal_left"], report.as_dict()
    s = report.sensors["thermal_left"]
    assert np.linalg.norm(np.subtract(s.rotation_deg, (0, 0, 0.3))) < 0.1, s
    assert set(s.pairs) == {"ccd_left", "thermal_right"}
    for name in ("tof", "ccd_left", "ccd_right", "thermal_right"):
        assert report.sensors[name].verdict == "ok", report.sensors[name]
    refined = refined_rig(rig, report)
    truth = turned(rig, "thermal_left", (0.0, 0.0, 0.3))
    R_err = (
        refined["thermal_left"].T_rig_sensor[:3, :3].T @ truth["thermal_left"].T_rig_sensor[:3, :3]
    )
    assert rotation_angle_deg(R_err) < 0.1
    np.testing.assert_allclose(
        refined["thermal_left"].T_rig_sensor[:3, 3], rig["thermal_left"].T_rig_sensor[:3, 3]
    )
    for name in ("tof", "ccd_left", "ccd_right", "thermal_right"):
        np.testing.assert_array_equal(refined[name].T_rig_sensor, rig[name].T_rig_sensor)
    # checked again with the refined rig, the same pictures agree
    again = run(refined, rolled_frames)
    assert not again.drifted and again.sensors["thermal_left"].verdict == "ok", again.as_dict()


def test_without_tof_depth_or_a_camera_every_sensor_is_undecided_with_the_reason(
    rig: Rig, true_frames: list
) -> None:
    no_tof = [(t, {n: f for n, f in fs.items() if n != "tof"}) for t, fs in true_frames]
    report = run(rig, no_tof)
    for name in ("ccd_left", "thermal_left"):
        s = report.sensors[name]
        assert s.verdict == "undecided" and "no TOF depth (tof)" in s.reason, s
    # without the colour cameras the two thermal imagers are compared only with each other:
    # which one moved cannot be told
    thermal_only = [
        (t, {n: f for n, f in fs.items() if not n.startswith("ccd")}) for t, fs in true_frames
    ]
    report = run(rig, thermal_only)
    for name in ("thermal_left", "thermal_right"):
        s = report.sensors[name]
        assert s.verdict == "undecided" and "which of the two moved" in s.reason, s
    assert "no frame of ccd_left" in " ".join(report.problems)
    assert report.sensors["ccd_left"].verdict == "undecided"


# -- pure parts ------------------------------------------------------------------------------


def test_the_pairs_form_a_ring_of_the_cameras(rig: Rig) -> None:
    assert camera_pairs(rig) == [
        ("thermal_left", "ccd_left"),
        ("thermal_right", "ccd_right"),
        ("ccd_left", "ccd_right"),
        ("thermal_left", "thermal_right"),
    ]


def _estimate(work: str, other: str, theta_deg, sigma_deg: float = 0.01, n: int = 10):
    return PairEstimate(
        work, other, np.radians(theta_deg), np.eye(3) * np.radians(sigma_deg) ** 2, n
    )


def test_the_solve_puts_the_turn_on_the_sensor_the_others_agree_without() -> None:
    """Ring a-b-c-d; c turned by (0.2, 0, 0) rig frame: the pairs with c read +-0.2, the
    rest 0. Whichever sensor the least squares starts from, the geometric median leaves
    a, b, d at 0."""
    d = (0.2, 0.0, 0.0)
    est = [
        _estimate("a", "b", (0, 0, 0)),
        _estimate("c", "b", d),
        _estimate("c", "d", d),
        _estimate("a", "d", (0, 0, 0)),
    ]
    rot, cov = solve_sensors(est)
    np.testing.assert_allclose(np.degrees(rot["c"]), d, atol=1e-6)
    for n in "abd":
        np.testing.assert_allclose(np.degrees(rot[n]), 0.0, atol=1e-6)
    # a sensor's covariance: its two pairs' information held together
    np.testing.assert_allclose(np.degrees(np.sqrt(np.diag(cov["c"]))), 0.01 / np.sqrt(2))


def test_verdicts() -> None:
    cov = np.eye(3) * np.radians(0.01) ** 2
    turn = np.radians([0.3, 0.0, 0.0])
    assert verdict(turn, cov, 2, 4)[0] == "drifted"
    assert verdict(np.radians([0.05, 0, 0]), cov, 2, 4)[0] == "ok"
    # above the threshold but not by 4 sigma: undecided, never a guess
    assert verdict(np.radians([0.2, 0, 0]), cov * 100, 2, 4)[0] == "undecided"
    # small but poorly known: undecided
    v, why = verdict(np.radians([0.01, 0, 0]), cov * 64, 2, 4)
    assert v == "undecided" and "not enough structure" in why
    # compared with one other sensor only: which one moved is not known
    v, why = verdict(turn, cov, 1, 2)
    assert v == "undecided" and "which of the two moved" in why
    assert DRIFT_DEG == 0.15


def test_combine_down_weights_a_measurement_far_from_the_rest() -> None:
    rng = np.random.default_rng(7)
    truth = np.radians([0.1, -0.05, 0.02])
    sigma = np.radians(0.02)
    ms = [
        PairRotation("a", "b", truth + rng.normal(0, sigma, 3), np.eye(3) * sigma**2, 30, 1.0)
        for _ in range(20)
    ]
    ms.append(
        PairRotation("a", "b", truth + np.radians([1.0, 0, 0]), np.eye(3) * sigma**2, 30, 1.0)
    )
    e = combine(ms)
    assert e is not None and e.count == 21
    # 20 draws of 0.02 degrees: the mean within 3 sigma / sqrt(20) = 0.013 degrees plus the
    # outlier's Huber-limited pull (at most 2 sqrt(3) sigma / 21 = 0.003)
    assert np.degrees(np.abs(e.theta - truth)).max() < 0.016
    # its sigma: the floor's 0.02, the draws' 0.02 / sqrt(20) = 0.0045, and along x the
    # outlier's Huber-weighted residual in the scatter (weight 2 sqrt(3) 0.02 / 1 = 0.07,
    # 0.07 * 1^2 / 20 / 21: 0.013); together at most 0.025
    sig = np.degrees(np.sqrt(np.diag(e.cov)))
    assert (sig >= PAIR_FLOOR_DEG).all() and sig.max() < 0.026, sig
    assert sig[1:].max() < 0.021, sig


def _differing_instants(rng: np.random.Generator) -> tuple[list[PairRotation], np.ndarray]:
    """12 instants whose true rotations differ by 0.4 degrees (1-sigma, about 0.45 degrees
    about z), measured as the real czha626 pair's are (tests/fusion/test_drift_real_capture.py):
    0.009-0.05 degrees about x and y, 7 times that about the optical axis z, z correlated
    with x by -0.8 to 0.6. Returns the measurements and the instants' mean truth."""
    ms, truths = [], []
    for _ in range(12):
        truth = np.radians([0.0, 0.0, 0.45]) + rng.normal(0, np.radians(0.4), 3)
        sx = np.radians(rng.uniform(0.009, 0.05))
        sd = np.array([sx, sx, 7 * sx])
        rho = rng.uniform(-0.8, 0.6)
        cov = np.outer(sd, sd) * np.array([[1, 0, rho], [0, 1, 0], [rho, 0, 1]])
        ms.append(PairRotation("a", "b", rng.multivariate_normal(truth, cov), cov, 30, 1.0))
        truths.append(truth)
    return ms, np.mean(truths, axis=0)


def test_combine_of_instants_that_really_differ_is_their_mean_with_their_spread() -> None:
    """Over 30 sets of differing instants (:func:`_differing_instants`) the combined rotation
    is the instants' mean within 0.35 (x, y) and 1.0 (z) of the spread over the count
    (0.4 / sqrt(12) degrees) RMS: measured 0.10-0.16 and 0.45-0.63 over three seeds, where
    weighting by the measurements' own covariances alone gave 0.67-0.94 and 2.3-2.7 (their
    x residuals, 20 of their sigmas, moved z through the correlations; 0.5 degrees off on the
    real pair). And its uncertainty is that spread over the count, not the measurements'."""
    rng = np.random.default_rng(11)
    errors = []
    for trial in range(30):
        ms, mean = _differing_instants(rng)
        e = combine(ms)
        assert e is not None
        errors.append(e.theta - mean)
        if trial == 0:
            sig = np.sqrt(np.diag(e.cov))
            scatter = np.std([m.theta for m in ms], axis=0, ddof=1) / np.sqrt(len(ms))
            assert (sig > 0.6 * scatter).all() and (sig < 1.5 * scatter).all(), (sig, scatter)
    unit = np.radians(0.4) / np.sqrt(12)
    rms = np.sqrt(np.mean(np.square(errors), axis=0)) / unit
    assert (rms < [0.35, 0.35, 1.0]).all(), rms


def test_refine_refuses_more_than_two_degrees_and_needs_a_drifted_sensor(rig: Rig) -> None:
    ok = SensorCheck("ok", (0.0, 0.0, 0.0), (0.01,) * 3, "")
    big = SensorCheck("drifted", (0.0, 2.5, 0.0), (0.01,) * 3, "")
    with pytest.raises(ValueError, match="no sensor is drifted"):
        refined_rig(rig, DriftReport({"thermal_left": ok}, (), 5))
    with pytest.raises(RefineRefused, match=r"2\.50°, more than 2°.*recalibrate"):
        refined_rig(rig, DriftReport({"thermal_left": big}, (), 5))


def test_refine_keeps_the_reference_sensor_as_the_rig_frame(rig: Rig) -> None:
    """A drifted reference sensor: every other sensor is re-expressed so that the reference
    stays the identity and the sensors' relative poses are the corrected ones."""
    ref = rig.reference
    s = SensorCheck("drifted", (0.0, 0.5, 0.0), (0.01,) * 3, "")
    refined = refined_rig(rig, DriftReport({ref: s}, (), 5))
    np.testing.assert_allclose(refined[ref].T_rig_sensor, np.eye(4), atol=1e-12)
    truth = turned(rig, ref, (0.0, 0.5, 0.0))
    for n in rig.names:
        np.testing.assert_allclose(refined.T(n, ref), truth.T(n, ref), atol=1e-12)


def test_only_synchronous_frames_are_measured() -> None:
    f = lambda ns: SimpleNamespace(stamp_ns=ns)  # noqa: E731
    assert synchronous({"a": f(0), "b": f(12_000_000)})
    assert not synchronous({"a": f(0), "b": f(12_000_001)})
    assert synchronous({"a": f(5)})


def test_two_separate_groups_are_solved_each_in_its_own_gauge() -> None:
    """The colour pair and the thermal pair measured, neither eye: two groups of two
    sensors, each solved apart (no singular system); neither can tell which one moved."""
    est = [_estimate("ccd_left", "ccd_right", (0.2, 0, 0)), _estimate("tl", "tr", (0, 0.1, 0))]
    rot, _ = solve_sensors(est)
    np.testing.assert_allclose(np.degrees(rot["ccd_left"] - rot["ccd_right"]), (0.2, 0, 0))
    np.testing.assert_allclose(np.degrees(rot["tl"] - rot["tr"]), (0, 0.1, 0))
    assert groups(est) == [["ccd_left", "ccd_right"], ["tl", "tr"]]
