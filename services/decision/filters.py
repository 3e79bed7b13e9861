"""The supervisor's math as pure functions: operator target, contact, admittance, limits.

Frames: world R_w (the DH base frame, z up); tool R_t. Positions in m, rotations as 3×3
matrices (R world←tool) or rotation vectors (rad). Forces in N, moments in N·m; a
ForceSample gives them at the tool point in the tool frame, so the world force is
`f_w = tool_R · f_t`.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from typing import Literal

import numpy as np
from numpy.typing import ArrayLike, NDArray

Vec = NDArray[np.float64]
Mat = NDArray[np.float64]
TeleopFrame = Literal["world", "tool"]

_I3 = np.eye(3)
_TINY = 1e-12
ORTHO_TOL = 1e-10
"""`orthonormalize` leaves a matrix alone when ‖RᵀR − I‖_max is below this (≪ the 1e-6 of
the contract): the rounding of one product of rotations is ~1e-16."""


def _floats3(v: Vec | Sequence[float]) -> tuple[float, float, float]:
    x, y, z = v.tolist() if isinstance(v, np.ndarray) else v
    return float(x), float(y), float(z)


def norm3(v: Vec | Sequence[float]) -> float:
    """‖v‖ of a 3-vector, in plain floats (a numpy call costs more than the arithmetic)."""
    x, y, z = _floats3(v)
    return math.sqrt(x * x + y * y + z * z)


def skew(v: ArrayLike) -> Mat:
    """[v]×, the 3×3 matrix with [v]× u = v × u."""
    x, y, z = np.asarray(v, dtype=float)
    return np.array([[0.0, -z, y], [z, 0.0, -x], [-y, x, 0.0]])


def exp_so3(w: Vec | Sequence[float]) -> Mat:
    """The rotation of rotation vector `w` (rad), Rodrigues' formula (plain floats)."""
    x, y, z = _floats3(w)
    angle = math.sqrt(x * x + y * y + z * z)
    if angle < 1e-8:
        a, b = 1.0, 0.5
    else:
        a, b = math.sin(angle) / angle, (1.0 - math.cos(angle)) / (angle * angle)
    # I + a·[w]× + b·[w]×², with [w]×² = w wᵀ − |w|² I
    xx, yy, zz, xy, xz, yz = x * x, y * y, z * z, x * y, x * z, y * z
    return np.array(
        [
            [1.0 - b * (yy + zz), b * xy - a * z, b * xz + a * y],
            [b * xy + a * z, 1.0 - b * (xx + zz), b * yz - a * x],
            [b * xz - a * y, b * yz + a * x, 1.0 - b * (xx + yy)],
        ]
    )


def log_so3(R: ArrayLike) -> Vec:
    """The rotation vector (rad, angle in [0, π]) of rotation matrix `R`."""
    r = np.asarray(R, dtype=float)
    (r00, r01, r02), (r10, r11, r12), (r20, r21, r22) = r.tolist()
    cos = min(1.0, max(-1.0, 0.5 * (r00 + r11 + r22 - 1.0)))
    angle = math.acos(cos)
    wx, wy, wz = 0.5 * (r21 - r12), 0.5 * (r02 - r20), 0.5 * (r10 - r01)
    if angle < 1e-8:
        return np.array([wx, wy, wz])
    if angle < math.pi - 1e-4:
        k = angle / math.sin(angle)
        return np.array([k * wx, k * wy, k * wz])
    w = np.array([wx, wy, wz])
    # Near π the antisymmetric part vanishes: take the axis from the symmetric part.
    aat = 0.5 * (r + r.T) - cos * _I3
    j = int(np.argmax(np.diag(aat)))
    axis = aat[:, j] / math.sqrt(max(float(aat[j, j]), 1e-300))
    axis = axis / np.linalg.norm(axis)
    if float(axis @ w) < 0.0:
        axis = -axis
    return angle * axis


def _is_rotation(r: Mat, tol: float) -> bool:
    """max |RᵀR − I| < tol and det R > 0, in plain floats."""
    (a, b, c), (d, e, f), (g, h, i) = r.tolist()
    err = max(
        abs(a * a + d * d + g * g - 1.0),
        abs(b * b + e * e + h * h - 1.0),
        abs(c * c + f * f + i * i - 1.0),
        abs(a * b + d * e + g * h),
        abs(a * c + d * f + g * i),
        abs(b * c + e * f + h * i),
    )
    det = a * (e * i - f * h) - b * (d * i - f * g) + c * (d * h - e * g)
    return err < tol and det > 0.0


def orthonormalize(R: ArrayLike) -> Mat:
    """The nearest proper rotation to `R` (SVD), so products of many small steps stay
    within the contract's ‖RᵀR − I‖ ≤ 1e-6."""
    r = np.asarray(R, dtype=float)
    if _is_rotation(r, ORTHO_TOL):
        return r  # already a rotation to well within the contract: skip the SVD
    u, _, vt = np.linalg.svd(r)
    d = np.sign(np.linalg.det(u @ vt)) or 1.0
    return np.asarray(u @ np.diag([1.0, 1.0, d]) @ vt, dtype=float)


