"""Every intervention over Zenoh with the REAL arm and force services in simulation.

One private network per test: the arm (sim arm starting at home: tool at (0.55, 0, 0.65),
pointing down), the force service (sim wrist in the sim workcell), the decision server, an
operator's console and masters streaming robot/cmd at 100 Hz, each on a node of its own as
separate processes would be. Assertions are on events, states and counts; waits have
deadlines.
"""

from __future__ import annotations

import math
import threading
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field

import msgpack
import numpy as np
import pytest

from services.bus import keys
from services.bus.errors import RpcError
from services.bus.messages import IDENTITY_R, ArmTarget, Event, OperatorCommand, RobotState, vec
from services.bus.node import Node
from services.control.arm.model import load_model
from services.control.arm.puma560 import QN_RAD
from services.control.decision.config import DecisionConfig
from services.control.decision.service import DecisionService
from services.control.force.service import ForceService
from services.tools.cell.sim import LIGHT_FORCE, SimCell, light_arm
from services.world.workcell.mujoco_model import PhysicsParams
from services.world.workcell.scene import TABLE, Scene, default_scene
from tests.conftest import Net, wait_until

HOME_Q_RAD = load_model().home
"""The default model's home (the PUMA 560's)."""

pytestmark = [pytest.mark.system, pytest.mark.alone]

HOME_P = np.array([0.55, 0.0, 0.65])
TOP = TABLE.top_z
TOUCH = TOP + PhysicsParams().finger_length_m
"""The tool point's height when the gripper's fingertips touch the table."""
TABLE_ONLY = Scene(boxes=(TABLE,))
"""The cell of most tests: the table alone (the open fingers, 12 cm apart, would catch the
default scene's blocks beside the tool's path)."""
DpFn = Callable[[float], tuple[float, float, float]]


class Events:
    """robot/events as seen by the console, with waits on a condition."""

    def __init__(self, node: Node) -> None:
        self._cond = threading.Condition()
        self.items: list[Event] = []
        node.subscribe(keys.EVENTS, self._on)

    def _on(self, ev: Event) -> None:
        with self._cond:
            self.items.append(ev)
            self._cond.notify_all()

    def of(self, kind: str, source: str = "decision") -> list[Event]:
        with self._cond:
            return [e for e in self.items if e.kind == kind and e.source == source]

    def wait(self, pred: Callable[[Event], bool], timeout_s: float = 5.0) -> Event:
        deadline = time.monotonic() + timeout_s
        with self._cond:
            while True:
                for e in self.items:
                    if pred(e):
                        return e
                left = deadline - time.monotonic()
                if left <= 0:
                    raise AssertionError(
                        "no such event; got "
                        + repr([(e.source, e.kind, e.message) for e in self.items][-15:])
                    )
                self._cond.wait(left)


class Recorder:
    """Every robot/arm/target, in arrival order."""

    def __init__(self, node: Node) -> None:
        self._cond = threading.Condition()
        self.items: list[ArmTarget] = []
        node.subscribe(keys.ARM_TARGET, self._on)

    def _on(self, c: ArmTarget) -> None:
        with self._cond:
            self.items.append(c)
            self._cond.notify_all()

    def count(self) -> int:
        with self._cond:
            return len(self.items)

    def since(self, n: int) -> list[ArmTarget]:
        with self._cond:
            return self.items[n:]

    def held_after(self, n: int, more: int = 50, timeout_s: float = 5.0) -> bool:
        """From the first hold after the n-th target on, `more` targets, all holds (moving
        ones sent before the hold may still be in flight when it is announced)."""
        cmds = self.wait_more(n, more, timeout_s)
        first = next((i for i, c in enumerate(cmds) if c.hold), None)
        if first is None:
            return False
        cmds = self.wait_more(n + first, more, timeout_s)
        return all(c.hold for c in cmds)

    def wait_more(self, n: int, more: int, timeout_s: float = 5.0) -> list[ArmTarget]:
        deadline = time.monotonic() + timeout_s
        with self._cond:
            while len(self.items) < n + more:
                left = deadline - time.monotonic()
                assert left > 0, f"only {len(self.items) - n} of {more} arm commands"
                self._cond.wait(left)
            return self.items[n:]


