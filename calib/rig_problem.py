"""The joint rig calibration's least-squares problem (:mod:`calib.rig_calibration`).

Every corner of every sensor's views flattened to points, the parameter vector's layout,
the projection with per-point intrinsics and its analytic sparse Jacobian.

Parameters (:class:`CornerProblem`): 6 per sensor but the reference (rotation vector in
radians and translation in metres of ``T_rig_sensor``), 6 per view (``T_rig_board``, the
same units), then, when the intrinsics are refined, each sensor's ``fx fy cx cy`` (px) and
its estimated distortion coefficients. Residuals are pixels, two rows (u, v) per corner.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass
from functools import cached_property

import numpy as np
from scipy import sparse

from trifuse.calib.board import Board
from trifuse.calib.camera import Intrinsics
from trifuse.calib.transforms import rotations_from_rvecs, rvec_from_rotation

# BLAS threads of the whole calibration: the products are small (sparse, n x n with n of a
# few hundred, the screening's (n M, 3) x (3, 3 J)), so more threads gain little and, beside
# other busy processes, spinning OpenBLAS threads cost up to 10x (BENCHMARKS.md).
BLAS_THREADS = 1


# -- projection with per-point parameters -------------------------------------------------


def project_points(Q: np.ndarray, K4: np.ndarray, D8: np.ndarray) -> np.ndarray:
    """Project camera-frame points (M, 3) (metres) with per-point intrinsics (M, 4) fx fy cx
    cy (px) and distortion (M, 8) k1 k2 p1 p2 k3 k4 k5 k6 (OpenCV's model, as calib.camera)
    to pixels (M, 2) (u, v)."""
    x = Q[:, 0] / Q[:, 2]
    y = Q[:, 1] / Q[:, 2]
    k1, k2, p1, p2, k3, k4, k5, k6 = D8.T
    r2 = x * x + y * y
    rad = (1 + r2 * (k1 + r2 * (k2 + r2 * k3))) / (1 + r2 * (k4 + r2 * (k5 + r2 * k6)))
    xd = x * rad + 2 * p1 * x * y + p2 * (r2 + 2 * x * x)
    yd = y * rad + p1 * (r2 + 2 * y * y) + 2 * p2 * x * y
    return np.stack([K4[:, 0] * xd + K4[:, 2], K4[:, 1] * yd + K4[:, 3]], axis=1)


def project_derivatives(
    Q: np.ndarray, K4: np.ndarray, D8: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Derivatives of :func:`project_points` (analytic, same per-point parameters).

    Args:
        Q: (M, 3) camera-frame points (metres).
        K4: (M, 4) fx fy cx cy (px).
        D8: (M, 8) k1 k2 p1 p2 k3 k4 k5 k6.

    Returns:
        ``d(u, v)/dQ`` (M, 2, 3) in px per metre, ``d(u, v)/d(fx, fy, cx, cy)`` (M, 2, 4)
        and ``d(u, v)/d(k1 ... k6)`` (M, 2, 8) in px per unit coefficient.
    """
    iz = 1.0 / Q[:, 2]
    x = Q[:, 0] * iz
    y = Q[:, 1] * iz
    k1, k2, p1, p2, k3, k4, k5, k6 = D8.T
    fx, fy = K4[:, 0], K4[:, 1]
    r2 = x * x + y * y
    a = 1 + r2 * (k1 + r2 * (k2 + r2 * k3))
    b = 1 + r2 * (k4 + r2 * (k5 + r2 * k6))
    rad = a / b
    drad = ((k1 + r2 * (2 * k2 + 3 * r2 * k3)) * b - a * (k4 + r2 * (2 * k5 + 3 * r2 * k6))) / (
        b * b
    )  # d rad / d r2
    xy = x * y
    xd = x * rad + 2 * p1 * xy + p2 * (r2 + 2 * x * x)
    yd = y * rad + p1 * (r2 + 2 * y * y) + 2 * p2 * xy
    # d(xd, yd)/d(x, y)
    dxx = rad + 2 * x * x * drad + 2 * p1 * y + 6 * p2 * x
    dxy = 2 * xy * drad + 2 * p1 * x + 2 * p2 * y
    dyy = rad + 2 * y * y * drad + 6 * p1 * y + 2 * p2 * x
    M = len(Q)
    # d(x, y)/dQ = [[1/z, 0, -x/z], [0, 1/z, -y/z]]
    dQ = np.empty((M, 2, 3))
    dQ[:, 0, 0] = fx * dxx * iz
    dQ[:, 0, 1] = fx * dxy * iz
    dQ[:, 0, 2] = -fx * (dxx * x + dxy * y) * iz
    dQ[:, 1, 0] = fy * dxy * iz
    dQ[:, 1, 1] = fy * dyy * iz
    dQ[:, 1, 2] = -fy * (dxy * x + dyy * y) * iz
    dK = np.zeros((M, 2, 4))
    dK[:, 0, 0] = xd
    dK[:, 1, 1] = yd
    dK[:, 0, 2] = 1.0
    dK[:, 1, 3] = 1.0
    dD = np.empty((M, 2, 8))
    powers = np.stack([r2, r2 * r2, r2 * r2 * r2], axis=1) / b[:, None]  # d rad / d k1 k2 k3
    dD[:, 0, [0, 1, 4]] = (fx * x)[:, None] * powers
    dD[:, 1, [0, 1, 4]] = (fy * y)[:, None] * powers
    dD[:, 0, [5, 6, 7]] = -(fx * x * rad)[:, None] * powers
    dD[:, 1, [5, 6, 7]] = -(fy * y * rad)[:, None] * powers
    dD[:, 0, 2] = fx * 2 * xy
    dD[:, 1, 2] = fy * (r2 + 2 * y * y)
    dD[:, 0, 3] = fx * (r2 + 2 * x * x)
    dD[:, 1, 3] = fy * 2 * xy
    return dQ, dK, dD


def right_jacobians(rvecs: np.ndarray) -> np.ndarray:
    """Right Jacobians of SO(3) at axis-angle vectors (K, 3) (radians): (K, 3, 3).

    ``R(r + dr) = R(r) exp([J_r(r) dr]x)`` to first order, with
    ``J_r = I - (1 - cos t) / t^2 [r]x + (t - sin t) / t^3 [r]x^2``, t = |r| (Taylor
    series below 1e-4 rad, where the closed form loses digits).
    """
    r = np.asarray(rvecs, dtype=np.float64).reshape(-1, 3)
    t2 = np.sum(r * r, axis=1)
    t = np.sqrt(t2)
    small = t < 1e-4
    ts = np.where(small, 1.0, t)
    c1 = np.where(small, 0.5 - t2 / 24.0, (1.0 - np.cos(ts)) / ts**2)
    c2 = np.where(small, 1.0 / 6.0 - t2 / 120.0, (ts - np.sin(ts)) / ts**3)
    S = np.zeros((len(r), 3, 3))
    S[:, 0, 1], S[:, 0, 2] = -r[:, 2], r[:, 1]
    S[:, 1, 0], S[:, 1, 2] = r[:, 2], -r[:, 0]
    S[:, 2, 0], S[:, 2, 1] = -r[:, 1], r[:, 0]
    return np.eye(3)[None] - c1[:, None, None] * S + c2[:, None, None] * (S @ S)


# -- the problem --------------------------------------------------------------------------


@dataclass
class CornerProblem:
    """Observations flattened to points, and the parameter vector's layout."""

    sensors: list[str]  # index = sensor id; [0] is the reference
    views: list[str]
    s_idx: np.ndarray  # (M,) sensor id of each corner
    v_idx: np.ndarray  # (M,) view id
    c_idx: np.ndarray  # (M,) corner index on the board
    X: np.ndarray  # (M, 3) board points
    uv: np.ndarray  # (M, 2) observed pixels
    free_dist: dict[str, list[int]]  # sensor -> indices (into 8) of estimated coefficients
    refine_intrinsics: bool

    def __post_init__(self) -> None:
        n_s, n_v = len(self.sensors), len(self.views)
        self.off_sensor = 0
        self.off_board = 6 * (n_s - 1)
        self.off_intr = self.off_board + 6 * n_v
        self.intr_slices: dict[int, slice] = {}
        o = self.off_intr
        if self.refine_intrinsics:
            for k, s in enumerate(self.sensors):
                n = 4 + len(self.free_dist[s])
                self.intr_slices[k] = slice(o, o + n)
                o += n
        self.n_params = o

    def pack(
        self,
        T_rig_sensor: dict[str, np.ndarray],
        T_rig_board: dict[str, np.ndarray],
        intr: dict[str, Intrinsics],
    ) -> np.ndarray:
        x = np.zeros(self.n_params)
        for k, s in enumerate(self.sensors[1:]):
            T = T_rig_sensor[s]
            x[6 * k : 6 * k + 3] = rvec_from_rotation(T[:3, :3])
            x[6 * k + 3 : 6 * k + 6] = T[:3, 3]
        for k, v in enumerate(self.views):
            T = T_rig_board[v]
            o = self.off_board + 6 * k
            x[o : o + 3] = rvec_from_rotation(T[:3, :3])
            x[o + 3 : o + 6] = T[:3, 3]
        for k, sl in self.intr_slices.items():
            i = intr[self.sensors[k]]
            d = np.zeros(8)
            d[: len(i.distortion)] = i.distortion
            x[sl] = [i.fx, i.fy, i.cx, i.cy, *d[self.free_dist[self.sensors[k]]]]
        return x

    def unpack_intrinsics(
        self, x: np.ndarray, fixed: dict[str, Intrinsics]
    ) -> tuple[np.ndarray, np.ndarray]:
        """(S, 4) and (S, 8) intrinsics/distortion arrays at ``x``."""
        K4 = np.zeros((len(self.sensors), 4))
        D8 = np.zeros((len(self.sensors), 8))
        for k, s in enumerate(self.sensors):
            i = fixed[s]
            K4[k] = (i.fx, i.fy, i.cx, i.cy)
            D8[k, : len(i.distortion)] = i.distortion
            if k in self.intr_slices:
                p = x[self.intr_slices[k]]
                K4[k] = p[:4]
                D8[k] = 0.0
                D8[k, self.free_dist[s]] = p[4:]
        return K4, D8

    def poses(self, x: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        n_s, n_v = len(self.sensors), len(self.views)
        sp = x[: self.off_board].reshape(n_s - 1, 6)
        bp = x[self.off_board : self.off_intr].reshape(n_v, 6)
        Rs = np.concatenate([np.eye(3)[None], rotations_from_rvecs(sp[:, :3])])
        ts = np.concatenate([np.zeros((1, 3)), sp[:, 3:]])
        return Rs, ts, rotations_from_rvecs(bp[:, :3]), bp[:, 3:]

    def project(self, x: np.ndarray, fixed: dict[str, Intrinsics]) -> np.ndarray:
        Rs, ts, Rb, tb = self.poses(x)
        K4, D8 = self.unpack_intrinsics(x, fixed)
        P = np.einsum("kij,kj->ki", Rb[self.v_idx], self.X) + tb[self.v_idx]
        Q = np.einsum("kji,kj->ki", Rs[self.s_idx], P - ts[self.s_idx])
        return project_points(Q, K4[self.s_idx], D8[self.s_idx])

    def subset(self, keep: np.ndarray) -> CornerProblem:
        """The problem on the corners where ``keep`` (M,) is true, in the same order; views
        left without corners are dropped (and the board poses' layout with them)."""
        used = np.unique(self.v_idx[keep])
        remap = np.zeros(len(self.views), dtype=np.int64)
        remap[used] = np.arange(len(used))
        return CornerProblem(
            self.sensors,
            [self.views[i] for i in used],
            self.s_idx[keep],
            remap[self.v_idx[keep]],
            self.c_idx[keep],
            self.X[keep],
            self.uv[keep],
            self.free_dist,
            self.refine_intrinsics,
        )

    @cached_property
    def _jacobian_layout(self) -> tuple[np.ndarray, np.ndarray, np.ndarray, list[np.ndarray]]:
        """Sparsity of the residuals' Jacobian, built once per problem.

        Each corner's two rows touch its board pose (6 columns), its sensor's pose (6,
        none for the reference) and its sensor's intrinsics (4 + free distortion
        coefficients, when refined). :meth:`jacobian` computes the values in that block
        order; ``order`` sorts them into CSR order (``indices``, ``indptr``).

        Returns:
            ``(order, indices, indptr, points)``: (nnz,) permutation, (nnz,) int32 column
            of each CSR value, (2M + 1,) row pointers, and the corner indices of each
            sensor.
        """
        M = len(self.s_idx)
        points = [np.flatnonzero(self.s_idx == k) for k in range(len(self.sensors))]
        row2 = 2 * np.arange(M)[:, None, None] + np.arange(2)[None, :, None]  # (M, 2, 1)
        rows = [np.broadcast_to(row2, (M, 2, 6))]
        cols = [
            np.broadcast_to(
                self.off_board + 6 * self.v_idx[:, None, None] + np.arange(6), (M, 2, 6)
            )
        ]
        moving = np.flatnonzero(self.s_idx > 0)
        rows.append(np.broadcast_to(row2[moving], (len(moving), 2, 6)))
        cols.append(
            np.broadcast_to(
                6 * (self.s_idx[moving, None, None] - 1) + np.arange(6), (len(moving), 2, 6)
            )
        )
        for k, sl in self.intr_slices.items():
            n = sl.stop - sl.start
            rows.append(np.broadcast_to(row2[points[k]], (len(points[k]), 2, n)))
            cols.append(np.broadcast_to(sl.start + np.arange(n), (len(points[k]), 2, n)))
        r = np.concatenate([a.ravel() for a in rows])
        c = np.concatenate([a.ravel() for a in cols])
        order = np.lexsort((c, r))
        indptr = np.concatenate([[0], np.cumsum(np.bincount(r, minlength=2 * M))])
        return order, c[order].astype(np.int32), indptr, points

    def jacobian(
        self, x: np.ndarray, fixed: dict[str, Intrinsics], weights: np.ndarray
    ) -> sparse.csr_matrix:
        """Analytic Jacobian of the weighted residuals ``(project(x) - uv) * weights``.

        Args:
            x: (n,) parameters (rotation vectors in radians, translations in metres,
                intrinsics in px, distortion coefficients).
            fixed: intrinsics of sensors whose intrinsics are not parameters.
            weights: (M,) weight of each corner (both of its rows), 1/px.

        Returns:
            (2M, n) CSR matrix, rows ``2m`` (u) and ``2m + 1`` (v) of corner m; about
            21 non-zeros per row (see :attr:`_jacobian_layout`).
        """
        order, indices, indptr, points = self._jacobian_layout
        n_s = len(self.sensors)
        s, v = self.s_idx, self.v_idx
        Rs, ts, Rb, tb = self.poses(x)
        K4, D8 = self.unpack_intrinsics(x, fixed)
        P = np.einsum("kij,kj->ki", Rb[v], self.X) + tb[v]
        Q = np.einsum("kji,kj->ki", Rs[s], P - ts[s])
        dQ, dK, dD = project_derivatives(Q, K4[s], D8[s])
        w = weights[:, None, None]
        dQ *= w
        dP = np.einsum("kai,kji->kaj", dQ, Rs[s])  # d/dP = d/dQ R_s^T
        Jrb = right_jacobians(x[self.off_board : self.off_intr].reshape(-1, 6)[:, :3])
        # P = R_b X + t_b: dP/dr_b = -R_b [X]x J_r(r_b), and c^T [X]x = (c x X)^T.
        dRb = -np.einsum(
            "kai,kij->kaj", np.cross(np.einsum("kai,kij->kaj", dP, Rb[v]), self.X[:, None]), Jrb[v]
        )
        blocks = [np.concatenate([dRb, dP], axis=2)]
        moving = s > 0
        if n_s > 1:
            # Q = R_s^T (P - t_s): dQ/dr_s = [Q]x J_r(r_s), dQ/dt_s = -R_s^T.
            Jrs = right_jacobians(x[: self.off_board].reshape(-1, 6)[:, :3])
            dRs = np.einsum(
                "kai,kij->kaj", np.cross(dQ[moving], Q[moving, None]), Jrs[s[moving] - 1]
            )
            blocks.append(np.concatenate([dRs, -dP[moving]], axis=2))
        for k in self.intr_slices:
            m = points[k]
            free = self.free_dist[self.sensors[k]]
            blocks.append(np.concatenate([dK[m], dD[m][:, :, free]], axis=2) * w[m])
        data = np.concatenate([b.ravel() for b in blocks])[order]
        return sparse.csr_matrix(
            (data, indices, indptr), shape=(2 * len(s), self.n_params), copy=False
        )


def build_problem(
    sensors: list[str],
    views: list[str],
    by_sensor: Mapping[str, Mapping[str, np.ndarray]],
    board: Board,
    free_dist: dict[str, list[int]],
    refine_intrinsics: bool,
) -> CornerProblem:
    """Every corner of every sensor's views, ordered by sensor, view (as ``views``: sorted)
    and corner.

    Args:
        sensors: sensor names, the reference first.
        views: every view any of them saw, sorted.
        by_sensor: sensor -> view -> (N, 2) corners, pixels; NaN rows (corners a partial
            view did not see) are left out of the problem.
        board: the board (N corners).
        free_dist: sensor -> indices (into k1 k2 p1 p2 k3 k4 k5 k6) of the estimated
            distortion coefficients.
        refine_intrinsics: intrinsics are parameters.
    """
    n = board.n_corners
    vpos = {v: i for i, v in enumerate(views)}
    s_idx, v_idx, uv = [], [], []
    for si, s in enumerate(sensors):
        names = sorted(by_sensor[s])
        if not names:
            continue
        s_idx.append(np.full(len(names) * n, si))
        v_idx.append(np.repeat([vpos[v] for v in names], n))
        uv.append(np.stack([by_sensor[s][v] for v in names]).reshape(-1, 2))
    s_all = np.concatenate(s_idx)
    c_idx = np.tile(np.arange(n), len(s_all) // n)
    uv_all = np.concatenate(uv).astype(np.float64)
    v_all = np.concatenate(v_idx)
    seen = np.all(np.isfinite(uv_all), axis=1)  # partial views (ChArUco): NaN rows unseen
    if not seen.all():
        s_all, v_all, c_idx, uv_all = s_all[seen], v_all[seen], c_idx[seen], uv_all[seen]
    return CornerProblem(
        list(sensors),
        list(views),
        s_all,
        v_all,
        c_idx,
        board.object_points()[c_idx],
        uv_all,
        free_dist,
        refine_intrinsics,
    )
