"""An operator's probe session of the deploy system tests (compose, zenohd): what it sees,
the console master's hand, and where a zenohd built here is."""

from __future__ import annotations

import math
import os
import shutil
import subprocess
import threading
import time
from dataclasses import dataclass, field
from importlib.metadata import version
from pathlib import Path
from typing import Any

from services.bus import keys
from services.bus.messages import ArmTarget, Event, RobotState
from services.bus.node import Node
from services.bus.router import endpoint_taken
from tests.conftest import wait_until

EYE = [1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0]
ZENOH_VERSION = version("eclipse-zenoh")


def zenohd_binary() -> Path | None:
    """The zenohd of the installed eclipse-zenoh's release: TELEROBOT_ZENOHD, or where
    `make zenohd` puts it, or one on PATH; None when there is none of that version."""
    cache = Path.home() / ".cache" / "telerobot" / f"zenohd-{ZENOH_VERSION}" / "bin" / "zenohd"
    for cand in (os.environ.get("TELEROBOT_ZENOHD"), str(cache), shutil.which("zenohd")):
        if not cand or not os.access(cand, os.X_OK):
            continue
        out = subprocess.run([cand, "--version"], capture_output=True, text=True, timeout=30)
        if ZENOH_VERSION in out.stdout:
            return Path(cand)
    return None


def router_listens(*ports: int, timeout_s: float) -> bool:
    """Whether something listens on each loopback port (a router started elsewhere: a
    client opened before it does fails at once)."""
    return bool(
        wait_until(
            lambda: all(endpoint_taken(f"tcp/127.0.0.1:{p}") for p in ports),
            timeout_s,
            poll_s=0.1,
            what=f"a router on {ports}",
        )
    )


@dataclass
class Watch:
    """What a probe session saw, appended from Zenoh's threads."""

    states: list[RobotState] = field(default_factory=list)
    targets: list[ArmTarget] = field(default_factory=list)
    events: list[Event] = field(default_factory=list)
    force: list[tuple[int, int]] = field(default_factory=list)
    lock: threading.Lock = field(default_factory=threading.Lock)

    def add(self, where: list[Any], item: Any) -> None:
        with self.lock:
            where.append(item)

    def snapshot(self, where: list[Any]) -> list[Any]:
        with self.lock:
            return list(where)

    def subscribe(self, node: Node) -> None:
        node.subscribe(keys.STATE, lambda m: self.add(self.states, m))
        node.subscribe(keys.ARM_TARGET, lambda m: self.add(self.targets, m))
        node.subscribe(keys.EVENTS, lambda m: self.add(self.events, m))
        node.subscribe(keys.FORCE, lambda m: self.add(self.force, (m.seq, m.t_ns)))

    def state(self) -> RobotState:
        states = self.snapshot(self.states)
        assert states, "no robot/state at the probe"
        return states[-1]


def hand(node: Node, p: tuple[float, float, float], clutch: bool = False) -> None:
    """The console's virtual master's hand at p (master frame), as its gizmo would put it."""
    args = {"p": list(p), "R": EYE, "clutch": clutch}
    node.call("master/console", "set_hand", args, 30.0)


def reengage(node: Node, p: tuple[float, float, float]) -> None:
    """Master-shift pressed and released with the hand at p: a new engagement, which the
    decision starts from where the arm is (one made before the arm was ready is refused
    and stays blocked)."""
    hand(node, p, clutch=True)
    time.sleep(0.1)
    hand(node, p, clutch=False)


def take_lease(node: Node, p: tuple[float, float, float], tries: int = 3) -> dict[str, Any]:
    """Engage the console's master anew until the decision gives it the lease (an
    engagement that arrives before the decision has seen the arm ready is refused and stays
    blocked); the decision's status then."""
    status: dict[str, Any] = {}

    def leased() -> bool:
        nonlocal status
        status = node.call("decision", "status", {}, 30.0)
        return status["lease"] == "console" and status["mode"] == "follow"

    def ready() -> bool:
        nonlocal status
        status = node.call("decision", "status", {}, 30.0)
        return bool(status["robot"]["status"] == "ready")

    assert wait_until(ready, 30.0, poll_s=0.2), f"the decision never saw the arm ready: {status}"
    for _ in range(tries):
        reengage(node, p)
        if wait_until(leased, 5.0, poll_s=0.2):
            return status
    raise AssertionError(f"the console's master never took the lease: {status.get('mode')}")


def sweep(node: Node, x0: float, x1: float, steps: int = 20) -> None:
    """The hand along x from x0 to x1, a step every 20 ms (below the speed limits)."""
    for i in range(1, steps + 1):
        hand(node, (x0 + (x1 - x0) * i / steps, 0.0, 0.0))
        time.sleep(0.02)


def moved_from(w: Watch, p0: tuple[float, ...], by_m: float) -> bool:
    return math.dist(w.state().tool_p, p0) > by_m
