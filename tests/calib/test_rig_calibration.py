"""The joint rig calibration on synthetic corners: exact projections plus seeded noise."""

from __future__ import annotations

import numpy as np
import pytest
from scipy import sparse
from scipy.optimize import least_squares
from threadpoolctl import threadpool_info

from tests.board_support import NOISE, RIG, SPECS, scenario_corners
from trifuse.app.sources.sim.scenarios import CALIBRATION_BOARD, calibration_poses
from trifuse.calib import polarity
from trifuse.calib.errors import CalibrationError
from trifuse.calib.rig_calibration import CalibrationOptions, _flag_outliers, calibrate_rig
from trifuse.calib.rig_problem import CornerProblem
from trifuse.calib.rig_uncertainty import parameter_sigma
from trifuse.calib.schur_lm import least_squares_schur
from trifuse.calib.transforms import make_T, rotation_from_rvec, rvec_from_rotation

# Per-axis corner noise (px) of each modality, about what the detectors achieve.


def _param_errors(name: str, result, reference: str = "tof"):
    """Errors of T_ref_sensor's rotation vector (deg) and translation (m), per component."""
    T_true = RIG.T(reference, name)
    T_est = result.sensors[name].T_rig_sensor
    rot = np.degrees(rvec_from_rotation(T_est[:3, :3]) - rvec_from_rotation(T_true[:3, :3]))
    return rot, T_est[:3, 3] - T_true[:3, 3]


@pytest.fixture(scope="module")
def full():
    return calibrate_rig(scenario_corners(), CALIBRATION_BOARD, SPECS)


def test_recovers_every_sensor_within_three_sigma(full) -> None:
    assert full.reference == "tof"
    assert not full.outliers
    for name in RIG.names:
        s, truth = full.sensors[name], RIG[name].intrinsics
        for k in ("fx", "fy", "cx", "cy"):
            err = getattr(s.intrinsics, k) - getattr(truth, k)
            assert abs(err) < 3 * s.sigma[k] + 1e-9, (name, k, err, s.sigma[k])
        if name == "tof":
            continue
        rot, trans = _param_errors(name, full)
        assert np.all(np.abs(rot) < 3 * np.array(s.sigma["rotation_deg"])), (name, rot)
        assert np.all(np.abs(trans) < 3 * np.array(s.sigma["translation_m"])), (name, trans)
        # And the issue's absolute targets (the noise here is the detectors' level).
        assert np.linalg.norm(rot) < 0.1 and np.linalg.norm(trans) < 0.001


def test_rms_matches_the_injected_noise(full) -> None:
    # RMS of 2-D errors = sqrt(2) * per-axis sigma, less the fitted degrees of freedom.
    for name, s in full.sensors.items():
        expected = np.sqrt(2) * NOISE[s.modality]
        assert s.rms_px == pytest.approx(expected, rel=0.1), name


def test_report_shape(full) -> None:
    report = full.to_report()
    for name in RIG.names:
        entry = report["sensors"][name]
        assert set(entry["intrinsics"]) == {"fx", "fy", "cx", "cy"}
        assert np.asarray(entry["T_rig_sensor"]).shape == (4, 4)
        assert {"fx", "fy", "cx", "cy", "rotation_deg", "translation_m"} <= set(entry["sigma"])
    some_view = next(iter(report["views"]))
    assert {"rms_px", "outlier"} <= set(next(iter(report["views"][some_view].values())))
    rig = full.rig()
    assert rig.reference == "tof" and rig["ccd_left"].uncertainty["fx"] > 0
    verdict = report["verdict"]
    assert report["min_views"] == 3 and set(verdict["sensors"]) == set(RIG.names)
    assert {"grade", "line", "figures", "advice", "more_views"} <= set(verdict["sensors"]["tof"])
    figure = verdict["sensors"]["ccd_left"]["figures"][2]
    assert figure["what"] == "rotation to tof" and figure["unit"] == "°"
    assert figure["target"] == pytest.approx(0.1) and len(figure["axes"]) == 3


