"""The system's geometry, once: SO(3) (skew/vee, exp/log, angles, slerp, quaternions), the
paper's Rxyz Euler angles and their inverse (eq. 5), the eq. 2–3 tool target, and the one
rotation-validity check of the contract.

Names say their frames, as in Pinocchio: `R_world_tool` is the tool frame R_t seen in the
world R_w (a vector v_tool maps to v_world = R_world_tool · v_tool), `p_world_tool` the tool
point in the world. Angles in rad, positions in m. Matrices are 3×3 numpy float arrays
unless a function says "row-major": those take and give 9 plain floats, for the per-message
paths (codec, ROS conversion) where a numpy call costs more than the arithmetic.

One pose, two forms: numpy `Array3`/`Mat3` (and Pinocchio's `pin.SE3`, 4×4) at the edges —
configuration, planning, drawing, the reference models; `V3`/`M9` tuples of floats, and
`PoseFloats` for a (p, R) pair, on the per-sample and per-command paths.

This module imports nothing from `services`: every layer, `services.bus` included, may use it.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from typing import Literal, cast

import numpy as np
from numpy.typing import ArrayLike, NDArray

Array3 = NDArray[np.float64]
"""A numpy 3-vector (the edges' form; `V3` is the per-message paths' form). Not the wire's
`services.bus.messages.Vec3`, which is a tuple of floats."""
Mat3 = NDArray[np.float64]
"""A numpy 3×3 matrix (`M9` is its row-major plain-float form)."""
TeleopFrame = Literal["world", "tool"]
Quat = tuple[float, float, float, float]
"""A unit quaternion, scalar first (w, x, y, z): viser's order (ROS's is `rosmsg.msgs.QuatXyzw`)."""

ROTATION_TOL = 1e-6
"""PROTOCOL.md conventions: a rotation with ‖RᵀR − I‖_F > 1e-6 or det R < 0 is rejected.
The one validity tolerance for every rotation received or configured."""

ORTHONORMAL_TOL = 1e-10
"""`orthonormalize` skips its SVD when ‖RᵀR − I‖_F is below this. A second tolerance on
purpose: it is not a validity test but a "nothing to repair" test, ≪ ROTATION_TOL so that a
product of many rotations is re-projected long before it could drift out of the contract,
and ≫ the ~1e-16 rounding of one product so that the SVD runs rarely."""

_SMALL_ANGLE_RAD = 1e-8
_GIMBAL_EPS = 1e-9
_TWO_SQRT2 = 2.0 * math.sqrt(2.0)


def _floats3(v: ArrayLike) -> tuple[float, float, float]:
    x, y, z = v.tolist() if isinstance(v, np.ndarray) else cast("Sequence[float]", v)
    return float(x), float(y), float(z)


def norm3(v: ArrayLike) -> float:
    """‖v‖ of a 3-vector, in plain floats (a numpy call costs more than the arithmetic)."""
    x, y, z = _floats3(v)
    return math.sqrt(x * x + y * y + z * z)


# --- rotation validity ------------------------------------------------------------------


def rotation_defect(r: Sequence[float]) -> tuple[float, float]:
    """(‖RᵀR − I‖_F, det R) of a row-major 3×3 `r`, in plain floats (no numpy)."""
    a, b, c, d, e, f, g, h, i = r
    # RᵀR is symmetric: its entries are the dot products of R's columns.
    n00 = a * a + d * d + g * g - 1.0
    n11 = b * b + e * e + h * h - 1.0
    n22 = c * c + f * f + i * i - 1.0
    n01 = a * b + d * e + g * h
    n02 = a * c + d * f + g * i
    n12 = b * c + e * f + h * i
    err = math.hypot(n00, n11, n22, n01, n01, n02, n02, n12, n12)
    det = a * (e * i - f * h) - b * (d * i - f * g) + c * (d * h - e * g)
    return err, det


def _row_major(R: ArrayLike) -> list[float] | None:
    """The 9 floats of a 3×3 R, or None when it has another shape."""
    m = np.asarray(R, dtype=float)
    if m.shape != (3, 3):
        return None
    out: list[float] = m.reshape(9).tolist()
    return out


def rotation_problem(R: ArrayLike, tol: float = ROTATION_TOL) -> str | None:
    """Why R is not a 3×3 proper rotation, or None (PROTOCOL conventions: finite,
    ‖RᵀR − I‖_F ≤ tol, det R ≥ 0). 9 row-major floats: `rotation_defect`."""
    r = _row_major(R)
    if r is None:
        return "not a 3x3 matrix"
    if not all(math.isfinite(x) for x in r):
        return "not finite"
    err, det = rotation_defect(r)
    if not err <= tol:  # NaN (opposite infinities in a product) is rejected too
        return f"not orthonormal (‖RᵀR − I‖ = {err:.3g} > {tol:g})"
    if not det >= 0.0:
        return "a reflection (det R < 0)"
    return None


def is_rotation(R: ArrayLike, tol: float = ROTATION_TOL) -> bool:
    """True when R is a finite proper rotation within `tol` (see `rotation_problem`)."""
    return rotation_problem(R, tol) is None


def orthonormalize(R: ArrayLike) -> Mat3:
    """The nearest proper rotation to R (SVD), so products of many small steps stay within
    the contract; R itself when it is already a rotation to within ORTHONORMAL_TOL."""
    m = np.asarray(R, dtype=float)
    err, det = rotation_defect(m.reshape(9).tolist())
    if err < ORTHONORMAL_TOL and det > 0.0:
        return m
    return _nearest_rotation(m)


def _nearest_rotation(m: Mat3) -> Mat3:
    u, _, vt = np.linalg.svd(m)
    d = np.sign(np.linalg.det(u @ vt)) or 1.0
    return np.asarray(u @ np.diag([1.0, 1.0, d]) @ vt, dtype=float)


# --- SO(3) ------------------------------------------------------------------------------


def skew(w: ArrayLike) -> Mat3:
    """[w]×, the 3×3 matrix with [w]×·v = w × v."""
    x, y, z = _floats3(w)
    return np.array([[0.0, -z, y], [z, 0.0, -x], [-y, x, 0.0]])


def vee(m: ArrayLike) -> Array3:
    """The vector of the skew-symmetric part of m (inverse of `skew`)."""
    a = np.asarray(m, dtype=float)
    return 0.5 * np.array([a[2, 1] - a[1, 2], a[0, 2] - a[2, 0], a[1, 0] - a[0, 1]])


def exp_so3(w: ArrayLike) -> Mat3:
    """The rotation by |w| rad about w/|w| (Rodrigues' formula, plain floats, exact)."""
    return np.array(exp9(_floats3(w))).reshape(3, 3)


def log_so3(R: ArrayLike) -> Array3:
    """The rotation vector w (axis·angle, |w| ≤ π) with exp_so3(w) == R."""
    r: list[float] = np.asarray(R, dtype=float).reshape(9).tolist()
    return np.array(log9(r))


def rotation_angle(R: ArrayLike) -> float:
    """The angle (rad, in [0, π]) of the rotation R."""
    (r00, r01, r02), (r10, r11, r12), (r20, r21, r22) = np.asarray(R, dtype=float).tolist()
    vx, vy, vz = r21 - r12, r02 - r20, r10 - r01
    return math.atan2(0.5 * math.sqrt(vx * vx + vy * vy + vz * vz), 0.5 * (r00 + r11 + r22 - 1.0))


def angle_between(R_a: ArrayLike, R_b: ArrayLike) -> float:
    """The angle (rad) of R_aᵀ·R_b, the rotation taking frame a to frame b, accurate for
    small angles: ‖R_a − R_b‖_F = 2√2·sin(θ/2)."""
    return angle9(m9(R_a), m9(R_b))


def slerp(R0: ArrayLike, R1: ArrayLike, u: float) -> Mat3:
    """Geodesic interpolation from R0 (u = 0) to R1 (u = 1)."""
    A = np.asarray(R0, dtype=float)
    B = np.asarray(R1, dtype=float)
    return np.asarray(A @ exp_so3(u * log_so3(A.T @ B)), dtype=float)


def rotation_about(axis: ArrayLike, angle_rad: float) -> Mat3:
    """The rotation by `angle_rad` about `axis` (any non-zero length)."""
    a = np.asarray(axis, dtype=float)
    return exp_so3(a * (angle_rad / norm3(a)))


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


# --- quaternions (Hamilton, scalar first: (w, x, y, z)) -------------------------------


def quat_of_rotation(r: Sequence[float]) -> Quat:
    """The unit quaternion (w, x, y, z), w ≥ 0, of a row-major rotation (Shepperd's method,
    stable for every angle; plain floats)."""
    m00, m01, m02, m10, m11, m12, m20, m21, m22 = r
    tr = m00 + m11 + m22
    if tr > 0.0:
        s = 2.0 * math.sqrt(tr + 1.0)
        x, y, z, w = (m21 - m12) / s, (m02 - m20) / s, (m10 - m01) / s, 0.25 * s
    elif m00 >= m11 and m00 >= m22:
        s = 2.0 * math.sqrt(max(1.0 + m00 - m11 - m22, 0.0))
        x, y, z, w = 0.25 * s, (m01 + m10) / s, (m02 + m20) / s, (m21 - m12) / s
    elif m11 >= m22:
        s = 2.0 * math.sqrt(max(1.0 + m11 - m00 - m22, 0.0))
        x, y, z, w = (m01 + m10) / s, 0.25 * s, (m12 + m21) / s, (m02 - m20) / s
    else:
        s = 2.0 * math.sqrt(max(1.0 + m22 - m00 - m11, 0.0))
        x, y, z, w = (m02 + m20) / s, (m12 + m21) / s, 0.25 * s, (m10 - m01) / s
    n = math.sqrt(x * x + y * y + z * z + w * w)
    k = (1.0 if w >= 0.0 else -1.0) / n
    return (k * w, k * x, k * y, k * z)


def rotation_of_quat(w: float, x: float, y: float, z: float) -> tuple[float, ...]:
    """The row-major rotation of the quaternion w + xi + yj + zk, normalised first (so one
    that drifted off unit length still gives a proper rotation). ValueError for a null or
    non-finite quaternion."""
    n = math.sqrt(w * w + x * x + y * y + z * z)
    if not math.isfinite(n) or n < 1e-9:
        raise ValueError("not a quaternion")
    w, x, y, z = w / n, x / n, y / n, z / n
    return (
        1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y),
        2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x),
        2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y),
    )  # fmt: skip


