"""The supervisor's parts on their own: the events' rate limits and edges (notices.py), the
per-master records (masters.py), the forwarded-motion watch (watch.py)."""

from __future__ import annotations

import dataclasses
import itertools
import math
from collections.abc import Callable
from typing import Any

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st

from services.bus.messages import ForceSample, OperatorCommand, RobotState, vec
from services.control.decision.config import DecisionConfig
from services.control.decision.masters import MAX_MASTERS, RESTART_GAP_NS, Masters
from services.control.decision.notices import (
    EDGE_RELEASE_NS,
    MAX_NOTICE_KEYS,
    NOTICES_PER_S,
    Notices,
)
from services.control.decision.target import SupervisedTarget
from services.control.decision.watch import (
    WATCH_START_NS,
    Watch,
    WatchStop,
    contact_stop,
    forwarded_target,
    watch_step,
)
from tests.control.decision.rig import Rig

MS = 1_000_000
S = 1_000_000_000


def cmd(master: str, seq: int, engage: int = 1, t_ns: int = 0) -> OperatorCommand:
    return OperatorCommand(
        seq=seq,
        t_ns=t_ns,
        master=master,
        engage=engage,
        active=True,
        frame="world",
        dp=(0.0, 0.0, 0.0),
        dR=vec(np.eye(3)),
    )


# --- notices -------------------------------------------------------------------------------
calls = st.lists(
    st.tuples(
        st.integers(0, 400 * MS),  # time since the previous call
        st.sampled_from(["limit", "lease", "contact"]),
        st.integers(0, 5),  # which key of that kind
    ),
    max_size=120,
)


@settings(max_examples=60, deadline=None)
@given(calls)
def test_every_intervention_is_counted_and_sent_or_said_suppressed(
    seq: list[tuple[int, str, int]],
) -> None:
    notices = Notices(interval_s=1.0)
    now = 0
    asked: dict[str, int] = {}
    sent_at: dict[str, list[int]] = {}
    for dt, kind, key in seq:
        now += dt
        asked[kind] = asked.get(kind, 0) + 1
        before = len(sent_at.get(f"{kind}:{key}", []))
        notices.intervene(now, kind, "m", {"k": key}, limit_key=f"{kind}:{key}")
        out = notices.drain()
        assert len(out) <= 1
        if out:
            sent_at.setdefault(f"{kind}:{key}", []).append(now)
            assert out[0].kind == kind and out[0].data["k"] == key
            told = int(out[0].data.get("suppressed", 0))
            asked[kind] -= 1 + told
        assert len(sent_at.get(f"{kind}:{key}", [])) - before in (0, 1)
    for kind, n in asked.items():
        assert notices.suppressed.get(kind, 0) == n  # the rest is still to be told
    for times in sent_at.values():  # at most one per key per interval
        assert all(b - a >= S for a, b in itertools.pairwise(times))
    assert sum(notices.counters.values()) == len(seq)


def test_a_flood_of_keys_is_a_trickle_and_memory_stays_bounded() -> None:
    notices = Notices(interval_s=1.0)
    for i in range(3000):
        notices.intervene(i * MS, "lease", "m", {}, limit_key=f"held:{i}")
    sent = notices.drain()
    assert len(sent) == 3 * NOTICES_PER_S  # 3 s of 1 ms calls: NOTICES_PER_S a second
    assert notices.counters["lease"] == 3000
    told = sum(int(n.data.get("suppressed", 0)) for n in sent) + notices.suppressed["lease"]
    assert told == 3000 - len(sent)  # every one held back is said so
    for i in range(3000, 3000 + 2 * MAX_NOTICE_KEYS):
        notices.post(i * S, "task", "m", {}, limit_key=f"k{i}")
    assert notices.keys_remembered == MAX_NOTICE_KEYS


def test_an_edge_counts_once_until_it_has_been_off_long_enough() -> None:
    notices = Notices(interval_s=0.001)
    for i in range(100):  # 200 ms of continuous contact
        notices.edge(i * 2 * MS, "contact", True, "contact", "m", {})
    assert notices.counters["contact"] == 1
    notices.edge(198 * MS + EDGE_RELEASE_NS, "contact", True, "contact", "m", {})
    assert notices.counters["contact"] == 1  # off for exactly the release time: same one
    notices.edge(200 * MS + 2 * EDGE_RELEASE_NS, "contact", True, "contact", "m", {})
    assert notices.counters["contact"] == 2
    notices.clear_edges()  # a new engagement
    notices.edge(201 * MS + 2 * EDGE_RELEASE_NS, "contact", True, "contact", "m", {})
    assert notices.counters["contact"] == 3
    assert [n.kind for n in notices.drain()] == ["contact"] * 3