def test_thirty_views_are_judged_good(full) -> None:
    """30 views meet the accuracy targets (test above); the verdicts, from the
    calibration's own sigmas, agree: every sensor good, nothing to capture."""
    for name, v in full.verdict.sensors.items():
        assert v.grade == "good" and v.more_views == 0 and v.advice is None, (name, v.line)
        assert all(f.sigma <= f.target for f in v.judged)


@pytest.mark.parametrize(
    ("sensors", "reference"),
    [(["ccd_left", "ccd_right"], "ccd_left"), (["ccd_right", "thermal_right"], None)],
)
def test_subsets_of_sensors(sensors: list[str], reference: str | None) -> None:
    obs = scenario_corners(sensors=sensors, seed=3)
    result = calibrate_rig(obs, CALIBRATION_BOARD, SPECS, CalibrationOptions(reference=reference))
    ref = reference or sorted(sensors)[0]  # no TOF: the first sensor by name
    assert result.reference == ref and sorted(result.sensors) == sorted(sensors)
    other = next(s for s in sensors if s != ref)
    T_est = result.sensors[other].T_rig_sensor
    rot, trans = _param_errors(other, result, reference=ref)
    sig = result.sensors[other].sigma
    assert np.all(np.abs(rot) < 3 * np.array(sig["rotation_deg"]))
    assert np.all(np.abs(trans) < 3 * np.array(sig["translation_m"]))
    assert np.allclose(result.sensors[ref].T_rig_sensor, np.eye(4))
    assert T_est.shape == (4, 4)


def test_outlier_view_and_corners_are_flagged_and_left_out() -> None:
    obs = scenario_corners(seed=5)
    rng = np.random.default_rng(11)
    obs["0007"]["thermal_left"] = obs["0007"]["thermal_left"] + rng.normal(0, 1.5, (54, 2))
    obs["0012"]["ccd_right"][20] += (4.0, -3.0)  # one mis-detected corner
    result = calibrate_rig(obs, CALIBRATION_BOARD, SPECS)
    view_out = {(o.view, o.sensor) for o in result.outliers if o.corner is None}
    corner_out = {(o.view, o.sensor, o.corner) for o in result.outliers if o.corner is not None}
    assert ("0007", "thermal_left") in view_out
    assert result.views["0007"]["thermal_left"].outlier
    assert "corners are beyond 5 sigma" in result.views["0007"]["thermal_left"].reason
    assert ("0012", "ccd_right", 20) in corner_out
    assert len(view_out) == 1 and len(corner_out) <= 2
    rot, trans = _param_errors("thermal_left", result)
    assert np.linalg.norm(rot) < 0.1 and np.linalg.norm(trans) < 0.001
    assert result.sensors["thermal_left"].worst_view == "0007"


def test_bad_input_gives_clear_errors() -> None:
    with pytest.raises(CalibrationError, match="not detected in any image"):
        calibrate_rig({}, CALIBRATION_BOARD, SPECS)
    one = {"0001": scenario_corners(views=1)["0001"]}
    with pytest.raises(CalibrationError, match=r"reference sensor 'tof': .*1 view"):
        calibrate_rig(one, CALIBRATION_BOARD, SPECS)
    obs = scenario_corners(views=6)
    with pytest.raises(CalibrationError, match="unknown sensor 'lidar'"):
        calibrate_rig(obs, CALIBRATION_BOARD, SPECS, CalibrationOptions(reference="lidar"))
    obs["0001"]["tof"] = obs["0001"]["tof"][:10]
    with pytest.raises(CalibrationError, match=r"expected corners of shape \(54, 2\)"):
        calibrate_rig(obs, CALIBRATION_BOARD, SPECS)


