"""Rotation helpers for the master station: elementary rotations, the paper's Rxyz Euler
angles and their inverse (eq. 5), and the exponential map used to integrate hand rates.

All matrices are 3×3 numpy float arrays; angles in rad.
"""

from __future__ import annotations

import math

import numpy as np
from numpy.typing import ArrayLike, NDArray

Vec3 = NDArray[np.float64]
Mat3 = NDArray[np.float64]

ROTATION_TOL = 1e-6
"""PROTOCOL.md conventions: a rotation with ‖RᵀR − I‖ > 1e-6 or det R < 0 is rejected."""

_GIMBAL_EPS = 1e-9


def rot_x(angle_rad: float) -> Mat3:
    """Rotation about x by `angle_rad`."""
    c, s = math.cos(angle_rad), math.sin(angle_rad)
    return np.array([[1.0, 0.0, 0.0], [0.0, c, -s], [0.0, s, c]])


def rot_y(angle_rad: float) -> Mat3:
    """Rotation about y by `angle_rad`."""
    c, s = math.cos(angle_rad), math.sin(angle_rad)
    return np.array([[c, 0.0, s], [0.0, 1.0, 0.0], [-s, 0.0, c]])


def rot_z(angle_rad: float) -> Mat3:
    """Rotation about z by `angle_rad`."""
    c, s = math.cos(angle_rad), math.sin(angle_rad)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def rxyz(angles_rad: ArrayLike) -> Mat3:
    """The paper's Rxyz(a) = Rx(a_x)·Ry(a_y)·Rz(a_z) (§2.2.1, used by eq. 5)."""
    a = np.asarray(angles_rad, dtype=float)
    return rot_x(float(a[0])) @ rot_y(float(a[1])) @ rot_z(float(a[2]))


def _branch_from_ax(R: Mat3, ax: float) -> Vec3:
    """Given a_x, the remaining angles follow exactly from Rx(a_x)ᵀ·R = Ry(a_y)·Rz(a_z)."""
    Q = rot_x(ax).T @ R
    ay = math.atan2(Q[0, 2], Q[2, 2])
    az = math.atan2(Q[1, 0], Q[1, 1])
    return np.array([ax, ay, az])


def rxyz_inv(R: ArrayLike) -> Vec3:
    """Principal inverse of Rxyz (eq. 5): angles with a_y ∈ [−π/2, π/2], a_x, a_z ∈ (−π, π].

    At gimbal lock (a_y = ±π/2) only a_x ± a_z is defined; a_x = 0 is chosen.
    Rxyz(rxyz_inv(R)) == R for every rotation R.
    """
    M = np.asarray(R, dtype=float)
    ax = 0.0 if math.hypot(M[1, 2], M[2, 2]) < _GIMBAL_EPS else math.atan2(-M[1, 2], M[2, 2])
    a = _branch_from_ax(M, ax)
    # atan2 returns −π for (−0.0, negative); the branch is documented as (−π, π].
    a[[0, 2]] = np.where(a[[0, 2]] <= -math.pi, math.pi, a[[0, 2]])
    return a


def _unwrap_near(a: Vec3, ref: Vec3) -> Vec3:
    return a + 2.0 * math.pi * np.round((ref - a) / (2.0 * math.pi))


def rxyz_inv_near(R: ArrayLike, near_rad: ArrayLike) -> Vec3:
    """Inverse of Rxyz (eq. 5) on the branch closest to `near_rad`.

    Rxyz⁻¹ is multi-valued: (a_x, a_y, a_z) and (a_x + π, π − a_y, a_z + π), each up to 2π
    per angle, give the same R. Tracking the branch closest to the previous tick's angles
    keeps the scaled rotation Rxyz(s·a) continuous while the hand turns past ±180° about
    x or z or past ±90° about y; at s = 1 every branch gives the same dR.
    """
    M = np.asarray(R, dtype=float)
    ref = np.asarray(near_rad, dtype=float)
    if math.hypot(M[1, 2], M[2, 2]) < _GIMBAL_EPS:
        candidates = [_branch_from_ax(M, float(ref[0]))]
    else:
        ax = math.atan2(-M[1, 2], M[2, 2])
        candidates = [_branch_from_ax(M, ax), _branch_from_ax(M, ax + math.pi)]
    unwrapped = [_unwrap_near(c, ref) for c in candidates]
    return min(unwrapped, key=lambda c: float(np.sum((c - ref) ** 2)))