class Master:
    """A master streaming robot/cmd at 100 Hz: dp = dp_fn(seconds since the engagement)."""

    def __init__(self, net: Net, master_id: str, token: bool = True) -> None:
        self.node = net.node("master", instance=master_id) if token else net.node("script")
        self.id = master_id
        self.pub = self.node.publisher(keys.CMD)
        if token:
            self.node.announce()
        self._lock = threading.Lock()
        self.seq = 0
        self.engage = 0
        self.active = False
        self._dp_fn: DpFn = lambda t: (0.0, 0.0, 0.0)
        self._t0 = time.monotonic()
        self._streaming = threading.Event()
        self._closed = threading.Event()
        self._thread = threading.Thread(target=self._run, daemon=True)
        self._thread.start()

    def engage_new(self, dp_fn: DpFn | None = None) -> None:
        with self._lock:
            self.engage += 1
            self.active = True
            self._dp_fn = dp_fn or (lambda t: (0.0, 0.0, 0.0))
            self._t0 = time.monotonic()
        self._streaming.set()

    def disengage(self) -> None:
        with self._lock:
            self.active = False

    def pause(self) -> None:
        self._streaming.clear()

    def resume(self) -> None:
        self._streaming.set()

    def close(self) -> None:
        self._closed.set()
        self._streaming.set()
        self._thread.join(2.0)

    def _run(self) -> None:
        while not self._closed.is_set():
            self._streaming.wait()
            if self._closed.is_set():
                return
            with self._lock:
                self.seq += 1
                cmd = OperatorCommand(
                    seq=self.seq,
                    t_ns=time.time_ns(),
                    master=self.id,
                    engage=self.engage,
                    active=self.active,
                    frame="world",
                    dp=vec(self._dp_fn(time.monotonic() - self._t0)),
                    dR=IDENTITY_R,
                )
            if not self.node.closed:
                self.pub.put(cmd)
            time.sleep(0.01)  # the stream's rate (100 Hz), not a synchronisation


@dataclass
class Cell:
    net: Net
    console: Node
    events: Events
    arm_cmds: Recorder
    decision: DecisionService
    force: ForceService
    force_node: Node
    state: object
    closers: list[Callable[[], None]] = field(default_factory=list)

    def call(
        self, method: str, args: dict[str, object] | None = None, timeout_s: float = 5.0
    ) -> dict[str, object]:
        return self.console.call("decision", method, args or {}, timeout_s)

    def robot(self, pred: Callable[[RobotState], bool], timeout_s: float = 5.0) -> RobotState:
        st = self.state.wait_for(pred, timeout_s)  # type: ignore[attr-defined]
        if st is None:  # say where the arm was and what the decision said meanwhile
            last = self.state.get()  # type: ignore[attr-defined]
            where = None if last is None else (last.status, [round(x, 4) for x in last.tool_p])
            told = [(e.source, e.kind, e.message[:80]) for e in self.events.items][-12:]
            raise AssertionError(f"robot/state never satisfied the condition; last {where}; {told}")
        return st  # type: ignore[no-any-return]

    def tool_p(self) -> np.ndarray:
        return np.asarray(self.robot(lambda s: True).tool_p)

    def master(self, master_id: str = "m1", token: bool = True) -> Master:
        m = Master(self.net, master_id, token)
        self.closers.append(m.close)
        return m