# --- masters -------------------------------------------------------------------------------
def test_masters_classify_new_stale_and_restarted() -> None:
    masters = Masters()
    assert masters.classify(cmd("a", 5, 2, t_ns=S)) == "new"
    masters.record(cmd("a", 5, 2, t_ns=S), lease=None)
    assert masters.classify(cmd("a", 5, 2, t_ns=S)) == "stale"  # same seq
    assert masters.classify(cmd("a", 6, 1, t_ns=S)) == "stale"  # lower engage
    assert masters.classify(cmd("a", 4, 2, t_ns=S + RESTART_GAP_NS)) == "stale"
    assert masters.classify(cmd("a", 1, 0, t_ns=S + RESTART_GAP_NS + 1)) == "restarted"
    assert masters.classify(cmd("a", 6, 2, t_ns=S)) == "new"
    rec = masters.record(cmd("a", 6, 3, t_ns=2 * S), lease=None)
    assert (rec.seq, rec.engage, rec.t_ns, rec.blocked) == (6, 3, 2 * S, -1)
    rec.block(2)
    rec.block(1)
    assert rec.blocked == 2
    masters.block_all()
    assert rec.blocked == 3


def test_masters_stay_bounded_and_keep_the_lease_holder() -> None:
    masters = Masters()
    masters.record(cmd("holder", 1), lease="holder")
    for i in range(5 * MAX_MASTERS):
        masters.record(cmd(f"m{i}", 1), lease="holder")
        assert len(masters) <= MAX_MASTERS and "holder" in masters
    assert list(masters)[-1] == f"m{5 * MAX_MASTERS - 1}"


def test_an_engagement_starts_where_the_arm_starts_it() -> None:
    """The arm records the setpoint's pose as an engagement's start; the measured tool
    trails it (0.13 mm here). The supervised target starts there too, so `dp = 0` is "stay
    where the arm aims", and the checks see the target the arm will reach."""
    measured = state("moving")
    setpoint = (0.6, 0.0, 0.6 - 1.3e-4)
    target = SupervisedTarget(0, 0, 0.002)
    target.begin(dataclasses.replace(measured, tool_p_cmd=setpoint), 0, 0.002)
    assert target.p0 is not None and np.array_equal(target.p0, setpoint)
    assert np.array_equal(target.p_sup, setpoint)
    target.begin(measured, 1, 0.002)  # a arm that does not say: the measured pose
    assert target.p0 is not None and np.array_equal(target.p0, measured.tool_p)


# --- watch ---------------------------------------------------------------------------------
def state(status: str, p: tuple[float, float, float] = (0.6, 0.0, 0.6)) -> RobotState:
    return Rig(p=p, status=status).robot_state()


def test_a_watch_ends_with_the_motion_and_stops_it_at_a_contact_or_the_box() -> None:
    cfg = DecisionConfig()
    w = Watch("move_pose", since_ns=0)
    assert watch_step(w, cfg, 1, state("ready"), None) is w  # not started yet
    assert watch_step(w, cfg, WATCH_START_NS + 1, state("ready"), None) is None  # never did
    w = Watch("move_pose", since_ns=0)
    assert watch_step(w, cfg, 1, state("moving"), None) is w and w.moving
    assert watch_step(w, cfg, 2, state("ready"), None) is None  # over
    w = Watch("home", since_ns=0)
    free = ForceSample(seq=1, t_ns=0, f=(0.0, 0.0, 0.0), c=(0.0, 0.0, 0.0))
    assert watch_step(w, cfg, 1, state("moving"), free) is w
    push = ForceSample(seq=2, t_ns=10**9, f=(0.0, 0.0, cfg.max_force_n + 1.0), c=(0.0, 0.0, 0.0))
    stop = watch_step(w, cfg, 1, state("moving"), push)
    assert isinstance(stop, WatchStop) and stop.kind == "contact"
    assert stop.data["method"] == "home" and stop.data["force_n"] > cfg.max_force_n
    assert stop.data["now"] is True  # at once: braking would press on
    out = (0.6, 0.0, cfg.workspace_min[2] - 0.01)
    stop = watch_step(Watch("home", 0), cfg, 1, state("moving", out), None)
    assert isinstance(stop, WatchStop) and stop.kind == "limit"
    assert stop.data["reason"] == "workspace"


