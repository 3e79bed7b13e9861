"""Autonomous tasks on the pure Supervisor: plans, guarded moves, pick & place, pre-emption."""

from __future__ import annotations

import itertools

import numpy as np
import pytest

from services.bus.errors import ProtocolError, RpcError
from services.control.decision.config import DecisionConfig
from services.control.decision.supervisor import Mode
from services.control.decision.taskrun import FORCE_GAP_S, TaskRun
from services.control.decision.tasks import (
    Grip,
    GuardedMove,
    MoveTo,
    guarded_move_plan,
    pick_place_plan,
)
from services.world.workcell.scene import TABLE
from tests.control.decision.rig import FINGER_M, TICK_NS, Rig

CFG = DecisionConfig()
TOP = TABLE.top_z
TOUCH = TOP + FINGER_M
"""The tool point's height when the gripper's fingertips touch the table (the rig's cell)."""


def run_until_done(rig: Rig, run: TaskRun, max_ticks: int = 20_000) -> None:
    for _ in range(max_ticks):
        rig.step()
        if run.done:
            return
    raise AssertionError(f"task {run.name} did not finish")


def test_guarded_move_plan_validates_its_arguments() -> None:
    plan = guarded_move_plan({"direction": [0, 0, -2]}, CFG)
    (step,) = plan.steps
    assert isinstance(step, GuardedMove)
    assert step.direction == (0.0, 0.0, -1.0)
    assert step.speed_m_s == CFG.guarded_speed_m_s and plan.wait
    with pytest.raises(RpcError) as e:
        guarded_move_plan({"direction": [0, 0, 0]}, CFG)
    assert e.value.code == "bad_request" and e.value.message.startswith("|direction|")
    with pytest.raises(ProtocolError):
        guarded_move_plan({"direction": [0, 0, float("nan")]}, CFG)
    for absurd in ([1e308] * 3, [0.0, 0.0, 5e-324], [-1e300, 0.0, 1.0]):
        with pytest.raises(RpcError) as e:  # refused before the norm could overflow
            guarded_move_plan({"direction": absurd}, CFG)
        assert e.value.code == "bad_request" and "direction" in e.value.message
    with pytest.raises(ProtocolError):
        guarded_move_plan({"direction": [0, 0, -1], "max_force_n": -1}, CFG)
    with pytest.raises(RpcError) as e:
        guarded_move_plan({"direction": [0, 0, -1], "speed_m_s": 1.0}, CFG)
    assert e.value.code == "limit"


def test_pick_place_plan_and_its_workspace_check() -> None:
    plan = pick_place_plan({"pick": [0.5, -0.1, 0.45], "place": [0.6, 0.2, 0.45]}, CFG)
    kinds = [type(s).__name__ for s in plan.steps]
    assert kinds == [
        "Grip", "MoveTo", "MoveTo", "Grip", "MoveTo", "MoveTo", "GuardedMove", "Grip", "MoveTo",
    ]  # fmt: skip
    assert [s.value for s in plan.steps if isinstance(s, Grip)] == [0.0, 1.0, 0.0]
    assert isinstance(plan.steps[2], MoveTo) and plan.steps[2].guard_force_n is not None
    with pytest.raises(RpcError) as e:
        pick_place_plan({"pick": [0.5, -0.1, 0.30], "place": [0.6, 0.2, 0.45]}, CFG)
    assert e.value.code == "limit"


