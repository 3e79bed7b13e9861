"""Poses of what the console's 3D view draws, from the bus messages: a cylinder between two
points, the force arrow, the workspace box's edges, the hand; pure geometry.

Frames: world R_w (the arm's base frame, z up, m); rotations are 3×3 matrices or unit
quaternions `wxyz` (w first, viser's convention). Nothing here touches the bus or the page.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike, NDArray

from services.geometry import Array3, Mat3, R_from_wxyz, wxyz_from_R

MIN_SEGMENT_M = 1e-6


def rotation_z_to(direction: ArrayLike) -> Mat3:
    """A rotation whose z axis is `direction` (any non-zero length; identity for a null
    one): how a cylinder along its local z is turned to join two points (a skeleton's
    link, the tool). The twist about z is arbitrary (a cylinder does not show it); the x
    axis is taken square to the world axis least aligned with `direction`, which is
    accurate for every direction, antiparallel to z included."""
    d = np.asarray(direction, dtype=float).reshape(3)
    n = float(np.linalg.norm(d))
    if n < MIN_SEGMENT_M:
        return np.eye(3)
    z = d / n
    helper = np.zeros(3)
    helper[int(np.argmin(np.abs(z)))] = 1.0
    x = np.cross(helper, z)
    x /= np.linalg.norm(x)
    return np.column_stack([x, np.cross(z, x), z])


def cylinder_pose(a: ArrayLike, b: ArrayLike) -> tuple[Array3, NDArray[np.float64], float]:
    """(centre, wxyz, length) of a cylinder along local z drawn from point a to point b."""
    pa = np.asarray(a, dtype=float).reshape(3)
    pb = np.asarray(b, dtype=float).reshape(3)
    d = pb - pa
    return 0.5 * (pa + pb), wxyz_from_R(rotation_z_to(d)), float(np.linalg.norm(d))


def force_arrow(
    tool_p: ArrayLike, tool_R: ArrayLike, f_tool: ArrayLike, m_per_n: float, max_len_m: float
) -> NDArray[np.float64]:
    """The force at the tool point as an arrow (2, 3), m, world: from the tool point along
    f_world = R_wt · f_tool (a ForceSample is in the tool frame), `m_per_n` long per newton,
    clipped to `max_len_m` (direction kept)."""
    p = np.asarray(tool_p, dtype=float).reshape(3)
    f_w = np.asarray(tool_R, dtype=float).reshape(3, 3) @ np.asarray(f_tool, dtype=float).reshape(3)
    v = m_per_n * f_w
    n = float(np.linalg.norm(v))
    if n > max_len_m:
        v *= max_len_m / n
    return np.stack([p, p + v])


def box_edges(lo: ArrayLike, hi: ArrayLike) -> NDArray[np.float64]:
    """The 12 edges (12, 2, 3) of the axis-aligned box [lo, hi] (m, world), e.g. the
    supervisor's workspace box: the corners differing in exactly one coordinate."""
    a = np.asarray(lo, dtype=float).reshape(3)
    b = np.asarray(hi, dtype=float).reshape(3)
    corners = [np.where([(i >> k) & 1 for k in range(3)], b, a) for i in range(8)]
    edges = [
        (corners[i], corners[i | (1 << k)]) for i in range(8) for k in range(3) if not i & (1 << k)
    ]
    return np.array(edges, dtype=float)


def hand_pose(position: ArrayLike, wxyz: ArrayLike) -> tuple[Array3, Mat3]:
    """The virtual master's hand pose (p (3,), R (3, 3), world) from the gizmo's pose: the
    hand IS the gizmo, so with scale 1, frame world and the hand engaged at the tool pose,
    eq. 5 and §2 make the tool target equal the gizmo pose."""
    return np.asarray(position, dtype=float).reshape(3).copy(), R_from_wxyz(wxyz)