def test_sensor_with_too_few_views_is_left_out_and_said() -> None:
    obs = scenario_corners(views=12, seed=2)
    seen = [v for v in obs if "thermal_right" in obs[v]]
    for v in seen[2:]:
        del obs[v]["thermal_right"]
    result = calibrate_rig(obs, CALIBRATION_BOARD, SPECS)
    assert "thermal_right" not in result.sensors
    assert "2 view(s)" in result.excluded_sensors["thermal_right"]


# -- the solver's parts: analytic sparse Jacobian, covariance, Schur complement steps -------


def _problem(
    views: int = 6, refine_intrinsics: bool = True, seed: int = 0
) -> tuple[CornerProblem, np.ndarray, dict]:
    """A joint problem of the default head (every sensor), and a point near its solution."""
    obs = scenario_corners(views=views, seed=seed)
    sensors = ["tof", "ccd_left", "ccd_right", "thermal_left", "thermal_right"]
    names = sorted(obs)
    obj = CALIBRATION_BOARD.object_points()
    rows = [(si, vi, s, v) for si, s in enumerate(sensors) for vi, v in enumerate(names)]
    seen = [(si, vi, obs[v][s]) for si, vi, s, v in rows if s in obs[v]]
    n = len(obj)
    prob = CornerProblem(
        sensors,
        names,
        np.concatenate([np.full(n, si) for si, _, _ in seen]),
        np.concatenate([np.full(n, vi) for _, vi, _ in seen]),
        np.concatenate([np.arange(n) for _ in seen]),
        np.concatenate([obj for _ in seen]),
        np.concatenate([uv for _, _, uv in seen]),
        {s: [0, 1, 2, 3] + ([4] if RIG[s].modality == "color" else []) for s in sensors},
        refine_intrinsics,
    )
    poses = dict(zip(names, calibration_poses(views, seed=1, rig=RIG), strict=True))
    intr = {s: RIG[s].intrinsics for s in sensors}
    x = prob.pack({s: RIG.T("tof", s) for s in sensors}, poses, intr)
    x += np.random.default_rng(seed).normal(0, 1e-3, x.shape)  # rotations off zero too
    return prob, x, intr


@pytest.mark.parametrize("refine_intrinsics", [True, False])
def test_analytic_jacobian_matches_central_differences(refine_intrinsics: bool) -> None:
    prob, x, intr = _problem(refine_intrinsics=refine_intrinsics)
    w = np.random.default_rng(1).uniform(5.0, 20.0, len(prob.sensors))[prob.s_idx]

    def fun(x: np.ndarray) -> np.ndarray:
        return ((prob.project(x, intr) - prob.uv) * w[:, None]).ravel()

    J = prob.jacobian(x, intr, w)
    assert sparse.isspmatrix_csr(J) and J.shape == (2 * len(prob.s_idx), prob.n_params)
    numeric = np.empty(J.shape)
    for j in range(len(x)):
        h = 1e-6 * max(1.0, abs(x[j]))
        step = np.zeros_like(x)
        step[j] = h
        numeric[:, j] = (fun(x + step) - fun(x - step)) / (2 * h)
    # Central differences are good to about 1e-8 of a column's scale here.
    scale = np.abs(numeric).max(axis=0)
    assert np.all(np.abs(J.toarray() - numeric).max(axis=0) <= 1e-7 * scale)
    # Nothing outside the declared sparsity: every non-zero derivative is a stored entry.
    assert np.count_nonzero(np.abs(numeric) > 1e-9 * scale) <= J.nnz


