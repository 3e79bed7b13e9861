"""Kinematics of a 6-joint master arm from a standard DH table.

Convention as PROTOCOL.md §1: A_i = Rz(q_i)·Tz(d_i)·Tx(a_i)·Rx(α_i), no joint offsets. The
master's base frame (DH frame 0) is the operator frame the hand pose is given in; the hand
point is the origin of DH frame 6 (put a handle offset in d_6).
"""

from __future__ import annotations

import math

import numpy as np
from numpy.typing import ArrayLike, NDArray

DhRow = tuple[float, float, float]
"""One DH row: (d_m, a_m, alpha_rad)."""

DEFAULT_MASTER_DH: tuple[DhRow, ...] = (
    (0.15, 0.0, math.pi / 2),
    (0.0, 0.20, 0.0),
    (0.0, 0.0, math.pi / 2),
    (0.20, 0.0, -math.pi / 2),
    (0.0, 0.0, math.pi / 2),
    (0.06, 0.0, 0.0),
)
"""A desk-sized elbow arm with a spherical wrist: 0.15 m column, 0.20 m upper arm and
forearm, the handle 0.06 m beyond the wrist centre. Replace it with the table of the arm
you build (`MasterConfig.arm_dh`)."""


def dh_transform(q_rad: float, d_m: float, a_m: float, alpha_rad: float) -> NDArray[np.float64]:
    """A_i = Rz(q)·Tz(d)·Tx(a)·Rx(α) as a 4×4 homogeneous matrix."""
    cq, sq = math.cos(q_rad), math.sin(q_rad)
    ca, sa = math.cos(alpha_rad), math.sin(alpha_rad)
    return np.array(
        [
            [cq, -sq * ca, sq * sa, a_m * cq],
            [sq, cq * ca, -cq * sa, a_m * sq],
            [0.0, sa, ca, d_m],
            [0.0, 0.0, 0.0, 1.0],
        ]
    )


def _frames(q_rad: ArrayLike, dh: tuple[DhRow, ...]) -> list[NDArray[np.float64]]:
    q = np.asarray(q_rad, dtype=float)
    if q.shape != (len(dh),):
        raise ValueError(f"q must have {len(dh)} joints, got shape {q.shape}")
    T = np.eye(4)
    out = [T]
    for qi, (d, a, alpha) in zip(q, dh, strict=True):
        T = T @ dh_transform(float(qi), d, a, alpha)
        out.append(T)
    return out


def forward_kinematics(
    q_rad: ArrayLike, dh: tuple[DhRow, ...] = DEFAULT_MASTER_DH
) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """Hand pose in the master base frame: (p (3,) m, R (3, 3)) of DH frame 6."""
    T = _frames(q_rad, dh)[-1]
    return T[:3, 3].copy(), T[:3, :3].copy()


def geometric_jacobian(
    q_rad: ArrayLike, dh: tuple[DhRow, ...] = DEFAULT_MASTER_DH
) -> NDArray[np.float64]:
    """6×n Jacobian at the hand point, base-frame aligned: [v; ω] = J·q̇.

    Column i (revolute joint i about z_{i−1}): [z_{i−1} × (o_n − o_{i−1}); z_{i−1}].
    """
    frames = _frames(q_rad, dh)
    o_n = frames[-1][:3, 3]
    J = np.zeros((6, len(dh)))
    for i, T in enumerate(frames[:-1]):
        z = T[:3, 2]
        J[:3, i] = np.cross(z, o_n - T[:3, 3])
        J[3:, i] = z
    return J


def joint_torques_for_wrench(
    q_rad: ArrayLike,
    force_n: ArrayLike,
    torque_nm: ArrayLike,
    dh: tuple[DhRow, ...] = DEFAULT_MASTER_DH,
) -> NDArray[np.float64]:
    """τ = Jᵀ·[f; c]: joint torques (N·m) that make the hand push with force f (N) and moment
    c (N·m), both in the master base frame, at the hand point (static duality)."""
    F = np.concatenate([np.asarray(force_n, dtype=float), np.asarray(torque_nm, dtype=float)])
    if F.shape != (6,):
        raise ValueError("force and torque must have 3 components each")
    return geometric_jacobian(q_rad, dh).T @ F