unit = st.tuples(*[st.floats(-1.0, 1.0)] * 3).filter(lambda v: math.hypot(*v) > 0.1)


@settings(max_examples=200, deadline=None)
@given(u=unit, w=unit, f_n=st.floats(45.0, 2_000.0), dist=st.floats(0.002, 0.3))
def test_a_motion_leaving_a_contact_is_never_stopped_for_it_and_one_into_it_always(
    u: tuple[float, float, float],
    w: tuple[float, float, float],
    f_n: float,
    dist: float,
) -> None:
    """A watched motion that began below the limit meets a force `f_n` above it, pushing the
    tool along `u` (world): a goal within 55° of `u` leaves the contact and goes on, one past
    65° is stopped; without a goal the limit applies as before."""
    cfg = DecisionConfig()
    st_ = state("moving")
    R = np.asarray(st_.tool_R, dtype=float).reshape(3, 3)
    a = np.asarray(u) / np.linalg.norm(u)
    b = np.asarray(w) - (np.asarray(w) @ a) * a  # ⟂ a, for the goal's angle from it
    if np.linalg.norm(b) < 1e-3:
        b = np.cross(a, [1.0, 0.0, 0.0]) if abs(a[0]) < 0.9 else np.cross(a, [0.0, 1.0, 0.0])
    b /= np.linalg.norm(b)

    def sample(seq: int, force_w: np.ndarray) -> ForceSample:
        f = R.T @ force_w  # the sensor's frame is the tool's
        return ForceSample(seq=seq, t_ns=seq * S, f=(f[0], f[1], f[2]), c=(0.0, 0.0, 0.0))

    for deg, stopped in ((0.0, False), (55.0, False), (65.0, True), (180.0, True), (None, True)):
        goal = None
        if deg is not None:
            th = math.radians(deg)
            d = math.cos(th) * a + math.sin(th) * b
            g = np.asarray(st_.tool_p) + dist * d
            goal = (float(g[0]), float(g[1]), float(g[2]))
        watch = Watch("move_relative", since_ns=0, goal=goal)
        assert watch_step(watch, cfg, 1, st_, sample(1, 0.5 * cfg.max_force_n * a)) is watch
        got = watch_step(watch, cfg, 2, st_, sample(2, f_n * a))
        assert isinstance(got, WatchStop) is stopped, (deg, got)


Ask = Callable[[str, dict[str, Any]], dict[str, Any] | None]


def test_a_forwarded_motion_s_target_point_by_method_and_frame() -> None:
    st_ = state("ready")  # tool at (0.6, 0, 0.6), tool and flange z down: diag(−1, 1, −1)
    asked: list[tuple[str, dict[str, object]]] = []

    def arm(reply: dict[str, object] | None) -> Ask:
        def ask(method: str, args: dict[str, object]) -> dict[str, object] | None:
            asked.append((method, args))
            return reply

        return ask

    def target(
        method: str, args: dict[str, object], reply: dict[str, object] | None = None
    ) -> list[float] | None:
        return forwarded_target(method, args, lambda: st_, arm(reply))

    assert target("move_pose", {"p": [0.5, 0.1, 0.4]}) == [0.5, 0.1, 0.4]
    assert target("move_pose", {"p": [1e9, 0.0, 0.0]}) is None  # absurd: the arm refuses it
    assert target("move_pose", {"p": "here"}) is None
    dp = [0.01, 0.02, 0.03]
    assert np.allclose(target("move_relative", {"dp": dp, "frame": "world"}), [0.61, 0.02, 0.63])
    assert np.allclose(target("move_relative", {"dp": dp, "frame": "tool"}), [0.59, 0.02, 0.57])
    assert np.allclose(target("move_relative", {"dp": dp, "frame": "wrist"}), [0.59, 0.02, 0.57])
    assert asked == []
    # no frame: the arm's own (`set_frame`), asked; world if it cannot say
    assert np.allclose(target("move_relative", {"dp": dp}, {"frame": "tool"}), [0.59, 0.02, 0.57])
    assert np.allclose(target("move_relative", {"dp": dp}, None), [0.61, 0.02, 0.63])
    assert [m for m, _ in asked] == ["status", "status"]
    assert target("move_relative", {"dp": dp, "frame": "elsewhere"}) is None
    assert (
        forwarded_target("move_relative", {"dp": dp, "frame": "world"}, lambda: None, arm(None))
        is None
    )
    asked.clear()
    q = [0.0, 0.1, 0.2, 0.3, 0.4, 0.5]
    assert target("move_joints", {"q": q}, {"tool_p": [0.1, 0.2, 0.3]}) == [0.1, 0.2, 0.3]
    assert target("move_joints", {"q": q}, None) is None  # the arm refused fk
    # any joint count is the arm's to judge (n joints, contract v2): its fk refuses 5 of 6
    assert target("move_joints", {"q": q[:5]}) is None
    assert target("move_joints", {"q": q * 6}) is None  # 36: no arm has that many
    assert asked == [("fk", {"q": q}), ("fk", {"q": q}), ("fk", {"q": q[:5]})]
    assert target("home", {}) is None


