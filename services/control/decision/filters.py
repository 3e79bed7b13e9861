"""The supervisor's math as pure functions: contact, admittance, limits (the operator target
and SO(3) are in services.geometry).

Frames: world R_w (the DH base frame, z up); tool R_t. Positions in m, rotations as 3×3
matrices (R world←tool) or rotation vectors (rad). Forces in N, moments in N·m; a
ForceSample gives them at the tool point in the tool frame, so the world force is
`f_w = tool_R · f_t`.
"""

from __future__ import annotations

from numpy.typing import ArrayLike

from services.geometry import V3, len3, v3

_TINY = 1e-12


# The per-command filters below work in plain floats (V3 tuples; numpy arrays are accepted):
# the decision runs them on every operator command.


def without_motion_into(inc: ArrayLike, normal: ArrayLike) -> tuple[V3, float]:
    """The contact filter: `inc` without its component into a contact.

    `normal` points out of the contact (along the force the environment applies to the tool,
    §2.1.4's F_t expressed in the same frame as `inc`). The component of `inc` along
    −normal is removed; motion along the surface or away from it is kept. Returns the
    filtered increment and the length removed (≥ 0).
    """
    vx, vy, vz = v = v3(inc)
    nx, ny, nz = v3(normal)
    norm = len3((nx, ny, nz))
    if norm < _TINY:
        return v, 0.0
    nx, ny, nz = nx / norm, ny / norm, nz / norm
    s = vx * nx + vy * ny + vz * nz
    if s >= 0.0:
        return v, 0.0
    return (vx - s * nx, vy - s * ny, vz - s * nz), -s


def deadband(v: ArrayLike, width: float) -> V3:
    """`v` shrunk by `width` along its direction (zero inside the band): the admittance
    ignores sensor noise and a small bias, and is continuous at the band's edge."""
    x, y, z = v3(v)
    n = len3((x, y, z))
    if n <= width or n < _TINY:
        return (0.0, 0.0, 0.0)
    k = (n - width) / n
    return (x * k, y * k, z * k)


def admittance_step(wrench: ArrayLike, gain: float, width: float, dt_s: float) -> V3:
    """Active compliance (§2.1.4, the wrench used "as supervisory function"): the target
    yields along the measured force, Δx = gain · deadband(F, width) · dt.

    For translation: F = f_w (N, world), gain in m/(N·s), Δx in m (world). For rotation:
    F = c_t (N·m, tool), gain in rad/(N·m·s), Δx a rotation vector in the tool frame."""
    x, y, z = deadband(wrench, width)
    k = gain * dt_s
    return (k * x, k * y, k * z)


def clip_norm(v: ArrayLike, max_norm: float) -> tuple[V3, bool]:
    """`v` scaled down to length `max_norm` if longer; and whether it was."""
    x, y, z = a = v3(v)
    n = len3(a)
    if n <= max_norm:
        return a, False
    k = max_norm / n
    return (x * k, y * k, z * k), True


def effective_box(lo: ArrayLike, hi: ArrayLike, p: ArrayLike) -> tuple[V3, V3]:
    """The workspace box grown, per axis, just enough to contain `p`.

    A target that starts outside the box (the arm was outside at engagement, or the box was
    just changed) may move towards it but never further out; once inside it stays inside.
    """
    (lx, ly, lz), (hx, hy, hz), (x, y, z) = v3(lo), v3(hi), v3(p)
    return (min(lx, x), min(ly, y), min(lz, z)), (max(hx, x), max(hy, y), max(hz, z))


def slow_near_box(
    p: V3, step: V3, lo: V3, hi: V3, zone_m: float, max_step_m: float
) -> tuple[V3, bool]:
    """`step` from `p` with its motion towards each face of the box [lo, hi] limited to
    `max_step_m` inside the `zone_m` next to that face (free up to the zone's edge); whether
    it was limited. Motion away from a face, or along it, is not touched; per axis, so the
    limit holds for each face whatever the direction of the step."""
    out = list(step)
    slowed = False
    for i in range(3):
        s = out[i]
        if s < 0.0:
            room = max(p[i] - lo[i] - zone_m, 0.0) + max_step_m
            if -s > room:
                out[i], slowed = -room, True
        elif s > 0.0:
            room = max(hi[i] - p[i] - zone_m, 0.0) + max_step_m
            if s > room:
                out[i], slowed = room, True
    return (out[0], out[1], out[2]), slowed


def clamp_box(p: ArrayLike, lo: ArrayLike, hi: ArrayLike) -> V3:
    """The point of the box [lo, hi] closest to `p` (the projection; it is non-expansive, so
    clamping a step that starts inside the box never lengthens it)."""
    (x, y, z), (lx, ly, lz), (hx, hy, hz) = v3(p), v3(lo), v3(hi)
    return (min(max(x, lx), hx), min(max(y, ly), hy), min(max(z, lz), hz))


def in_box(p: ArrayLike, lo: ArrayLike, hi: ArrayLike, tol: float = 0.0) -> bool:
    """Whether `p` lies in [lo − tol, hi + tol] on every axis."""
    (x, y, z), (lx, ly, lz), (hx, hy, hz) = v3(p), v3(lo), v3(hi)
    return lx - tol <= x <= hx + tol and ly - tol <= y <= hy + tol and lz - tol <= z <= hz + tol
