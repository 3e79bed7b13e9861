"""A whole position–force bilateral loop over a bad link, in simulation (pure, seeded).

hand → device → [link] → slave (follows the commanded position kinematically, at most at
an arm's tool speed, as the simulated arm does behind its safety filter) → wall → force →
[link] → device → hand. The master sends its position and its
cumulative input energy each tick; the slave sends the wall force and its cumulative input
energy. The link delays every packet by `delay_s` ± `jitter` (a fraction, uniform), loses a
fraction `loss`, and the receiver keeps the newest packet (highest seq), as our latest-wins
subscribers do. With `tdpa` both passivity controllers run; the slave's is the reference
controller, or with `slave_port` the decision service's own port.

`simulate` returns a `LoopResult` with the traces and the energy figures; `contact_metrics`
turns it into the bench's measures (peak and steady force, oscillation RMS, penetration).
"""

from __future__ import annotations

import heapq
import math
import random
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Any

from services.control.passivity.controller import MasterPassivity, SlavePassivity
from services.control.passivity.dynamics import Device, Operator, Path, Wall, press_hold_release
from services.control.passivity.observer import dot
from services.control.passivity.rotation import (
    RotationTrack,
    angles_of,
    angles_towards,
    port_angles,
    port_moment,
)
from services.control.passivity.slave import SlavePort
from services.geometry import M9, exp9


@dataclass(frozen=True, slots=True)
class LinkSpec:
    """One direction's link: delay_s one way, jitter as a fraction of it, loss in [0, 1)."""

    delay_s: float = 0.0
    jitter: float = 0.0
    loss: float = 0.0

    def __post_init__(self) -> None:
        if not (0.0 <= self.delay_s <= 10.0):
            raise ValueError("delay_s must be within 0 … 10 s")
        if not (0.0 <= self.jitter <= 1.0):
            raise ValueError("jitter must be within 0 … 1")
        if not (0.0 <= self.loss < 1.0):
            raise ValueError("loss must be within 0 … 1 (excluded)")


class Link:
    """Packets in, the newest delivered packet out (latest-wins), with delay/jitter/loss."""

    def __init__(self, spec: LinkSpec, rng: random.Random) -> None:
        self.spec = spec
        self._rng = rng
        self._queue: list[tuple[float, int, Any]] = []
        self._seq = 0
        self._newest = -1
        self.latest: Any = None
        self.sent = 0
        self.lost = 0

    def send(self, t_s: float, payload: Any) -> None:
        self._seq += 1
        self.sent += 1
        if self._rng.random() < self.spec.loss:
            self.lost += 1
            return
        j = self.spec.jitter * self.spec.delay_s
        arrive = t_s + self.spec.delay_s + (self._rng.uniform(-j, j) if j > 0 else 0.0)
        heapq.heappush(self._queue, (arrive, self._seq, payload))

    def receive(self, t_s: float) -> Any:
        """Delivers what has arrived by t_s; returns the newest payload so far (or None)."""
        while self._queue and self._queue[0][0] <= t_s:
            _, seq, payload = heapq.heappop(self._queue)
            if seq > self._newest:
                self._newest = seq
                self.latest = payload
        return self.latest


SLAVE_SPEED_M_S = 0.5
"""The simulated slave's speed limit: ArmConfig's `max_tool_speed_m_s` default."""
SLAVE_ROT_SPEED_RAD_S = 1.5
"""Its turning speed limit: ArmConfig's `max_tool_rot_speed_rad_s` default."""
MAX_MOMENT_NM = 2.0
"""The largest moment the simulated master displays (N·m)."""


@dataclass(frozen=True, slots=True)
class Twist:
    """A turn against a torsional stop about the wall's normal, during the press: the hand
    turns the handle (`inertia_kg_m2`, `damping_nms_rad`) towards `target_rad` past the stop
    at `stop_rad`, as a torsional spring–damper (`operator_*`), and while pressing turns on
    until it feels `goal_nm`. The stop resists with `stiffness_nm_rad` and
    `stop_damping_nms_rad`, never pulling (a unilateral contact, as the wall). Each side
    then runs a rotational port beside the force's, the master's with the handle's inertia,
    the slave's the decision's (`SlavePort` in `port_angles` coordinates): docs/passivity.md,
    "Rotations"."""

    inertia_kg_m2: float = 0.002
    damping_nms_rad: float = 0.008
    stop_rad: float = 0.2
    target_rad: float = 0.35
    stiffness_nm_rad: float = 30.0
    stop_damping_nms_rad: float = 0.03
    operator_stiffness_nm_rad: float = 2.0
    operator_damping_nms_rad: float = 0.04
    goal_nm: float = 0.5
    push_gain_rad_nms: float = 1.0
    max_push_rad: float = 0.5

    def moment(self, phi: float, omega: float) -> float:
        """The stop's moment (N·m) about the axis on a tool turned to phi at omega."""
        pen = phi - self.stop_rad
        if pen <= 0.0:
            return 0.0
        return -max(self.stiffness_nm_rad * pen + self.stop_damping_nms_rad * omega, 0.0)


