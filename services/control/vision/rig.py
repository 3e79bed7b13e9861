"""Pinhole geometry of a rectified stereo rig (pure numpy, no OpenCV).

Frames: world R_w (the DH base frame, z up, m). Each eye's camera frame follows OpenCV:
x right, y down, z forward along the optical axis; `wRc` holds those axes as columns in
world coordinates. Both eyes share `wRc`; the right eye sits `baseline_m` further along the
rig's x axis than the left one, so a point at depth Z (m, along z) appears `fx·B/Z` pixels
further right in the left image than in the right one (the disparity).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray

from services.control.vision.camera import Intrinsics
from services.control.vision.config import VisionConfig

F64 = NDArray[np.float64]

WORLD_UP = np.array([0.0, 0.0, 1.0])


@dataclass(frozen=True, slots=True, eq=False)
class PinholeCamera:
    """One eye: optical centre `position_m` (world, m), orientation `wRc` (see module doc),
    `intrinsics` (px) and image size `width` × `height` (px)."""

    position_m: F64
    wRc: F64
    intrinsics: Intrinsics
    width: int
    height: int

    def to_camera(self, p_world: ArrayLike) -> F64:
        """World points (N, 3) or (3,) → camera-frame points, same shape (m)."""
        return (np.asarray(p_world, dtype=np.float64) - self.position_m) @ self.wRc

    def project_camera(self, p_cam: ArrayLike) -> F64:
        """Camera-frame points (N, 3) with z > 0 → pixel coordinates (N, 2).

        The pinhole model: u = fx·x/z + cx, v = fy·y/z + cy.
        """
        p = np.asarray(p_cam, dtype=np.float64).reshape(-1, 3)
        k = self.intrinsics
        z = p[:, 2]
        return np.stack([k.fx * p[:, 0] / z + k.cx, k.fy * p[:, 1] / z + k.cy], axis=1)

    def project(self, p_world: ArrayLike) -> tuple[F64, F64]:
        """World points (N, 3) → (pixel coordinates (N, 2), depth z (N,) in m).

        Points with z ≤ 0 are behind the camera; their pixel coordinates are meaningless.
        """
        p = self.to_camera(np.asarray(p_world, dtype=np.float64).reshape(-1, 3))
        with np.errstate(divide="ignore", invalid="ignore"):
            return self.project_camera(p), p[:, 2]

    def pixel_rays(self, supersample: int = 1) -> F64:
        """Ray directions (H·s, W·s, 3) in world for every (sub)pixel centre, scaled so that
        their camera-frame z is 1: a point at depth z along pixel (i, j) is
        `position_m + z · rays[i, j]`."""
        s = supersample
        k = self.intrinsics
        u = (np.arange(self.width * s) + 0.5) / s - 0.5
        v = (np.arange(self.height * s) + 0.5) / s - 0.5
        x = (u - k.cx) / k.fx
        y = (v - k.cy) / k.fy
        d_cam = np.empty((v.size, u.size, 3))
        d_cam[:, :, 0] = x[None, :]
        d_cam[:, :, 1] = y[:, None]
        d_cam[:, :, 2] = 1.0
        return d_cam @ self.wRc.T


@dataclass(frozen=True, slots=True, eq=False)
class StereoRig:
    """Two `PinholeCamera`s sharing orientation, optical centres `baseline_m` apart."""

    left: PinholeCamera
    right: PinholeCamera
    baseline_m: float

    @property
    def intrinsics(self) -> Intrinsics:
        return self.left.intrinsics

    @property
    def center_m(self) -> F64:
        """The midpoint of the two optical centres (world, m)."""
        return 0.5 * (self.left.position_m + self.right.position_m)

    @property
    def wRc(self) -> F64:
        return self.left.wRc

    @classmethod
    def look_at(
        cls,
        position_m: ArrayLike,
        target_m: ArrayLike,
        baseline_m: float,
        intrinsics: Intrinsics,
        width: int,
        height: int,
    ) -> StereoRig:
        """A rig centred at `position_m` looking at `target_m` (world, m), x axis horizontal.

        The optical axis z points from the centre to the target; x = z × up (to the right
        of a viewer standing upright) and y = z × x (down). The eyes sit at ∓baseline/2
        along x.
        """
        pos = np.asarray(position_m, dtype=np.float64)
        z = np.asarray(target_m, dtype=np.float64) - pos
        z /= np.linalg.norm(z)
        x = np.cross(z, WORLD_UP)
        nx = float(np.linalg.norm(x))
        if nx < 1e-9:
            raise ValueError("the rig cannot look straight up or down")
        x /= nx
        y = np.cross(z, x)
        wRc = np.stack([x, y, z], axis=1)
        half = 0.5 * baseline_m * x
        return cls(
            PinholeCamera(pos - half, wRc, intrinsics, width, height),
            PinholeCamera(pos + half, wRc.copy(), intrinsics, width, height),
            float(baseline_m),
        )

    @classmethod
    def from_config(cls, config: VisionConfig) -> StereoRig:
        """The rig `config` describes (`rig_position_m`, `rig_target_m`, `baseline_m`,
        `intrinsics` or else `fov_deg`, `width`, `height`)."""
        k = (
            Intrinsics(*config.intrinsics)
            if config.intrinsics is not None
            else Intrinsics.from_fov(config.width, config.height, config.fov_deg)
        )
        return cls.look_at(
            config.rig_position_m,
            config.rig_target_m,
            config.baseline_m,
            k,
            config.width,
            config.height,
        )

    def depth_m(self, p_world: ArrayLike) -> F64:
        """Depth (m) of world points along the shared optical axis: the same for both eyes."""
        return self.left.to_camera(p_world)[..., 2]

    def disparity_px(self, p_world: ArrayLike) -> F64:
        """Predicted disparity u_left − u_right (px) = fx·B/Z of world points."""
        return self.intrinsics.fx * self.baseline_m / self.depth_m(p_world)