def wxyz_from_R(R: ArrayLike) -> NDArray[np.float64]:
    """`quat_of_rotation` of a 3×3 (or 9 row-major) R, as an array (w, x, y, z)."""
    return np.array(quat_of_rotation(np.asarray(R, dtype=float).reshape(9).tolist()))


def R_from_wxyz(wxyz: ArrayLike) -> Mat3:
    """`rotation_of_quat` of (w, x, y, z), as a 3×3 array."""
    w, x, y, z = np.asarray(wxyz, dtype=float).reshape(4).tolist()
    return np.array(rotation_of_quat(w, x, y, z)).reshape(3, 3)


# --- the paper's Rxyz (eq. 5) ---------------------------------------------------------


def rxyz(angles_rad: ArrayLike) -> Mat3:
    """The paper's Rxyz(a) = Rx(a_x)·Ry(a_y)·Rz(a_z) (§2.2.1, used by eq. 5)."""
    a = np.asarray(angles_rad, dtype=float)
    return rot_x(float(a[0])) @ rot_y(float(a[1])) @ rot_z(float(a[2]))


def _branch_from_ax(R: Mat3, ax: float) -> Array3:
    """Given a_x, the remaining angles follow exactly from Rx(a_x)ᵀ·R = Ry(a_y)·Rz(a_z)."""
    Q = rot_x(ax).T @ R
    ay = math.atan2(Q[0, 2], Q[2, 2])
    az = math.atan2(Q[1, 0], Q[1, 1])
    return np.array([ax, ay, az])


