"""The joint covariance of a rig's sensor parameters, as a rig file carries it.

The joint calibration (:mod:`calib.rig_calibration`) knows how its estimates err together:
two sensors placed from the same views move together, a focal length and a distance trade
off. The per-sensor ``uncertainty`` blocks keep only each parameter's own 1-sigma; this
keeps the correlations, so that anything computed from several sensors (where a thermal
value lands in a colour image, :mod:`fusion.registration`) gets its true uncertainty.

Parameters are named ``<sensor>.<name>``:

- ``rx ry rz`` (radians): a rotation of the sensor about its own axes, applied on the
  right of its pose, ``R_rig_sensor exp([r]x)``; ``tx ty tz`` (metres): its position in
  the rig frame, ``t_rig_sensor + t``. The reference sensor has none (it defines the frame).
- ``fx fy cx cy`` (pixels) and ``k1 k2 p1 p2 k3 k4 k5 k6`` (OpenCV's distortion
  coefficients): added to the sensor's intrinsics.

Parameters a calibration did not estimate (a coefficient held at 0) are left out. The
covariance is stored as each parameter's 1-sigma and a lower-triangular factor ``F`` of the
correlation matrix (``C = diag(sigma) F F^T diag(sigma)``, rows of ``F`` of unit length),
so that whatever is read back is a valid covariance.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

from trifuse.calib.rig_problem import right_jacobians
from trifuse.calib.rig_uncertainty import RigCovariance
from trifuse.calib.sensor_result import SensorResult

COVARIANCE_MODEL = "trifuse-covariance/1"
POSE_PARAMETERS = ("rx", "ry", "rz", "tx", "ty", "tz")
INTRINSIC_PARAMETERS = ("fx", "fy", "cx", "cy")
DISTORTION_PARAMETERS = ("k1", "k2", "p1", "p2", "k3", "k4", "k5", "k6")
PARAMETERS = POSE_PARAMETERS + INTRINSIC_PARAMETERS + DISTORTION_PARAMETERS


def split_name(name: str) -> tuple[str, str]:
    """``"<sensor>.<parameter>"`` -> (sensor, parameter); ValueError if malformed."""
    sensor, dot, param = str(name).rpartition(".")
    if not dot or not sensor or param not in PARAMETERS:
        raise ValueError(
            f"parameter {name!r}: expected '<sensor>.<name>' with a name among {PARAMETERS}"
        )
    return sensor, param


@dataclass(frozen=True, eq=False)
class ParameterCovariance:
    """The joint covariance of named sensor parameters (module docstring).

    Attributes:
        names: (p,) ``<sensor>.<parameter>`` names, unique.
        sigma: (p,) float64 1-sigma of each, in its unit (rad, m, px, coefficient).
        factor: (p, p) float64 lower-triangular factor of the correlation matrix, rows of
            unit length.
    """

    names: tuple[str, ...]
    sigma: np.ndarray
    factor: np.ndarray

    @classmethod
    def from_matrix(cls, names: Sequence[str], matrix: np.ndarray) -> ParameterCovariance:
        """From a (p, p) covariance; parameters of zero variance are left out.

        A matrix that is not quite positive semi-definite (rounding) is brought to the
        nearest one that is before it is factored.
        """
        C = 0.5 * (np.asarray(matrix, dtype=np.float64) + np.asarray(matrix).T)
        names = [str(n) for n in names]
        if C.shape != (len(names), len(names)) or not np.all(np.isfinite(C)):
            raise ValueError(
                f"covariance: expected a finite ({len(names)}, {len(names)}) matrix, got "
                f"shape {C.shape}"
            )
        for n in names:
            split_name(n)
        if len(set(names)) != len(names):
            raise ValueError("covariance: a parameter is named twice")
        keep = np.flatnonzero(np.diag(C) > 0)
        C = C[np.ix_(keep, keep)]
        sigma = np.sqrt(np.diag(C))
        corr = C / sigma[:, None] / sigma[None, :]
        return cls(tuple(names[i] for i in keep), sigma, _correlation_factor(corr))

    def matrix(self) -> np.ndarray:
        """(p, p) the covariance, in the parameters' units squared."""
        F = self.factor * self.sigma[:, None]
        return F @ F.T

    @property
    def sensors(self) -> tuple[str, ...]:
        """The sensors with parameters here, in order of first appearance."""
        return tuple(dict.fromkeys(split_name(n)[0] for n in self.names))

    def restricted(self, sensors: Sequence[str]) -> ParameterCovariance:
        """The parameters of ``sensors`` only (their joint covariance, others marginalised)."""
        keep = [i for i, n in enumerate(self.names) if split_name(n)[0] in set(sensors)]
        C = self.matrix()[np.ix_(keep, keep)]
        return ParameterCovariance.from_matrix([self.names[i] for i in keep], C)

    def moves(self, delta: np.ndarray) -> dict[str, dict[str, float]]:
        """``delta`` (p,), in :attr:`names`' order and units, as sensor -> parameter ->
        value (what :meth:`calib.rig.Rig.perturbed` applies)."""
        delta = np.asarray(delta, dtype=np.float64).reshape(-1)
        if delta.shape != (len(self.names),):
            raise ValueError(f"delta: expected ({len(self.names)},), got {delta.shape}")
        by_sensor: dict[str, dict[str, float]] = {}
        for n, d in zip(self.names, delta, strict=True):
            s, p = split_name(n)
            by_sensor.setdefault(s, {})[p] = float(d)
        return by_sensor

    def sample(self, rng: np.random.Generator, count: int) -> np.ndarray:
        """(count, p) draws of the parameters' errors from this normal distribution."""
        z = rng.standard_normal((count, len(self.names)))
        return (z @ self.factor.T) * self.sigma

    def to_dict(self) -> dict[str, Any]:
        """The rig file's ``covariance`` block (docs/FORMATS.md)."""
        return {
            "model": COVARIANCE_MODEL,
            "parameters": list(self.names),
            "sigma": [float(s) for s in self.sigma],
            "correlation_factor": [
                [float(v) for v in self.factor[i, : i + 1]] for i in range(len(self.names))
            ],
        }

    @classmethod
    def from_dict(cls, block: Any) -> ParameterCovariance:
        """Read a ``covariance`` block; ValueError naming what is wrong."""
        if not isinstance(block, Mapping):
            raise ValueError(f"covariance: expected a mapping, got {type(block).__name__}")
        keys = {"model", "parameters", "sigma", "correlation_factor"}
        if set(block) != keys:
            raise ValueError(
                f"covariance: expected the keys {sorted(keys)}, got {sorted(map(str, block))}"
            )
        if block["model"] != COVARIANCE_MODEL:
            raise ValueError(
                f"covariance.model: expected {COVARIANCE_MODEL!r}, got {block['model']!r}"
            )
        names = block["parameters"]
        if not isinstance(names, list) or not all(isinstance(n, str) for n in names):
            raise ValueError("covariance.parameters: expected a list of names")
        for n in names:
            split_name(n)
        if len(set(names)) != len(names):
            raise ValueError("covariance.parameters: a parameter is named twice")
        p = len(names)
        sigma = _numbers(block["sigma"], "covariance.sigma")
        if sigma.shape != (p,) or np.any(sigma <= 0):
            raise ValueError(f"covariance.sigma: expected {p} positive numbers")
        rows = block["correlation_factor"]
        if not isinstance(rows, list) or len(rows) != p:
            raise ValueError(f"covariance.correlation_factor: expected {p} rows")
        F = np.zeros((p, p))
        for i, row in enumerate(rows):
            r = _numbers(row, f"covariance.correlation_factor[{i}]")
            if r.shape != (i + 1,) or not np.linalg.norm(r) > 0:
                raise ValueError(
                    f"covariance.correlation_factor[{i}]: expected {i + 1} numbers, not all 0"
                )
            norm = np.linalg.norm(r)
            F[i, : i + 1] = r if abs(norm - 1.0) < 1e-12 else r / norm
        return cls(tuple(names), sigma, F)

    def __eq__(self, other: object) -> bool:
        if not isinstance(other, ParameterCovariance):
            return NotImplemented
        return (
            self.names == other.names
            and np.array_equal(self.sigma, other.sigma)
            and np.array_equal(self.factor, other.factor)
        )