def skew(w: ArrayLike) -> Mat3:
    """[w]× such that [w]×·v = w × v."""
    x, y, z = (float(v) for v in np.asarray(w, dtype=float))
    return np.array([[0.0, -z, y], [z, 0.0, -x], [-y, x, 0.0]])


def exp_so3(w: ArrayLike) -> Mat3:
    """Rodrigues' formula: the rotation by |w| rad about w/|w| (exact, no small-angle error)."""
    v = np.asarray(w, dtype=float)
    theta = float(np.linalg.norm(v))
    K = skew(v)
    if theta < 1e-12:
        return np.eye(3) + K
    return (
        np.eye(3) + (math.sin(theta) / theta) * K + ((1.0 - math.cos(theta)) / theta**2) * (K @ K)
    )


def log_so3(R: ArrayLike) -> Vec3:
    """Rotation vector w (axis·angle, |w| ≤ π) with exp_so3(w) == R."""
    M = np.asarray(R, dtype=float)
    vee = np.array([M[2, 1] - M[1, 2], M[0, 2] - M[2, 0], M[1, 0] - M[0, 1]])
    sin_t = 0.5 * float(np.linalg.norm(vee))
    cos_t = 0.5 * (float(np.trace(M)) - 1.0)
    theta = math.atan2(sin_t, cos_t)
    if theta < 1e-9:
        return 0.5 * vee
    if theta < 0.75 * math.pi:
        return (theta / (2.0 * sin_t)) * vee
    # Near π the antisymmetric part vanishes: take the axis from the symmetric part,
    # (R + Rᵀ)/2 = cos θ·I + (1 − cos θ)·a·aᵀ, and only its sign from the antisymmetric one.
    aaT = (0.5 * (M + M.T) - cos_t * np.eye(3)) / (1.0 - cos_t)
    i = int(np.argmax(np.diag(aaT)))
    axis = aaT[:, i] / math.sqrt(max(float(aaT[i, i]), 1e-300))
    axis /= np.linalg.norm(axis)
    if float(np.dot(axis, vee)) < 0.0:
        axis = -axis
    return theta * axis


def rotation_angle(R: ArrayLike) -> float:
    """Angle (rad, in [0, π]) of the rotation R."""
    M = np.asarray(R, dtype=float)
    vee = np.array([M[2, 1] - M[1, 2], M[0, 2] - M[2, 0], M[1, 0] - M[0, 1]])
    return math.atan2(0.5 * float(np.linalg.norm(vee)), 0.5 * (float(np.trace(M)) - 1.0))


def orthonormalize(R: ArrayLike) -> Mat3:
    """Nearest rotation to R (SVD), to stop round-off drift in integrated orientations."""
    U, _, Vt = np.linalg.svd(np.asarray(R, dtype=float))
    Q = U @ Vt
    if np.linalg.det(Q) < 0.0:
        U[:, -1] = -U[:, -1]
        Q = U @ Vt
    return np.asarray(Q, dtype=float)


def is_rotation(R: ArrayLike, tol: float = ROTATION_TOL) -> bool:
    """True when R is 3×3, finite, ‖RᵀR − I‖ ≤ tol and det R > 0 (PROTOCOL.md conventions)."""
    M = np.asarray(R, dtype=float)
    if M.shape != (3, 3) or not np.all(np.isfinite(M)):
        return False
    return bool(np.linalg.norm(M.T @ M - np.eye(3)) <= tol and np.linalg.det(M) > 0.0)


def slerp(R0: ArrayLike, R1: ArrayLike, u: float) -> Mat3:
    """Geodesic interpolation from R0 (u = 0) to R1 (u = 1)."""
    A = np.asarray(R0, dtype=float)
    B = np.asarray(R1, dtype=float)
    return np.asarray(A @ exp_so3(u * log_so3(A.T @ B)), dtype=float)


def rot_from_quat(w: float, x: float, y: float, z: float) -> Mat3:
    """The rotation of the quaternion w + xi + yj + zk (Hamilton, scalar first), normalised
    first: exp of the rotation vector 2·atan2(|v|, w)·v/|v|. ValueError for a null or
    non-finite quaternion."""
    q = np.array([w, x, y, z], dtype=float)
    norm = float(np.linalg.norm(q))
    if not math.isfinite(norm) or norm < 1e-9:
        raise ValueError("not a quaternion")
    v = q[1:] / norm
    sin_half = float(np.linalg.norm(v))
    if sin_half < 1e-15:
        return np.eye(3)
    angle = 2.0 * math.atan2(sin_half, q[0] / norm)
    return exp_so3(v * (angle / sin_half))
