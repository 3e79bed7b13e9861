"""The compliant-wrist force sensor model: the paper's eq. (4), forward and inverse.

The sensor (§2.1.4) is two parallel plates joined by three elastic links: p1 is fixed to the
flange (frame R_e), p2 carries the tool (frame R_s, the sensor frame). A force on the tool
deflects p2 relative to p1 by a small translation ΔS and rotation ΔM, which six sensing
signals measure. The tool frame R_t sits on p2 at the placement sMt = (M_s^t, s_p_t).

Frames and names (SE3 names say their frames, as in Pinocchio: `eMs` is R_s in R_e):

- `eMs = (R_es, p_es)`: the sensor frame at rest, in the flange frame. The paper has
  R_s ≡ R_e at rest (the plates are thin): the default is the identity.
- `eMt = (R_et, p_et)`: the tool placement in the flange frame, as arm's `set_tool`.
- `sMt = eMs⁻¹ · eMt = (R_st, p_st)`: the tool in the sensor frame; R_st = M_s^t and
  p_st = M_s^t T_t, the tool point seen from the sensor origin.
- The calibration reports the plate motion (ΔS, ΔM) in R_s at rest; with the paper's
  eMs = I this is the paper's "measured in R_e".

Units: signals in whatever the device gives (counts, volts; the calibration absorbs it),
ΔS in m, rotations as rotation vectors in rad, K_l in N/m, K_r in N·m/rad, forces in N,
moments in N·m about the tool point, both in the tool frame R_t.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field, replace
from typing import Literal

import numpy as np
from numpy.typing import ArrayLike, NDArray

from services.geometry import ROTATION_TOL, exp_so3, log_so3, rotation_problem, skew, vee

Vec = NDArray[np.float64]
Mat = NDArray[np.float64]
RotationMode = Literal["exact", "small_angle"]

_I3 = np.eye(3)
CALIBRATION_MAX_COND = 1e12
"""A calibration this ill-conditioned cannot be inverted for the simulated sensor."""


def rotation_from_vector(theta: ArrayLike, mode: RotationMode) -> Mat:
    """ΔM from a rotation vector: exact (Rodrigues) or small-angle I + [θ]×."""
    if mode == "exact":
        return exp_so3(theta)
    return _I3 + skew(theta)


def vector_from_rotation(m: Mat, mode: RotationMode) -> Vec:
    """rotvec(ΔM): exact (log) or small-angle (the vector of ΔM's skew part)."""
    if mode == "exact":
        return log_so3(m)
    return vee(m)


def _inverse(m: Mat, mode: RotationMode) -> Mat:
    # A small-angle ΔM = I + [θ]× is not orthogonal: invert it truly so that the
    # inverse model is the exact inverse of the forward one in both modes.
    if mode == "exact":
        return m.T
    return np.asarray(np.linalg.inv(m), dtype=np.float64)


# --- eq. (4), forward: signals → plate motion → tool deflection → wrench -------------------


def plate_motion(
    signals: ArrayLike, calibration: Mat, mode: RotationMode = "exact"
) -> tuple[Vec, Mat]:
    """Six sensing signals → plate motion (ΔS (m), ΔM) of p2 in R_s (§2.1.4).

    `calibration` (6×6) maps the signals to x = (ΔS, θ), θ the rotation vector (rad) of ΔM.
    """
    x: Vec = calibration @ np.asarray(signals, dtype=float)
    return x[:3], rotation_from_vector(x[3:], mode)


def tool_deflection(
    dS: Vec, dM: Mat, R_st: Mat, p_st: Vec, mode: RotationMode = "exact"
) -> tuple[Vec, Mat]:
    """Plate motion → tool deflection in the tool frame: the paper's eq. (4).

        ΔT_e = ΔS_e + (ΔM_e − I) M_s^t T_t          deflection of the tool point
        ΔM_t = M_t^s ΔM M_s^t                         tool rotation, in R_t
        ΔT_t = M_t^s ΔM⁻¹ ΔT_e                        (4), since M_e^t = ΔM M_s^t

    with M_s^t = `R_st`, M_s^t T_t = `p_st` (tool point from the sensor origin, in R_s).
    Returns (ΔT_t (m), ΔM_t).
    """
    dT_s = dS + (dM - _I3) @ p_st
    dT_t = R_st.T @ (_inverse(dM, mode) @ dT_s)
    dM_t = R_st.T @ dM @ R_st
    return dT_t, dM_t


def tool_wrench(
    dT_t: Vec, dM_t: Mat, K_l: Vec, K_r: Vec, mode: RotationMode = "exact"
) -> tuple[Vec, Vec]:
    """Tool deflection → force and moment at the tool point, tool frame (§2.1.4).

        F_t = K_l ΔT_t,   C_t = K_r · rotvec(ΔM_t)

    K_l (N/m) and K_r (N·m/rad) are the diagonals of the passive compliance matrices.
    """
    return K_l * dT_t, K_r * vector_from_rotation(dM_t, mode)


# --- inverse: wrench → tool deflection → plate motion → signals (for the simulated wrist) ---


def deflection_from_wrench(
    F_t: Vec, C_t: Vec, K_l: Vec, K_r: Vec, mode: RotationMode = "exact"
) -> tuple[Vec, Mat]:
    """Inverse of `tool_wrench`: ΔT_t = F_t / K_l, ΔM_t = rot(C_t / K_r)."""
    return np.asarray(F_t, dtype=float) / K_l, rotation_from_vector(
        np.asarray(C_t, dtype=float) / K_r, mode
    )


def plate_motion_from_deflection(dT_t: Vec, dM_t: Mat, R_st: Mat, p_st: Vec) -> tuple[Vec, Mat]:
    """Inverse of eq. (4): ΔM = M_s^t ΔM_t M_t^s, ΔT_e = ΔM M_s^t ΔT_t,
    ΔS = ΔT_e − (ΔM − I) M_s^t T_t."""
    dM = R_st @ dM_t @ R_st.T
    dT_s = dM @ (R_st @ dT_t)
    return dT_s - (dM - _I3) @ p_st, dM


def signals_from_plate_motion(
    dS: Vec, dM: Mat, calibration_inv: Mat, mode: RotationMode = "exact"
) -> Vec:
    """Inverse of `plate_motion`, given the inverse of the calibration matrix."""
    x = np.concatenate([np.asarray(dS, dtype=float), vector_from_rotation(dM, mode)])
    return calibration_inv @ x


# --- the model object the service holds ------------------------------------------------


def as_vec3(value: float | Sequence[float] | Vec, name: str) -> Vec:
    """A scalar (isotropic) or a 3-vector as a 3-vector; positive and finite."""
    v = np.asarray(value, dtype=float)
    if v.shape == ():
        v = np.full(3, float(v))
    if v.shape != (3,):
        raise ValueError(f"{name}: expected a number or 3 numbers, got shape {v.shape}")
    if not (np.all(np.isfinite(v)) and np.all(v > 0.0)):
        raise ValueError(f"{name}: must be positive and finite, got {v.tolist()}")
    return v


def as_rotation(value: ArrayLike, name: str, tol: float = ROTATION_TOL) -> Mat:
    """A proper rotation from 9 row-major floats or a 3×3 array (PROTOCOL.md conventions)."""
    r = np.asarray(value, dtype=float).reshape(3, 3)
    why = rotation_problem(r, tol)
    if why is not None:
        raise ValueError(f"{name}: not a proper rotation: {why}")
    return r


def as_calibration(value: ArrayLike | str) -> Mat:
    """The 6×6 calibration from "identity" or 36 row-major floats; finite and invertible."""
    if isinstance(value, str):
        if value != "identity":
            raise ValueError(f'calibration: "identity" or 36 numbers, got {value!r}')
        return np.eye(6)
    c = np.asarray(value, dtype=float)
    if c.size != 36:
        raise ValueError(f"calibration: expected 36 numbers (6×6 row-major), got {c.size}")
    c = c.reshape(6, 6)
    if not np.all(np.isfinite(c)):
        raise ValueError("calibration: not finite")
    if np.linalg.cond(c) > CALIBRATION_MAX_COND:
        raise ValueError("calibration: singular or ill-conditioned")
    return c


@dataclass(frozen=True, slots=True, eq=False)
class WristModel:
    """Eq. (4) with its parameters: signals ↔ (F_t, C_t) at the tool point, tool frame.

    Immutable: `with_tool` and `with_compliance` return a new model, so the sampling thread
    can swap the reference atomically while an RPC thread changes a parameter.
    """

    calibration: Mat = field(default_factory=lambda: np.eye(6))
    K_l: Vec = field(default_factory=lambda: np.full(3, 10_000.0))
    K_r: Vec = field(default_factory=lambda: np.full(3, 50.0))
    R_es: Mat = field(default_factory=lambda: np.eye(3))
    p_es: Vec = field(default_factory=lambda: np.zeros(3))
    R_et: Mat = field(default_factory=lambda: np.eye(3))
    p_et: Vec = field(default_factory=lambda: np.array([0.0, 0.0, 0.2]))
    mode: RotationMode = "exact"
    R_st: Mat = field(init=False)
    p_st: Vec = field(init=False)
    calibration_inv: Mat = field(init=False)

    def __post_init__(self) -> None:
        cal = as_calibration(self.calibration)
        R_es = as_rotation(self.R_es, "R_es")
        R_et = as_rotation(self.R_et, "R_et")
        p_es = np.asarray(self.p_es, dtype=float).reshape(3)
        p_et = np.asarray(self.p_et, dtype=float).reshape(3)
        if not (np.all(np.isfinite(p_es)) and np.all(np.isfinite(p_et))):
            raise ValueError("p_es, p_et: not finite")
        if self.mode not in ("exact", "small_angle"):
            raise ValueError(f"mode: exact or small_angle, got {self.mode!r}")
        s = object.__setattr__
        s(self, "calibration", cal)
        s(self, "K_l", as_vec3(self.K_l, "K_l"))
        s(self, "K_r", as_vec3(self.K_r, "K_r"))
        s(self, "R_es", R_es)
        s(self, "p_es", p_es)
        s(self, "R_et", R_et)
        s(self, "p_et", p_et)
        s(self, "R_st", R_es.T @ R_et)
        s(self, "p_st", R_es.T @ (p_et - p_es))
        s(self, "calibration_inv", np.linalg.inv(cal))

    def with_tool(self, p_et: ArrayLike, R_et: ArrayLike) -> WristModel:
        """The same wrist with the tool placed at eMt = (R_et, p_et) in the flange frame."""
        return replace(self, p_et=np.asarray(p_et, dtype=float), R_et=np.asarray(R_et, dtype=float))

    def with_compliance(
        self,
        K_l: float | Sequence[float] | Vec | None = None,
        K_r: float | Sequence[float] | Vec | None = None,
    ) -> WristModel:
        """The same wrist with new stiffness diagonals (None keeps the current one)."""
        return replace(
            self,
            K_l=self.K_l if K_l is None else as_vec3(K_l, "K_l"),
            K_r=self.K_r if K_r is None else as_vec3(K_r, "K_r"),
        )

    def wrench_from_signals(self, signals: ArrayLike) -> tuple[Vec, Vec]:
        """Six sensing signals → (F_t (N), C_t (N·m)) at the tool point, tool frame: eq. (4)."""
        dS, dM = plate_motion(signals, self.calibration, self.mode)
        dT_t, dM_t = tool_deflection(dS, dM, self.R_st, self.p_st, self.mode)
        return tool_wrench(dT_t, dM_t, self.K_l, self.K_r, self.mode)

    def signals_from_wrench(self, F_t: ArrayLike, C_t: ArrayLike) -> Vec:
        """(F_t, C_t) at the tool point, tool frame → the six signals: eq. (4) inverted."""
        dT_t, dM_t = deflection_from_wrench(
            np.asarray(F_t, dtype=float),
            np.asarray(C_t, dtype=float),
            self.K_l,
            self.K_r,
            self.mode,
        )
        dS, dM = plate_motion_from_deflection(dT_t, dM_t, self.R_st, self.p_st)
        return signals_from_plate_motion(dS, dM, self.calibration_inv, self.mode)

    def wrench_from_sensor_wrench(self, F_s: ArrayLike, C_s: ArrayLike) -> tuple[Vec, Vec]:
        """A wrench measured at the sensor origin in R_s (a Net F/T) → at the tool point in R_t.

        F_t = M_t^s F_s,   C_t = M_t^s (C_s − s_p_t × F_s)
        """
        F = np.asarray(F_s, dtype=float)
        C = np.asarray(C_s, dtype=float)
        return self.R_st.T @ F, self.R_st.T @ (C - np.cross(self.p_st, F))

    def sensor_wrench_from_tool(self, F_t: ArrayLike, C_t: ArrayLike) -> tuple[Vec, Vec]:
        """Inverse of `wrench_from_sensor_wrench`: the wrench a sensor at R_s would read."""
        F_s = self.R_st @ np.asarray(F_t, dtype=float)
        return F_s, self.R_st @ np.asarray(C_t, dtype=float) + np.cross(self.p_st, F_s)
