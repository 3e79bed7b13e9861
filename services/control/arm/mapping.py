"""The teleoperation mapping on the slave side: operator command → target tool pose (PROTOCOL §2).

The master sends the operator's scaled motion since the current engagement (`dp`, `dR`), not a
per-tick increment, so a lost or reordered command causes no drift. The slave records the tool
pose (p0, R0) at the first active command of each engagement and maps every command of that
engagement to a target tool pose; `effector_target` turns it into the flange target for the
tool placement eMt. Frames: world R_w; tool R_t; `dR` is a rotation in the tool frame. Units: m.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import pinocchio as pin
from numpy.typing import NDArray

from services.geometry import TeleopFrame, tool_target_pose

Vec = NDArray[np.float64]


@dataclass(frozen=True, slots=True)
class TeleopInput:
    """The mapping's view of one OperatorCommand (PROTOCOL §3).

    `seq` strictly increases per master; `engage` never decreases; `active` is false during
    master-shift (hold). `dp` (3,) m is the translation since the engagement, in the world or
    the tool frame per `frame`; `dR` (3, 3) the rotation since the engagement, in the tool frame.
    The codec has already checked `dR` is a rotation; shapes and finiteness are checked here.
    """

    seq: int
    engage: int
    active: bool
    frame: TeleopFrame
    dp: Vec
    dR: Vec

    def __post_init__(self) -> None:
        dp = np.asarray(self.dp, dtype=np.float64)
        dR = np.asarray(self.dR, dtype=np.float64)
        # Checked on plain floats: one per command at up to 1 kHz, and a numpy reduction on
        # 3 or 9 values costs more than the checks.
        if dp.shape != (3,) or not all(map(math.isfinite, dp.tolist())):
            raise ValueError(f"dp must be 3 finite floats, got {self.dp!r}")
        if dR.shape != (3, 3) or not all(map(math.isfinite, dR.reshape(9).tolist())):
            raise ValueError(f"dR must be a finite 3x3 matrix, got {self.dR!r}")
        if self.frame not in ("world", "tool"):
            raise ValueError(f"frame must be 'world' or 'tool', got {self.frame!r}")
        object.__setattr__(self, "dp", dp)
        object.__setattr__(self, "dR", dR)


def effector_target(p_target: Vec, R_target: Vec, eMt: pin.SE3) -> pin.SE3:
    """The flange target oMe for a tool target, eMt = (R_et, p_et) (eqs. 1–3).

    M_w^e+ = R_target·R_etᵀ and E_w+ = p_target − M_w^e+·p_et. Relative to the engagement this
    is eq. (2), ΔE_w = M_w^t (I − ΔM_t) T_t + ΔT, and eq. (3) with the transpose the paper
    omits, ΔM_e = M_e^t ΔM_t (M_e^t)ᵀ; so a pure rotation turns the tool about the tool point.
    """
    R_e = np.asarray(R_target, dtype=np.float64) @ eMt.rotation.T
    return pin.SE3(R_e, np.asarray(p_target, dtype=np.float64) - R_e @ eMt.translation)


class TeleopMapping:
    """Per-master state of the mapping: the newest applied command and the engagement pose.

    `last_seq` (-1 before any) and `engage` (None before any active command) are what the last
    applied command carried; RobotState reports them as `cmd_seq` and `engage`. Called from the
    service's loop thread only.
    """

    def __init__(self) -> None:
        self.last_seq: int = -1
        self.engage: int | None = None
        self._p0: Vec | None = None
        self._R0: Vec | None = None

    def apply(self, cmd: TeleopInput, oMt_now: pin.SE3) -> pin.SE3 | None:
        """The target tool pose oMt for `cmd`, or None when the arm must hold.

        None for a command with a `seq` not above the last applied one or an `engage` below the
        current one (ignored: state unchanged), and for an inactive command (hold; its seq is
        recorded). The first active command of a new engagement records the current tool pose
        `oMt_now` as (p0, R0), so its target is the current pose moved by its own dp/dR.
        """
        if cmd.seq <= self.last_seq:
            return None
        if self.engage is not None and cmd.engage < self.engage:
            return None
        self.last_seq = cmd.seq
        if not cmd.active:
            return None
        if cmd.engage != self.engage:
            self._p0 = np.array(oMt_now.translation, dtype=np.float64)
            self._R0 = np.array(oMt_now.rotation, dtype=np.float64)
        elif self._p0 is None or self._R0 is None:
            # Re-based inside an engagement: dp/dR hold the operator's whole motion since the
            # engagement started, so the reference is chosen to map this command onto the
            # current pose (p0 = p_now − offset, R0 = R_now·dRᵀ) rather than jump by it.
            self._R0 = np.array(oMt_now.rotation, dtype=np.float64) @ cmd.dR.T
            offset = cmd.dp if cmd.frame == "world" else self._R0 @ cmd.dp
            self._p0 = np.array(oMt_now.translation, dtype=np.float64) - offset
        self.engage = cmd.engage
        p, R = tool_target_pose(self._p0, self._R0, cmd.dp, cmd.dR, cmd.frame)
        return pin.SE3(R, p)

    def rebase(self) -> None:
        """Forget the engagement pose: the next active command (even of the same engagement)
        re-records it from the then-current tool pose, so the arm does not jump after it was
        moved by something else (a joint move, a stop, a supervisor hold)."""
        self._p0 = None
        self._R0 = None