@dataclass(frozen=True, slots=True)
class LoopSpec:
    """The simulated contact task. Defaults: 1 kHz, 1-DoF, a 5 kN/m wall 5 cm away, the hand
    aiming 3 cm past it. `slave_speed_m_s`: the slave arm chases its target at most this fast
    (ArmConfig.max_tool_speed_m_s, 0.5 m/s); 0: it jumps to each target in one tick (over a
    jittery link the positions arrive in bunches, and the jumps are impacts faster than the
    slave's controller can see: docs/passivity.md). `slave_port`: the slave side is the
    decision service's own port (`SlavePort`: it corrects the target against the measured
    tool, repays an impact's overdraw from what the wall gives back) instead of the
    reference controller (`SlavePassivity`); it needs `slave_speed_m_s` > 0 (the arm chases
    the target it is given)."""

    round_trip_s: float = 0.0
    jitter: float = 0.0
    loss: float = 0.0
    tdpa: bool = False
    dofs: int = 1
    dt_s: float = 0.001
    duration_s: float = 7.0
    force_scale: float = 1.0
    max_force_n: float = 40.0
    drift_m_s: float = 0.03
    slave_speed_m_s: float = SLAVE_SPEED_M_S
    slack_m: float = 0.0
    slave_port: bool = False
    ramp_n_s: float = 0.0
    limit: bool = True
    limit_mass: bool = True
    reserve_j: float = 1e-4
    hand_rate_n_s: float = 20.0
    bound_current: bool = True
    damp: bool = True
    seed: int = 1
    wall: Wall = field(default_factory=Wall)
    operator_stiffness_n_m: float = 300.0
    operator_damping_ns_m: float = 10.0
    target_m: tuple[float, ...] = (0.08,)
    goal_force_n: float = 8.0
    push_gain_m_ns: float = 0.001
    approach_s: float = 1.0
    hold_s: float = 4.0
    release_s: float = 1.0
    twist: Twist | None = None


@dataclass(slots=True)
class LoopResult:
    """Traces at every tick: t, displayed force and slave contact force (along the wall
    normal, N), penetration (m), and the cumulative energies of both ports."""

    spec: LoopSpec
    t: list[float] = field(default_factory=list)
    f_display: list[float] = field(default_factory=list)
    f_contact: list[float] = field(default_factory=list)
    f_hand: list[float] = field(default_factory=list)
    """The operator's hand pushing into the wall: the force the operator intends (N)."""
    penetration: list[float] = field(default_factory=list)
    x_master: list[float] = field(default_factory=list)
    x_slave: list[float] = field(default_factory=list)
    master_in: list[float] = field(default_factory=list)
    master_out: list[float] = field(default_factory=list)
    slave_in: list[float] = field(default_factory=list)
    slave_out: list[float] = field(default_factory=list)
    m_display: list[float] = field(default_factory=list)
    m_contact: list[float] = field(default_factory=list)
    twist_penetration: list[float] = field(default_factory=list)
    """With `LoopSpec.twist`: the moment displayed and the stop's (N·m, against the turn)
    and how far the tool is past the stop (rad)."""
    master_dissipated_j: float = 0.0
    slave_dissipated_j: float = 0.0
    master_active: int = 0
    slave_active: int = 0
    diverged: bool = False


