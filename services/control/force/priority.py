"""OS priority of one thread: the paper's five SensorThreadPriority levels on Linux.

The paper's force sensing component runs in its own thread whose priority "can be adjusted
during runtime to allow for the management of CPU usage" (§2.1.3), one of five OS levels.
On Linux a thread is a schedulable task with its own id (`threading.get_native_id()`), so
`setpriority(PRIO_PROCESS, tid, nice)` sets the nice value of that one thread and
`sched_setscheduler(tid, …)` its policy. Levels map to nice values; `highest` asks for
SCHED_FIFO first. Unprivileged processes may not lower nice below their RLIMIT_NICE floor
nor use SCHED_FIFO, so every call reads back what the kernel actually applied and reports
it: a caller never believes a priority it did not get.
"""

from __future__ import annotations

import os
import sys
from dataclasses import dataclass
from typing import Any, Literal, get_args

PriorityLevel = Literal["lowest", "below_normal", "normal", "above_normal", "highest"]
PRIORITY_LEVELS: tuple[PriorityLevel, ...] = get_args(PriorityLevel)

NICE_OF_LEVEL: dict[PriorityLevel, int] = {
    "lowest": 10,
    "below_normal": 5,
    "normal": 0,
    "above_normal": -5,
    "highest": -10,
}
"""Nice value of each level under SCHED_OTHER (−20 most favoured … 19 least)."""

FIFO_RT_PRIORITY = 10
"""SCHED_FIFO priority for `highest`: above ordinary tasks, below the kernel's own IRQ
threads (50), so a runaway sensor thread cannot starve interrupt handling."""

NICE_MAX = 19

Policy = Literal[
    "SCHED_OTHER", "SCHED_FIFO", "SCHED_RR", "SCHED_BATCH", "SCHED_IDLE", "unsupported"
]


@dataclass(frozen=True, slots=True)
class PriorityReport:
    """What was asked for and what the kernel applied to the thread.

    `applied` is the most favoured level whose promise the thread's actual scheduling meets
    (SCHED_FIFO/RR ⇒ `highest`; otherwise the level with the largest nice ≥ the actual
    nice). `reason` says why `applied` differs from `requested` (empty when equal).
    """

    requested: PriorityLevel
    applied: PriorityLevel
    policy: Policy
    nice: int
    rt_priority: int = 0
    reason: str = ""

    def as_dict(self) -> dict[str, Any]:
        return {
            "requested": self.requested,
            "applied": self.applied,
            "policy": self.policy,
            "nice": self.nice,
            "rt_priority": self.rt_priority,
            "reason": self.reason,
        }


def supported() -> bool:
    """Per-thread priority is a Linux feature (threads are tasks with their own nice)."""
    return sys.platform.startswith("linux") and hasattr(os, "sched_setscheduler")


def level_of(policy: Policy, nice: int) -> PriorityLevel:
    """The most favoured level that (policy, nice) achieves."""
    if policy in ("SCHED_FIFO", "SCHED_RR"):
        return "highest"
    for level in reversed(PRIORITY_LEVELS):
        if nice <= NICE_OF_LEVEL[level]:
            return level
    return "lowest"


def read_thread_priority(tid: int) -> tuple[Policy, int, int]:
    """(policy, nice, rt_priority) of thread `tid`, as the kernel has them now."""
    if not supported():
        return "unsupported", 0, 0
    policy = _policy_name(os.sched_getscheduler(tid))
    nice = os.getpriority(os.PRIO_PROCESS, tid)
    rt = os.sched_getparam(tid).sched_priority
    return policy, nice, rt


def apply_thread_priority(tid: int, level: PriorityLevel) -> PriorityReport:
    """Give thread `tid` (a Linux task id) the priority `level`; report what was applied.

    `highest` tries SCHED_FIFO at FIFO_RT_PRIORITY; when refused it falls back to the most
    favoured nice value permitted at or above the level's nice. Other levels return the
    thread to SCHED_OTHER and set the nice value, again falling back to the most favoured
    nice permitted (an unprivileged process cannot lower nice below its RLIMIT_NICE floor,
    so after `lowest` it may be unable to come back to `normal`: the report says so).
    """
    if level not in NICE_OF_LEVEL:
        raise ValueError(f"unknown priority level {level!r}")
    if not supported():
        return PriorityReport(
            level, "normal", "unsupported", 0, 0, "per-thread priority is Linux-only"
        )
    notes: list[str] = []
    if level == "highest":
        try:
            os.sched_setscheduler(tid, os.SCHED_FIFO, os.sched_param(FIFO_RT_PRIORITY))
        except PermissionError as e:
            notes.append(f"SCHED_FIFO refused ({e.strerror})")
        else:
            return _report(tid, level, notes)
    elif os.sched_getscheduler(tid) != os.SCHED_OTHER:
        # Leaving a real-time policy is always permitted; nice means nothing until we do.
        os.sched_setscheduler(tid, os.SCHED_OTHER, os.sched_param(0))
    target = NICE_OF_LEVEL[level]
    for nice in range(target, NICE_MAX + 1):
        try:
            os.setpriority(os.PRIO_PROCESS, tid, nice)
        except PermissionError:
            continue
        if nice != target:
            notes.append(f"nice {target} refused, lowest permitted is {nice}")
        break
    return _report(tid, level, notes)


def _report(tid: int, requested: PriorityLevel, notes: list[str]) -> PriorityReport:
    policy, nice, rt = read_thread_priority(tid)
    applied = level_of(policy, nice)
    if applied != requested and not notes:
        notes.append(f"kernel reports {policy} nice {nice}")
    return PriorityReport(requested, applied, policy, nice, rt, "; ".join(notes))


def _policy_name(policy: int) -> Policy:
    names: dict[int, Policy] = {
        os.SCHED_OTHER: "SCHED_OTHER",
        os.SCHED_FIFO: "SCHED_FIFO",
        os.SCHED_RR: "SCHED_RR",
    }
    if hasattr(os, "SCHED_BATCH"):
        names[os.SCHED_BATCH] = "SCHED_BATCH"
    if hasattr(os, "SCHED_IDLE"):
        names[os.SCHED_IDLE] = "SCHED_IDLE"
    return names.get(policy, "SCHED_OTHER")