def test_guarded_move_finds_the_table_top() -> None:
    rig = Rig(p=(0.6, 0.0, TOUCH + 0.03), cell=True)
    run = rig.sup.start_task(guarded_move_plan({"direction": [0, 0, -1]}, CFG), rig.now_ns)
    run_until_done(rig, run)
    assert run.error is None and run.result is not None
    r = run.result
    assert r["contact"] is True and r["stopped"] == "contact"
    # where the target was when the force passed the guard: the arm's servo and the
    # contact (≈ 5 kN/m together) let the target run ≈ 5 mm past the fingertips' touch
    assert r["contact_p"][2] == pytest.approx(TOUCH - 0.005, abs=0.003)
    assert r["force_n"] > CFG.guarded_max_force_n
    assert r["distance_m"] == pytest.approx(0.03, abs=0.002)  # from the start to the touch
    assert rig.sup.mode is Mode.HOLD and not rig.outputs[-1].active
    # the move went at the guarded speed, in a straight line down
    zs = [c.dp[2] for c in rig.outputs if c.active]
    assert max(abs(a - b) for a, b in itertools.pairwise(zs)) <= 0.02 * 0.002 + 1e-12
    assert all(abs(c.dp[0]) < 1e-12 and abs(c.dp[1]) < 1e-12 for c in rig.outputs)


def test_guarded_move_without_contact_stops_at_its_distance() -> None:
    rig = Rig(p=(0.6, 0.0, 0.8))
    plan = guarded_move_plan({"direction": [1, 0, 0], "max_distance_m": 0.01}, CFG)
    run = rig.sup.start_task(plan, rig.now_ns)
    run_until_done(rig, run)
    assert run.result is not None and run.result["contact"] is False
    assert run.result["stopped"] == "distance"
    assert rig.p[0] == pytest.approx(0.61, abs=1e-9)


def test_guarded_move_needs_the_force_stream() -> None:
    """Without a fresh force it holds still, and fails not_ready after FORCE_GAP_S."""
    rig = Rig(p=(0.6, 0.0, 0.6))
    start = rig.p.copy()
    run = rig.sup.start_task(guarded_move_plan({"direction": [0, 0, -1]}, CFG), rig.now_ns)
    t0 = rig.now_ns
    while not run.done and rig.now_ns - t0 < 2 * FORCE_GAP_S * 1e9:
        rig.step(force=False)
        assert rig.p == pytest.approx(start, abs=1e-12)  # never moved blind
    assert run.error is not None and run.error[0] == "not_ready"
    assert FORCE_GAP_S * 1e9 < rig.now_ns - t0 <= FORCE_GAP_S * 1e9 + 2 * TICK_NS


def test_a_guarded_move_pauses_through_a_gap_in_the_force_stream_and_goes_on() -> None:
    rig = Rig(p=(0.6, 0.0, TOUCH + 0.03), cell=True)
    run = rig.sup.start_task(guarded_move_plan({"direction": [0, 0, -1]}, CFG), rig.now_ns)
    for _ in range(100):
        rig.step()
    z = float(rig.outputs[-1].p[2])  # the target's height
    assert z < TOUCH + 0.03  # on its way down
    gap = []
    for _ in range(60):  # 120 ms without a force sample (stale after 50 ms)
        rig.step(force=False)
        gap.append(float(rig.outputs[-1].p[2]))
    assert gap[0] < z and not run.done
    held = gap[-30:]  # the last 60 ms of the gap: stale, so held
    assert max(held) - min(held) < 1e-12
    assert gap[0] > held[0]  # it moved while the last sample was still fresh
    run_until_done(rig, run)
    assert run.error is None and run.result is not None
    assert run.result["stopped"] == "contact"
    assert run.result["contact_p"][2] == pytest.approx(TOUCH - 0.005, abs=0.003)


