"""The teleoperation core: the paper's eq. 5 and the master-shift (clutch) state machine.

Per PROTOCOL.md §2 the master sends, at each tick, the operator's scaled motion since the
current engagement (not a per-tick increment), so a lost or reordered command causes no
drift. The slave applies `R_target = R0·dR` and `p_target = p0 + dp` (world) or
`p0 + R0·dp` (tool), with (p0, R0) its tool pose at the first command of the engagement.
"""

from __future__ import annotations

import threading
import time
from dataclasses import dataclass
from typing import cast

import numpy as np
from numpy.typing import ArrayLike

from services.bus.messages import MasterState, OperatorCommand
from services.control.master.config import FRAMES, Frame, MasterConfig
from services.control.master.device import HandReading
from services.geometry import Array3, Mat3, is_rotation, rxyz, rxyz_inv, rxyz_inv_near


@dataclass(frozen=True, slots=True)
class ScaledMotion:
    """Eq. 5 output: dp (3,) in slave axes, m; dR (3, 3) in the tool frame; the Euler
    angles a = Rxyz⁻¹(M0ᵀ·M) (rad) before scaling."""

    dp: Array3
    dR: Mat3
    angles_rad: Array3


def scaled_motion(
    E0: ArrayLike,
    M0: ArrayLike,
    E: ArrayLike,
    M: ArrayLike,
    scale_t: float,
    scale_r: float,
    alignment: ArrayLike | None = None,
    near_rad: ArrayLike | None = None,
) -> ScaledMotion:
    """Eq. (5) of the paper as fixed by PROTOCOL.md §2:

        dp = s_t · A · (E − E0)
        dR = Rxyz(s_r · Rxyz⁻¹(M0ᵀ·M)),   Rxyz(a) = Rx(a_x)·Ry(a_y)·Rz(a_z)

    (E0, M0): hand position (m) and orientation at engagement, (E, M) now, in the master
    frame; A: master→slave axis alignment (identity if None). With `near_rad` None, Rxyz⁻¹
    is the principal branch (a_y ∈ [−π/2, π/2]); otherwise the branch closest to `near_rad`
    (see `rxyz_inv_near`), which keeps dR continuous along a continuous hand motion.
    """
    A = np.eye(3) if alignment is None else np.asarray(alignment, dtype=float).reshape(3, 3)
    dE = np.asarray(E, dtype=float) - np.asarray(E0, dtype=float)
    rel = np.asarray(M0, dtype=float).T @ np.asarray(M, dtype=float)
    angles = rxyz_inv(rel) if near_rad is None else rxyz_inv_near(rel, near_rad)
    return ScaledMotion(scale_t * (A @ dE), rxyz(scale_r * angles), angles)


def _vec3(v: ArrayLike) -> tuple[float, float, float]:
    a = np.asarray(v, dtype=float).reshape(3)
    return (float(a[0]), float(a[1]), float(a[2]))


def _mat9(R: ArrayLike) -> tuple[float, ...]:
    return tuple(float(x) for x in np.asarray(R, dtype=float).reshape(9))


def _check_scale(name: str, value: float) -> float:
    v = float(value)
    if not 0.0 < v <= 1.0:
        raise ValueError(f"{name} must satisfy 0 < s ≤ 1, got {value}")
    return v


_IDENTITY9 = _mat9(np.eye(3))
_ZERO3 = (0.0, 0.0, 0.0)


