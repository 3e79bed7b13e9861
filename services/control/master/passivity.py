"""The master side of time-domain passivity on the bus (docs/passivity.md).

`MasterTdpa.hook` is a `ForceDisplay` hook: it observes the master port (the wrench shown ×
the hand's motion, master frame), bounds the displayed force to what the reservoir can pay
over the next tick, with the hand's own force in the prediction (`MasterPassivity`, limiter
on, its damper's gain bounded: `BETA_MAX_NS_M`), and publishes the port's energies on
`robot/passivity/master`; it reads the slave's on `robot/passivity/slave`. With moments
shown (`[master] passivity_moments`), a second port of the same kind on the moment against
the hand's rotation, with the device's rotational inertia and energies of its own
(`services/control/passivity/rotation.py`). A new engagement
starts a new count on both sides (no energy is in the channel then, so nothing jumps: the
display also ramps in). Called by the master loop thread only.
"""

from __future__ import annotations

import time
from collections import deque
from collections.abc import Callable

import numpy as np

from services.bus import keys
from services.bus.messages import PassivityState
from services.bus.node import Node
from services.control.master.config import DEVICE_INERTIA_KG_M2
from services.control.master.device import HandReading
from services.control.master.feedback import DisplayWrench
from services.control.passivity.controller import MasterPassivity
from services.control.passivity.rotation import RotationTrack
from services.control.passivity.roundtrip import RoundTrip
from services.control.passivity.wire import passivity_state

RESERVE_J = 1e-4
"""The most the master port may ever owe the channel (J): see docs/passivity.md."""
HAND_RATE_N_S = 0.0
"""How fast the limiter assumes the hand's own force may change within a tick (N/s). 0: the
hand holds its force over the next tick; a hand that lets go within it shows as one tick's
overdraw, observed and owed: the display gives nothing more until the slave's energy has
repaid it (classic TDPA's correction after the fact).
At 20 N/s, as before 2026-11-26, the bound charged a still hand ṙ·h³/m a tick: the display
then held only while the hand sank at ṙ·h²/m (4–9 mm/s at 100 Hz), and the operator, never
feeling the contact, pressed the tool on (docs/passivity.md)."""
RISE = 0.3
"""While the limiter holds the force back, it rises by this fraction of the gap to the bound
a tick (`MasterPassivity.rise`): at once (1), the bound's own deadbeat made the display buzz."""
BETA_MAX_NS_M = 20.0
"""The classic TDPA damper's gain is bounded to this (`MasterPassivity.beta_max`, N·s/m). It
predicts the next tick's work from the hand's velocity alone; unbounded, with the reservoir
empty (a steady press: the slave sends nothing back while the tool presses) it removed the
whole force at any outward velocity, however small (8 µm/s), though the hand pressing in
stops the device within the tick. Traced tick by tick over the link (2026-11-26, 700 ms):
each such collapse let the hand lunge in at 10–30 mm/s, the limiter then allowed the full
force, the device bounced back and the force collapsed again, two or three times; every
lunge put 0.5–5 mJ into the channel, which the slave spent pressing the tool deeper (the
creep). Bounded, `β·v` is 0.16 mN at 8 µm/s and 0.4 N at 20 mm/s: no collapse, and a hand
that really moves out under a debt still has energy taken from it. Off altogether (the
limiter alone, 13:00–14:20 UTC) the link runs were as calm, but in-process one run in three
at 500 Hz gave the hand 22 mJ more than the slave sent: nothing paid a late loop's
mispredictions back (docs/passivity.md)."""
BOUND_CURRENT = False
"""The limiter's bound at the current velocity (`MasterPassivity.bound_current`) is off, for
the same reason: only its prediction with the hand's own force (the last tick's
acceleration) bounds the work. A hand that changes its force within a tick shows as that
tick's overdraw, observed, owed, and no more given until the slave pays (classic TDPA)."""
HORIZON_TICKS = 50
"""The limiter predicts over the longest of the last this many tick intervals (a loop late
once may be late again)."""


def master_port(
    device_mass_kg: float, enabled: bool = True, beta_max: float = BETA_MAX_NS_M
) -> MasterPassivity:
    """The master port's controller as the service runs it (the constants above). The
    rotational port is the same with the device's rotational inertia (kg·m²) for its mass
    and `rotation_beta_max` for the damper's bound."""
    return MasterPassivity(
        enabled=enabled,
        limit=True,
        mass_kg=device_mass_kg,
        reserve_j=RESERVE_J,
        hand_rate_n_s=HAND_RATE_N_S,
        rise=RISE,
        damp=True,
        beta_max=beta_max,
        bound_current=BOUND_CURRENT,
    )


