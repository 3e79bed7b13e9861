"""The command phases: the bench as a master streams `robot/cmd` through the decision to the
arm, and times the operator's path.

Two ways to time it, chosen per figure by what the running services send:

- **the contract-extension fields** (docs/protocol-extensions.md): the decision's
  `robot/puma/cmd` carries `origin_t_ns` (the `t_ns` of the bench command it carries out) and
  `robot/state` carries `cmd_rx_ns`, `setpoint_ns` and `cmd_origin_t_ns` for its `cmd_seq`.
  Commands reaching the arm = distinct bench `t_ns` seen as `origin_t_ns`; master → arm =
  `cmd_rx_ns − cmd_origin_t_ns`; master → setpoint = `setpoint_ns − cmd_origin_t_ns`, over the
  commands `robot/state` showed (a sample: states run slower than a 1 kHz master);
- **dp matching**, the fallback for services that do not send those fields: the bench encodes
  its command index k in `dp` (k · step), decodes it back from the decision's commands, and
  takes the arrival at the bench of the first arm command carrying k as "master → arm" and
  the `t_ns` of the first `robot/state` showing it applied as "master → setpoint".

Each phase records which way each figure was timed (`*_method`) and says so in a note.
"""

from __future__ import annotations

import time
from collections import Counter
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Any

from services.bus.errors import RpcError, Unavailable
from services.bus.keys import EVENTS, PUMA_CMD, STATE
from services.bus.messages import Event, OperatorCommand, RobotState
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
F_SEQ, F_MASTER, F_ACTIVE, F_DP_X, F_ENGAGE, F_ORIGIN, F_T = range(7)
S_T, S_CMD_SEQ, S_STATUS, S_RX, S_SETPOINT, S_ORIGIN = range(6)


def puma_cmd_fields(m: OperatorCommand) -> tuple[Any, ...]:
    """What the bench keeps of a `robot/puma/cmd` (indices F_*)."""
    return (m.seq, m.master, m.active, m.dp[0], m.engage, m.origin_t_ns, m.t_ns)


def state_fields(m: RobotState) -> tuple[Any, ...]:
    """What the bench keeps of a `robot/state` (indices S_*)."""
    return (m.t_ns, m.cmd_seq, m.status, m.cmd_rx_ns, m.setpoint_ns, m.cmd_origin_t_ns)


class HoldWatch:
    """Tells the command driver when the decision stopped following the bench's current
    engagement: an inactive arm command of the engagement it was following (a hold), or
    no active one at all `refused_after_s` after the engagement began (a refusal).

    `newest()` gives the newest robot/puma/cmd record `(rx_ns, puma_cmd_fields(m))`."""

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


def decision_active(
    fwd_rec: Sequence[Record], run: CommandRun, step_m: float
) -> list[tuple[int, int, int]]:
    """(rx_ns, seq, k) of the decision's active arm commands since the bench's first
    command, k decoded from dp within the bench engagement the decision engagement follows
    (dp matching)."""
    if not run.sent:
        return []
    t_first = run.sent[0][1]
    k0s = [k0 for _, k0 in run.starts]
    active = [
        (rx, f) for rx, f in fwd_rec if f[F_MASTER] == "decision" and f[F_ACTIVE] and rx >= t_first
    ]
    first_seen: dict[int, int] = {}
    for rx, f in active:
        first_seen.setdefault(int(f[F_ENGAGE]), rx)
    follows = stats.assign_engagements([t for t, _ in run.starts], first_seen)
    return [
        (rx, int(f[F_SEQ]), k0s[follows[int(f[F_ENGAGE])]] + stats.dp_index(f[F_DP_X], step_m))
        for rx, f in active
        if int(f[F_ENGAGE]) in follows
    ]


