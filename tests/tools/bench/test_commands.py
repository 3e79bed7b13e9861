"""A command phase's figures from synthetic probe records: the contract-extension path and the
dp-matching fallback of services that do not send the fields."""

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


def _records(fields: bool, setpoint: bool = True) -> tuple[list[Any], list[Any]]:
    """The decision forwards every other command (its tick carries the newest) from a tick
    0.1 ms after it was sent, and the bench sees that 0.5 ms after it was sent; the arm
    receives it 0.3 ms after it was sent, has its setpoint 0.8 ms after, and publishes a
    state 1 ms after — but only for every fourth command (states run slower)."""
    fwd, states = [], []
    for i, k in enumerate(range(0, N, 2)):
        t = T0 + k * MS
        origin = t if fields else None
        fwd.append((t + MS // 2, (SEQ0 + i, "decision", True, k * STEP, 7, origin, t + MS // 10)))
        if k % 4 == 0:
            rx = t + 3 * MS // 10 if fields else None
            sp = t + 8 * MS // 10 if fields and setpoint else None
            states.append((t + 11 * MS // 10, (t + MS, SEQ0 + i, "moving", rx, sp, origin)))
    hold = (SEQ0 + 9, "decision", False, 0.0, 7, None, T0 + 20 * MS)
    fwd.append((T0 + 20 * MS, hold))  # the hold after
    return fwd, states


def test_the_extension_fields_time_the_path_on_the_arm_clock() -> None:
    fwd, states = _records(fields=True)
    f = command_figures(1000.0, _run(), STEP, fwd, states)
    assert (f["reached_method"], f["arm_method"], f["setpoint_method"]) == (
        "origin_t_ns",
        "cmd_rx_ns",
        "setpoint_ns",
    )
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
    # the dp-matching figures are kept beside them
    assert f["forwarded_distinct"] == 5 and f["forward_ms"]["p50"] == pytest.approx(0.5)
    assert "timed from the extension fields" in method_note("commands_1000hz", f)
    assert "3 of 10 commands robot/state showed" in method_note("commands_1000hz", f)


def test_without_the_fields_dp_matching_stands_in() -> None:
    fwd, states = _records(fields=False)
    f = command_figures(1000.0, _run(), STEP, fwd, states)
    assert (f["reached_method"], f["arm_method"], f["setpoint_method"]) == (
        "dp",
        "bench_arrival",
        "state_t_ns",
    )
    assert f["reached_distinct"] == f["forwarded_distinct"] == 5
    # master→arm: arrival at the bench of the first arm command carrying k or a newer one
    # (k odd waits for k + 1's: 1.5 ms; k even 0.5 ms); k = 9 was never carried.
    assert f["arm_ms"]["n"] == 9 and f["unforwarded"] == 1
    assert f["arm_ms"]["min"] == pytest.approx(0.5) and f["arm_ms"]["max"] == pytest.approx(1.5)
    # master→setpoint: t_ns of the first state showing the carrying command (or a later one)
    # applied: k = 0 by its own state 1 ms later, k = 1 … 8 by the states of k = 4 and 8
    assert f["setpoint_ms"]["n"] == 9 and f["setpoint_ms"]["min"] == pytest.approx(1.0)
    assert f["setpoint_ms"]["max"] == pytest.approx(4.0)  # k = 1 → the state of k = 4
    assert f["stamped_sampled"] == 0 and f["na"] == {}
    assert "fallback dp matching" in method_note("commands_1000hz", f)


def test_a_arm_without_setpoint_ns_falls_back_for_that_figure_only() -> None:
    fwd, states = _records(fields=True, setpoint=False)
    f = command_figures(100.0, _run(), STEP, fwd, states)
    assert (f["arm_method"], f["setpoint_method"]) == ("cmd_rx_ns", "state_t_ns")
    assert f["setpoint_ms"]["n"] == 9


def test_nothing_forwarded_says_why() -> None:
    f = command_figures(100.0, _run(), STEP, [], [])
    assert f["reached_distinct"] == 0 and f["arm_ms"]["n"] == 0
    assert set(f["na"]) == {"arm_ms", "setpoint_ms"}
    assert "dp matching found none" in f["na"]["arm_ms"]
    empty = command_figures(100.0, CommandRun([], []), STEP, [], [])
    assert empty["sent"] == 0 and empty["reached_rate_hz"] == 0.0


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