def operator_target(
    p0: ArrayLike, R0: ArrayLike, dp: ArrayLike, dR: ArrayLike, frame: TeleopFrame
) -> tuple[Vec, Mat]:
    """The operator's desired tool pose from the engagement pose (p0, R0) (PROTOCOL §2).

    R = R0·dR (dR = ΔM_t, a rotation in the tool frame); p = p0 + dp in "world" mode (ΔT_w)
    or p0 + R0·dp in "tool" mode (M_w^t ΔT_t): the tool-point form of the paper's eq. (2),
    with eq. (3) giving the same tool rotation at the effector.
    """
    p0 = np.asarray(p0, dtype=float)
    R0 = np.asarray(R0, dtype=float)
    dp = np.asarray(dp, dtype=float)
    R = R0 @ np.asarray(dR, dtype=float)
    if frame == "world":
        return p0 + dp, R
    if frame == "tool":
        return p0 + R0 @ dp, R
    raise ValueError(f"frame must be 'world' or 'tool', got {frame!r}")


def engagement_command(p0: ArrayLike, R0: ArrayLike, p: ArrayLike, R: ArrayLike) -> tuple[Vec, Mat]:
    """The world-frame (dp, dR) that makes a §2 slave with engagement pose (p0, R0) go to
    the tool pose (p, R): the inverse of `operator_target`, dp = p − p0, dR = R0ᵀ·R."""
    R0 = np.asarray(R0, dtype=float)
    dR = orthonormalize(R0.T @ np.asarray(R, dtype=float))
    return np.asarray(p, dtype=float) - np.asarray(p0, dtype=float), dR


def without_motion_into(inc: ArrayLike, normal: ArrayLike) -> tuple[Vec, float]:
    """The contact filter: `inc` without its component into a contact.

    `normal` points out of the contact (along the force the environment applies to the tool,
    §2.1.4's F_t expressed in the same frame as `inc`). The component of `inc` along
    −normal is removed; motion along the surface or away from it is kept. Returns the
    filtered increment and the length removed (≥ 0).
    """
    v = np.asarray(inc, dtype=float)
    n = np.asarray(normal, dtype=float)
    norm = norm3(n)
    if norm < _TINY:
        return v.copy(), 0.0
    n = n / norm
    s = float(v @ n)
    if s >= 0.0:
        return v.copy(), 0.0
    return v - s * n, -s


def deadband(v: ArrayLike, width: float) -> Vec:
    """`v` shrunk by `width` along its direction (zero inside the band): the admittance
    ignores sensor noise and a small bias, and is continuous at the band's edge."""
    a = np.asarray(v, dtype=float)
    n = norm3(a)
    if n <= width or n < _TINY:
        return np.zeros_like(a)
    return a * ((n - width) / n)


def admittance_step(wrench: ArrayLike, gain: float, width: float, dt_s: float) -> Vec:
    """Active compliance (§2.1.4, the wrench used "as supervisory function"): the target
    yields along the measured force, Δx = gain · deadband(F, width) · dt.

    For translation: F = f_w (N, world), gain in m/(N·s), Δx in m (world). For rotation:
    F = c_t (N·m, tool), gain in rad/(N·m·s), Δx a rotation vector in the tool frame."""
    return gain * dt_s * deadband(wrench, width)


def clip_norm(v: ArrayLike, max_norm: float) -> tuple[Vec, bool]:
    """`v` scaled down to length `max_norm` if longer; and whether it was."""
    a = np.asarray(v, dtype=float)
    n = norm3(a)
    if n <= max_norm:
        return a.copy(), False
    return a * (max_norm / n), True


def effective_box(lo: ArrayLike, hi: ArrayLike, p: ArrayLike) -> tuple[Vec, Vec]:
    """The workspace box grown, per axis, just enough to contain `p`.

    A target that starts outside the box (the arm was outside at engagement, or the box was
    just changed) may move towards it but never further out; once inside it stays inside.
    """
    pp = np.asarray(p, dtype=float)
    return np.minimum(np.asarray(lo, dtype=float), pp), np.maximum(np.asarray(hi, dtype=float), pp)


def clamp_box(p: ArrayLike, lo: ArrayLike, hi: ArrayLike) -> Vec:
    """The point of the box [lo, hi] closest to `p` (the projection; it is non-expansive, so
    clamping a step that starts inside the box never lengthens it)."""
    return np.clip(
        np.asarray(p, dtype=float), np.asarray(lo, dtype=float), np.asarray(hi, dtype=float)
    )


def in_box(p: ArrayLike, lo: ArrayLike, hi: ArrayLike, tol: float = 0.0) -> bool:
    """Whether `p` lies in [lo − tol, hi + tol] on every axis."""
    a = np.asarray(p, dtype=float)
    return bool(
        np.all(a >= np.asarray(lo, dtype=float) - tol)
        and np.all(a <= np.asarray(hi, dtype=float) + tol)
    )