@pytest.fixture
def make_cell(net: Net) -> Iterator[Callable[..., Cell]]:
    made: list[Cell] = []

    def make(scene: Scene = TABLE_ONLY, **decision: object) -> Cell:
        # The arm's joints and the wrist's wrench from the workcell's MuJoCo cell of `scene`,
        # the wrist at 500 Hz without the final spin (the same behaviour for a third of the
        # CPU), the decision with the default watchdogs (command 100 ms, state 200 ms, force
        # 50 ms), as deployed.
        sim = SimCell(
            net.node,
            arm=light_arm(),
            force=LIGHT_FORCE,
            decision=DecisionConfig(**decision),  # type: ignore[arg-type]
            scene=scene,
        )
        console = net.node("console")
        cell = Cell(
            net,
            console,
            Events(console),
            Recorder(console),
            sim.decision,
            sim.force,
            sim.force.node,
            console.subscribe(keys.STATE),
        )
        cell.closers.append(sim.close)
        made.append(cell)
        cell.call("connect")
        cell.call("initialize")
        cell.robot(lambda s: s.status == "ready")
        cell.robot(lambda s: s.engage == 0 and np.allclose(s.tool_p, HOME_P, atol=1e-4))
        return cell

    try:
        yield make
    finally:
        for cell in made:
            for close in cell.closers:
                close()


def ramp(target: tuple[float, float, float], speed_m_s: float) -> DpFn:
    """dp going from 0 to `target` at `speed_m_s`, then staying there."""
    goal = np.asarray(target, dtype=float)
    dist = float(np.linalg.norm(goal))

    def fn(t: float) -> tuple[float, float, float]:
        s = min(1.0, speed_m_s * t / dist) if dist > 0 else 1.0
        return (float(goal[0] * s), float(goal[1] * s), float(goal[2] * s))

    return fn


def test_facade_forwards_and_status_is_a_superset(make_cell: Callable[..., Cell]) -> None:
    cell = make_cell(Scene())  # free space: QN stretches the arm out over the table's place
    st = cell.call("status")
    assert st["mode"] == "idle" and st["lease"] is None and st["estop"] is False
    assert st["robot"]["status"] == "ready" and st["arm"]["status"] == "ready"
    assert st["force"] is not None and st["sensor"]["running"] is True
    assert {"arm", "force", "decision"} <= set(st["alive"])
    assert set(st["interventions"]) >= {
        "watchdog",
        "lease",
        "limit",
        "contact",
        "estop",
        "rejected",
    }
    fk = cell.call("fk", {"q": list(HOME_Q_RAD)})
    assert np.allclose(fk["tool_p"], HOME_P, atol=1e-5)
    assert cell.call("limits")["max_tool_speed_m_s"] > 0
    assert cell.call("sensor_read")["seq"] > 0
    # same arguments, same error codes as the arm itself
    bad = {"q": [10.0, 0, 0, 0, 0, 0]}
    with pytest.raises(RpcError) as direct:
        cell.console.call("arm", "move_joints", {**bad, "supervised_by": "decision"}, 5.0)
    with pytest.raises(RpcError) as forwarded:
        cell.call("move_joints", bad)
    assert forwarded.value.code == direct.value.code
    # a forwarded motion with "wait": true replies on completion
    # (at half speed: at full speed the tool's own inertia in the physics reads ~10 N at
    # the wrist, which the contact watch cannot tell from a contact building up)
    reply = cell.call("move_joints", {"q": list(QN_RAD), "speed": 0.5, "wait": True}, 30.0)
    assert reply["completed"] is True, (
        reply,
        [(e.kind, e.message[:120]) for e in cell.events.items][-4:],
    )
    # the `home` task is the arm's home, replied on completion
    reply = cell.call("task", {"name": "home"}, 30.0)
    assert reply["task"] == "home" and reply["completed"] is True
    cell.robot(lambda s: bool(np.allclose(s.tool_p, HOME_P, atol=1e-4)))  # the arm settles
    assert cell.call("status")["supervisor"]["last_task"]["name"] == "home"
    # a service that is down: `unavailable`
    cell.force.close()
    cell.force_node.close()
    with pytest.raises(RpcError) as down:
        cell.call("sensor_status")
    assert down.value.code == "unavailable"


