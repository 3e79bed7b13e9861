"""The bench's view of its children (`services.tools.cell.procs` spawns and stops them): the
CPU each has used, and the wait for the arm to say it is ready.
"""

from __future__ import annotations

import time
from typing import Any

from services.tools.bench.cpu import cpu_by_group
from services.tools.cell.procs import Children


def cpu_by_child(kids: Children) -> dict[str, float]:
    """CPU time (s) each running child has used so far, with anything it started (its
    process group). A reaped child's time is in the bench's own
    `getrusage(RUSAGE_CHILDREN)` instead, so it is left out here."""
    live = {name: c.pid for name, c in kids.children.items() if c.alive}
    used = cpu_by_group(live.values())
    return {name: used[pid] for name, pid in live.items()}


def children_cpu_s(kids: Children) -> float:
    """CPU time (s) the running children have used so far (see `cpu_by_child`)."""
    return sum(cpu_by_child(kids).values())


def wait_arm_ready(kids: Children, node: Any, timeout_s: float) -> None:
    """Block until robot/state says the arm is `ready` (raise ChildFailed as soon as a child
    exits, TimeoutError after `timeout_s`); the probe is undeclared at once after, so it
    does not load the bench all along."""
    from services.bus.keys import STATE
    from services.tools.bench.probes import StreamProbe

    status = StreamProbe(node, STATE, lambda m: (m.status,)).start()
    try:
        deadline = time.monotonic() + timeout_s
        while (newest := status.newest()) is None or newest[1][0] != "ready":
            kids.check()
            if time.monotonic() > deadline:
                raise TimeoutError("the arm never reported ready on robot/state")
            time.sleep(0.05)
    finally:
        status.stop()