class Teleop:
    """Master-shift state machine and eq. 5, one instance per master.

    - Master-shift pressed (reading.clutch): disengaged, `active` false; dp/dR keep the last
      values sent, so a receiver that ignored `active` would still hold still, never jump back.
    - Release: a new engagement (`engage` + 1) with reference (E0, M0) = the hand at that
      tick, so its first command carries dp = 0, dR = I.
    - A change of scale or frame while engaged starts a new engagement at the next tick
      (rebase), so the command never jumps.
    - At start: engaged at the first tick without master-shift if `engage_on_start`, else
      only after the operator has pressed and released the master-shift once.

    `tick` is called by the loop thread; the setters may be called from any thread.
    `seq` and `engage` start from the wall clock by default (µs and ms since the epoch), so
    a restarted master keeps both above what the slave already applied and is not ignored.
    """

    def __init__(
        self,
        config: MasterConfig,
        device_name: str = "",
        *,
        seq_start: int | None = None,
        engage_start: int | None = None,
    ) -> None:
        now_ns = time.time_ns()
        self._config = config
        self._device = (device_name or config.device)[:128]
        self._A = config.alignment_matrix
        self._lock = threading.Lock()
        self._seq = now_ns // 1000 if seq_start is None else seq_start
        self._state_seq = self._seq
        self._engage = now_ns // 1_000_000 if engage_start is None else engage_start
        self._scale_t = config.scale_t
        self._scale_r = config.scale_r
        self._frame: Frame = config.frame
        self._armed = bool(config.engage_on_start)
        self._engaged = False
        self._rebase = False
        self._E0 = np.zeros(3)
        self._M0 = np.eye(3)
        self._angles = np.zeros(3)
        self._dp: tuple[float, float, float] = _ZERO3
        self._dR: tuple[float, ...] = _IDENTITY9
        self._hand: HandReading | None = None
        self._t_ns = 0

    @property
    def engaged(self) -> bool:
        with self._lock:
            return self._engaged

    @property
    def engage(self) -> int:
        with self._lock:
            return self._engage

    @property
    def scale_t(self) -> float:
        with self._lock:
            return self._scale_t

    @property
    def scale_r(self) -> float:
        with self._lock:
            return self._scale_r

    @property
    def frame(self) -> Frame:
        with self._lock:
            return self._frame

    def set_scale(self, scale_t: float | None = None, scale_r: float | None = None) -> None:
        """Change s_t and/or s_r (0 < s ≤ 1); rebases when engaged. ValueError if out of range."""
        checked_t = None if scale_t is None else _check_scale("scale_t", scale_t)
        checked_r = None if scale_r is None else _check_scale("scale_r", scale_r)
        with self._lock:
            new_t = self._scale_t if checked_t is None else checked_t
            new_r = self._scale_r if checked_r is None else checked_r
            if (new_t, new_r) != (self._scale_t, self._scale_r):
                self._scale_t, self._scale_r = new_t, new_r
                self._rebase = self._engaged

    def set_frame(self, frame: str) -> None:
        """Switch between 'world' and 'tool'; rebases when engaged."""
        if frame not in FRAMES:
            raise ValueError("frame must be 'world' or 'tool'")
        with self._lock:
            if frame != self._frame:
                self._frame = cast(Frame, frame)
                self._rebase = self._engaged

    def _start_engagement(self, reading: HandReading) -> None:
        self._engage += 1
        self._engaged = True
        self._rebase = False
        self._E0 = np.array(reading.hand_p)
        self._M0 = np.array(reading.hand_R)
        self._angles = np.zeros(3)
        self._dp, self._dR = _ZERO3, _IDENTITY9

    def tick(self, reading: HandReading, t_ns: int) -> OperatorCommand:
        """One control tick: the command to publish for this hand reading (PROTOCOL §2/§3)."""
        with self._lock:
            self._seq += 1
            self._hand = reading
            self._t_ns = t_ns
            if reading.clutch:
                self._armed = True
                self._engaged = False
                self._rebase = False
            elif self._rebase or (not self._engaged and self._armed):
                self._start_engagement(reading)
            elif self._engaged:
                motion = scaled_motion(
                    self._E0,
                    self._M0,
                    reading.hand_p,
                    reading.hand_R,
                    self._scale_t,
                    self._scale_r,
                    self._A,
                    near_rad=self._angles,
                )
                self._angles = motion.angles_rad
                self._dp, self._dR = _vec3(motion.dp), _mat9(motion.dR)
            return self._command(reading.grip)

    def reengage(self, engage: int) -> bool:
        """After the slave held engagement `engage` for a gap in the stream (not for anything
        the operator must see to): if the device still asks to move in that engagement, the
        next tick starts a new one where the hand is now (no jump). Whether it will."""
        with self._lock:
            if not (self._engaged and self._engage == engage):
                return False
            self._rebase = True
            return True

    def hold(self, t_ns: int, rearm: bool = False) -> OperatorCommand:
        """A command that disengages without a hand reading (device lost, operator absent):
        active false, dp/dR as last sent. Unless `rearm`, engaging again needs the operator
        to press and release the master-shift."""
        with self._lock:
            self._seq += 1
            self._t_ns = t_ns
            self._engaged = False
            self._rebase = False
            self._armed = rearm
            return self._command(None if self._hand is None else self._hand.grip)

    def _command(self, grip: float | None) -> OperatorCommand:
        return OperatorCommand(
            seq=self._seq,
            t_ns=self._t_ns,
            master=self._config.master_id,
            engage=self._engage,
            active=self._engaged,
            frame=self._frame,
            dp=self._dp,
            dR=self._dR,
            grip=grip,
        )

    def state(self, t_ns: int | None = None) -> MasterState:
        """The MasterState to publish now (its own strictly increasing seq); t_ns defaults to
        the last tick's time."""
        with self._lock:
            self._state_seq += 1
            hand = self._hand
            p = _ZERO3 if hand is None else _vec3(hand.hand_p)
            R = _IDENTITY9 if hand is None else _mat9(hand.hand_R)
            return MasterState(
                seq=self._state_seq,
                t_ns=self._t_ns if t_ns is None else t_ns,
                master=self._config.master_id,
                engage=self._engage,
                active=self._engaged,
                frame=self._frame,
                scale_t=self._scale_t,
                scale_r=self._scale_r,
                hand_p=p,
                hand_R=R,
                device=self._device,
            )


def check_command(cmd: OperatorCommand) -> None:
    """Raise ValueError unless cmd satisfies the contract's checks (finite, dR a rotation)."""
    if not all(np.isfinite(cmd.dp)) or len(cmd.dp) != 3:
        raise ValueError("dp must be 3 finite numbers")
    if len(cmd.dR) != 9 or not is_rotation(np.array(cmd.dR).reshape(3, 3)):
        raise ValueError("dR must be a rotation")