def test_command_watchdog_holds_until_a_new_engagement(make_cell: Callable[..., Cell]) -> None:
    cell = make_cell()
    m = cell.master("m1")
    m.engage_new(ramp((0.0, 0.03, 0.0), 0.1))
    cell.robot(lambda s: abs(s.tool_p[1] - 0.03) < 5e-4, 5.0)
    m.pause()  # the master's link stalls
    ev = cell.events.wait(lambda e: e.kind == "watchdog" and e.source == "decision")
    assert ev.data is not None and ev.data["reason"] == "command_timeout"
    assert cell.arm_cmds.held_after(cell.arm_cmds.count())
    # the same engagement comes back: it must not move the arm
    m._dp_fn = ramp((0.0, -0.05, 0.0), 1.0)
    m.resume()
    cell.events.wait(
        lambda e: e.kind == "lease" and (e.data or {}).get("reason") == "engagement_held"
    )
    assert cell.arm_cmds.held_after(cell.arm_cmds.count())
    # a new engagement moves again, from where the tool is
    m.engage_new(ramp((0.0, -0.03, 0.0), 0.1))
    cell.robot(lambda s: abs(s.tool_p[1] - 0.0) < 5e-4, 5.0)
    assert cell.call("status")["interventions"]["watchdog"] >= 1


def test_commands_do_not_wake_the_timer_each(make_cell: Callable[..., Cell]) -> None:
    """Following a 100 Hz master, each command is supervised on arrival, in Zenoh's
    callback; the timer wakes only at the watchdog deadlines it slept to (each command
    moved them later)."""
    cell = make_cell()
    m = cell.master("m1")
    m.engage_new(ramp((0.0, 0.02, 0.0), 0.1))
    cell.robot(lambda s: abs(s.tool_p[1] - 0.02) < 5e-4, 5.0)
    before = cell.call("status")["loop"]
    assert wait_until(lambda: cell.call("status")["loop"]["ticks"] >= before["ticks"] + 40, 5.0)
    after = cell.call("status")["loop"]
    ticks = after["ticks"] - before["ticks"]
    wakes = after["timer_wakes"] - before["timer_wakes"]
    assert wakes <= ticks // 2, (wakes, ticks)  # the 40+ ticks were the commands'
    # ... taken at once in Zenoh's callback: at 100 Hz the reader keeps up (intake.py)
    inline = after["intake"]["inline"] - before["intake"]["inline"]
    assert inline >= ticks // 4, (inline, ticks, after["intake"])
    assert after["intake"]["dropped"] == 0
    assert cell.call("status")["mode"] == "follow"
    m.pause()
    cell.events.wait(lambda e: e.kind == "watchdog" and e.source == "decision")


def test_a_second_master_is_refused(make_cell: Callable[..., Cell]) -> None:
    """While m1 holds the lease, m2's engagement is refused and moves nothing.

    The lease is what is tested, so the watchdogs here are 1 s. At their defaults (tested
    above and in tests/faults) one fresh-clone CI run (2026-11-26) found the lease released,
    which in this scenario only a hold does: a watchdog after a stall of this one-process
    cell. 14 local runs, 2 busy cores beside them or not, never did."""
    cell = make_cell(watchdog_ms=1000.0, state_stale_ms=1000.0)
    m1, m2 = cell.master("m1"), cell.master("m2")
    m1.engage_new(ramp((0.0, 0.02, 0.0), 0.1))
    cell.robot(lambda s: abs(s.tool_p[1] - 0.02) < 5e-4, 5.0)
    m2.engage_new(ramp((0.05, 0.0, 0.0), 0.2))
    ev = cell.events.wait(lambda e: e.kind == "lease" and (e.data or {}).get("master") == "m2")
    assert "m1" in ev.message
    n = cell.arm_cmds.count()
    cell.arm_cmds.wait_more(n, 100)  # 0.2 s more of both masters streaming
    assert cell.tool_p()[0] == pytest.approx(0.55, abs=5e-4)  # m2 moved nothing
    st = cell.call("status")
    holds = [e.message for e in cell.events.of("lease") + cell.events.of("watchdog")]
    assert st["lease"] == "m1", holds  # a hold would have released it: say why
    assert st["interventions"]["lease"] >= 10
    refused = [e for e in cell.events.of("lease") if (e.data or {}).get("master") == "m2"]
    assert len(refused) <= 2  # rate-limited: at most one a second per master


