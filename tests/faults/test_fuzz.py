"""Bad input everywhere: random payloads on every subscribed stream, random arguments to every
method of arm, force and decision. Nothing crashes, nothing moves, every rejection is
counted and reported.

These run IN-PROCESS for speed: the real ArmService (sim arm), ForceService (sim sensor),
DecisionService, a MasterService (virtual device, never engaged) and the console's BusMirror,
each on a Zenoh node of its own on a private `net`, exactly as the processes would wire them;
the fuzzer is one more node. Per-node counters (`Subscription.rejected`, `Node.rejected`,
the proxy's counters) are read directly, so the counts are exact.
"""

from __future__ import annotations

import math
import threading
import time
from collections import Counter
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from services.bus import codec, keys
from services.bus.errors import ERROR_CODES, ProtocolError, RpcError, Unavailable
from services.bus.keys import Topic
from services.bus.messages import (
    IDENTITY_R,
    ArmTarget,
    Event,
    ForceSample,
    MasterState,
    OperatorCommand,
    RobotState,
)
from services.bus.node import REJECT_REPORT_INTERVAL_S, Node
from services.control.arm.config import ArmConfig
from services.control.arm.model import load_model
from services.control.arm.service import MOTIONS, ArmService
from services.control.decision.config import DecisionConfig
from services.control.decision.service import ARM_METHODS, FORCE_METHODS, DecisionService
from services.control.force.config import ForceConfig
from services.control.force.service import ForceService
from services.control.master.config import MasterConfig
from services.control.master.service import MasterService
from services.frontends.console.mirror import BusMirror
from tests.conftest import Net, wait_until
from tests.faults.observe import REST_TOL_RAD, record

HOME_Q_RAD = load_model().home
"""The default model's home (the PUMA 560's)."""

pytestmark = [pytest.mark.faults, pytest.mark.timeout(180)]

CALL_TIMEOUT_S = 5.0
FUZZ_SETTINGS = settings(
    deadline=None,
    database=None,
    suppress_health_check=[HealthCheck.function_scoped_fixture, HealthCheck.too_slow],
)

# --- what is fuzzed --------------------------------------------------------------------------

FUZZED_TOPICS: tuple[Topic[Any], ...] = (
    keys.CMD,
    keys.ARM_TARGET,
    keys.STATE,
    keys.FORCE,
    keys.MASTER_STATE,
)
PUMA_RPC: tuple[str, ...] = (
    "status",
    "connect",
    "initialize",
    "set_tool",
    "set_frame",
    "stop",
    "estop",
    "fk",
    "ik",
    "limits",
    *MOTIONS,
)
FORCE_RPC: tuple[str, ...] = (*FORCE_METHODS, "set_tool")
DECISION_RPC: tuple[str, ...] = (
    *ARM_METHODS,
    *FORCE_METHODS,
    "status",
    "supervisor",
    "estop",
    "reset",
    "task",
)
METHODS: dict[str, tuple[str, ...]] = {
    "arm": PUMA_RPC,
    "force": FORCE_RPC,
    "decision": DECISION_RPC,
}
MOVERS = frozenset({*MOTIONS, "task"})
"""Methods that may legitimately move the arm when their arguments happen to be valid."""
ARG_NAMES = (
    "p",
    "R",
    "q",
    "dp",
    "dR",
    "frame",
    "speed",
    "config",
    "wait",
    "timeout_s",
    "period_ms",
    "priority",
    "K_l",
    "K_r",
    "n",
    "name",
    "reason",
    "compliance",
    "watchdog_ms",
    "workspace_min",
    "workspace_max",
    "max_force_n",
    "estop_power_off",
    "distance_m",
    "direction",
)

# --- strategies ---------------------------------------------------------------------------