def test_covariance_from_sparse_blocks_equals_the_dense_formula() -> None:
    prob, x, intr = _problem(views=8)
    rng = np.random.default_rng(2)
    J = prob.jacobian(x, intr, np.ones(len(prob.s_idx)))
    # Residuals correlated within each image (what the cluster-robust estimate is for).
    image = prob.v_idx * len(prob.sensors) + prob.s_idx
    r = rng.normal(0, 0.1, (image.max() + 1, 2))[image] + rng.normal(0, 0.05, (len(image), 2))
    r = r.ravel()
    # The dense computation, written out: the cluster-robust estimate in its jackknife
    # form (CR3), each image's residuals corrected by its leverage (I - H_gg)^+.
    Jd = J.toarray()
    bread = np.linalg.pinv(Jd.T @ Jd)
    cov_iid = bread * np.sum(r**2) / (Jd.shape[0] - Jd.shape[1])
    cluster = np.repeat(image, 2)
    groups = np.unique(cluster)
    meat = np.zeros_like(bread)
    for k in groups:
        rows = np.flatnonzero(cluster == k)
        H = Jd[rows] @ bread @ Jd[rows].T
        u = np.linalg.pinv(np.eye(len(rows)) - H, hermitian=True) @ r[rows]
        score = Jd[rows].T @ u
        meat += np.outer(score, score)
    g = len(groups)
    cov_cluster = bread @ meat @ bread * (g - 1) / g
    dense = np.sqrt(np.maximum(np.diag(cov_iid), np.diag(cov_cluster)))
    assert np.allclose(parameter_sigma(prob, J, r), dense, rtol=1e-6, atol=0)


@pytest.mark.parametrize("loss", ["soft_l1", "linear"])
def test_schur_solver_reaches_the_exact_trust_region_solution(loss: str) -> None:
    """Same problem, same start: scipy's dense exact solver (the former engine) and ours."""
    prob, x_true, intr = _problem(views=10, seed=3)
    rng = np.random.default_rng(4)
    x0 = x_true + rng.normal(0, 2e-3, x_true.shape)  # a few px off at the start
    w = np.repeat(rng.uniform(5.0, 20.0, len(prob.sensors))[prob.s_idx], 2)
    if loss == "soft_l1":  # a few gross errors for the robust loss to handle
        bad = rng.choice(len(prob.uv), 10, replace=False)
        prob.uv[bad] += rng.normal(0, 3.0, (10, 2))

    def fun(x: np.ndarray) -> np.ndarray:
        return (prob.project(x, intr) - prob.uv).ravel() * w

    def jac(x: np.ndarray) -> sparse.csr_matrix:
        return prob.jacobian(x, intr, w[::2])

    kw = dict(loss=loss, f_scale=1.0, ftol=1e-12, xtol=1e-12, gtol=1e-10, max_nfev=100)
    ours = least_squares_schur(fun, jac, x0, (prob.off_board, len(prob.views), 6), **kw)
    dense = {"method": "trf", "tr_solver": "exact", "x_scale": "jac"}
    ref = least_squares(fun, x0, jac=lambda x: jac(x).toarray(), **dense, **kw)
    assert ours.status in (1, 2, 3, 4) and ref.status in (1, 2, 3, 4)
    assert ours.cost == pytest.approx(ref.cost, rel=1e-9)
    # The parameters agree far below their uncertainty.
    sigma = parameter_sigma(prob, ref.jac, ref.fun)
    assert np.max(np.abs(ours.x - ref.x) / sigma) < 1e-5  # measured: 3e-7


# -- bookkeeping and threads (vectorised; no per-corner loops) -----------------------------