def _numbers(value: Any, where: str) -> np.ndarray:
    try:
        a = np.asarray(value, dtype=np.float64)
    except (TypeError, ValueError):
        raise ValueError(f"{where}: expected a list of numbers") from None
    if a.ndim != 1 or not np.all(np.isfinite(a)):
        raise ValueError(f"{where}: expected a list of finite numbers")
    return a


def _correlation_factor(corr: np.ndarray) -> np.ndarray:
    """Lower-triangular F with unit rows and ``F F^T`` = ``corr`` (nearest PSD matrix)."""
    p = len(corr)
    if p == 0:
        return np.zeros((0, 0))
    try:
        F = np.linalg.cholesky(corr)
    except np.linalg.LinAlgError:  # semi-definite or slightly indefinite: nudge it
        lam, U = np.linalg.eigh(corr)
        fixed = (U * np.clip(lam, 0.0, None)) @ U.T + 1e-12 * np.eye(p)
        F = np.linalg.cholesky(fixed / np.sqrt(np.outer(np.diag(fixed), np.diag(fixed))))
    return F / np.linalg.norm(F, axis=1, keepdims=True)


def bounding_covariance(iid: np.ndarray, cluster: np.ndarray) -> np.ndarray:
    """The smallest covariance (in the metric of ``iid``) at least as large as both.

    The calibration judges each figure by the larger of its independent-errors and its
    cluster-robust variance (:mod:`calib.rig_uncertainty`); one matrix that gives at least
    both in every direction: whiten by ``iid``, raise the cluster estimate's eigenvalues
    below 1 to 1, colour back.
    """
    lam, U = np.linalg.eigh(0.5 * (iid + iid.T))
    root = np.sqrt(np.clip(lam, 0.0, None))
    inv_root = np.where(root > root.max(initial=0.0) * 1e-12, 1.0 / np.where(root > 0, root, 1), 0)
    S, S_inv = (U * root) @ U.T, (U * inv_root) @ U.T
    mu, V = np.linalg.eigh(S_inv @ (0.5 * (cluster + cluster.T)) @ S_inv)
    M = (V * np.maximum(mu, 1.0)) @ V.T
    return S @ M @ S