_ROT_Z90 = (0.0, -1.0, 0.0, 1.0, 0.0, 0.0, 0.0, 0.0, 1.0)
BAD_VALUES = st.sampled_from(
    [
        math.nan,
        math.inf,
        -math.inf,
        1e308,
        -(2**63),
        2**64 - 1,
        [math.nan] * 3,
        [math.inf] * 6,
        [1.0] * 9,  # not a rotation
        [1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, -1.0],  # a reflection
        [0.0] * 8,
        [*_ROT_Z90, 0.0],
        "",
        "x" * 5000,
        b"\x00" * 16,
        {},
        [],
        True,
    ]
)
SCALARS = (
    st.none()
    | st.booleans()
    | st.integers(min_value=-(2**63), max_value=2**64 - 1)
    | st.floats()
    | st.text(max_size=12)
    | st.binary(max_size=12)
)
VALUES = st.recursive(
    SCALARS | BAD_VALUES,
    lambda inner: (
        st.lists(inner, max_size=10) | st.dictionaries(st.text(max_size=8), inner, max_size=5)
    ),
    max_leaves=24,
)
#: valid floats of every magnitude: 1e308, subnormals, the full range (finite but absurd)
ANY_MAGNITUDE = st.floats(allow_nan=False, allow_infinity=False) | st.sampled_from(
    [1e308, -1e308, 1e300, 5e-324, -5e-324, 2.2250738585072014e-308, 1e-300]
)
VECTORS = st.integers(min_value=1, max_value=10).flatmap(
    lambda n: st.lists(
        st.floats(min_value=-4.0, max_value=4.0) | ANY_MAGNITUDE, min_size=n, max_size=n
    )
)
ARG_VALUES = VALUES | VECTORS | BAD_VALUES


def _valid_maps() -> dict[str, dict[str, Any]]:
    """One valid wire map per fuzzed topic: the seed of the near-valid mutations."""
    now = time.time_ns()
    msgs = {
        keys.CMD.key: OperatorCommand(1, now, "m", 1, True, "world", (0.0,) * 3, IDENTITY_R),
        keys.ARM_TARGET.key: ArmTarget(1, now, now, "m", 1, (0.5, 0.0, 0.6), IDENTITY_R),
        keys.STATE.key: RobotState(
            1, now, "ready", HOME_Q_RAD, (0.5, 0, 0.6), IDENTITY_R, (0.5, 0, 0.8), IDENTITY_R, 1, 1
        ),
        keys.FORCE.key: ForceSample(1, now, (0.0,) * 3, (0.0,) * 3),
        keys.MASTER_STATE.key: MasterState(
            1, now, "m", 1, True, "world", 1.0, 1.0, (0.0,) * 3, IDENTITY_R, "virtual"
        ),
    }
    return {k: codec.to_fields(m) for k, m in msgs.items()}


VALID = _valid_maps()


def is_rejected(topic: Topic[Any], payload: bytes) -> bool:
    """Whether the contract rejects `payload` on `topic` (what every subscriber must do)."""
    try:
        codec.decode(topic.type, payload)
    except ProtocolError:
        return True
    return False


@st.composite
def bad_payloads(draw: st.DrawFn, topic: Topic[Any]) -> bytes:
    """Raw random bytes, a random msgpack structure (often a map with the message's field
    names), or a valid message with fields removed or replaced; always one the contract
    rejects."""
    kind = draw(st.sampled_from(("raw", "msgpack", "mutated")))
    if kind == "raw":
        payload = draw(st.binary(max_size=300))
    elif kind == "msgpack":
        names = st.sampled_from(sorted(VALID[topic.key])) | st.text(max_size=8)
        obj = draw(VALUES | st.dictionaries(names, VALUES, max_size=14))
        payload = codec.pack(obj)
    else:
        m = dict(VALID[topic.key])
        victims = draw(st.lists(st.sampled_from(sorted(m)), min_size=1, max_size=3, unique=True))
        for name in victims:
            if draw(st.booleans()):
                del m[name]
            else:
                m[name] = draw(BAD_VALUES | VALUES)
        if draw(st.booleans()):
            m[draw(st.text(max_size=8))] = draw(VALUES)  # unknown fields are ignored
        payload = codec.pack(m)
    if not is_rejected(topic, payload):
        # Rarely a mutation is still valid (e.g. an optional field set to nil): make it bad.
        payload = payload + b"\xc1"  # a byte msgpack never uses: extra data
    return payload


ARGS = st.dictionaries(st.sampled_from(ARG_NAMES) | st.text(max_size=10), ARG_VALUES, max_size=5)


# --- the system -----------------------------------------------------------------------------