def rotation_beta_max(device_mass_kg: float, device_inertia_kg_m2: float) -> float:
    """The rotational damper's bound (N·m·s/rad): BETA_MAX_NS_M as a rate, β/m, the same for
    the turn of the handle as for its motion (0.08 N·m·s/rad for 0.002 kg·m² and 0.5 kg)."""
    return BETA_MAX_NS_M / device_mass_kg * device_inertia_kg_m2


class MasterTdpa:
    """enabled: damp (true) or only observe and publish (false)."""

    def __init__(
        self,
        node: Node,
        master_id: str,
        engage: Callable[[], int],
        enabled: bool = True,
        device_mass_kg: float = 0.5,
        force_scale: float = 1.0,
        show_moments: bool = False,
        device_inertia_kg_m2: float = DEVICE_INERTIA_KG_M2,
    ) -> None:
        """`device_mass_kg`: the device's moving mass the force limiter predicts with
        (`[master] passivity_device_mass_kg`; 0.5 kg is the simulated haptic master's).
        `force_scale`: the display's (`[master] force_scale`), to report the forces asked and
        shown as newtons at the tool. `show_moments` (`[master] passivity_moments`): the
        moment is shown through a rotational port of its own (`rot`), against the hand's
        rotation, with `device_inertia_kg_m2` (`[master] passivity_device_inertia_kg_m2`)
        in its limiter; otherwise no moment is shown (a device without one: the haptic
        masters)."""
        self.master_id = master_id
        self.force_scale = force_scale
        self.pc = master_port(device_mass_kg, enabled)
        self.rot: MasterPassivity | None = None
        if show_moments:
            beta = rotation_beta_max(device_mass_kg, device_inertia_kg_m2)
            self.rot = master_port(device_inertia_kg_m2, enabled, beta_max=beta)
        self._turn = RotationTrack()
        self._engage = engage
        self._pub = node.publisher(keys.PASSIVITY_MASTER)
        self.link = RoundTrip()
        """The round trip to the decision and back, from its echoes of ours (which ride on
        one message in many: every message is read, not only the newest)."""
        self._slave = node.latest(keys.PASSIVITY_SLAVE, each=self._heard)
        self._seq = 0
        self._epoch: int | None = None
        self._dts: deque[float] = deque(maxlen=HORIZON_TICKS)

    def hook(self, wrench: DisplayWrench, hand: HandReading, dt_s: float) -> DisplayWrench:
        engage = self._engage()
        rot = self.rot
        if engage != self._epoch:
            self._epoch = engage
            self.pc.reset(engage)
            if rot is not None:
                rot.reset(engage)
                self._turn.reset()
        got = self._slave.read()
        if got is not None:
            msg = got[0]
            if msg.master == self.master_id and msg.side == "slave":
                self.pc.remote.update(msg.engage, msg.e_in)
                if rot is not None and msg.rot_e_in is not None:
                    rot.remote.update(msg.engage, msg.rot_e_in)
        self._dts.append(dt_s)
        horizon = max(self._dts)
        self.pc.horizon_s = horizon
        f = self.pc.step([float(x) for x in wrench.f], [float(x) for x in hand.hand_p], dt_s)
        c = [0.0, 0.0, 0.0]
        if rot is not None:
            rot.horizon_s = horizon
            c = rot.step([float(x) for x in wrench.c], self._turn.update(hand.hand_R), dt_s)
        self._publish(engage)
        return DisplayWrench(
            np.asarray(f, dtype=float),
            np.asarray(c, dtype=float),
            wrench.force_saturated,
            wrench.torque_saturated and rot is not None,
        )

    def _heard(self, msg: PassivityState) -> None:
        """Each of the decision's figures as read (the loop's thread): its echo of ours."""
        if msg.master == self.master_id and msg.side == "slave":
            self.link.heard(msg, time.time_ns(), time.monotonic_ns())

    def _publish(self, engage: int) -> None:
        self._seq += 1
        echo, rtt_s = self.link.carry(time.monotonic_ns())
        self._pub.put(
            passivity_state(
                self._seq,
                self.master_id,
                engage,
                "master",
                self.pc,
                self.force_scale,
                rot=self.rot,
                echo=echo,
                rtt_s=rtt_s,
            )
        )
