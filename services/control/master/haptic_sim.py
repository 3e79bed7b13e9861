"""A simulated haptic master with an operator on it: the bilateral loop closes in simulation.

The device has its own mass and damping; the operator's hand is a spring–damper pulling it
towards an intended path (down `depth_m` along the master's −z over `approach_s`, hold
`hold_s`, back up over `release_s`), and while holding the operator presses until the force
felt reaches `goal_force_n` (`services.control.passivity.dynamics`). The force the master service
displays acts on the device from the next read on, so the whole loop — hand → master →
decision → arm → contact → force → master → hand — runs with the real services. Physics
is integrated in steps of at most `STEP_S` within each read.

With `twist_rad` ≠ 0 the handle also turns about the master's z: a rotational inertia and
damping, the hand a torsional spring–damper turning it towards `twist_rad` on the same
timing as the press (or, with `twist_after_s`, over `twist_s` from that time on: turning
what the press has seated), and on, while holding, until the moment felt about z reaches
`goal_moment_nm`; the displayed moment acts on it. Without (the default) the handle never
turns and a displayed moment is ignored, as before.
"""

from __future__ import annotations

import threading

import numpy as np
from numpy.typing import ArrayLike

from services.control.master.device import HandReading
from services.control.passivity.dynamics import Device, Operator, press_hold_release
from services.geometry import rot_z

STEP_S = 0.001


class SimHapticMaster:
    """`MasterDevice`: a simulated device and operator; engaged (no clutch) from the start."""

    def __init__(
        self,
        name: str = "haptic_sim",
        depth_m: float = 0.1,
        approach_s: float = 2.0,
        hold_s: float = 4.0,
        release_s: float = 1.0,
        goal_force_n: float = 8.0,
        mass_kg: float = 0.5,
        damping_ns_m: float = 2.0,
        hand_stiffness_n_m: float = 300.0,
        hand_damping_ns_m: float = 10.0,
        push_gain_m_ns: float = 0.001,
        twist_rad: float = 0.0,
        goal_moment_nm: float = 0.5,
        inertia_kg_m2: float = 0.002,
        rot_damping_nms_rad: float = 0.008,
        hand_torsion_nm_rad: float = 2.0,
        hand_torsion_damping_nms_rad: float = 0.04,
        twist_gain_rad_nms: float = 1.0,
        twist_after_s: float | None = None,
        twist_s: float = 1.0,
    ) -> None:
        for key, value in (
            ("depth_m", depth_m),
            ("approach_s", approach_s),
            ("mass_kg", mass_kg),
            ("hand_stiffness_n_m", hand_stiffness_n_m),
            ("inertia_kg_m2", inertia_kg_m2),
            ("hand_torsion_nm_rad", hand_torsion_nm_rad),
        ):
            if not value > 0.0:
                raise ValueError(f"{key} must be positive")
        self._name = name
        self._lock = threading.Lock()
        self.t_s = 0.0
        hold = (approach_s, approach_s + hold_s)
        path = press_hold_release(
            [0.0, 0.0, 0.0],
            [0.0, 0.0, -depth_m],
            approach_s=approach_s,
            hold_s=hold_s,
            release_s=release_s,
        )
        self.operator = Operator(
            path,
            hand_stiffness_n_m,
            hand_damping_ns_m,
            press=(0.0, 0.0, -1.0),
            goal_force_n=goal_force_n,
            gain_m_ns=push_gain_m_ns,
            pressing=lambda t: hold[0] <= t < hold[1],
        )
        self.device = Device(mass_kg, damping_ns_m, [0.0, 0.0, 0.0], [0.0, 0.0, 0.0])
        self._f_display = [0.0, 0.0, 0.0]
        self._c_display = 0.0  # about the master's z
        self.turning = twist_rad != 0.0
        turn_from = 0.0 if twist_after_s is None else twist_after_s
        turn_s = approach_s if twist_after_s is None else twist_s
        turn = press_hold_release(
            [0.0],
            [twist_rad],
            approach_s=turn_s,
            hold_s=max(approach_s + hold_s - turn_from - turn_s, 0.0),
            release_s=release_s,
        )
        hold_turn = (turn_from + turn_s, approach_s + hold_s)
        self.wrist = Operator(
            lambda t: turn(t - turn_from) if t >= turn_from else [0.0],
            hand_torsion_nm_rad,
            hand_torsion_damping_nms_rad,
            press=(1.0 if twist_rad >= 0.0 else -1.0,),
            goal_force_n=goal_moment_nm,
            gain_m_ns=twist_gain_rad_nms,
            max_push_m=0.5,
            pressing=lambda t: hold_turn[0] <= t < hold_turn[1],
        )
        self.handle = Device(inertia_kg_m2, rot_damping_nms_rad, [0.0], [0.0])

    @property
    def name(self) -> str:
        return self._name

    @property
    def can_display_force(self) -> bool:
        return True

    def open(self) -> None:
        """Nothing to connect."""

    def read(self, dt_s: float) -> HandReading:
        """Advance the simulation by dt_s (at most 0.1 s at once) and return the hand."""
        left = min(max(float(dt_s), 0.0), 0.1)
        with self._lock:
            f_show = list(self._f_display)
            c_show = [self._c_display]
            while left > 1e-9:
                h = min(STEP_S, left)
                self.operator.feel(self.t_s, f_show, h)
                f_hand = self.operator.force(self.t_s, self.device.x, self.device.v)
                self.device.step([a + b for a, b in zip(f_hand, f_show, strict=True)], h)
                if self.turning:
                    self.wrist.feel(self.t_s, c_show, h)
                    c_hand = self.wrist.force(self.t_s, self.handle.x, self.handle.v)[0]
                    self.handle.step([c_hand + c_show[0]], h)
                self.t_s += h
                left -= h
            p = np.array(self.device.x)
            R = rot_z(self.handle.x[0]) if self.turning else np.eye(3)
        return HandReading(p, R, False, None, 0)

    def display_force(self, f: ArrayLike, c: ArrayLike) -> None:
        """The force (master frame, N) acts on the device from the next read on; with a
        twist, the moment about the master's z (N·m) on the handle too."""
        force = [float(x) for x in np.asarray(f, dtype=float).reshape(3)]
        moment = float(np.asarray(c, dtype=float).reshape(3)[2])
        with self._lock:
            self._f_display = force
            self._c_display = moment if self.turning else 0.0

    def close(self) -> None:
        """Nothing to release; the displayed force is dropped."""
        with self._lock:
            self._f_display = [0.0, 0.0, 0.0]
            self._c_display = 0.0
