"""1-sigma uncertainties of the parameters of the joint rig calibration
(:mod:`calib.rig_calibration`).

The covariance of the final least-squares pass, from its sparse Jacobian: the larger of the
independent-errors estimate ``s^2 (J^T J)^-1`` and a cluster-robust (per image) one; then one
sensor's share of it in the units of the calibration report.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np
import scipy.linalg
from scipy import sparse
from threadpoolctl import threadpool_limits

from trifuse.calib.camera import Intrinsics
from trifuse.calib.rig_problem import BLAS_THREADS, CornerProblem


@dataclass(frozen=True)
class CovarianceEstimates:
    """The two covariance estimates of a least-squares solution, in factored form.

    Attributes:
        bread: (n, n) ``(J^T J)^-1`` (units of ``x`` squared, for unit residual variance).
        information: (n, n) ``J^T J``.
        scale: ``s^2``, the residuals' variance per degree of freedom.
        scores: (g, n) the leverage-corrected ``r_g^T (I - H_gg)^+ J_g B`` per image g
            (view, sensor), times ``sqrt((g - 1) / g)``: the cluster-robust covariance is
            ``scores^T scores``.
    """

    bread: np.ndarray
    information: np.ndarray
    scale: float
    scores: np.ndarray

    def iid(self, columns: np.ndarray | slice = slice(None)) -> np.ndarray:
        """``s^2 (J^T J)^-1`` on ``columns``: right when corner errors are independent."""
        return self.bread[columns][:, columns] * self.scale

    def cluster(self, columns: np.ndarray | slice = slice(None)) -> np.ndarray:
        """The cluster-robust (sandwich) covariance on ``columns``."""
        S = self.scores[:, columns]
        return S.T @ S

    def sigma(self) -> np.ndarray:
        """(n,) 1-sigma of every parameter: the larger of the two estimates."""
        var_cluster = np.sum(self.scores * self.scores, axis=0)
        var = np.maximum(np.diag(self.bread) * self.scale, var_cluster)
        return np.sqrt(np.clip(var, 0.0, None))


def covariance_estimates(
    prob: CornerProblem, J: sparse.spmatrix | np.ndarray, r: np.ndarray
) -> CovarianceEstimates:
    """Both covariance estimates of the solution of ``prob``.

    * ``s^2 (J^T J)^-1``: right when corner errors are independent;
    * a cluster-robust (sandwich) estimate with one cluster per (view, sensor) image:
      detector errors are correlated within an image (blur, lighting or heating gradients
      move neighbouring corners alike), which the first estimate ignores and this one
      measures. It is the jackknife form (CR3): each image's score uses its residuals
      corrected for its own leverage, ``J_g^T (I - H_gg)^+ r_g`` with ``H_gg = J_g B J_g^T``
      and ``B = (J^T J)^-1``, and the sum is scaled by ``(g - 1) / g``. With few views an
      image pulls the solution towards itself, so its fitted residuals understate its
      errors. On rendered captures of 4-8 views (tests/calib/test_few_views.py) the plain form
      (``J_g^T r_g``) gave translation sigmas 2-3 times too small (errors up to 6.7
      sigma); this one errors of RMS 0.6-1.1 sigma. It is conservative where errors are
      independent (synthetic corners: RMS 0.4-0.9 sigma) and where one view alone
      determines a parameter (its leverage near 1).

    Args:
        prob: the problem ``J`` and ``r`` belong to.
        J: (2M, n) Jacobian of the weighted residuals, sparse (or dense); only the
            (n, n) ``J^T J`` and, per image, its rows on the columns it touches are formed.
        r: (2M,) weighted residuals at the solution.
    """
    J = sparse.csr_matrix(J)
    A = (J.T @ J).toarray()  # (n, n)
    # Invert the equilibrated matrix (unit diagonal): parameters in px, metres and radians
    # differ by orders of magnitude; scaling keeps the inverse accurate.
    diag = np.diag(A).copy()
    d = 1.0 / np.sqrt(np.where(diag > 0, diag, 1.0))
    As = A * d[:, None] * d[None, :]
    with threadpool_limits(limits=BLAS_THREADS, user_api="blas"):
        try:
            inv = scipy.linalg.cho_solve(scipy.linalg.cho_factor(As), np.eye(len(As)))
        except np.linalg.LinAlgError:  # singular: some parameter is not determined
            inv = np.linalg.pinv(As, hermitian=True)
        bread = inv * d[:, None] * d[None, :]
        dof = max(1, J.shape[0] - J.shape[1])
        image = np.repeat(prob.v_idx * len(prob.sensors) + prob.s_idx, 2)
        _, group = np.unique(image, return_inverse=True)
        g = int(group.max()) + 1
        order = np.argsort(group, kind="stable")
        bounds = np.r_[0, np.cumsum(np.bincount(group, minlength=g))]
        SB = np.empty((g, len(A)))
        for k in range(g):
            rows = order[bounds[k] : bounds[k + 1]]
            Jg = J[rows]
            cols = np.unique(Jg.indices)
            Jc = Jg[:, cols].toarray()
            SB[k] = _jackknife_score(Jc, r[rows], bread[np.ix_(cols, cols)], bread[cols])
        SB *= np.sqrt((g - 1) / g)
    return CovarianceEstimates(bread, A, float(np.sum(r**2) / dof), SB)


def _jackknife_score(
    Jc: np.ndarray, r: np.ndarray, Bc: np.ndarray, B_rows: np.ndarray
) -> np.ndarray:
    """One image's leverage-corrected score times ``B``: ``r^T (I - H)^+ Jc B[cols]``, (n,).

    Args:
        Jc: (m, c) the image's Jacobian rows on the c columns they touch.
        r: (m,) its weighted residuals.
        Bc: (c, c) ``B[cols, cols]`` of ``B = (J^T J)^-1``.
        B_rows: (c, n) ``B[cols]``.

    ``H = Jc Bc Jc^T`` (m x m) has rank at most c and is handled in that space: with
    ``Bc = L L^T`` and ``L^T Jc^T Jc L = V diag(l) V^T``, H's eigenvectors are
    ``q_i = Jc L v_i / sqrt(l_i)`` with eigenvalues ``l_i``, and ``(I - H)^+ = I + sum_i
    w_i q_i q_i^T`` with ``w_i = l_i / (1 - l_i)``, or ``-1`` where ``l_i`` is 1 (a
    direction the image alone determines, such as its board pose when no other sensor saw
    the view: it carries no residual).
    """
    # Bc = L L^T through the equilibrated matrix (its entries span px^2 to rad^2).
    dc = np.sqrt(np.clip(np.diag(Bc), 1e-300, None))
    Bs = Bc / dc[:, None] / dc[None, :]
    try:
        L = dc[:, None] * np.linalg.cholesky(Bs)
    except np.linalg.LinAlgError:  # semi-definite: some parameter is not determined
        lam_b, U = np.linalg.eigh(Bs)
        L = dc[:, None] * (U * np.sqrt(np.clip(lam_b, 0.0, None)))
    G = Jc.T @ Jc
    lam, V = np.linalg.eigh(L.T @ G @ L)
    keep = lam > 1e-12 * max(1.0, float(lam.max(initial=0.0)))
    lam, V = lam[keep], V[:, keep]
    w = np.where(lam < 1.0 - 1e-8, lam / np.maximum(1.0 - lam, 1e-300), -1.0)
    P = (V / np.sqrt(lam)).T @ L.T  # (k, c): q_i^T Jc = P_i G, q_i^T r = P_i Jc^T r
    s = Jc.T @ r
    score = s + ((w * (P @ s)) @ P) @ G
    return score @ B_rows


def parameter_sigma(
    prob: CornerProblem, J: sparse.spmatrix | np.ndarray, r: np.ndarray
) -> np.ndarray:
    """1-sigma of every parameter (units of ``x``): the larger of the two estimates of
    :func:`covariance_estimates` (same arguments); (n,)."""
    return covariance_estimates(prob, J, r).sigma()


@dataclass(frozen=True)
class RigCovariance:
    """The joint uncertainty of every sensor's pose and intrinsics, the board poses
    marginalised out: what derived figures (relative poses, baselines) and "what if more
    views were added" predictions are computed from (calib.verdict).

    Attributes:
        problem: the final pass's problem (layout: sensor poses but the reference's, board
            poses, then the intrinsics when refined; calib.rig_problem).
        x: (n,) its parameters at the solution.
        fixed: intrinsics of sensors whose intrinsics are not parameters.
        weights: (S,) weight of each sensor's residuals, 1/px (1 / its per-axis noise).
        columns: (p,) the kept parameters (every column but the board poses'), in order.
        iid: (p, p) ``s^2 (J^T J)^-1`` on them.
        cluster: (p, p) the cluster-robust estimate on them.
        information: (p, p) the information on them with the board poses eliminated
            (Schur complement of ``J^T J``; unit residual variance): ``inv(iid / scale)``.
        scale: ``s^2`` of the weighted fit.
    """

    problem: CornerProblem
    x: np.ndarray
    fixed: dict[str, Intrinsics]
    weights: np.ndarray
    columns: np.ndarray
    iid: np.ndarray
    cluster: np.ndarray
    information: np.ndarray
    scale: float

    def column(self, index: int) -> int:
        """Position in ``columns`` of the problem's parameter ``index``."""
        return int(np.searchsorted(self.columns, index))


def rig_covariance(
    prob: CornerProblem,
    est: CovarianceEstimates,
    x: np.ndarray,
    fixed: dict[str, Intrinsics],
    weights: np.ndarray,
) -> RigCovariance:
    """The sensors' share of ``est`` (:class:`RigCovariance`).

    Args:
        prob: the problem solved.
        est: its :func:`covariance_estimates`.
        x: (n,) its parameters at the solution.
        fixed: intrinsics of the sensors whose intrinsics are not parameters.
        weights: (S,) each sensor's residual weight, 1/px.
    """
    n = prob.n_params
    keep = np.r_[np.arange(prob.off_board), np.arange(prob.off_intr, n)]
    board = np.arange(prob.off_board, prob.off_intr)
    A = est.information
    # Schur complement over the board poses: V is block diagonal (6 x 6 per view).
    W = A[np.ix_(keep, board)]
    V_inv = np.zeros((len(board), len(board)))
    for k in range(0, len(board), 6):
        blk = A[np.ix_(board[k : k + 6], board[k : k + 6])]
        V_inv[k : k + 6, k : k + 6] = np.linalg.pinv(blk, hermitian=True)
    info = A[np.ix_(keep, keep)] - W @ V_inv @ W.T
    return RigCovariance(
        prob,
        x.copy(),
        dict(fixed),
        np.asarray(weights, dtype=np.float64).copy(),
        keep,
        est.iid(keep),
        est.cluster(keep),
        0.5 * (info + info.T),
        est.scale,
    )


def sensor_sigma(
    prob: CornerProblem, k: int, sig: np.ndarray, std_zhang: np.ndarray, free: list[int]
) -> dict[str, Any]:
    """1-sigma of one sensor's parameters (from the joint covariance, or Zhang's)."""
    out: dict[str, Any] = {}
    if k in prob.intr_slices:
        p = sig[prob.intr_slices[k]]
        out.update(fx=float(p[0]), fy=float(p[1]), cx=float(p[2]), cy=float(p[3]))
        dist = [0.0] * 5
        for j, idx in enumerate(free):
            if idx < 5:
                dist[idx] = float(p[4 + j])
        out["distortion"] = dist
    else:
        out.update(
            fx=float(std_zhang[0]),
            fy=float(std_zhang[1]),
            cx=float(std_zhang[2]),
            cy=float(std_zhang[3]),
            distortion=[float(v) for v in std_zhang[4:9]],
        )
    if k == 0:
        out["rotation_deg"] = [0.0, 0.0, 0.0]
        out["translation_m"] = [0.0, 0.0, 0.0]
    else:
        p = sig[6 * (k - 1) : 6 * k]
        out["rotation_deg"] = [float(np.degrees(v)) for v in p[:3]]
        out["translation_m"] = [float(v) for v in p[3:]]
    return out