def test_master_liveliness_lost_holds_at_once(make_cell: Callable[..., Cell]) -> None:
    cell = make_cell()
    token = cell.net.node("master", instance="m1")
    token.announce()  # alive/master/m1 on a node of its own …
    m = cell.master("m1", token=False)  # … while the commands come from another one
    m.engage_new(ramp((0.0, 0.02, 0.0), 0.1))
    cell.robot(lambda s: abs(s.tool_p[1] - 0.02) < 5e-4, 5.0)
    token.close()  # the master's process is gone; its commands still flow
    ev = cell.events.wait(lambda e: e.kind == "watchdog" and e.source == "decision")
    assert ev.data is not None and ev.data["reason"] == "master_lost"
    assert cell.arm_cmds.held_after(cell.arm_cmds.count())
    assert not [
        e for e in cell.events.of("watchdog") if (e.data or {}).get("reason") == "command_timeout"
    ]


def test_contact_with_the_table_stops_the_motion(make_cell: Callable[..., Cell]) -> None:
    cell = make_cell()
    m = cell.master("m1")
    depth = HOME_P[2] - (TOP + 0.0015)  # the hand goes to 1.5 mm above the workspace floor

    def down(t: float) -> tuple[float, float, float]:
        fast = 0.20  # 20 cm at 0.2 m/s, then the last 5 cm at 5 cm/s
        z = 0.2 * t if t < fast / 0.2 else fast + 0.05 * (t - fast / 0.2)
        return (0.0, 0.0, -min(z, depth))

    m.engage_new(down)
    ev = cell.events.wait(lambda e: e.kind == "contact" and e.source == "decision", 10.0)
    assert ev.data is not None and ev.data["force_n"] > 40.0
    # The arm trails its setpoint by a servo lag (up to 0.8 mm at 5 cm/s on a loaded
    # machine): "stopped" is measured once it has caught up with the held target.
    n = cell.arm_cmds.count()
    cell.arm_cmds.wait_more(n, 50, 10.0)
    first = cell.robot(lambda s: True)
    # (MuJoCo's soft contact and the servo: the pressed fingertips a few mm into the table)
    assert TOUCH - 0.004 < first.tool_p[2] < TOUCH + 0.002
    n = cell.arm_cmds.count()
    cell.arm_cmds.wait_more(n, 250, 10.0)  # 0.5 s of the master pushing on
    later = cell.robot(lambda s: s.seq > first.seq)
    assert TOUCH - 0.004 < later.tool_p[2] < TOUCH + 0.002  # the fingertips touch
    # stopped: 0.5 s of the master pushing on took it no deeper. (The back-off from the
    # impact's peak lifts it, by 2-3 mm on a loaded host, 2026-12-02: bounded by the band
    # above, where the fingertips still touch.)
    assert later.tool_p[2] >= first.tool_p[2] - 1e-3
    f = cell.call("sensor_read")["f"]
    assert 1.0 < float(np.linalg.norm(f)) < 1.5 * 40.0  # touching, not past the limit
    assert cell.call("status")["interventions"]["contact"] >= 1