def _sample(i: int, f_n: float) -> ForceSample:
    """The i-th 1 kHz sample, pressing |f| = f_n straight up (the tool points down)."""
    return ForceSample(seq=i, t_ns=i * 1_000_000, f=(0.0, 0.0, -f_n), c=(0.0, 0.0, 0.0))


@settings(max_examples=60, deadline=None)
@given(
    speed=st.floats(0.005, 0.05),  # the tool speed into the contact: up to the guard's
    angle=st.floats(0.0, 1.0),  # from the surface's normal (rad)
    stiffness=st.floats(5_000.0, 20_000.0),  # up to contact_stiffness_n_per_m
    delay_ms=st.integers(1, 8),  # from the stopping sample to the arm told to hold
    decel=st.floats(2.0, 20.0),  # the arm's deceleration once told (m/s², PUMA ≥ 2.2)
    phase_ms=st.integers(0, 4),  # where the 200 Hz watch falls against the contact
)
def test_a_watched_approach_stops_within_one_and_a_half_times_the_limit(
    speed: float, angle: float, stiffness: float, delay_ms: int, decel: float, phase_ms: int
) -> None:
    """The contact stop as a property: a tool meets a surface at any angle, speed up to the
    guarded 5 cm/s and stiffness up to the configured 20 kN/m; the watch judges every 5th
    1 kHz sample; once it says stop, the arm goes on for `delay_ms` and then decelerates.
    The peak force never passes 1.5 × max_force_n."""
    cfg = DecisionConfig()
    v = speed * math.cos(angle)  # into the surface
    w = Watch("move_pose", since_ns=0)
    depth, peak, stopped_at = -0.002, 0.0, None  # 2 mm above it at first
    for i in range(1, 60_000):
        depth += v * 1e-3
        f_n = stiffness * max(depth, 0.0)
        peak = max(peak, f_n)
        judged = stopped_at is None and i % 5 == phase_ms
        if judged and contact_stop(w, cfg.max_force_n, i * 1_000_000, f_n) is not None:
            stopped_at = i
        if stopped_at is not None and i - stopped_at >= delay_ms:
            v = max(0.0, v - decel * 1e-3)
            if v == 0.0:
                break
    assert stopped_at is not None and v == 0.0
    assert peak <= 1.5 * cfg.max_force_n, (peak, stopped_at)


@settings(max_examples=100, deadline=None)
@given(
    start=st.floats(41.0, 2_000.0),
    falls=st.lists(st.floats(0.0, 5.0), min_size=1, max_size=50),
    rise=st.floats(0.0, 3.8),
)
def test_a_motion_that_lowers_a_contact_force_is_never_stopped_for_it(
    start: float, falls: list[float], rise: float
) -> None:
    """Started pressing harder than the limit (after a stop, say), a motion that lowers the
    force, or lets it creep up by less than 10 % of the limit, goes on: the way out. (The
    creep's own rate counts: 3.89 N in the last 0.995 s, projected CONTACT_REACT_S ahead,
    passes start + 4 N and is "heading past"; 3.8 N over ≥ 0.75 s stays below it.)"""
    cfg = DecisionConfig()
    w = Watch("move_relative", since_ns=0)
    f_n = start
    assert contact_stop(w, cfg.max_force_n, 0, f_n) is None
    for i, d in enumerate(falls, 1):
        f_n = max(0.0, f_n - d)
        assert contact_stop(w, cfg.max_force_n, i * 5_000_000, f_n) is None
    assert contact_stop(w, cfg.max_force_n, 10**9, f_n + rise) is None
    assert contact_stop(w, cfg.max_force_n, 2 * 10**9, start + 0.2 * cfg.max_force_n) == ">"