def command_figures(
    rate_hz: float,
    run: CommandRun,
    step_m: float,
    fwd_rec: Sequence[Record],
    st_rec: Sequence[Record],
    drain_s: float = DRAIN_TIMEOUT_S,
) -> dict[str, Any]:
    """A command phase's figures from what the probes recorded (pure: no bus).

    `fwd_rec`: `(rx_ns, puma_cmd_fields)` per robot/puma/cmd; `st_rec`: `(rx_ns,
    state_fields)` per robot/state, both in arrival order. Each headline figure —
    `reached_rate_hz`, `arm_ms`, `setpoint_ms` — comes from the extension fields when the
    services send them and from dp matching otherwise (`reached_method`, `arm_method`,
    `setpoint_method`); the dp-matching figures are kept beside them whatever the path.
    `na` names, for a headline figure left empty, why.
    """
    sent = run.sent
    t_first, t_last = (sent[0][1], sent[-1][1]) if sent else (0, 0)
    duration_s = (t_last - t_first) / stats.NS_PER_S
    forwarded = [r for r in decision_active(fwd_rec, run, step_m) if 0 <= r[2] < len(sent)]
    st_rows = [(rx, int(s[S_T]), int(s[S_CMD_SEQ])) for rx, s in st_rec if rx >= t_first]
    m = stats.match_commands(sent, forwarded, st_rows)
    fwd_rx = [r[0] for r in forwarded if r[0] <= t_last + drain_s * stats.NS_PER_S]

    has_origin = any(f[F_ORIGIN] is not None for _, f in fwd_rec)
    has_rx = any(s[S_RX] is not None and s[S_ORIGIN] is not None for _, s in st_rec)
    has_setpoint = any(s[S_SETPOINT] is not None and s[S_ORIGIN] is not None for _, s in st_rec)
    stamped = stats.stamped_commands(
        [t for _, t in sent],
        [(int(f[F_SEQ]), f[F_ORIGIN]) for _, f in fwd_rec],
        [(int(s[S_CMD_SEQ]), s[S_RX], s[S_SETPOINT], s[S_ORIGIN]) for rx, s in st_rec
         if rx >= t_first],
        {int(f[F_SEQ]): int(f[F_T]) for _, f in fwd_rec if f[F_ORIGIN] is not None},
    )  # fmt: skip
    reached = stamped.reached if has_origin else m.forwarded_distinct
    arm_ms = stamped.arm_ms if has_rx else m.forward_ms
    setpoint_ms = stamped.setpoint_ms if has_setpoint else m.applied_ms
    na: dict[str, str] = {}
    if arm_ms.size == 0:
        na["arm_ms"] = (
            "robot/state showed none of the bench's commands (cmd_origin_t_ns)"
            if has_rx
            else "no robot/puma/cmd carried a bench command (dp matching found none)"
        )
    if setpoint_ms.size == 0:
        na["setpoint_ms"] = (
            "robot/state showed no setpoint_ns for the bench's commands"
            if has_setpoint
            else "no robot/state showed a bench command applied (dp matching)"
        )
    return {
        "rate_hz_target": rate_hz,
        "sent": len(sent),
        "sent_rate_hz": stats.rate_hz(max(len(sent) - 1, 0), duration_s),
        "step_m": step_m,
        "engagements": len(run.starts),
        "reached_distinct": reached,
        "reached_rate_hz": stats.rate_hz(reached, duration_s),
        "reached_method": "origin_t_ns" if has_origin else "dp",
        "arm_ms": stats.summarize(arm_ms).as_dict(),
        "arm_method": "cmd_rx_ns" if has_rx else "bench_arrival",
        "setpoint_ms": stats.summarize(setpoint_ms).as_dict(),
        "setpoint_method": "setpoint_ns" if has_setpoint else "state_t_ns",
        "stamped_sampled": stamped.sampled,
        "hops_ms": {
            "decision": stats.summarize(stamped.decision_ms).as_dict(),
            "to_arm": stats.summarize(stamped.to_arm_ms).as_dict(),
            "apply": stats.summarize(stamped.apply_ms).as_dict(),
        },
        "forwarded_distinct": m.forwarded_distinct,
        "forwarded_rate_hz": stats.rate_hz(m.forwarded_distinct, duration_s),
        "arm_cmd_rate_hz": stats.rate_from_times(fwd_rx),
        "matched": m.matched,
        "unforwarded": m.unforwarded,
        "forward_ms": stats.summarize(m.forward_ms).as_dict(),
        "applied_ms": stats.summarize(m.applied_ms).as_dict(),
        "seen_ms": stats.summarize(m.seen_ms).as_dict(),
        "states_moving": sum(1 for rx, s in st_rec if rx >= t_first and s[S_STATUS] == "moving"),
        "na": na,
    }


def method_note(key: str, fig: dict[str, Any]) -> str:
    """How a command phase was timed, in words (one note per phase)."""
    if fig["arm_method"] == "cmd_rx_ns":
        how = (
            f"timed from the extension fields: commands reaching the arm by origin_t_ns "
            f"({fig['reached_method']}), master→arm = cmd_rx_ns − cmd_origin_t_ns, "
            f"master→setpoint = setpoint_ns − cmd_origin_t_ns ({fig['setpoint_method']}), over "
            f"the {fig['stamped_sampled']} of {fig['sent']} commands robot/state showed (a "
            "sample: the state stream is slower than the master)"
        )
    else:
        how = (
            "the services send no cmd_rx_ns/cmd_origin_t_ns yet: fallback dp matching — "
            f"commands reaching the arm by the k decoded from dp ({fig['reached_method']}), "
            "master→arm = arrival at the bench of the first robot/puma/cmd carrying the "
            f"command, master→setpoint = t_ns of the first robot/state showing it applied "
            f"({fig['setpoint_method']})"
        )
    return f"{key}: {how}."


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
    """Stream `robot/cmd` at `rate_hz` for `duration_s` with robot/puma/cmd, robot/state and
    robot/events recorded, engaging again after a hold (HoldWatch); then wait (with a
    deadline) until the arm reports the last forwarded command applied. `mark("start")`
    and `mark("end")` are called right around the stream itself (a CPU window)."""
    step = step_for(rate_hz, duration_s, sign)
    fwd = StreamProbe(node, PUMA_CMD, puma_cmd_fields).start()
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
        last_seq = max((r[1] for r in decision_active(fwd.snapshot(), run, step)), default=None)
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
        f"({fig['reached_rate_hz']:.0f} Hz, {fig['reached_method']}"
        + (f"; arm counted {counter['rate_hz']:.0f}/s" if counter else "")
        + f"); master→arm p50 {ms_text(fig['arm_ms']['p50'])} p99 "
        f"{ms_text(fig['arm_ms']['p99'])}; master→setpoint p50 "
        f"{ms_text(fig['setpoint_ms']['p50'])} p99 {ms_text(fig['setpoint_ms']['p99'])} "
        f"({fig['arm_method']}, {fig['setpoint_method']})" + intake_text(fig["decision_intake"])
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
