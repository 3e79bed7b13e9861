"""Safety properties of the pure Supervisor under random command streams (hypothesis).

Raw command maps go through `codec.from_fields`, as the node's subscription does, so garbage
and NaN are refused there and only valid commands reach the supervisor, in any order: stale
seq, huge jumps, several masters, lost masters, pushes on the tool, e-stops, at random
intervals (a master at 30 Hz or 10 kHz, bursts). Whatever happens, the supervised target never
leaves the workspace box, never moves faster than the speed limits over the time since it
last moved (one period's worth at an engagement's first step), and an engagement that was
held never moves again.
"""

from __future__ import annotations

from typing import Any

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import event as note
from hypothesis import strategies as st

from services.bus.codec import from_fields, to_fields
from services.bus.errors import ProtocolError, RpcError
from services.bus.messages import OperatorCommand
from services.control.decision.config import DecisionConfig
from services.control.decision.filters import in_box
from services.control.decision.target import MAX_SPAN_S
from services.control.decision.tasks import guarded_move_plan
from services.geometry import angle_between, exp_so3
from tests.control.decision.rig import Rig

CFG = DecisionConfig()
LO, HI = np.array(CFG.workspace_min), np.array(CFG.workspace_max)
PERIOD_NS = int(CFG.period_s * 1e9)

any_float = st.one_of(
    st.floats(allow_nan=True, allow_infinity=True),
    st.floats(-1e3, 1e3),
    st.floats(-0.3, 0.3),
)
small = st.lists(st.floats(-0.3, 0.3), min_size=3, max_size=3)
jump = st.lists(st.floats(-2.0, 2.0), min_size=3, max_size=3)  # huge jumps
#: valid floats, absurd magnitudes: 1e308, subnormals, anything finite (issue: they moved it)
absurd = st.lists(
    st.one_of(
        st.floats(allow_nan=False, allow_infinity=False),
        st.sampled_from([1e308, -1e308, 1e300, 5e-324, -5e-324, 2.2250738585072014e-308]),
    ),
    min_size=3,
    max_size=3,
)
garbage = st.one_of(
    st.lists(any_float, min_size=3, max_size=3),
    st.lists(any_float, max_size=5),
    st.text(max_size=3),
    st.none(),
)
raw_vec3 = st.one_of(small, small, small, jump, garbage)
rotation = st.lists(st.floats(-3.0, 3.0), min_size=3, max_size=3).map(
    lambda w: [float(x) for x in exp_so3(w).ravel()]
)
raw_rot = st.one_of(
    rotation, rotation, rotation, st.lists(any_float, min_size=9, max_size=9), st.just("I")
)
garbage_cmd = st.fixed_dictionaries(
    {
        "seq": st.one_of(st.none(), st.integers(-3, 300), st.just("7")),
        "master": st.sampled_from(["a", "b", ""]),
        "engage": st.one_of(st.integers(0, 3), st.integers(-2, 10**6)),
        "active": st.sampled_from([True, False, 1]),
        "frame": st.sampled_from(["world", "tool", "base"]),
        "dp": raw_vec3,
        "dR": raw_rot,
    },
    optional={"grip": any_float},
)
valid_cmd = st.fixed_dictionaries(
    {
        "seq": st.one_of(st.none(), st.none(), st.none(), st.integers(0, 300)),  # None: next
        "master": st.sampled_from(["a", "a", "b"]),
        "engage": st.integers(0, 3),
        "active": st.sampled_from([True, True, True, False]),
        "frame": st.sampled_from(["world", "tool"]),
        "dp": st.one_of(small, small, jump, absurd),
        "dR": rotation,
    },
    optional={"grip": st.floats(0, 1)},
)
raw_cmd = st.one_of(valid_cmd, valid_cmd, valid_cmd, garbage_cmd)
event = st.one_of(
    st.tuples(st.just("cmd"), raw_cmd),
    st.tuples(st.just("cmd"), raw_cmd),
    st.tuples(st.just("cmd"), raw_cmd),
    st.tuples(st.just("ticks"), st.integers(1, 25)),
    st.tuples(st.just("ticks"), st.integers(1, 60)),
    st.tuples(st.just("lost"), st.sampled_from(["master/a", "master/b", "arm", "force"])),
    st.tuples(st.just("push"), st.lists(st.floats(-200, 200), min_size=3, max_size=3)),
    st.tuples(st.just("estop"), st.booleans()),
    st.tuples(st.just("task"), st.lists(st.floats(-1, 1), min_size=3, max_size=3)),
)
start = st.tuples(st.floats(LO[0], HI[0]), st.floats(LO[1], HI[1]), st.floats(LO[2], HI[2]))
#: time between two inputs (ns): a 1 kHz master, 100 Hz, 30 Hz, a burst, the nominal period
interval = st.sampled_from([PERIOD_NS, PERIOD_NS, 1_000_000, 10_000_000, 33_000_000, 50_000])