def simulate(spec: LoopSpec) -> LoopResult:
    """Runs the contact task once; deterministic for a given spec (its seed)."""
    n = spec.dofs
    if n not in (1, 3) or len(spec.target_m) != n or len(spec.wall.normal) != n:
        raise ValueError("dofs must be 1 or 3, with target_m and wall.normal of that length")
    if not 0.0 <= spec.slave_speed_m_s < math.inf:
        raise ValueError("slave_speed_m_s must be ≥ 0 (0: no limit) and finite")
    if spec.slave_port and spec.slave_speed_m_s <= 0.0:
        raise ValueError("slave_port needs slave_speed_m_s > 0 (the arm chases its target)")
    tw = spec.twist
    if tw is not None and not (spec.slave_port and n == 3):
        raise ValueError("twist needs dofs = 3 and slave_port (the services' ports)")
    rng = random.Random(spec.seed)
    one_way = LinkSpec(spec.round_trip_s / 2.0, spec.jitter, spec.loss)
    to_slave, to_master = Link(one_way, rng), Link(one_way, rng)
    path: Path = press_hold_release(
        [0.0] * n,
        spec.target_m,
        approach_s=spec.approach_s,
        hold_s=spec.hold_s,
        release_s=spec.release_s,
    )
    norm = math.sqrt(dot(spec.target_m, spec.target_m))
    hold = (spec.approach_s, spec.approach_s + spec.hold_s)
    hand = Operator(
        path,
        spec.operator_stiffness_n_m,
        spec.operator_damping_ns_m,
        press=tuple(x / norm for x in spec.target_m),
        goal_force_n=spec.goal_force_n,
        gain_m_ns=spec.push_gain_m_ns,
        pressing=lambda t: hold[0] <= t < hold[1],
    )
    device = Device(x=[0.0] * n, v=[0.0] * n)
    master = MasterPassivity(
        enabled=spec.tdpa,
        ramp_n_s=spec.ramp_n_s,
        limit=spec.limit,
        mass_kg=device.mass_kg if spec.limit_mass else 0.0,
        reserve_j=spec.reserve_j,
        hand_rate_n_s=spec.hand_rate_n_s,
        bound_current=spec.bound_current,
        damp=spec.damp,
    )
    slave = SlavePassivity(enabled=spec.tdpa, drift_m_s=spec.drift_m_s, slack_m=spec.slack_m)
    port = SlavePort(enabled=spec.tdpa, drift_m_s=spec.drift_m_s, offset=[0.0] * n)
    turn = _Turning(tw, spec, device.mass_kg, hold) if tw is not None else None
    use_port = spec.slave_port
    x_goal = [0.0] * n
    x_s = [0.0] * n
    x_tgt = [0.0] * n
    done: list[float] | None = None
    v_s = [0.0] * n
    x_cmd_prev = [0.0] * n
    f_env = [0.0] * n
    res = LoopResult(spec)
    normal = spec.wall.normal
    steps = round(spec.duration_s / spec.dt_s)
    for k in range(steps):
        t = k * spec.dt_s
        # --- master side ---
        back = to_master.receive(t)
        f_show = [0.0] * n
        if back is not None:
            f_remote, e_in_s = back[0], back[1]
            master.remote.update(0, e_in_s)
            f_show = _saturate([spec.force_scale * fi for fi in f_remote], spec.max_force_n)
        f_show = master.step(f_show, device.x, spec.dt_s)
        hand.feel(t, f_show, spec.dt_s)
        f_hand = hand.force(t, device.x, device.v)
        device.step([a + b for a, b in zip(f_hand, f_show, strict=True)], spec.dt_s)
        up: tuple[Any, ...] = (list(device.x), master.observer.e_in)
        if turn is not None:
            up += (turn.master_step(t, back),)
        to_slave.send(t, up)
        # --- slave side ---
        cmd = to_slave.receive(t)
        if cmd is not None and use_port:
            x_goal, e_in_m = cmd[0], cmd[1]
            port.remote.update(0, e_in_m)
            dx = [0.0] * n
        elif cmd is not None:
            x_cmd, e_in_m = cmd
            slave.remote.update(0, e_in_m)
            dx = [a - b for a, b in zip(x_cmd, x_cmd_prev, strict=True)]
            x_cmd_prev = list(x_cmd)
        else:
            dx = [0.0] * n
        if use_port:
            # The service's port: the tool's motion observed as it happened, the target
            # corrected against the tool (the master's position is the port's target).
            port.observe(f_env, x_s)
            x_tgt = port.correct(x_goal, x_s, f_env, spec.dt_s)
            dx = _chase(x_tgt, x_s, spec.slave_speed_m_s * spec.dt_s)
        elif spec.slave_speed_m_s > 0.0:
            # The arm chases its target at its speed limit: the controller corrects the
            # whole motion still to come (target − tool), as the service's slave port does.
            pend = [g - x + d for g, x, d in zip(x_tgt, x_s, dx, strict=True)]
            out = slave.step(f_env, pend, spec.dt_s, done=done)
            x_tgt = [x + o for x, o in zip(x_s, out, strict=True)]
            dx = _chase(x_tgt, x_s, spec.slave_speed_m_s * spec.dt_s)
            done = dx
        else:
            dx = slave.step(f_env, dx, spec.dt_s)
        v_s = [d / spec.dt_s for d in dx]
        x_s = [a + d for a, d in zip(x_s, dx, strict=True)]
        f_env = spec.wall.force(x_s, v_s)
        e_in_slave = port.observer.e_in if use_port else slave.observer.e_in
        down: tuple[Any, ...] = (list(f_env), e_in_slave)
        if turn is not None:
            down += (turn.slave_step(cmd),)
        to_master.send(t, down)
        # --- traces ---
        res.t.append(t)
        res.f_display.append(-dot(f_show, normal))
        res.f_contact.append(-dot(f_env, normal))
        res.f_hand.append(dot(f_hand, normal))
        res.penetration.append(spec.wall.penetration_m(x_s))
        res.x_master.append(dot(device.x, normal))
        res.x_slave.append(dot(x_s, normal))
        res.master_in.append(master.observer.e_in)
        res.master_out.append(master.observer.e_out)
        if use_port:
            # What the wall gave back to repay an overdraw is input the master never saw.
            res.slave_in.append(port.observer.e_in + port.recovered_j)
            res.slave_out.append(port.observer.e_out)
        else:
            res.slave_in.append(slave.observer.e_in)
            res.slave_out.append(slave.observer.e_out)
        if turn is not None:
            turn.trace(res)
        if not all(math.isfinite(x) and abs(x) < 10.0 for x in device.x) or (
            turn is not None and not abs(turn.handle.x[0]) < 100.0
        ):
            res.diverged = True
            break
    res.master_dissipated_j = master.telemetry.dissipated_j
    sp = port.telemetry if use_port else slave.telemetry
    res.slave_dissipated_j = sp.dissipated_j
    res.master_active = master.telemetry.active_steps
    res.slave_active = sp.active_steps
    return res


