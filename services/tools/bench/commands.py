"""The command phases: the bench as a master streams `robot/cmd` through the decision to the
arm, and times the operator's path.

Timed from the contract's `origin_t_ns` and the extension fields
(docs/protocol-extensions.md): the decision's `robot/arm/target` carries `origin_t_ns` (the
`t_ns` of the bench command it carries out) and `robot/state` carries `cmd_rx_ns`,
`setpoint_ns` and `cmd_origin_t_ns` for its `cmd_seq`. Commands reaching the arm = distinct
bench `t_ns` seen as `origin_t_ns`; master → arm = `cmd_rx_ns − cmd_origin_t_ns`; master →
setpoint = `setpoint_ns − cmd_origin_t_ns`, over the commands `robot/state` showed (a
sample: states run slower than a 1 kHz master).
"""

from __future__ import annotations

import itertools
import subprocess
import sys
import time
from collections import Counter
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Any

from services.bus.errors import RpcError, Unavailable
from services.bus.keys import ARM_TARGET, EVENTS, STATE
from services.bus.messages import ArmTarget, Event, RobotState
from services.bus.node import Node
from services.tools.bench import stats
from services.tools.bench.probes import CommandDriver, CommandRun, StreamProbe
from services.tools.bench.report import ms_text

Say = Callable[[str], None]
Record = tuple[int, tuple[Any, ...]]

CMD_TRAVEL_M = 0.02
"""How far one command phase moves the tool (m, world x; alternately + and −)."""
CMD_MAX_STEP_M = 5e-6
"""dp step per command (m): k · step must stay far below the supervisor's speed limit."""
DRAIN_TIMEOUT_S = 2.0
CALL_TIMEOUT_S = 5.0
HOLD_KINDS = ("watchdog", "rejected", "limit", "contact", "estop", "busy")
"""Decision event kinds that mean the bench's commands were held back, refused or altered
("lease" events also announce the lease being taken and released, so they are left out;
lease refusals are in the decision's intervention counters)."""
MAX_MESSAGES = 10

# Field positions in the probes' records.
F_SEQ, F_MASTER, F_ACTIVE, F_ENGAGE, F_ORIGIN, F_T = range(6)
S_T, S_CMD_SEQ, S_STATUS, S_RX, S_SETPOINT, S_ORIGIN = range(6)


def target_fields(m: ArmTarget) -> tuple[Any, ...]:
    """What the bench keeps of a `robot/arm/target` (indices F_*)."""
    return (m.seq, m.master, not m.hold, m.engage, m.origin_t_ns, m.t_ns)


def state_fields(m: RobotState) -> tuple[Any, ...]:
    """What the bench keeps of a `robot/state` (indices S_*)."""
    return (m.t_ns, m.cmd_seq, m.status, m.cmd_rx_ns, m.setpoint_ns, m.cmd_origin_t_ns)


class HoldWatch:
    """Tells the command driver when the decision stopped following the bench's current
    engagement: a hold target of the engagement it was following, or no moving one at all
    `refused_after_s` after the engagement began (a refusal).

    `newest()` gives the newest robot/arm/target record `(rx_ns, target_fields(m))`."""

    def __init__(
        self,
        newest: Callable[[], Record | None],
        refused_after_s: float = 1.0,
    ) -> None:
        self.newest = newest
        self.refused_after_ns = int(refused_after_s * stats.NS_PER_S)
        self._started = -1
        self._following: int | None = None

    def __call__(self, started_ns: int) -> bool:
        if started_ns != self._started:
            self._started, self._following = started_ns, None
        newest = self.newest()
        waited = time.time_ns() - started_ns > self.refused_after_ns
        if newest is None or newest[0] < started_ns or newest[1][F_MASTER] != "decision":
            return waited and self._following is None
        active, engage = newest[1][F_ACTIVE], newest[1][F_ENGAGE]
        if active:
            self._following = engage
            return False
        if self._following is not None:
            return bool(engage == self._following)
        return waited


def step_for(rate_hz: float, duration_s: float, sign: float) -> float:
    """The dp step (m) of a phase: small enough that the phase travels ≤ CMD_TRAVEL_M."""
    n_planned = max(1, round(rate_hz * duration_s))
    return sign * min(CMD_MAX_STEP_M, CMD_TRAVEL_M / n_planned)