def test_robot_force_is_received_only_while_the_arm_may_move(
    make_cell: Callable[..., Cell],
) -> None:
    """Idle, the decision is not subscribed to robot/force (and, with nobody else, the
    force service sends nothing), a master's token alone changes nothing; an engagement
    subscribes it (deferred until the first sample, never refused, even with compliance
    on, which needs the force to engage), and it stays while the master teleoperates; the
    supervisor holding, it unsubscribes. `status` still reports the force, asked of the
    sensor while unsubscribed."""
    cell = make_cell(compliance=True)
    dec = cell.decision
    assert not dec._force.watching
    assert wait_until(lambda: not cell.force._watched)
    st = cell.call("status")
    assert st["force"]["via"] == "sensor_read" and st["force"]["seq"] > 0
    m = cell.master("m1")
    assert m.node.alive.wait("master/m1", 5.0)
    m.engage_new()
    assert wait_until(lambda: cell.call("status")["mode"] == "follow")
    assert dec._force.watching and cell.force._watched
    st = cell.call("status")
    assert "via" not in st["force"] and st["force"]["age_ms"] < 1000.0
    assert st["interventions"]["rejected"] == 0  # deferred, not refused
    assert st["supervisor"]["stats"]["engagements"] == 1
    assert st["supervisor"]["stats"]["deferred"] >= 1  # it waited for the stream
    m.disengage()
    assert wait_until(lambda: cell.call("status")["mode"] == "hold")
    assert wait_until(lambda: not dec._force.watching)
    assert wait_until(lambda: not cell.force._watched)
    unsent = cell.force.unsent
    assert wait_until(lambda: cell.force.unsent > unsent)
    deferred = cell.call("status")["supervisor"]["stats"]["deferred"]
    m.engage_new()  # again from the hold: subscribed again, engaged again
    engaged = wait_until(lambda: cell.call("status")["supervisor"]["stats"]["engagements"] == 2)
    st = cell.call("status")
    assert engaged, (st["mode"], st["supervisor"]["hold_reason"], st["interventions"])
    assert st["supervisor"]["stats"]["deferred"] > deferred
    assert st["interventions"]["rejected"] == 0


def test_workspace_limit_set_through_supervisor(make_cell: Callable[..., Cell]) -> None:
    cell = make_cell()
    before = cell.call("status", {})["settings"]["workspace_max"]
    with pytest.raises(RpcError) as bad:
        cell.call("supervisor", {"workspace_max": [0.95, -0.6, 1.2]})  # max below min
    assert bad.value.code == "bad_request"
    for fixed in ({"rate_hz": 100}, {"passivity": True}):
        with pytest.raises(RpcError) as refused:
            cell.call("supervisor", fixed)
        assert refused.value.code == "bad_request" and "fixed at start-up" in str(refused.value)
    reply = cell.call("supervisor", {"workspace_max": [0.95, 0.05, 1.2]})
    assert reply["settings"]["workspace_max"] == [0.95, 0.05, 1.2]
    # the box given wins over the one the arm's description gives, now and when it comes again
    assert reply["settings"]["workspace_from_arm"] is False
    # status keeps its settings map per configuration: the change shows at once
    assert before != [0.95, 0.05, 1.2]
    assert cell.call("status", {})["settings"]["workspace_max"] == [0.95, 0.05, 1.2]
    m = cell.master("m1")
    m.engage_new(ramp((0.0, 0.12, 0.0), 0.2))
    ev = cell.events.wait(
        lambda e: e.kind == "limit" and (e.data or {}).get("reason") == "workspace"
    )
    assert ev.data is not None and ev.data["max"][1] == 0.05
    cell.robot(lambda s: abs(s.tool_p[1] - 0.05) < 5e-4, 5.0)
    n = cell.arm_cmds.count()
    cell.arm_cmds.wait_more(n, 200)
    assert cell.tool_p()[1] == pytest.approx(0.05, abs=5e-4)
    assert max(c.p[1] for c in cell.arm_cmds.since(0)) <= 0.05 + 1e-9