@dataclass
class System:
    net: Net
    arm: ArmService
    force: ForceService
    decision: DecisionService
    master: MasterService
    fuzzer: Node
    watcher: Node
    state: Any
    events: list[Event] = field(default_factory=list)
    lock: threading.Lock = field(default_factory=threading.Lock)

    @property
    def nodes(self) -> dict[str, Node]:
        """The service nodes under test (not the fuzzer's or the watcher's)."""
        return {
            "arm": self.arm.node,
            "force": self.force.node,
            "decision": self.decision.node,
            "master": self.master.node,
            "console": self._console,
        }

    _console: Node = field(default=None)  # type: ignore[assignment]

    def q(self) -> np.ndarray:
        st_ = self.state.latest
        assert st_ is not None
        return np.asarray(st_.q)

    def fresh_q(self) -> np.ndarray:
        """Joints from a robot/state published after now."""
        n = self.state.received
        assert self.state.wait_count(n + 2, 5.0), "robot/state stopped"
        return self.q()

    def settle(self, timeout_s: float = 30.0) -> np.ndarray:
        """Bring the arm to rest (stop any motion) and return where it rests."""
        self.arm.proxy.rpc_stop({})
        deadline = time.monotonic() + timeout_s
        q = self.fresh_q()
        while time.monotonic() < deadline:
            self.state.wait_count(self.state.received + 25, 1.0)
            q2 = self.q()
            if self.arm.proxy.status != "moving" and np.max(np.abs(q2 - q)) <= REST_TOL_RAD:
                return q2
            q = q2
        raise AssertionError("the arm did not come to rest")

    def rejected_on_subs(self, key: str) -> dict[str, int]:
        """Per service node: rejections counted by its subscriptions to `key`."""
        out = {}
        for name, node in self.nodes.items():
            subs = [s for s in node._subs if s.topic.key == key]
            if subs:
                out[name] = sum(s.rejected for s in subs)
        return out

    def reported(self, source: str, key: str) -> int:
        """The highest count a `rejected` event of `source` reported for `key`."""
        with self.lock:
            counts = [
                int((e.data or {}).get("count", 0))
                for e in self.events
                if e.source == source and e.kind == "rejected" and (e.data or {}).get("key") == key
            ]
        return max(counts, default=0)


@pytest.fixture
def system(net: Net) -> Iterator[System]:
    closers: list[Callable[[], None]] = []
    try:
        arm = ArmService(net.node("arm"), ArmConfig(sim_calibration_s=0.05))
        closers.append(arm.close)
        force = ForceService(net.node("force"), ForceConfig(seed=1))
        closers.append(force.close)
        decision = DecisionService(net.node("decision"), DecisionConfig())
        closers.append(decision.close)
        master_cfg = MasterConfig(device="virtual", engage_on_start=False)
        master = MasterService(net.node("master", instance="master"), master_cfg)
        closers.append(master.close)
        console = net.node("console")
        BusMirror(console, events=256, force_capacity=64)
        watcher = net.node("watcher")
        sys_ = System(net, arm, force, decision, master, net.node("fuzzer"), watcher, None)
        sys_._console = console

        def on_event(ev: Event) -> None:
            with sys_.lock:
                sys_.events.append(ev)

        watcher.subscribe(keys.EVENTS, on_event)
        sys_.state = watcher.subscribe(keys.STATE)
        watcher.call("arm", "connect", {}, 30.0)
        watcher.call("arm", "initialize", {}, 30.0)
        assert sys_.state.wait_for(lambda s: s.status == "ready", 30.0) is not None
        for name in ("arm", "force", "decision", "master/master"):
            assert watcher.alive.wait(name, 30.0)
        yield sys_
    finally:
        for close in reversed(closers):
            close()


def _answers_status(s: System) -> None:
    """Every service still answers, and its loop threads still run."""
    assert s.watcher.call("arm", "status", {}, CALL_TIMEOUT_S)["status"]
    assert "running" in s.watcher.call("force", "sensor_status", {}, CALL_TIMEOUT_S)
    assert s.watcher.call("decision", "status", {}, CALL_TIMEOUT_S)["service"] == "decision"
    assert s.watcher.call("master/master", "status", {}, CALL_TIMEOUT_S)["master"] == "master"
    assert s.arm._thread.is_alive() and s.decision._thread.is_alive()
    assert s.master._thread.is_alive()


# --- subscribers ---------------------------------------------------------------------------