def rxyz_inv(R: ArrayLike) -> Array3:
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


def _unwrap_near(a: Array3, ref: Array3) -> Array3:
    return a + 2.0 * math.pi * np.round((ref - a) / (2.0 * math.pi))


def rxyz_inv_near(R: ArrayLike, near_rad: ArrayLike) -> Array3:
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


# --- plain floats: V3 and row-major M9 --------------------------------------------------
# The per-command paths (the decision's supervised target) in tuples of floats: on a
# 3-vector a numpy call costs more than the arithmetic. Same formulas as the numpy forms.

V3 = tuple[float, float, float]
M9 = tuple[float, float, float, float, float, float, float, float, float]
"""A 3×3 matrix as 9 floats, row-major."""
I9: M9 = (1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0)
PoseFloats = tuple[Sequence[float], Sequence[float]]
"""A frame's pose (p, R) as plain floats: p 3 floats (m), R 9 floats row-major — a (V3, M9),
or lists of the same numbers (the arm's tick builds them as lists: `Kinematics.se3_floats`)."""


def v3(v: ArrayLike) -> V3:
    """A V3 from any 3-vector (a 3-tuple is taken as it is)."""
    if type(v) is tuple and len(v) == 3:
        return cast(V3, v)
    return _floats3(v)


def m9(R: ArrayLike) -> M9:
    """An M9 from a 3×3 matrix or 9 row-major numbers."""
    if isinstance(R, np.ndarray):
        a, b, c, d, e, f, g, h, i = R.reshape(9).tolist()
    else:
        a, b, c, d, e, f, g, h, i = cast("Sequence[float]", R)
    return (
        float(a),
        float(b),
        float(c),
        float(d),
        float(e),
        float(f),
        float(g),
        float(h),
        float(i),
    )