def test_outlier_flags_and_inlier_problem_match_a_per_image_loop() -> None:
    """``_flag_outliers`` (per-image sums) and ``CornerProblem.subset`` against the plain loops
    over images and corners they replaced."""
    prob, _, _ = _problem(views=8)
    rng = np.random.default_rng(7)
    err = np.abs(rng.normal(0, 0.1, len(prob.s_idx)))
    image = prob.v_idx * len(prob.sensors) + prob.s_idx
    first = np.unique(image)
    err[image == first[3]] += 2.0  # a whole bad image: outlier by its corners
    err[image == first[9]] *= 8.0  # a noisy image: outlier by its RMS
    bad_corner = err > 0.35
    bad_corner[np.flatnonzero(image == first[5])[4]] = True  # one bad corner elsewhere
    limit = np.full(len(err), 0.35)
    opts = CalibrationOptions()
    outliers, in_bad_view = _flag_outliers(prob, err, bad_corner, limit, opts)

    bad_images, expected = set(), []
    for k, s in enumerate(prob.sensors):
        rms = {}
        for vi, v in enumerate(prob.views):
            sel = (prob.s_idx == k) & (prob.v_idx == vi)
            if not sel.any():
                continue
            if bad_corner[sel].sum() > 0.2 * sel.sum():
                bad_images.add((k, vi))
                expected.append((v, s, None, np.sqrt(np.mean(err[sel] ** 2))))
            else:
                rms[vi] = np.sqrt(np.mean(err[sel & ~bad_corner] ** 2))
        med = np.median(list(rms.values()))
        for vi, r in rms.items():
            if r > opts.view_outlier_factor * med and r > opts.view_outlier_min_px:
                bad_images.add((k, vi))
                expected.append((prob.views[vi], s, None, r))
    in_bad = np.array([(k, vi) in bad_images for k, vi in zip(prob.s_idx, prob.v_idx, strict=True)])
    for m in np.flatnonzero(bad_corner & ~in_bad):
        expected.append(
            (prob.views[prob.v_idx[m]], prob.sensors[prob.s_idx[m]], prob.c_idx[m], err[m])
        )
    assert len(bad_images) == 2 and (bad_corner & ~in_bad).sum() == 1
    assert [(o.view, o.sensor, o.corner) for o in outliers] == [e[:3] for e in expected]
    assert np.allclose([o.error_px for o in outliers], [e[3] for e in expected], rtol=1e-12)
    assert np.array_equal(in_bad_view, in_bad)

    # The inlier problem: the same corners in the same order, views renumbered.
    keep = ~bad_corner & ~in_bad_view
    keep[prob.v_idx == 2] = False  # a view with no corner left is dropped
    sub = prob.subset(keep)
    assert sub.views == [v for i, v in enumerate(prob.views) if i != 2]
    assert [sub.views[i] for i in sub.v_idx] == [prob.views[i] for i in prob.v_idx[keep]]
    for name in ("s_idx", "c_idx", "X", "uv"):
        assert np.array_equal(getattr(sub, name), getattr(prob, name)[keep])
    assert sub.n_params == prob.n_params - 6


def test_consensus_angles_in_chunks_equal_the_broadcast_formula(monkeypatch) -> None:
    """The screening's vote (calib.polarity) in chunks of transforms, against the direct
    (J, n, K, M, 3) broadcast it replaced."""
    rng = np.random.default_rng(3)
    n, K, M, J = 7, 2, 54, 11
    T = np.stack(
        [make_T(rotation_from_rvec(rng.normal(0, 0.3, 3)), rng.normal(0, 0.2, 3)) for _ in range(J)]
    )
    far = np.array([0.0, 0.0, 1.5])  # in front of the camera
    P = rng.normal(0, 0.2, (n, M, 3)) + far
    moved = rng.normal(0, 0.2, (n, K, M, 3)) + far
    direct = polarity.angle_deg(moved[None], polarity.apply_T(T[:, None], P[None])[:, :, None])
    monkeypatch.setattr(polarity, "_CHUNK_ELEMENTS", 3 * n * K * M)  # chunks of 3: 3+3+3+2
    assert direct.shape == (J, n, K)
    assert np.allclose(polarity._angle_deg_each(moved, P, T), direct, rtol=1e-12, atol=1e-12)


def test_blas_runs_on_one_thread_during_the_calibration() -> None:
    seen: list[list[int]] = []

    def progress(_stage: str, _fraction: float) -> None:
        seen.append([p["num_threads"] for p in threadpool_info() if p["user_api"] == "blas"])

    calibrate_rig(scenario_corners(views=10, seed=4), CALIBRATION_BOARD, SPECS, progress=progress)
    assert len(seen) > 5 and all(threads and set(threads) == {1} for threads in seen)
