"""Levenberg-Marquardt for least squares with many small independent parameter blocks.

The joint rig calibration has a few shared parameters (sensor poses, intrinsics: tens) and
one small block per view (the board pose: 6 parameters) that no residual shares with
another view. Its normal matrix ``H = J^T J`` is therefore

    H = [[U,   W],      U: shared x shared (dense, small)
         [W^T, V]]      V: block diagonal, one (b, b) block per view

and each damped Gauss-Newton step is solved exactly through the Schur complement
``S = U - W V^-1 W^T`` (shared x shared): the cost of an iteration grows linearly with the
number of views, and no dense (m, n) matrix, SVD or long iterative solve is needed. (An
iterative trust-region solver, scipy's ``tr_solver="lsmr"`` with the same sparse Jacobian,
had not converged after 300 evaluations (10 s) on the 40-view calibration's robust pass,
which this one solves in 8 (0.15 s): BENCHMARKS.md, rig calibration.)

The iteration follows scipy's ``least_squares(method="trf")`` where it matters for the
result: the same cost ``0.5 * sum(rho(f^2))`` with ``soft_l1``'s ``rho`` and ``f_scale``, the
same second-order scaling of a robust loss (Triggs), and the same termination tests
(``ftol``, ``xtol``, ``gtol``, ``max_nfev``). The damping is Marquardt's (proportional to
the diagonal of ``H``, never decreasing), updated by the gain ratio (Nielsen).

Pure: arrays and callables in, a result out.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
import scipy.linalg
from scipy import sparse

LOSSES = ("linear", "soft_l1")

# After a successful step the damping shrinks by Nielsen's factor 1 - (2 rho - 1)^3 (rho the
# gain ratio), but by at most this much: Nielsen's own 1/3 left a slow tail of 8-10 small
# steps on the calibration (the damping decayed slowly from the start's level); 1/100 halved
# the Jacobian evaluations (measured on 40 and 150 simulated views).
_MIN_SHRINK = 0.01
_MIN_DAMPING = 1e-15


@dataclass
class SchurResult:
    """Solution of :func:`least_squares_schur`.

    Attributes:
        x: (n,) parameters at the solution.
        fun: (m,) residuals at ``x`` (not scaled by the loss).
        jac: (m, n) sparse CSR Jacobian at ``x`` (not scaled by the loss).
        cost: ``0.5 * sum(rho)`` at ``x`` (``0.5 * |fun|^2`` for the linear loss).
        optimality: infinity norm of the cost's gradient at ``x``.
        nfev: residual evaluations (the first included); ``njev``: Jacobian evaluations.
        status: 0 ``max_nfev`` reached, 1 ``gtol``, 2 ``ftol``, 3 ``xtol``, 4 both ``ftol``
            and ``xtol`` satisfied (scipy's codes).
    """

    x: np.ndarray
    fun: np.ndarray
    jac: sparse.csr_matrix
    cost: float
    optimality: float
    nfev: int
    njev: int
    status: int


def _loss(f: np.ndarray, loss: str, f_scale: float) -> tuple[float, np.ndarray, np.ndarray]:
    """Cost and the (m,) factors scaling the residuals and the Jacobian's rows.

    With them, ``J_s^T f_s`` is the cost's gradient and ``J_s^T J_s`` its Gauss-Newton
    Hessian including the loss's curvature (``J_s = jac * row``, ``f_s = f * fac``).
    """
    if loss == "linear":
        ones = np.ones_like(f)
        return 0.5 * float(f @ f), ones, ones
    z1 = 1.0 + (f / f_scale) ** 2
    cost = float(f_scale**2 * np.sum(np.sqrt(z1) - 1.0))
    rho1 = z1**-0.5
    row = z1**-0.75  # sqrt(rho' + 2 rho'' f^2) = sqrt(z1^-1.5)
    return cost, rho1 / row, row


def _cost(f: np.ndarray, loss: str, f_scale: float) -> float:
    if loss == "linear":
        return 0.5 * float(f @ f)
    return float(f_scale**2 * np.sum(np.sqrt(1.0 + (f / f_scale) ** 2) - 1.0))


def _normal_blocks(
    J: sparse.csr_matrix, shared: np.ndarray, start: int, count: int, size: int
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """``U`` (ns, ns), ``W`` (ns, count * size), ``V`` (count, size, size), diag(H) (n,)."""
    H = (J.T @ J).tocsr()
    Hs = H[shared].toarray()
    stop = start + count * size
    U, W = Hs[:, shared], Hs[:, start:stop]
    Hb = H[start:stop, start:stop].tocoo()
    bi, bj = Hb.row // size, Hb.col // size
    if np.any((bi != bj) & (Hb.data != 0)):
        raise ValueError(
            "least_squares_schur: a residual depends on two of the independent blocks "
            f"(parameters {start}..{stop - 1} in blocks of {size})"
        )
    V = np.zeros((count, size, size))
    keep = bi == bj
    np.add.at(V, (bi[keep], Hb.row[keep] % size, Hb.col[keep] % size), Hb.data[keep])
    return U, W, V, H.diagonal()


def least_squares_schur(
    fun: Callable[[np.ndarray], np.ndarray],
    jac: Callable[[np.ndarray], sparse.spmatrix],
    x0: np.ndarray,
    blocks: tuple[int, int, int],
    loss: str = "linear",
    f_scale: float = 1.0,
    ftol: float = 1e-12,
    xtol: float = 1e-12,
    gtol: float = 1e-10,
    max_nfev: int = 100,
    initial_damping: float = 1e-4,
) -> SchurResult:
    """Minimise ``0.5 * sum(rho(fun(x)^2))`` by Levenberg-Marquardt with a Schur complement.

    Args:
        fun: ``fun(x)`` -> (m,) residuals.
        jac: ``jac(x)`` -> (m, n) sparse Jacobian of ``fun``.
        x0: (n,) starting parameters.
        blocks: ``(start, count, size)``: ``x[start : start + count * size]`` are ``count``
            blocks of ``size`` parameters, no residual depending on two of them (the board
            poses of a calibration); the other parameters are shared.
        loss: ``"linear"`` or ``"soft_l1"`` (``rho(z) = 2 (sqrt(1 + z) - 1)``, scipy's).
        f_scale: the robust loss's scale, in the residuals' unit.
        ftol, xtol, gtol, max_nfev: scipy's termination tests (relative cost reduction
            with a good step, relative step length, gradient norm, evaluations).
        initial_damping: first Marquardt damping, relative to the diagonal of ``J^T J``.

    Returns:
        A :class:`SchurResult`.

    Raises:
        ValueError: an unknown loss, blocks outside ``x0``, a residual coupling two blocks,
            or non-finite residuals at ``x0``.
    """
    if loss not in LOSSES:
        raise ValueError(f"loss: expected one of {LOSSES}, got {loss!r}")
    x = np.array(x0, dtype=np.float64)
    n = len(x)
    start, count, size = (int(v) for v in blocks)
    if start < 0 or count < 0 or size < 1 or start + count * size > n:
        raise ValueError(
            f"blocks: expected (start, count, size) within {n} parameters, got {blocks!r}"
        )
    stop = start + count * size
    shared = np.r_[np.arange(start), np.arange(stop, n)]
    f = np.asarray(fun(x), dtype=np.float64)
    if not np.all(np.isfinite(f)):
        raise ValueError("least_squares_schur: residuals at x0 are not finite")
    nfev, njev = 1, 1
    J = sparse.csr_matrix(jac(x))
    damping, grow = initial_damping, 2.0
    diag_max = np.zeros(n)
    status = 0
    while True:
        cost, fac, row = _loss(f, loss, f_scale)
        Js = sparse.diags(row) @ J if loss != "linear" else J
        g = Js.T @ (f * fac)
        if np.linalg.norm(g, ord=np.inf) < gtol:
            status = 1
            break
        U, W, V, diag = _normal_blocks(Js, shared, start, count, size)
        diag_max = np.maximum(diag_max, diag)
        scale = np.where(diag_max > 0, diag_max, 1.0)
        Wb = W.reshape(len(shared), count, size)
        gs, gb = g[shared], g[start:stop].reshape(count, size)
        accepted = False
        while nfev < max_nfev:
            Vd = V + damping * np.einsum(
                "ij,ki->kij", np.eye(size), scale[start:stop].reshape(count, size)
            )
            Vinv = np.linalg.inv(Vd)
            WVi = np.einsum("gvi,vij->gvj", Wb, Vinv)
            S = U + np.diag(damping * scale[shared]) - np.einsum("gvj,hvj->gh", WVi, Wb)
            rhs = -gs + np.einsum("gvj,vj->g", WVi, gb)
            step = np.empty(n)
            if len(shared):
                try:
                    step[shared] = scipy.linalg.cho_solve(scipy.linalg.cho_factor(S), rhs)
                except np.linalg.LinAlgError:
                    step[shared] = np.linalg.lstsq(S, rhs, rcond=None)[0]
            back = -gb - np.einsum("gvi,g->vi", Wb, step[shared])
            step[start:stop] = np.einsum("vij,vj->vi", Vinv, back).ravel()
            Jstep = Js @ step
            predicted = -(float(g @ step) + 0.5 * float(Jstep @ Jstep))
            x_new = x + step
            f_new = np.asarray(fun(x_new), dtype=np.float64)
            nfev += 1
            if not np.all(np.isfinite(f_new)):
                damping *= grow
                grow *= 2.0
                continue
            actual = cost - _cost(f_new, loss, f_scale)
            ratio = actual / predicted if predicted > 0 else 0.0
            ftol_ok = actual < ftol * cost and ratio > 0.25
            xtol_ok = float(np.linalg.norm(step)) < xtol * (xtol + float(np.linalg.norm(x)))
            status = 4 if ftol_ok and xtol_ok else 2 if ftol_ok else 3 if xtol_ok else 0
            if actual > 0:
                x, f = x_new, f_new
                J = sparse.csr_matrix(jac(x))
                njev += 1
                damping = max(
                    _MIN_DAMPING, damping * max(_MIN_SHRINK, 1.0 - (2.0 * ratio - 1.0) ** 3)
                )
                grow = 2.0
                accepted = True
                break
            if status:
                break
            damping *= grow
            grow *= 2.0
        if status or not accepted:
            break
    cost, fac, row = _loss(f, loss, f_scale)
    g = (sparse.diags(row) @ J).T @ (f * fac) if loss != "linear" else J.T @ f
    return SchurResult(
        x=x,
        fun=f,
        jac=J,
        cost=cost,
        optimality=float(np.linalg.norm(g, ord=np.inf)),
        nfev=nfev,
        njev=njev,
        status=status,
    )
