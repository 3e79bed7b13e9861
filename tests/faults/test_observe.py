"""The fault suite's analyses, on hand-made messages: rest detection, jumps, event seqs."""

from __future__ import annotations

import pytest
from hypothesis import given
from hypothesis import strategies as st

from services.bus.messages import IDENTITY_R, Event, RobotState
from tests.faults.observe import count_between, event_continuity, rest_start, tool_steps

pytestmark = pytest.mark.faults

PERIOD_S = 0.004


def _state(seq: int, x: float, t_s: float | None = None) -> RobotState:
    t_ns = int((seq * PERIOD_S if t_s is None else t_s) * 1e9)
    return RobotState(
        seq=seq,
        t_ns=t_ns,
        status="ready",
        q=(x, 0.0, 0.0, 0.0, 0.0, 0.0),
        tool_p=(x, 0.0, 0.5),
        tool_R=IDENTITY_R,
        flange_p=(x, 0.0, 0.7),
        flange_R=IDENTITY_R,
        engage=1,
        cmd_seq=seq,
    )


def _event(source: str, seq: int) -> Event:
    return Event(seq=seq, t_ns=seq, source=source, kind="status", message="")


def test_rest_starts_where_the_joints_stop_changing() -> None:
    qs = [[0.0] * 6, [0.1] * 6, [0.2] * 6, [0.2] * 6, [0.2] * 6]
    assert rest_start(qs) == 2
    assert rest_start([[0.0] * 6] * 3) == 0
    assert rest_start([]) == 0
    assert rest_start([[0.0] * 6, [1e-7] * 6]) == 0  # within the tolerance


def test_a_step_faster_than_the_limit_is_a_jump_and_a_slow_one_is_not() -> None:
    slow = [_state(i, 0.001 * i) for i in range(1, 50)]  # 0.25 m/s
    assert tool_steps(slow, 0.5, PERIOD_S).jumps == 0
    jump = [*slow, _state(50, 0.2)]
    steps = tool_steps(jump, 0.5, PERIOD_S)
    assert steps.jumps == 1
    assert steps.max_step_m == pytest.approx(0.2 - 0.049)


def test_a_dropped_state_allows_a_longer_step_and_a_restart_is_no_step() -> None:
    gap = [_state(1, 0.0), _state(6, 0.009)]  # 5 periods at 0.45 m/s
    assert tool_steps(gap, 0.5, PERIOD_S).jumps == 0
    restart = [_state(500, 0.3), _state(1, 0.0, t_s=3.0)]
    assert tool_steps(restart, 0.5, PERIOD_S).n == 0


def test_a_slowly_read_arm_may_move_one_reading_per_change() -> None:
    # Joints read every 28 ms, states every 4 ms: the position changes in steps of 28 ms.
    states = [_state(i, 0.014 * (i // 7)) for i in range(1, 30)]  # 0.5 m/s
    assert tool_steps(states, 0.5, PERIOD_S).jumps > 0
    assert tool_steps(states, 0.5, PERIOD_S, sample_period_s=0.028).jumps == 0


def test_joints_read_before_the_stamp_allow_one_read_age_more() -> None:
    # At the 0.5 m/s limit, the second state's joints read 1 ms later in its 4 ms than the
    # first's: 2.5 mm between stamps 4 ms apart. Allowed with a 2 ms read age; 1 cm is not.
    at_limit = [_state(1, 0.0), _state(2, 0.0025)]
    assert tool_steps(at_limit, 0.5, PERIOD_S).jumps == 1
    assert tool_steps(at_limit, 0.5, PERIOD_S, read_age_s=0.002).jumps == 0
    far = [_state(1, 0.0), _state(2, 0.01)]
    steps = tool_steps(far, 0.5, PERIOD_S, read_age_s=0.002)
    assert steps.jumps == 1 and steps.max_ratio == pytest.approx(0.01 / (0.5 * 0.006 + 1e-6))


def test_event_seqs_restart_at_one_and_gaps_are_counted() -> None:
    evs = [_event("arm", s) for s in (1, 2, 3, 1, 2, 5, 6)] + [_event("force", 1)]
    c = event_continuity(evs)
    assert c["arm"].segments == 2 and c["arm"].lost == 2 and c["arm"].disorder == 0
    assert c["force"].received == 1 and c["force"].lost == 0
    late = event_continuity([_event("decision", 4), _event("decision", 3)])
    assert late["decision"].lost == 3 and late["decision"].disorder == 1


@given(
    runs=st.lists(st.integers(min_value=1, max_value=30), min_size=1, max_size=6),
    drops=st.sets(st.integers(min_value=0, max_value=200)),
)
def test_continuity_counts_exactly_the_events_dropped_inside_each_run(
    runs: list[int], drops: set[int]
) -> None:
    """A node restarted len(runs) times, each run publishing 1..n; events at the indices in
    `drops` are lost (never the first of a run, which marks the restart)."""
    seqs = [s for n in runs for s in range(1, n + 1)]
    kept = [s for i, s in enumerate(seqs) if s == 1 or i not in drops]
    # A loss shows only when a later event of the same run arrives (a lost tail is a
    # truncation, which no receiver can tell from a crash).
    lost_inside = sum(
        1
        for i, s in enumerate(seqs)
        if s != 1 and i in drops and any(j > i and _kept(seqs, drops, j) for j in _run_of(seqs, i))
    )
    c = event_continuity([_event("n", s) for s in kept])["n"]
    assert c.segments == len(runs)
    assert c.disorder == 0
    assert c.lost == lost_inside


def _run_of(seqs: list[int], i: int) -> list[int]:
    """The indices of the run (1..n) that index i belongs to."""
    start = i
    while seqs[start] != 1:
        start -= 1
    end = i
    while end + 1 < len(seqs) and seqs[end + 1] != 1:
        end += 1
    return list(range(start, end + 1))


def _kept(seqs: list[int], drops: set[int], j: int) -> bool:
    return seqs[j] == 1 or j not in drops


def test_count_between_is_half_open() -> None:
    times = [0.0, 1.0, 1.0, 2.0, 3.0]
    assert count_between(times, 1.0, 2.0) == 2
    assert count_between(times, 0.0, 10.0) == 5
    assert count_between([], 0.0, 1.0) == 0
