"""1-sigma uncertainties of the parameters of the joint rig calibration
(:mod:`calib.rig_calibration`).

The covariance of the final least-squares pass, from its sparse Jacobian: the larger of the
independent-errors estimate ``s^2 (J^T J)^-1`` and a cluster-robust (per image) one; then one
sensor's share of it in the units of the calibration report.
"""

from __future__ import annotations

from typing import Any

import numpy as np
import scipy.linalg
from scipy import sparse
from threadpoolctl import threadpool_limits

from calib.rig_problem import BLAS_THREADS, CornerProblem


def parameter_sigma(
    prob: CornerProblem, J: sparse.spmatrix | np.ndarray, r: np.ndarray
) -> np.ndarray:
    """1-sigma of every parameter (units of ``x``): the larger of two covariance estimates.

    * ``s^2 (J^T J)^-1``: right when corner errors are independent;
    * the cluster-robust (sandwich) estimate ``B (sum_g J_g^T r_g r_g^T J_g) B`` with
      ``B = (J^T J)^-1`` and one cluster per (view, sensor) image: detector errors are
      correlated within an image (blur, lighting or heating gradients move neighbouring
      corners alike), which the first estimate ignores and this one measures.

    Args:
        prob: the problem ``J`` and ``r`` belong to.
        J: (2M, n) Jacobian of the weighted residuals, sparse (or dense); only the
            (n, n) ``J^T J`` and the (images, n) sparse per-image scores are formed.
        r: (2M,) weighted residuals at the solution.

    Returns:
        (n,) standard deviations.
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
        var_iid = np.diag(bread) * float(np.sum(r**2) / dof)
        cluster = np.repeat(prob.v_idx * len(prob.sensors) + prob.s_idx, 2)
        _, group = np.unique(cluster, return_inverse=True)
        g = int(group.max()) + 1
        C = sparse.csr_matrix((r, (group, np.arange(len(r)))), shape=(g, len(r)))
        scores = (C @ J).tocsr()  # (g, n): sum over the image's rows of r_i J_i
        SB = np.asarray(scores @ bread)  # (g, n)
        var_cluster = np.sum(SB * SB, axis=0) * (g / max(1, g - 1))
    var = np.maximum(var_iid, var_cluster)
    return np.sqrt(np.clip(var, 0.0, None))


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