def _max_gap_ms(times_ns: Sequence[int]) -> float | None:
    """The longest interval between consecutive times (ms), None for fewer than two."""
    if len(times_ns) < 2:
        return None
    return max(b - a for a, b in itertools.pairwise(times_ns)) / 1e6


def command_figures(
    rate_hz: float,
    run: CommandRun,
    step_m: float,
    fwd_rec: Sequence[Record],
    st_rec: Sequence[Record],
) -> dict[str, Any]:
    """A command phase's figures from what the probes recorded (pure: no bus).

    `fwd_rec`: `(rx_ns, target_fields)` per robot/arm/target; `st_rec`: `(rx_ns,
    state_fields)` per robot/state, both in arrival order. `na` names, for a headline
    figure left empty, why.
    """
    sent = run.sent
    t_first, t_last = (sent[0][1], sent[-1][1]) if sent else (0, 0)
    duration_s = (t_last - t_first) / stats.NS_PER_S
    stamped = stats.stamped_commands(
        [t for _, t in sent],
        [(int(f[F_SEQ]), f[F_ORIGIN]) for _, f in fwd_rec],
        [(int(s[S_CMD_SEQ]), s[S_RX], s[S_SETPOINT], s[S_ORIGIN]) for rx, s in st_rec
         if rx >= t_first],
        {int(f[F_SEQ]): int(f[F_T]) for _, f in fwd_rec},
    )  # fmt: skip
    na: dict[str, str] = {}
    if stamped.arm_ms.size == 0:
        na["arm_ms"] = "robot/state showed none of the bench's commands (cmd_origin_t_ns)"
    if stamped.setpoint_ms.size == 0:
        na["setpoint_ms"] = "robot/state showed no setpoint_ns for the bench's commands"
    fwd_rx = [
        rx
        for rx, f in fwd_rec
        if f[F_MASTER] == "decision" and f[F_ACTIVE] and t_first <= rx
        and rx <= t_last + DRAIN_TIMEOUT_S * stats.NS_PER_S
    ]  # fmt: skip
    return {
        "rate_hz_target": rate_hz,
        "sent": len(sent),
        "sent_rate_hz": stats.rate_hz(max(len(sent) - 1, 0), duration_s),
        "step_m": step_m,
        "engagements": len(run.starts),
        "reached_distinct": stamped.reached,
        "reached_rate_hz": stats.rate_hz(stamped.reached, duration_s),
        "arm_ms": stats.summarize(stamped.arm_ms).as_dict(),
        "setpoint_ms": stats.summarize(stamped.setpoint_ms).as_dict(),
        "stamped_sampled": stamped.sampled,
        "hops_ms": {
            "decision": stats.summarize(stamped.decision_ms).as_dict(),
            "to_arm": stats.summarize(stamped.to_arm_ms).as_dict(),
            "apply": stats.summarize(stamped.apply_ms).as_dict(),
        },
        "arm_cmd_rate_hz": stats.rate_from_times(fwd_rx),
        # the longest silences: of the bench master's own sending, and of the decision's
        # targets reaching the arm (what a 100 ms watchdog would see)
        "sent_max_gap_ms": _max_gap_ms([t for _, t in sent]),
        "arm_cmd_max_gap_ms": _max_gap_ms(fwd_rx),
        "states_moving": sum(1 for rx, s in st_rec if rx >= t_first and s[S_STATUS] == "moving"),
        "na": na,
    }


def method_note(key: str, fig: dict[str, Any]) -> str:
    """How a command phase was timed, in words (one note per phase)."""
    return (
        f"{key}: commands reaching the arm by origin_t_ns, master→arm = cmd_rx_ns − "
        "cmd_origin_t_ns, master→setpoint = setpoint_ns − cmd_origin_t_ns, over the "
        f"{fig['stamped_sampled']} of {fig['sent']} commands robot/state showed (a sample: "
        "the state stream is slower than the master)."
    )


@dataclass(frozen=True, slots=True)
class Streamed:
    """One command stream and what the probes recorded around it."""

    run: CommandRun
    step_m: float
    fwd_rec: list[Record]
    st_rec: list[Record]
    ev_rec: list[Record]
    wall_s: float