class _Turning:
    """The twist task's rotational half (`Twist`) about the wall's normal, both sides, each
    with a rotational port of its own beside the force's (as the services run them): the
    handle and the hand turning it behind the master's port on moment × rotation, and the
    tool turning against the stop behind the slave's (the decision's, in `port_angles`
    coordinates). Angles about the axis are plain floats; the ports see
    orientations (`exp(φ·axis)`) through their own `RotationTrack`."""

    def __init__(
        self, tw: Twist, spec: LoopSpec, mass_kg: float, hold: tuple[float, float]
    ) -> None:
        self.tw, self.spec = tw, spec
        self.axis = spec.wall.normal
        # The force's settings, the hand's force rate as fast in unit-mass coordinates.
        self.master = MasterPassivity(
            enabled=spec.tdpa,
            limit=spec.limit,
            mass_kg=tw.inertia_kg_m2 if spec.limit_mass else 0.0,
            reserve_j=spec.reserve_j,
            hand_rate_n_s=spec.hand_rate_n_s * math.sqrt(tw.inertia_kg_m2 / mass_kg),
            bound_current=spec.bound_current,
            damp=spec.damp,
        )
        self.port = SlavePort(enabled=spec.tdpa, drift_m_s=spec.drift_m_s)
        self.handle = Device(mass_kg=tw.inertia_kg_m2, damping_ns_m=tw.damping_nms_rad)
        self.hand = Operator(
            press_hold_release(
                [0.0],
                [tw.target_rad],
                approach_s=spec.approach_s,
                hold_s=spec.hold_s,
                release_s=spec.release_s,
            ),
            tw.operator_stiffness_nm_rad,
            tw.operator_damping_nms_rad,
            goal_force_n=tw.goal_nm,
            gain_m_ns=tw.push_gain_rad_nms,
            max_push_m=tw.max_push_rad,
            pressing=lambda t: hold[0] <= t < hold[1],
        )
        self.master_track = RotationTrack()
        self.track = RotationTrack()
        self.phi_goal = 0.0
        self.phi = 0.0
        self.omega = 0.0
        self.c_env = [0.0, 0.0, 0.0]
        self.c_show = [0.0, 0.0, 0.0]

    def _R(self, phi: float) -> M9:
        a = self.axis
        return exp9((phi * a[0], phi * a[1], phi * a[2]))

    def master_step(self, t: float, back: Any) -> tuple[float, float]:
        """The master's rotational port: the moment shown, the handle turned; returns what
        goes to the slave (the handle's angle, the port's input energy)."""
        spec, dt = self.spec, self.spec.dt_s
        c_show = [0.0, 0.0, 0.0]
        if back is not None:
            c_remote, e_in_s = back[2]
            self.master.remote.update(0, e_in_s)
            c_show = _saturate([spec.force_scale * ci for ci in c_remote], MAX_MOMENT_NM)
        theta = self.master_track.update(self._R(self.handle.x[0]))
        self.c_show = self.master.step(c_show, theta, dt)
        c_axis = dot(self.c_show, self.axis)
        self.hand.feel(t, [c_axis], dt)
        c_hand = self.hand.force(t, self.handle.x, self.handle.v)[0]
        self.handle.step([c_hand + c_axis], dt)
        return self.handle.x[0], self.master.observer.e_in

    def slave_step(self, cmd: Any) -> tuple[list[float], float]:
        """The slave's rotational port: the tool turned towards the master's angle as
        corrected, at the arm's turning speed, against the stop; returns what goes to the
        master (the stop's moment, the port's input energy)."""
        dt, port = self.spec.dt_s, self.port
        if cmd is not None:
            self.phi_goal, e_in_m = cmd[2]
            port.remote.update(0, e_in_m)
        R_s = self._R(self.phi)
        theta = self.track.update(R_s)
        now = port_angles(theta)
        c_env = port_moment(self.c_env)
        port.observe(c_env, now)
        goal = port_angles(angles_towards(theta, R_s, self._R(self.phi_goal)))
        th_tgt = angles_of(port.correct(goal, now, c_env, dt))
        ahead = dot([a - b for a, b in zip(th_tgt, theta, strict=True)], self.axis)
        cap = SLAVE_ROT_SPEED_RAD_S * dt
        step = min(max(ahead, -cap), cap)
        self.phi += step
        self.omega = step / dt
        c = self.tw.moment(self.phi, self.omega)
        self.c_env = [c * a for a in self.axis]
        return list(self.c_env), port.observer.e_in

    def trace(self, res: LoopResult) -> None:
        """The moment's traces; the energies of both rotational ports added to the force's."""
        res.m_display.append(-dot(self.c_show, self.axis))
        res.m_contact.append(-dot(self.c_env, self.axis))
        res.twist_penetration.append(max(self.phi - self.tw.stop_rad, 0.0))
        res.master_in[-1] += self.master.observer.e_in
        res.master_out[-1] += self.master.observer.e_out
        res.slave_in[-1] += self.port.observer.e_in + self.port.recovered_j
        res.slave_out[-1] += self.port.observer.e_out