def as_mat3(r: M9) -> Mat3:
    """The numpy 3×3 of an M9."""
    return np.array(r).reshape(3, 3)


def mul9(A: M9, B: M9) -> M9:
    """A·B."""
    a, b, c, d, e, f, g, h, i = A
    j, k, l, m, n, o, p, q, r = B
    return (
        a * j + b * m + c * p, a * k + b * n + c * q, a * l + b * o + c * r,
        d * j + e * m + f * p, d * k + e * n + f * q, d * l + e * o + f * r,
        g * j + h * m + i * p, g * k + h * n + i * q, g * l + h * o + i * r,
    )  # fmt: skip


def tmul9(A: M9, B: M9) -> M9:
    """Aᵀ·B."""
    a, b, c, d, e, f, g, h, i = A
    j, k, l, m, n, o, p, q, r = B
    return (
        a * j + d * m + g * p, a * k + d * n + g * q, a * l + d * o + g * r,
        b * j + e * m + h * p, b * k + e * n + h * q, b * l + e * o + h * r,
        c * j + f * m + i * p, c * k + f * n + i * q, c * l + f * o + i * r,
    )  # fmt: skip


def mv9(A: M9, v: V3) -> V3:
    """A·v."""
    a, b, c, d, e, f, g, h, i = A
    x, y, z = v
    return (a * x + b * y + c * z, d * x + e * y + f * z, g * x + h * y + i * z)


def add3(u: V3, v: V3) -> V3:
    return (u[0] + v[0], u[1] + v[1], u[2] + v[2])


def sub3(u: V3, v: V3) -> V3:
    return (u[0] - v[0], u[1] - v[1], u[2] - v[2])


def scale3(k: float, v: V3) -> V3:
    return (k * v[0], k * v[1], k * v[2])


def dot3(u: V3, v: V3) -> float:
    return u[0] * v[0] + u[1] * v[1] + u[2] * v[2]


def len3(v: V3) -> float:
    """‖v‖ of a V3 (`norm3` for any array-like)."""
    x, y, z = v
    return math.sqrt(x * x + y * y + z * z)


def finite9(r: Sequence[float]) -> bool:
    return all(math.isfinite(x) for x in r)


def ortho9(r: M9) -> M9:
    """`orthonormalize` of an M9: r itself when it is a rotation to within ORTHONORMAL_TOL
    (the arithmetic only), else the SVD."""
    err, det = rotation_defect(r)
    if err < ORTHONORMAL_TOL and det > 0.0:
        return r
    return m9(_nearest_rotation(as_mat3(r)))


def angle9(R_a: Sequence[float], R_b: Sequence[float]) -> float:
    """`angle_between` of two rotations as 9 row-major floats: the chord formula
    ‖R_a − R_b‖_F = 2√2·sin(θ/2)."""
    return 2.0 * math.asin(min(1.0, math.dist(R_a, R_b) / _TWO_SQRT2))