def stream(
    node: Node,
    driver: CommandDriver,
    rate_hz: float,
    duration_s: float,
    sign: float,
    mark: Callable[[str], None] | None = None,
) -> Streamed:
    """Stream `robot/cmd` at `rate_hz` for `duration_s` with robot/arm/target, robot/state and
    robot/events recorded, engaging again after a hold (HoldWatch); then wait (with a
    deadline) until the arm reports the last forwarded command applied. `mark("start")`
    and `mark("end")` are called right around the stream itself (a CPU window)."""
    step = step_for(rate_hz, duration_s, sign)
    fwd = StreamProbe(node, ARM_TARGET, target_fields).start()
    states = StreamProbe(node, STATE, state_fields).start()
    events = StreamProbe(node, EVENTS, _event_fields).start()
    try:
        if not states.wait_count(1, 5.0):
            raise TimeoutError("no robot/state before the command phase")
        t0 = time.monotonic()
        if mark is not None:
            mark("start")
        run = driver.stream(rate_hz, duration_s, step, held=HoldWatch(fwd.newest))
        if mark is not None:
            mark("end")
        ours = {t for _, t in run.sent}
        last_seq = max(
            (int(f[F_SEQ]) for _, f in fwd.snapshot() if f[F_ORIGIN] in ours), default=None
        )
        if last_seq is not None:
            deadline = time.monotonic() + DRAIN_TIMEOUT_S
            while time.monotonic() < deadline:
                newest = states.newest()
                if newest is not None and newest[1][S_CMD_SEQ] >= last_seq:
                    break
                time.sleep(0.01)
        wall_s = time.monotonic() - t0
    finally:
        fwd_rec, st_rec, ev_rec = fwd.stop(), states.stop(), events.stop()
    return Streamed(run, step, fwd_rec, st_rec, ev_rec, wall_s)


def _event_fields(m: Event) -> tuple[Any, ...]:
    return (m.source, m.kind, m.message)


def phase_commands(
    node: Node, driver: CommandDriver, rate_hz: float, sign: float, duration_s: float, say: Say
) -> tuple[dict[str, Any], list[str]]:
    """One command phase: its figures (command_figures, plus the decision's interventions and
    events and the arm's own command counter around it) and its notes."""
    key = f"commands_{rate_hz:.0f}hz"
    say(f"[{key}] robot/cmd at {rate_hz:g} Hz through decision to arm for {duration_s:g} s …")
    before = decision_counters(node)
    arm_before, t_before = arm_commands_counter(node), time.monotonic()
    s = stream(node, driver, rate_hz, duration_s, sign)
    arm_after, t_after = arm_commands_counter(node), time.monotonic()
    after = decision_counters(node)
    fig = command_figures(rate_hz, s.run, s.step_m, s.fwd_rec, s.st_rec)
    t_first = s.run.sent[0][1] if s.run.sent else 0
    ev = [e for rx, e in s.ev_rec if rx >= t_first and e[0] == "decision"]
    fig["arm_counter"] = counter_delta(arm_before, arm_after, t_after - t_before)
    if fig["arm_counter"] is None:
        fig["na"]["arm_counter"] = "arm status has no counters.commands"
    fig["decision_events"] = dict(Counter(e[1] for e in ev))
    fig["decision_interventions"], fig["decision_intake"] = (
        (changed_counters(before[0], after[0]), changed_counters(before[1], after[1]))
        if before is not None and after is not None
        else (None, None)
    )
    fig["decision_messages"] = [e[2] for e in ev if e[1] != "status"][:MAX_MESSAGES]
    notes = [method_note(key, fig)]
    held = [e[2] for e in ev if e[1] in HOLD_KINDS]
    if held or len(s.run.starts) > 1:
        notes.append(
            f"{key}: the decision intervened {len(held)} time(s) (first: "
            f"{held[0] if held else 'none reported'}); the bench engaged "
            f"{len(s.run.starts)} time(s), as an operator engages again after a hold."
        )
    counter = fig["arm_counter"]
    say(
        f"    sent {fig['sent']} ({fig['sent_rate_hz']:.0f} Hz) in {len(s.run.starts)} "
        f"engagement(s), {fig['reached_distinct']} reached the arm "
        f"({fig['reached_rate_hz']:.0f} Hz"
        + (f"; arm counted {counter['rate_hz']:.0f}/s" if counter else "")
        + f"); master→arm p50 {ms_text(fig['arm_ms']['p50'])} p99 "
        f"{ms_text(fig['arm_ms']['p99'])}; master→setpoint p50 "
        f"{ms_text(fig['setpoint_ms']['p50'])} p99 {ms_text(fig['setpoint_ms']['p99'])}"
        + intake_text(fig["decision_intake"])
    )
    return fig, notes