def twist_metrics(res: LoopResult, settle_s: float = 2.0) -> dict[str, float | bool]:
    """`contact_metrics` of the twist task's moment (N·m in place of N, rad past the stop in
    place of m: `penetration_mm` is then mrad); the energy balance is both ports'."""
    moment = LoopResult(
        res.spec,
        t=res.t,
        f_display=res.m_display,
        f_contact=res.m_contact,
        penetration=res.twist_penetration,
        master_in=res.master_in,
        master_out=res.master_out,
        slave_in=res.slave_in,
        slave_out=res.slave_out,
        master_dissipated_j=res.master_dissipated_j,
        slave_dissipated_j=res.slave_dissipated_j,
        diverged=res.diverged,
    )
    return contact_metrics(moment, settle_s)


def _chase(target: Sequence[float], x: Sequence[float], cap_m: float) -> list[float]:
    """The arm's step towards `target` from `x`: all of it, or `cap_m` along it."""
    gap = [g - xi for g, xi in zip(target, x, strict=True)]
    gap_m = math.sqrt(dot(gap, gap))
    return gap if gap_m <= cap_m else [g * cap_m / gap_m for g in gap]


def _saturate(f: Sequence[float], max_n: float) -> list[float]:
    norm = math.sqrt(dot(f, f))
    if norm <= max_n:
        return list(f)
    return [x * max_n / norm for x in f]


def trend_n_s(points: Sequence[tuple[float, float]]) -> float:
    """The least-squares slope (N/s) of (t_s, f_n) points: how fast the contact force
    climbs or sinks over a window (a creep, which the RMS about the mean also counts); 0
    for fewer than two distinct times."""
    n = len(points)
    if n < 2:
        return 0.0
    mt = math.fsum(t for t, _ in points) / n
    mf = math.fsum(f for _, f in points) / n
    stt = math.fsum((t - mt) ** 2 for t, _ in points)
    if stt <= 0.0:
        return 0.0
    return math.fsum((t - mt) * (f - mf) for t, f in points) / stt


