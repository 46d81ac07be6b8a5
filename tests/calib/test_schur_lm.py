"""Levenberg-Marquardt with a Schur complement (calib.schur_lm) against scipy's exact solver."""

from __future__ import annotations

import numpy as np
import pytest
from scipy import sparse
from scipy.optimize import least_squares

from trifuse.calib.schur_lm import least_squares_schur

TOL = {"ftol": 1e-12, "xtol": 1e-12, "gtol": 1e-10}


def circles(
    count: int = 12, points: int = 15, seed: int = 0, outliers: int = 0
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Points on ``count`` ellipses sharing a radius and an x-stretch; noisy, seeded.

    Parameters ``x = [radius, cx0, cy0, cx1, cy1, ..., stretch]``: one shared parameter on
    either side of the blocks (the centres). Returns (truth, per-point circle index,
    (N, 2) points).
    """
    rng = np.random.default_rng(seed)
    centres = rng.uniform(-5, 5, (count, 2))
    truth = np.r_[2.0, centres.ravel(), 1.3]
    which = np.repeat(np.arange(count), points)
    angle = rng.uniform(0, 2 * np.pi, len(which))
    pts = centres[which] + 2.0 * np.stack([np.cos(angle) / 1.3, np.sin(angle)], axis=1)
    pts += rng.normal(0, 0.01, pts.shape)
    if outliers:
        pts[rng.choice(len(pts), outliers, replace=False)] += rng.normal(0, 1.0, (outliers, 2))
    return truth, which, pts


def problem(which: np.ndarray, pts: np.ndarray, count: int):
    n = 2 + 2 * count
    rows = np.arange(len(which))

    def fun(x: np.ndarray) -> np.ndarray:
        c = x[1:-1].reshape(-1, 2)[which]
        d = pts - c
        return np.hypot(d[:, 0] * x[-1], d[:, 1]) - x[0]

    def jac(x: np.ndarray) -> sparse.csr_matrix:
        c = x[1:-1].reshape(-1, 2)[which]
        d = pts - c
        rho = np.hypot(d[:, 0] * x[-1], d[:, 1])
        J = sparse.lil_matrix((len(which), n))
        J[rows, 0] = -1.0
        J[rows, 1 + 2 * which] = -d[:, 0] * x[-1] ** 2 / rho
        J[rows, 2 + 2 * which] = -d[:, 1] / rho
        J[rows, n - 1] = d[:, 0] ** 2 * x[-1] / rho
        return J.tocsr()

    return fun, jac


@pytest.mark.parametrize(("loss", "outliers"), [("linear", 0), ("soft_l1", 8)])
def test_same_minimum_as_scipys_exact_trust_region(loss: str, outliers: int) -> None:
    truth, which, pts = circles(outliers=outliers)
    fun, jac = problem(which, pts, 12)
    x0 = truth + np.random.default_rng(1).normal(0, 0.2, truth.shape)
    ours = least_squares_schur(fun, jac, x0, (1, 12, 2), loss=loss, f_scale=0.05, **TOL)
    ref = least_squares(
        fun,
        x0,
        jac=lambda x: jac(x).toarray(),
        method="trf",
        tr_solver="exact",
        x_scale="jac",
        loss=loss,
        f_scale=0.05,
        **TOL,
    )
    assert ours.status in (1, 2, 3, 4)
    assert ours.cost == pytest.approx(ref.cost, rel=1e-10)
    assert np.allclose(ours.x, ref.x, rtol=0, atol=1e-7)
    # And the truth within the noise (0.01 per point, 15 points per circle).
    assert np.allclose(ours.x, truth, atol=0.02)
    # The result carries the residuals and Jacobian at the solution.
    assert np.allclose(ours.fun, fun(ours.x))
    assert np.allclose(ours.jac.toarray(), jac(ours.x).toarray())


def test_without_shared_parameters() -> None:
    truth, which, pts = circles(count=4, seed=2)
    fun_all, jac_all = problem(which, pts, 4)
    radius, stretch = truth[0], truth[-1]

    def fun(c: np.ndarray) -> np.ndarray:
        return fun_all(np.r_[radius, c, stretch])

    def jac(c: np.ndarray) -> sparse.csr_matrix:
        return jac_all(np.r_[radius, c, stretch])[:, 1:-1]

    res = least_squares_schur(fun, jac, truth[1:-1] + 0.3, (0, 4, 2), **TOL)
    assert res.status in (1, 2, 3, 4)
    assert np.allclose(res.x, truth[1:-1], atol=0.02)


def test_stops_at_max_nfev_and_says_so() -> None:
    truth, which, pts = circles()
    fun, jac = problem(which, pts, 12)
    res = least_squares_schur(fun, jac, truth + 0.5, (1, 12, 2), max_nfev=3, **TOL)
    assert res.status == 0 and res.nfev == 3


def test_bad_input() -> None:
    truth, which, pts = circles(count=3)
    fun, jac = problem(which, pts, 3)
    with pytest.raises(ValueError, match="loss: expected one of"):
        least_squares_schur(fun, jac, truth, (1, 3, 2), loss="cauchy")
    with pytest.raises(ValueError, match=r"blocks: expected \(start, count, size\) within 8"):
        least_squares_schur(fun, jac, truth, (1, 4, 2))
    # Blocks of 3 straddle two circles' centres: residuals couple two blocks.
    with pytest.raises(ValueError, match="depends on two of the independent blocks"):
        least_squares_schur(fun, jac, truth, (1, 2, 3))
    with pytest.raises(ValueError, match="not finite"):
        least_squares_schur(lambda x: fun(x) + np.nan, jac, truth, (1, 3, 2))
