"""A command phase's figures from synthetic probe records (the contract's `origin_t_ns` and
the extension timing fields)."""

from __future__ import annotations

from typing import Any

import pytest

from services.tools.bench import stats
from services.tools.bench.commands import (
    changed_counters,
    command_figures,
    counter_delta,
    intake_text,
    method_note,
    step_for,
)
from services.tools.bench.probes import CommandRun

MS = stats.NS_PER_MS
S = stats.NS_PER_S
T0 = 1_700_000_000 * S
STEP = 5e-6
N = 10  # bench commands k = 0 … 9, 1 ms apart
SEQ0 = 100


def _run() -> CommandRun:
    return CommandRun(sent=[(k, T0 + k * MS) for k in range(N)], starts=[(T0, 0)])


def _records(setpoint: bool = True) -> tuple[list[Any], list[Any]]:
    """The decision forwards every other command (its tick carries the newest) from a tick
    0.1 ms after it was sent, and the bench sees that 0.5 ms after it was sent; the arm
    receives it 0.3 ms after it was sent, has its setpoint 0.8 ms after, and publishes a
    state 1 ms after — but only for every fourth command (states run slower)."""
    fwd, states = [], []
    for i, k in enumerate(range(0, N, 2)):
        t = T0 + k * MS
        fwd.append((t + MS // 2, (SEQ0 + i, "decision", True, 7, t, t + MS // 10)))
        if k % 4 == 0:
            rx = t + 3 * MS // 10
            sp = t + 8 * MS // 10 if setpoint else None
            states.append((t + 11 * MS // 10, (t + MS, SEQ0 + i, "moving", rx, sp, t)))
    hold = (SEQ0 + 9, "decision", False, 7, T0 + 20 * MS, T0 + 20 * MS)
    fwd.append((T0 + 20 * MS, hold))  # the hold after, with its own time as origin
    return fwd, states


def test_the_extension_fields_time_the_path_on_the_arm_clock() -> None:
    fwd, states = _records()
    f = command_figures(1000.0, _run(), STEP, fwd, states)
    assert f["sent"] == N and f["reached_distinct"] == 5  # k = 0, 2, 4, 6, 8
    assert f["reached_rate_hz"] == pytest.approx(5 / 0.009)  # over first → last sent
    assert f["stamped_sampled"] == 3  # the states showed k = 0, 4, 8
    assert f["arm_ms"]["n"] == 3 and f["arm_ms"]["p50"] == pytest.approx(0.3)
    assert f["setpoint_ms"]["n"] == 3 and f["setpoint_ms"]["p50"] == pytest.approx(0.8)
    assert f["na"] == {}
    # hop by hop: master → the decision's tick for all 5 it carried, then, for the 3 shown,
    # the tick → the arm's receipt and the receipt → the setpoint; they add up.
    hops = f["hops_ms"]
    assert (hops["decision"]["n"], hops["to_arm"]["n"], hops["apply"]["n"]) == (5, 3, 3)
    assert hops["decision"]["p50"] == pytest.approx(0.1)
    assert hops["to_arm"]["p50"] == pytest.approx(0.2)
    assert hops["apply"]["p50"] == pytest.approx(0.5)
    assert f["arm_cmd_rate_hz"] > 0.0
    # the longest silences: 1 ms between sends; 2 ms between the active targets at the arm
    assert f["sent_max_gap_ms"] == pytest.approx(1.0)
    assert f["arm_cmd_max_gap_ms"] == pytest.approx(2.0)
    assert "3 of 10 commands robot/state showed" in method_note("commands_1000hz", f)


def test_an_arm_without_setpoint_ns_leaves_that_figure_empty_and_says_why() -> None:
    fwd, states = _records(setpoint=False)
    f = command_figures(100.0, _run(), STEP, fwd, states)
    assert f["arm_ms"]["n"] == 3 and f["setpoint_ms"]["n"] == 0
    assert set(f["na"]) == {"setpoint_ms"}


def test_nothing_forwarded_says_why() -> None:
    f = command_figures(100.0, _run(), STEP, [], [])
    assert f["reached_distinct"] == 0 and f["arm_ms"]["n"] == 0
    assert set(f["na"]) == {"arm_ms", "setpoint_ms"}
    assert "cmd_origin_t_ns" in f["na"]["arm_ms"]
    empty = command_figures(100.0, CommandRun([], []), STEP, [], [])
    assert empty["sent"] == 0 and empty["reached_rate_hz"] == 0.0
    assert empty["sent_max_gap_ms"] is None and empty["arm_cmd_max_gap_ms"] is None


def test_counter_delta_and_step() -> None:
    assert counter_delta(10, 510, 5.0) == {"commands": 500, "window_s": 5.0, "rate_hz": 100.0}
    assert counter_delta(None, 5, 1.0) is None
    assert step_for(1000.0, 5.0, -1.0) == pytest.approx(-4e-6)  # 20 mm over 5000 commands
    assert step_for(100.0, 5.0, 1.0) == 5e-6  # capped


def test_the_decision_counters_change_over_a_phase_and_say_how_commands_were_taken() -> None:
    before = {"inline": 10, "handed": 2, "dropped": 0, "batches": 11}
    after = {"inline": 4710, "handed": 290, "dropped": 0, "batches": 4830}
    delta = changed_counters(before, after)
    assert delta == {"inline": 4700, "handed": 288, "batches": 4819}  # unchanged: left out
    assert intake_text(delta) == (
        "; the decision took 4700 at once in Zenoh's callback, 288 handed to its intake "
        "thread, 0 dropped, in 4819 ticks"
    )
    assert intake_text(None) == "" and intake_text({}) == ""