def test_random_payloads_on_every_stream_are_rejected_counted_reported_and_move_nothing(
    system: System,
) -> None:
    s = system
    pubs = {t.key: s.fuzzer.publisher(t) for t in FUZZED_TOPICS}
    before = {t.key: s.rejected_on_subs(t.key) for t in FUZZED_TOPICS}
    q0 = s.settle()
    sent: Counter[str] = Counter()

    @settings(FUZZ_SETTINGS, max_examples=500)
    @given(st.data())
    def fuzz(data: st.DataObject) -> None:
        topic = data.draw(st.sampled_from(FUZZED_TOPICS))
        payload = data.draw(bad_payloads(topic))
        pubs[topic.key].put_bytes(payload)
        sent[topic.key] += 1

    fuzz()
    # Dangerous but well-formed targets on robot/arm/target: beyond the arm's reach or its
    # step bound. The arm must refuse them itself (the decision server is bypassed here).
    now = time.time_ns()
    far = [
        codec.encode(ArmTarget(10**9 + i, now, now, "rogue", 10**9, p, IDENTITY_R))
        for i, p in enumerate([(3.0, 0.0, 0.0), (0.0, 0.0, -1e9), (1.0, 0.6, 0.6)])
    ]
    arm_rejected0 = s.arm.proxy.counters["rejected"]
    for i, p in enumerate(far):
        # robot/arm/target is latest-wins: the control loop applies only the newest target
        # of each tick, so each one is sent once the previous one has been dealt with.
        pubs[keys.ARM_TARGET.key].put_bytes(p)
        deadline = time.monotonic() + 5.0
        while s.arm.proxy.counters["rejected"] - arm_rejected0 <= i:
            assert time.monotonic() < deadline, "the arm never refused the command"
            s.state.wait_count(s.state.received + 1, 0.1)

    def delivered() -> bool:
        return all(
            n - before[t.key].get(name, 0) >= sent[t.key]
            for t in FUZZED_TOPICS
            for name, n in s.rejected_on_subs(t.key).items()
        ) and (s.arm.proxy.counters["rejected"] - arm_rejected0 >= len(far))

    deadline = time.monotonic() + 20.0
    while not delivered() and time.monotonic() < deadline:
        s.state.wait_count(s.state.received + 10, 0.5)
    counted = {
        t.key: {n: c - before[t.key].get(n, 0) for n, c in s.rejected_on_subs(t.key).items()}
        for t in FUZZED_TOPICS
    }
    q1 = s.fresh_q()
    moved = float(np.max(np.abs(q1 - q0)))
    # Rejected events are rate-limited (one a second per key and node): after the interval,
    # one more bad payload per topic makes each node report its final count.
    time.sleep(REJECT_REPORT_INTERVAL_S)  # the documented rate limit, not a synchronisation
    for t in FUZZED_TOPICS:
        pubs[t.key].put_bytes(b"\xc1")
        sent[t.key] += 1
    expected = {
        (node_name, t.key): node.rejected.get(t.key, 0)
        for node_name, node in s.nodes.items()
        for t in FUZZED_TOPICS
        if any(sub.topic.key == t.key for sub in node._subs)
    }

    def final_counts_reported() -> bool:
        return all(
            s.nodes[n].rejected.get(k, 0) >= sent[k]
            and s.reported(s.nodes[n].name, k) == s.nodes[n].rejected.get(k, 0)
            for n, k in expected
        )

    deadline = time.monotonic() + 10.0
    while not final_counts_reported() and time.monotonic() < deadline:
        s.state.wait_count(s.state.received + 10, 0.5)
    reported = {f"{n}:{k}": s.reported(s.nodes[n].name, k) for n, k in expected}
    _answers_status(s)
    record(
        "fuzz_streams",
        payloads_sent=dict(sent),
        rejected_per_subscriber=counted,
        rejected_reported=reported,
        arm_refused_far_commands=s.arm.proxy.counters["rejected"] - arm_rejected0,
        joint_motion_rad=moved,
    )
    for t in FUZZED_TOPICS:
        for name, n in counted[t.key].items():
            assert n == sent[t.key] - 1, f"{name} on {t.key}: {n} of {sent[t.key] - 1}"
    assert s.arm.proxy.counters["rejected"] - arm_rejected0 == len(far)
    assert final_counts_reported(), f"reported {reported}, counted {expected}"
    assert moved <= REST_TOL_RAD, f"the arm moved by {moved} rad"


# --- methods -------------------------------------------------------------------------------


@dataclass
class CallStats:
    calls: Counter[str] = field(default_factory=Counter)
    outcomes: Counter[str] = field(default_factory=Counter)
    accepted_motions: int = 0
    max_motion_without_command_rad: float = 0.0


def _call(node: Node, service: str, method: str, args: Any) -> str:
    """One call: "ok", or the error code; a non-map argument goes out as raw bytes."""
    try:
        if isinstance(args, bytes):
            return _raw_call(node, service, method, args)
        node.call(service, method, args, CALL_TIMEOUT_S)
        return "ok"
    except RpcError as e:
        return e.code
    except Unavailable:
        return "no_reply"


def _raw_call(node: Node, service: str, method: str, payload: bytes) -> str:
    replies = list(node.session.get(keys.rpc_key(service, method), payload=payload, timeout=5.0))
    if not replies:
        return "no_reply"
    ok, err = replies[0].ok, replies[0].err
    if ok is not None or err is None:
        return "ok"
    body = codec.unpack(err.payload.to_bytes())
    return str(body.get("error")) if isinstance(body, dict) else "malformed"