def from_calibration(
    cov: RigCovariance, sensors: Mapping[str, SensorResult]
) -> ParameterCovariance:
    """The rig file's covariance of a joint calibration.

    Args:
        cov: the calibration's joint covariance (board poses marginalised).
        sensors: its calibrated sensors; those whose intrinsics were not refined jointly
            add their own (Zhang) 1-sigmas, uncorrelated with the rest.
    """
    prob = cov.problem
    C = bounding_covariance(cov.iid, cov.cluster)
    names: list[str] = []
    # the problem's rotation vectors -> rotations about the sensor's own axes
    A = np.eye(len(cov.columns))
    for k, s in enumerate(prob.sensors[1:]):
        names += [f"{s}.{p}" for p in POSE_PARAMETERS]
        j = cov.column(6 * k)
        A[j : j + 3, j : j + 3] = right_jacobians(cov.x[6 * k : 6 * k + 3])[0]
    for k, s in enumerate(prob.sensors):
        if k in prob.intr_slices:
            names += [f"{s}.{p}" for p in INTRINSIC_PARAMETERS]
            names += [f"{s}.{DISTORTION_PARAMETERS[i]}" for i in prob.free_dist[s]]
    C = A @ C @ A.T
    extra: list[tuple[str, float]] = []
    for k, s in enumerate(prob.sensors):
        if k in prob.intr_slices or s not in sensors:
            continue
        sig = sensors[s].sigma
        extra += [(f"{s}.{p}", float(sig[p])) for p in INTRINSIC_PARAMETERS]
        dist = list(sig.get("distortion", []))
        extra += [(f"{s}.{DISTORTION_PARAMETERS[i]}", float(v)) for i, v in enumerate(dist)]
    if len(names) != len(C):
        raise AssertionError(f"covariance layout: {len(names)} names for {len(C)} columns")
    full = np.zeros((len(C) + len(extra),) * 2)
    full[: len(C), : len(C)] = C
    for i, (_, sig) in enumerate(extra):
        full[len(C) + i, len(C) + i] = sig * sig
    return ParameterCovariance.from_matrix(names + [n for n, _ in extra], full)