def intake_text(intake: dict[str, int] | None) -> str:
    """How the decision took the phase's commands (status loop.intake), for the log line."""
    if not intake:
        return ""
    return (
        f"; the decision took {intake.get('inline', 0)} at once in Zenoh's callback, "
        f"{intake.get('handed', 0)} handed to its intake thread, {intake.get('dropped', 0)} "
        f"dropped, in {intake.get('batches', 0)} ticks"
    )


def counter_delta(
    before: int | None, after: int | None, window_s: float
) -> dict[str, float | int] | None:
    """The arm's command counter over a window: `{commands, window_s, rate_hz}` (None when
    either reading is missing). It counts every command the arm received, holds included."""
    if before is None or after is None:
        return None
    delta = after - before
    return {
        "commands": delta,
        "window_s": window_s,
        "rate_hz": stats.rate_hz(max(delta, 0), window_s),
    }


def arm_commands_counter(node: Node) -> int | None:
    """`counters.commands` of arm's `status` (None when absent or unanswered)."""
    try:
        got = node.call("arm", "status", {}, CALL_TIMEOUT_S).get("counters")
    except (Unavailable, RpcError):
        return None
    value = got.get("commands") if isinstance(got, dict) else None
    return value if isinstance(value, int) and not isinstance(value, bool) else None


def decision_counters(node: Node) -> tuple[dict[str, int], dict[str, int]] | None:
    """The decision's intervention counters and its command intake's (`status`:
    `interventions`, `loop.intake`), to difference around a phase; None when the decision
    did not answer."""
    try:
        got = node.call("decision", "status", {}, CALL_TIMEOUT_S)
    except (Unavailable, RpcError):
        return None
    loop = got.get("loop")
    intake = loop.get("intake") if isinstance(loop, dict) else None
    return _ints(got.get("interventions")), _ints(intake)


def _ints(d: Any) -> dict[str, int]:
    if not isinstance(d, dict):
        return {}
    return {str(k): v for k, v in d.items() if isinstance(v, int) and not isinstance(v, bool)}


def changed_counters(before: dict[str, int], after: dict[str, int]) -> dict[str, int]:
    """What changed between two readings of counters (those that did not are left out)."""
    return {k: d for k, d in (stats.counters_delta(before, after) or {}).items() if d}


BUSY_LOOPS = 2
BUSY_RATE_HZ = 100.0


def phase_busy_host(
    node: Node, driver: CommandDriver, duration_s: float, say: Say
) -> tuple[dict[str, Any], list[str]]:
    """Teleoperation beside other work on the host (issue 42 item 5): a 100 Hz master for
    `duration_s` while BUSY_LOOPS busy loops run at nice 19 in a session of their own (as
    a compile in another terminal does: with the kernel's autogroup scheduling, nice counts
    only within a session, so such a job weighs as much as the whole telerobot session).
    Figures: the command phase's, plus `watchdog_holds` and the longest gaps."""
    say(f"[busy_host] {BUSY_LOOPS} nice-19 busy loops (own session) beside a 100 Hz master …")
    loops = [
        subprocess.Popen(
            ["nice", "-n", "19", sys.executable, "-c", "while True: pass"],
            start_new_session=True,
            stdout=subprocess.DEVNULL,
            stderr=subprocess.DEVNULL,
        )
        for _ in range(BUSY_LOOPS)
    ]
    try:
        fig, notes = phase_commands(node, driver, BUSY_RATE_HZ, 1.0, duration_s, say)
    finally:
        for p in loops:
            p.kill()
        for p in loops:
            p.wait(5.0)
    fig["busy_loops"] = BUSY_LOOPS
    fig["watchdog_holds"] = int(fig.get("decision_events", {}).get("watchdog", 0))
    return fig, [n.replace("commands_100hz", "busy_host") for n in notes]