RAW_ARGS = st.binary(max_size=64) | st.builds(codec.pack, VALUES)


@pytest.mark.parametrize("service", ["arm", "force", "decision"])
def test_random_arguments_to_every_method_never_crash_and_move_nothing_unasked(
    system: System, service: str
) -> None:
    s = system
    methods = METHODS[service]
    # Every listed method exists: a call with no arguments is never "no method".
    for m in methods:
        if m in MOVERS or m in ("estop", "initialize", "sensor_stop"):
            continue
        try:
            s.watcher.call(service, m, {}, CALL_TIMEOUT_S)
        except RpcError as e:
            assert not e.message.startswith("no method"), e.message
    stats = CallStats()
    baseline = [s.settle()]
    allowed = set(ERROR_CODES) | {"ok", "unavailable"}

    unknown = st.from_regex(r"[a-z_]{1,12}", fullmatch=True)

    @settings(FUZZ_SETTINGS, max_examples=200)
    @given(st.data())
    def fuzz(data: st.DataObject) -> None:
        method = data.draw(st.sampled_from((*methods, "")))
        if not method:
            method = data.draw(unknown)  # one draw in len(methods) + 1: an unknown method
        args = data.draw(ARGS if data.draw(st.integers(0, 3)) else RAW_ARGS)
        if isinstance(args, dict) and method in MOVERS:
            # A waiting motion blocks its caller by design: never wait here.
            args = {**args, "wait": False}
        outcome = _call(s.fuzzer, service, method, args)
        stats.calls[method if method in methods else "<unknown>"] += 1
        stats.outcomes[outcome] += 1
        assert outcome in allowed, f"{service}.{method}({args!r:.200}) → {outcome}"
        if outcome == "ok" and method in MOVERS:
            # A valid motion was asked for: it may move; stop it and start again from there.
            stats.accepted_motions += 1
            s.watcher.call("decision", "task", {"name": "cancel"}, CALL_TIMEOUT_S)
            baseline[0] = s.settle()
            return
        moved = float(np.max(np.abs(s.fresh_q() - baseline[0])))
        stats.max_motion_without_command_rad = max(stats.max_motion_without_command_rad, moved)
        assert moved <= REST_TOL_RAD, f"{service}.{method}({args!r:.200}) moved the arm"

    fuzz()
    # Put things back (an e-stop or a stopped sensor may have been asked for) and check that
    # every service still answers.
    s.watcher.call("decision", "reset", {}, CALL_TIMEOUT_S)
    if s.arm.proxy.status == "error":
        s.watcher.call("arm", "connect", {}, CALL_TIMEOUT_S)
        s.watcher.call("arm", "initialize", {}, CALL_TIMEOUT_S)
    _answers_status(s)
    prefix = keys.rpc_key(service, "")
    counted = {k: n for k, n in s.nodes[service].rejected.items() if k.startswith(prefix)}
    reported = {k: s.reported(service, k) for k in counted if s.reported(service, k)}
    known = {k[len(prefix) :]: n for k, n in counted.items() if k[len(prefix) :] in methods}
    record(
        f"fuzz_methods_{service}",
        calls=sum(stats.calls.values()),
        per_method=dict(stats.calls),
        outcomes=dict(stats.outcomes),
        accepted_motions=stats.accepted_motions,
        max_motion_without_command_rad=stats.max_motion_without_command_rad,
        bad_requests_counted=sum(counted.values()),
        bad_requests_per_method=known,
        bad_requests_unknown_methods=sum(counted.values()) - sum(known.values()),
        rejected_events=len(reported),
    )
    assert stats.outcomes["no_reply"] == 0
    assert stats.outcomes["bad_request"] > 0
    # Every refusal said so on robot/events: in an event of its own or counted as suppressed
    # in the next one (events are rate-limited per key and per service), none unaccounted.
    node = s.nodes[service]

    def accounted() -> tuple[int, int]:
        with s.lock:
            mine = [e for e in s.events if e.source == service and e.kind == "rejected"]
        told = len(mine) + sum(int((e.data or {}).get("suppressed", 0)) for e in mine)
        return sum(node.rejected.values()), told + node._reject_suppressed

    assert wait_until(lambda: accounted()[0] == accounted()[1], CALL_TIMEOUT_S), accounted()
    assert reported and all(0 < reported[k] <= counted[k] for k in reported)