class Checker:
    """Feeds the events to a Rig and checks the invariants after every tick."""

    def __init__(self, rig: Rig) -> None:
        self.rig = rig
        self.p = rig.p.copy()  # the first engagement starts from the tool's pose
        self.R = rig.R.copy()
        self.t_moved = rig.now_ns
        self.held: set[int] = set()
        self.last_active: dict[int, OperatorCommand] = {}
        self.last_seq = -1
        self.n_out = 0
        self.pending: list[OperatorCommand] = []

    def tick(self, lost: tuple[str, ...] = (), dt_ns: int = PERIOD_NS) -> None:
        rig = self.rig
        rig.step(self.pending, lost=lost, dt_ns=dt_ns)
        self.pending = []
        sup = rig.sup
        if sup.stats["engagements"] == 0:
            self.t_moved = rig.now_ns
            return  # nothing was ever commanded: there is no target yet
        step = float(np.linalg.norm(sup.target.p_sup - self.p))
        turn = angle_between(self.R, sup.target.R_sup)
        # The limit is a rate over time: since the target last moved, capped at one watchdog
        # period (longer is a hold), at least one period (an engagement's first step).
        span_s = min(max(rig.now_ns - self.t_moved, PERIOD_NS), CFG.watchdog_ms * 1e6) * 1e-9
        span_s = min(span_s, MAX_SPAN_S)
        assert step <= CFG.max_tool_speed_m_s * span_s + 1e-12, f"target jumped {step} m"
        assert turn <= CFG.max_tool_rot_speed_rad_s * span_s + 1e-9
        assert in_box(sup.target.p_sup, LO, HI, tol=1e-12), (
            f"target {sup.target.p_sup} left the box"
        )
        cfg = rig.config
        if cfg.approach_zone_m > 0.0:
            # towards a face, inside its zone: at most the approach speed over the span
            slow = cfg.approach_speed_m_s * span_s + 1e-12
            for i in range(3):
                a, b = float(self.p[i]), float(sup.target.p_sup[i])
                if b < a:
                    assert a - b <= max(a - LO[i] - cfg.approach_zone_m, 0.0) + slow, (
                        f"axis {i}: {a - b} m towards the min face inside the approach zone"
                    )
                elif b > a:
                    assert b - a <= max(HI[i] - a - cfg.approach_zone_m, 0.0) + slow, (
                        f"axis {i}: {b - a} m towards the max face inside the approach zone"
                    )
        if step > 0.0 or turn > 0.0:
            self.t_moved = rig.now_ns
        self.p, self.R = sup.target.p_sup.copy(), sup.target.R_sup.copy()
        for c in rig.outputs[self.n_out :]:
            to_fields(c.target)
            assert c.seq > self.last_seq
            self.last_seq = c.seq
            if c.active:
                assert c.engage not in self.held, "a held engagement moved again"
                self.last_active[c.engage] = c
            else:
                self.held.add(c.engage)
                last = self.last_active.get(c.engage)
                if last is not None:  # the hold repeats the last target sent
                    assert c.dp == last.dp and c.dR == last.dR
        self.n_out = len(rig.outputs)

    def command(self, raw: dict[str, Any], seqs: dict[str, int]) -> None:
        data = dict(raw)
        master = data.get("master")
        if data["seq"] is None and isinstance(master, str):
            seqs[master] = seqs.get(master, 0) + 1
            data["seq"] = seqs[master]
        data["t_ns"] = self.rig.now_ns
        try:
            cmd = from_fields(OperatorCommand, data)
        except ProtocolError:
            return  # the node's subscription drops it: it never reaches the supervisor
        self.pending.append(cmd)


@pytest.mark.filterwarnings("ignore:overflow encountered:RuntimeWarning")  # 1e308 squared → "no"
@settings(max_examples=120, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(
    p=start,
    compliance=st.booleans(),
    zone=st.sampled_from([0.0, 0.0, 0.02, 0.3]),
    events=st.lists(st.tuples(event, interval), min_size=8, max_size=50),
)
def test_random_streams_never_leave_the_box_nor_exceed_the_speed_limits(
    p: tuple[float, float, float],
    compliance: bool,
    zone: float,
    events: list[tuple[tuple[str, Any], int]],
) -> None:
    """... nor, with an approach zone (0.3 m: the whole box is near a face), move towards a
    face faster than the approach speed inside its zone."""
    rig = Rig(DecisionConfig(compliance=compliance, approach_zone_m=zone), p=p)
    check = Checker(rig)
    seqs: dict[str, int] = {}
    for (kind, value), dt_ns in events:
        if kind == "cmd":
            check.command(value, seqs)
            check.tick(dt_ns=dt_ns)
        elif kind == "ticks":
            for _ in range(value):
                check.tick(dt_ns=dt_ns)
        elif kind == "lost":
            check.tick(lost=(value,), dt_ns=dt_ns)
        elif kind == "push":
            rig.push_w = np.asarray(value, dtype=float)
        elif kind == "estop":
            if value:
                rig.sup.estop(rig.now_ns)
            else:
                rig.sup.reset(rig.now_ns)
        elif kind == "task":
            try:
                direction = value if np.linalg.norm(value) > 1e-3 else [0.0, 0.0, -1.0]
                plan = guarded_move_plan({"direction": direction, "speed_m_s": 0.25}, CFG)
                rig.sup.start_task(plan, rig.now_ns)
            except RpcError:
                pass
        check.tick()
    stats = rig.sup.stats
    note(f"engagements: {min(stats['engagements'], 3)}")
    note(f"moved: {bool(rig.outputs and any(np.any(c.dp) for c in rig.outputs))}")
    note(f"interventions: {sum(1 for v in rig.sup.notices.counters.values() if v)}")