def test_estop_latches_until_reset(make_cell: Callable[..., Cell]) -> None:
    # The latch is the point here, not the watchdog (tested above): in two fresh-clone runs
    # this test's own 100 Hz master thread was late by over 100 ms on the loaded VM and the
    # default watchdog held the arm before the estop ("no command from master 'm1' for
    # 100 ms: holding"), as it must. 500 ms leaves the latch's checks unchanged.
    cell = make_cell(watchdog_ms=500.0)
    m = cell.master("m1")
    m.engage_new(ramp((0.0, 0.02, 0.0), 0.1))
    cell.robot(lambda s: abs(s.tool_p[1] - 0.02) < 5e-4, 5.0)
    reply = cell.call("estop")
    assert reply["estop"] is True and "error" not in reply["arm"]
    cell.events.wait(lambda e: e.kind == "estop" and (e.data or {}).get("latched") is True)
    m.engage_new(ramp((0.0, -0.05, 0.0), 0.2))  # a new engagement during the latch
    cell.events.wait(lambda e: e.kind == "estop" and (e.data or {}).get("master") == "m1")
    assert cell.arm_cmds.held_after(cell.arm_cmds.count())
    for method, args in (
        ("move_joints", {"q": list(HOME_Q_RAD)}),
        ("home", {}),
        ("task", {"name": "guarded_move", "direction": [0, 0, -1]}),
    ):
        with pytest.raises(RpcError) as e:
            cell.call(method, args)
        assert e.value.code == "estop", method
    assert cell.call("status")["estop"] is True
    assert cell.call("reset")["was_latched"] is True
    assert cell.arm_cmds.held_after(cell.arm_cmds.count())  # still that engagement
    m.engage_new(ramp((0.0, -0.02, 0.0), 0.1))
    cell.robot(lambda s: abs(s.tool_p[1] - 0.0) < 5e-4, 5.0)


def test_bad_commands_never_reach_the_arm(make_cell: Callable[..., Cell]) -> None:
    cell = make_cell()
    good = {
        "seq": 1,
        "t_ns": 1,
        "master": "x",
        "engage": 1,
        "active": True,
        "frame": "world",
        "dp": [0.0, 0.0, 0.0],
        "dR": list(IDENTITY_R),
    }
    for payload in (
        {**good, "dp": [math.nan, 0.0, 0.0]},
        {**good, "dR": [1.0, 0, 0, 0, 1.0, 0, 0, 0, -1.0]},
        {**good, "frame": "base"},
        b"\xc1 not msgpack",
    ):
        data = payload if isinstance(payload, bytes) else msgpack.packb(payload)
        cell.console.session.put(keys.CMD.key, data)
    ev = cell.events.wait(lambda e: e.kind == "rejected" and e.source == "decision")
    assert ev.data is not None and ev.data["key"] == keys.CMD.key
    deadline = time.monotonic() + 5.0
    while cell.call("status")["interventions"]["rejected"] < 4:
        assert time.monotonic() < deadline, "not every bad command was counted"
    assert cell.arm_cmds.count() == 0  # nothing was ever sent to the arm
    st = cell.call("status")
    assert st["mode"] == "idle" and st["supervisor"]["stats"]["commands"] == 0


def test_guarded_move_finds_the_table_top(make_cell: Callable[..., Cell]) -> None:
    cell = make_cell()
    down = [-1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, -1.0]
    cell.call("move_pose", {"p": [0.55, 0.0, TOUCH + 0.03], "R": down, "wait": True}, 20.0)
    m = cell.master("m1")
    m.engage_new(ramp((0.05, 0.0, 0.0), 0.1))  # an operator tries to move during the task
    reply = cell.call("task", {"name": "guarded_move", "direction": [0, 0, -1]}, 30.0)
    assert reply["contact"] is True and reply["stopped"] == "contact", reply
    # the target ≈ 5 mm past the touch when the force passed the guard (the arm's servo
    # and the contact together ≈ 5 kN/m)
    assert reply["contact_p"][2] == pytest.approx(TOUCH - 0.005, abs=0.003)
    assert reply["force_n"] > 5.0
    busy = cell.events.wait(lambda e: e.kind == "busy" and e.source == "decision")
    assert busy.data is not None and busy.data["master"] == "m1"
    st = cell.call("status")
    assert st["mode"] == "hold" and st["supervisor"]["last_task"]["done"] is True
    # the operator moved nothing (their ramp is 5 cm along x; the press's fingertip friction
    # shifts the tool by up to 0.6 mm on a loaded host, 2026-12-02)
    assert cell.tool_p()[0] == pytest.approx(0.55, abs=2e-3)


