"""The supervisor's math as pure functions: contact, admittance, limits (the operator target
and SO(3) are in services.geometry).

Frames: world R_w (the DH base frame, z up); tool R_t. Positions in m, rotations as 3×3
matrices (R world←tool) or rotation vectors (rad). Forces in N, moments in N·m; a
ForceSample gives them at the tool point in the tool frame, so the world force is
`f_w = tool_R · f_t`.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike, NDArray

from services.geometry import norm3, orthonormalize

Vec = NDArray[np.float64]
Mat = NDArray[np.float64]

_TINY = 1e-12


def engagement_command(p0: ArrayLike, R0: ArrayLike, p: ArrayLike, R: ArrayLike) -> tuple[Vec, Mat]:
    """The world-frame (dp, dR) that makes a §2 slave with engagement pose (p0, R0) go to
    the tool pose (p, R): the inverse of `tool_target_pose`, dp = p − p0, dR = R0ᵀ·R."""
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