def _nondecreasing_fit(values: Sequence[float]) -> list[float]:
    """The least-squares non-decreasing fit of `values` (pool adjacent violators)."""
    sums: list[float] = []
    counts: list[int] = []
    for v in values:
        sums.append(v)
        counts.append(1)
        # Merge while the block before has the higher mean (cross-multiplied: no division).
        while len(sums) > 1 and sums[-2] * counts[-1] > sums[-1] * counts[-2]:
            s, c = sums.pop(), counts.pop()
            sums[-1] += s
            counts[-1] += c
    fit: list[float] = []
    for s, c in zip(sums, counts, strict=True):
        fit.extend([s / c] * c)
    return fit


def swing_rms(values: Sequence[float]) -> float:
    """The RMS of `values` about their best monotone fit (rising or falling, least squares):
    the back-and-forth no steady rise or fall explains. A contact force that steps or
    creeps to a new level swings 0; one that bounces swings about as much as its RMS about
    the mean, which bounds it (a constant is monotone). 0 for no values."""
    n = len(values)
    if n == 0:
        return 0.0
    best = math.inf
    for sign in (1.0, -1.0):
        ys = [sign * float(v) for v in values]
        fit = _nondecreasing_fit(ys)
        best = min(best, math.fsum((y - f) ** 2 for y, f in zip(ys, fit, strict=True)))
    return math.sqrt(best / n)


def held(window: Sequence[float], steady_n: float) -> bool:
    """The contact held through the window: its force never fell below 10 % of the steady
    force. A bounce whose period is longer than the window leaves the surface and hits it
    again once in it, which no swing shows (a rise from 0 is monotone: over the link at
    700 ms without TDPA, 2026-11-26)."""
    return bool(window) and min(window) >= 0.1 * steady_n


def contact_metrics(res: LoopResult, settle_s: float = 2.0) -> dict[str, float | bool]:
    """The bench's measures of one run.

    peak_force_n: largest contact force; steady_force_n / oscillation_rms_n: mean and RMS
    about the mean of the contact force over the hold after `settle_s`; swing_rms_n: its
    RMS about its best monotone fit over that window (`swing_rms`: a step or a creep of
    the contact is not an oscillation); felt_force_n: the mean force displayed on the hand
    over the same window; creep_n_s: its least-squares slope over that window
    (`trend_n_s`); penetration_mm: the largest; energy_generated_j: how far the channel's
    observed output ever exceeded its input (> 0 means energy was created); stable: no
    divergence, the contact held through the window (`held`) and a swing below 10 % of
    the steady force (no sustained oscillation); settled: no divergence and oscillation RMS
    below 10 % of the steady force (nor a step inside the window: the operator still
    pressing towards its goal force counts here).
    """
    spec = res.spec
    lo = spec.approach_s + settle_s
    hi = spec.approach_s + spec.hold_s
    points = [(t, f) for t, f in zip(res.t, res.f_contact, strict=True) if lo <= t < hi]
    window = [f for _, f in points]
    felt = [f for t, f in zip(res.t, res.f_display, strict=True) if lo <= t < hi]
    steady = sum(window) / len(window) if window else 0.0
    rms = math.sqrt(sum((f - steady) ** 2 for f in window) / len(window)) if window else 0.0
    generated = 0.0
    for mi, mo, si, so in zip(
        res.master_in, res.master_out, res.slave_in, res.slave_out, strict=True
    ):
        generated = max(generated, (mo + so) - (mi + si))
    swing = swing_rms(window)
    calm = (not res.diverged) and steady > 0.0
    stable = calm and held(window, steady) and swing < 0.1 * steady
    return {
        "peak_force_n": max(res.f_contact, default=0.0),
        "steady_force_n": steady,
        "felt_force_n": sum(felt) / len(felt) if felt else 0.0,
        "oscillation_rms_n": rms,
        "swing_rms_n": swing,
        "creep_n_s": trend_n_s(points),
        "penetration_mm": 1e3 * max(res.penetration, default=0.0),
        "energy_generated_j": generated,
        "master_dissipated_j": res.master_dissipated_j,
        "slave_dissipated_j": res.slave_dissipated_j,
        "stable": stable,
        "settled": calm and rms < 0.1 * steady,
    }