class ForceLog:
    """|f| of every robot/force sample (N), with the monotonic time it arrived."""

    def __init__(self, node: Node) -> None:
        self._lock = threading.Lock()
        self.items: list[tuple[float, float]] = []
        node.subscribe(keys.FORCE, self._on)

    def _on(self, s: object) -> None:
        f = float(np.linalg.norm(s.f))  # type: ignore[attr-defined]
        with self._lock:
            self.items.append((time.monotonic(), f))

    def since(self, t: float) -> list[tuple[float, float]]:
        with self._lock:
            return [x for x in self.items if x[0] >= t]


BLOCK_TOP = TOP + 0.05
"""block2 of the default scene: a 5 cm cube on the table at (0.50, 0, …)."""
DOWN = [-1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, -1.0]


@pytest.mark.parametrize("guard", [True, False], ids=["guarded", "unguarded"])
def test_a_move_into_a_block_stays_near_the_force_limit_and_backs_off(
    make_cell: Callable[..., Cell], guard: bool
) -> None:
    """Issue 42 item 1: `move_pose` from 5 cm above a block to 4 cm into it. Before: 549 N
    against a 40 N limit, and every motion after, away too, was stopped. Now, with the
    default guard (the goal is within 10 cm of the table: planned at 5 cm/s), the watch
    stops it at once before the force passes 1.5 × the limit; without the guard (the old
    speed) the peak is higher, and the arm backs off below the limit within 1 s. Either
    way `move_relative` away from the block then completes."""
    block2 = Scene(boxes=(TABLE, default_scene().box("block2")))
    cell = make_cell(block2, **({} if guard else {"motion_guard_zone_m": 0.0}))
    cell.call("move_pose", {"p": [0.5, 0.0, BLOCK_TOP + 0.05], "R": DOWN, "wait": True}, 20.0)
    forces = ForceLog(cell.console)
    t0 = time.monotonic()
    reply = cell.call("move_pose", {"p": [0.5, 0.0, BLOCK_TOP - 0.04], "R": DOWN, "wait": True}, 20)
    told = "; ".join(f"{e.source} {e.kind} {e.message}" for e in cell.events.items[-10:])
    assert reply["reason"] == "stopped", (reply, told)
    stop = cell.events.wait(lambda e: e.kind == "contact" and "stopped" in e.message, 10.0)
    assert stop.data is not None and stop.data["now"] is True
    assert wait_until(lambda: cell.robot(lambda s: True).status == "ready", 5.0)
    t_stop = time.monotonic()

    def under() -> bool:
        got = forces.since(t_stop)
        return bool(got) and got[-1][1] < 40.0

    assert wait_until(under, 1.0), (
        forces.since(t_stop)[-1:],
        "; ".join(f"{e.source} {e.kind} {e.message}" for e in cell.events.items[-8:]),
    )
    peak = max(f for _, f in forces.since(t0))
    if guard:
        assert peak <= 1.5 * 40.0, peak
    backing = [e for e in cell.events.of("contact") if "backing off" in e.message]
    if backing:  # it came to rest above the limit: the back-off says when it is under
        backed = cell.events.wait(lambda e: e.kind == "contact" and "backed off" in e.message)
        assert backed.data is not None and backed.data["force_n"] <= 40.0
    z = cell.tool_p()[2]
    away = cell.call("move_relative", {"dp": [0.0, 0.0, 0.05], "wait": True}, 20.0)
    told = [(e.kind, e.message) for e in cell.events.items if e.source == "decision"]

    assert away["completed"] is True, (away["reason"], told)
    # (z was taken pressed: lifted, the contact's and the servo's compression comes back)
    assert cell.tool_p()[2] == pytest.approx(z + 0.05, abs=3e-3)