def exp9(w: V3) -> M9:
    """`exp_so3` as an M9: I + a·[w]× + b·[w]×², [w]×² = w wᵀ − |w|² I (Rodrigues)."""
    x, y, z = w
    angle = math.sqrt(x * x + y * y + z * z)
    if angle < _SMALL_ANGLE_RAD:
        a, b = 1.0, 0.5
    else:
        a, b = math.sin(angle) / angle, (1.0 - math.cos(angle)) / (angle * angle)
    xx, yy, zz, xy, xz, yz = x * x, y * y, z * z, x * y, x * z, y * z
    return (
        1.0 - b * (yy + zz), b * xy - a * z, b * xz + a * y,
        b * xy + a * z, 1.0 - b * (xx + zz), b * yz - a * x,
        b * xz - a * y, b * yz + a * x, 1.0 - b * (xx + yy),
    )  # fmt: skip


def log9(r: Sequence[float]) -> V3:
    """`log_so3` of 9 row-major floats: the rotation vector (axis·angle, |w| ≤ π)."""
    r00, r01, r02, r10, r11, r12, r20, r21, r22 = r
    vx, vy, vz = r21 - r12, r02 - r20, r10 - r01  # 2·sin θ·axis
    sin_t = 0.5 * math.sqrt(vx * vx + vy * vy + vz * vz)
    cos_t = 0.5 * (r00 + r11 + r22 - 1.0)
    angle = math.atan2(sin_t, cos_t)
    if angle < _GIMBAL_EPS:
        return (0.5 * vx, 0.5 * vy, 0.5 * vz)
    if angle < 0.75 * math.pi:
        k = angle / (2.0 * sin_t)
        return (k * vx, k * vy, k * vz)
    # Near π the antisymmetric part vanishes: take the axis from the symmetric part,
    # (R + Rᵀ)/2 = cos θ·I + (1 − cos θ)·a·aᵀ, and only its sign from the antisymmetric one.
    s01, s02, s12 = 0.5 * (r01 + r10), 0.5 * (r02 + r20), 0.5 * (r12 + r21)
    cols = (
        (r00 - cos_t, s01, s02),
        (s01, r11 - cos_t, s12),
        (s02, s12, r22 - cos_t),
    )
    j = max(range(3), key=lambda k: cols[k][k])  # the first largest, as np.argmax
    col = cols[j]
    axis = scale3(1.0 / math.sqrt(max(col[j], 1e-300)), col)
    axis = scale3(1.0 / len3(axis), axis)
    if dot3(axis, (vx, vy, vz)) < 0.0:
        axis = scale3(-1.0, axis)
    return scale3(angle, axis)


# --- the tool target of an operator command (eqs. 2–3, PROTOCOL §2) -------------------


def tool_target_point(
    p_world_tool0: ArrayLike, R_world_tool0: ArrayLike, dp: ArrayLike, frame: TeleopFrame
) -> Array3:
    """The tool point an operator command asks for (the paper's eq. 2, tool-point form):
    p0 + dp in frame "world" (ΔT_w), p0 + R0·dp in frame "tool" (M_w^t ΔT_t), where
    (p0, R0) = (p_world_tool0, R_world_tool0) is the tool pose at the engagement."""
    p0 = np.asarray(p_world_tool0, dtype=float).reshape(3)
    d = np.asarray(dp, dtype=float).reshape(3)
    if frame == "world":
        return p0 + d
    if frame == "tool":
        return np.asarray(p0 + np.asarray(R_world_tool0, dtype=float).reshape(3, 3) @ d)
    raise ValueError(f"frame must be 'world' or 'tool', got {frame!r}")


def tool_target_pose(
    p_world_tool0: ArrayLike,
    R_world_tool0: ArrayLike,
    dp: ArrayLike,
    dR_tool: ArrayLike,
    frame: TeleopFrame,
) -> tuple[Array3, Mat3]:
    """The tool pose (p_world_tool, R_world_tool) an operator command asks for, from the
    engagement pose (PROTOCOL §2): R = R0·dR (dR = ΔM_t, a rotation in the tool frame) and
    p as `tool_target_point`; eq. (3) gives the same tool rotation at the effector."""
    R0 = np.asarray(R_world_tool0, dtype=float).reshape(3, 3)
    p = tool_target_point(p_world_tool0, R0, dp, frame)
    return p, R0 @ np.asarray(dR_tool, dtype=float).reshape(3, 3)