def test_pick_and_place_runs_its_steps_with_the_gripper() -> None:
    rig = Rig(p=(0.6, 0.0, 0.6), cell=True)
    plan = pick_place_plan(
        {"pick": [0.6, -0.05, 0.45], "place": [0.6, 0.05, TOP + 0.01],
         "approach_height_m": 0.05, "speed_m_s": 0.1},
        CFG,
    )  # fmt: skip
    run = rig.sup.start_task(plan, rig.now_ns)
    run_until_done(rig, run)
    assert run.error is None and run.result is not None and run.result["done"]
    grips = [c.grip for c in rig.outputs if c.active]
    changes = [g for i, g in enumerate(grips) if i == 0 or g != grips[i - 1]]
    assert changes == [0.0, 1.0, 0.0]
    # the place descent was stopped by the table (the fingertips touch it), above its full
    # distance
    lowest = 0.6 + min(c.dp[2] for c in rig.outputs)
    assert TOUCH - 0.003 < lowest < TOUCH + 0.003
    assert rig.p == pytest.approx([0.6, 0.05, TOP + 0.01 + 0.05], abs=0.003)
    assert rig.notices_of("task")[-1].data["action"] == "done"


def test_unexpected_contact_aborts_a_guarded_descent() -> None:
    rig = Rig(p=(0.6, 0.0, 0.5), cell=True)
    plan = pick_place_plan(
        {"pick": [0.6, 0.0, TOP], "place": [0.6, 0.1, 0.5], "approach_height_m": 0.05},
        CFG,
    )  # the pick point is on the table top: the fingertips touch it first
    run = rig.sup.start_task(plan, rig.now_ns)
    run_until_done(rig, run)
    assert run.error is not None and run.error[0] == "limit"
    assert "unexpected contact" in run.error[1]


def test_a_task_preempts_teleoperation_refuses_commands_and_cancel_stops_it() -> None:
    rig = Rig(p=(0.6, 0.0, 0.8))
    for _ in range(3):
        rig.step([rig.cmd()])
    assert rig.sup.mode is Mode.FOLLOW
    plan = guarded_move_plan({"direction": [0, 0, -1], "max_distance_m": 0.1}, CFG)
    run = rig.sup.start_task(plan, rig.now_ns)
    assert rig.sup.lease is None
    rig.run(20, lambda i: [rig.cmd(dp=(0.05, 0, 0))])
    assert rig.sup.notices.counters["busy"] == 20 and len(rig.notices_of("busy")) == 1
    assert all(c.engage == 2 for c in rig.outputs[-20:])  # the task's own engagement
    with pytest.raises(RpcError) as e:
        rig.sup.start_task(plan, rig.now_ns)
    assert e.value.code == "busy"
    with pytest.raises(RpcError) as e:
        rig.sup.claim("move_pose")
    assert e.value.code == "busy"
    assert rig.sup.cancel_task(rig.now_ns) is run
    assert run.done and run.cancelled and run.result == {
        "task": "guarded_move", "cancelled": True, "done": False,
    }  # fmt: skip
    rig.run(5, lambda i: [rig.cmd(dp=(0.05, 0, 0))])  # the operator's engagement stays held
    assert rig.sup.mode is Mode.HOLD and not rig.outputs[-1].active


def test_estop_preempts_a_task() -> None:
    rig = Rig(p=(0.6, 0.0, 0.8))
    plan = guarded_move_plan({"direction": [0, 0, -1]}, CFG)
    run = rig.sup.start_task(plan, rig.now_ns)
    rig.run(10)
    rig.sup.estop(rig.now_ns)
    assert run.done and run.error is not None and run.error[0] == "estop"
    n = len(rig.outputs)
    rig.run(3)
    assert rig.sup.mode is Mode.ESTOP and len(rig.outputs) > n
    assert all(not c.active for c in rig.outputs[n:])


def test_a_move_that_cannot_arrive_fails_as_unreachable() -> None:
    rig = Rig(p=(0.6, 0.0, 0.6))
    run = rig.sup.start_task(
        pick_place_plan({"pick": [0.6, 0.0, 0.55], "place": [0.6, 0.1, 0.55]}, CFG), rig.now_ns
    )
    rig.step()
    rig._slave = lambda c: None  # type: ignore[method-assign]  # the arm stops following
    run_until_done(rig, run)
    assert run.error is not None and run.error[0] == "unreachable"
    assert np.allclose(rig.p, [0.6, 0.0, 0.6])
