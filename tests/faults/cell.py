"""The simulated cell of the fault suite: router, arm, force, decision and a scripted
master, each a separate process, with an in-process observer connected throughout.

The master plays a long generated circle (radius 5 cm, 4 s a turn, ~8 cm/s at the tool), so
the arm is moving whenever a fault strikes. It starts only once the arm is `ready`: an
engagement that begins before then is held by the decision server for good (a master must
engage anew), which is also how a test gets a fresh engagement: restart the master.
"""

from __future__ import annotations

import time
from pathlib import Path
from typing import Any

import numpy as np

from services.bus.errors import RpcError, Unavailable
from services.bus.messages import RobotState
from services.control.master.devices.scripted import generate_motion, save_trajectory
from services.tools.cell.procs import Child
from tests.conftest import wait_until
from tests.faults.observe import Observer
from tests.faults.procs import Cell

MASTER_ID = "master"
START_TIMEOUT_S = 60.0
"""Generous: five Python processes importing Pinocchio and NumPy on a loaded 2-core host."""
CALL_TIMEOUT_S = 3.0
FOLLOW_TIMEOUT_S = 20.0
CIRCLE_CYCLES = 60


class FaultCell:
    """Processes by name (`router` is `cell.router`), the observer, and the steps every
    fault test shares. `close()` kills every process and closes the observer."""

    def __init__(self, tmp: Path) -> None:
        self.cell = Cell(tmp / "logs")
        script = tmp / "circle.jsonl"
        save_trajectory(script, generate_motion("circle", cycles=CIRCLE_CYCLES))
        try:
            self.cell.start_router()
            # The observer joins before any service, so it sees every event from seq 1.
            self.obs = Observer(self.cell.endpoint)
        except BaseException:
            self.cell.close()
            raise
        self.cell.add("arm", "arm", "--autostart")
        self.cell.add("force", "force")
        self.cell.add("decision", "decision")
        self.cell.add("master", "master", "--device", "script", "--script", str(script))
        self.expected_down: set[str] = set()
        self.recoveries: list[str] = []

    # --- processes -------------------------------------------------------------------
    def __getitem__(self, name: str) -> Child:
        return self.cell[name]

    @property
    def router(self) -> Child:
        return self.cell.router

    def kill(self, name: str) -> None:
        """SIGKILL a service (it is expected down until started again)."""
        self.expected_down.add(name)
        self.cell[name].kill()

    def start(self, name: str) -> None:
        self.expected_down.discard(name)
        self.cell[name].start()

    def replace(self, name: str, service: str, *extra: str) -> Child:
        """Stop `name` (SIGTERM) and declare a new process under that name (not started)."""
        self.cell[name].stop()
        self.expected_down.add(name)
        return self.cell.add(name, service, *extra)

    def crashed(self) -> dict[str, int | None]:
        """Processes that ended without a test stopping them."""
        out = {n: rc for n, rc in self.cell.crashed().items() if n not in self.expected_down}
        if not self.router.alive and "router" not in self.expected_down:
            out["router"] = self.router.returncode
        return out

    def assert_no_crash(self) -> None:
        crashed = self.crashed()
        assert not crashed, f"processes died: {crashed}\n{self.diagnose()}"

    # --- calls -----------------------------------------------------------------------
    def call(self, method: str, args: dict[str, Any] | None = None) -> dict[str, Any]:
        """A method of the decision server (the operator's single entry point)."""
        return self.obs.node.call("decision", method, args or {}, CALL_TIMEOUT_S)

    def mode(self) -> str | None:
        try:
            return str(self.call("status")["mode"])
        except (RpcError, Unavailable):
            return None

    # --- the shared steps ------------------------------------------------------------
    def wait_ready(self, timeout_s: float = START_TIMEOUT_S) -> RobotState:
        """Until a fresh robot/state says `ready` or `moving`; an arm in `error` (a serial
        link that timed out on a starved host, say) is recovered as an operator would."""
        start = self.obs.n_states()

        def settled() -> bool:
            st = self.obs.latest_state()
            return (
                st is not None
                and self.obs.n_states() > start
                and st.status in ("ready", "moving", "error")
            )

        deadline = time.monotonic() + timeout_s
        while True:
            ok = wait_until(settled, max(deadline - time.monotonic(), 0.0), 0.02)
            st = self.obs.latest_state()
            assert ok and st is not None, f"the arm never became ready\n{self.diagnose()}"
            if st.status != "error":
                return st
            self.recoveries.append(f"arm in error: {self.last_error()}")
            try:
                self.call("connect")
                self.call("initialize")
            except RpcError as e:
                self.recoveries.append(f"recovery refused: {e.code}: {e.message}")
            start = self.obs.n_states()

    def ensure_following(self, attempts: int = 3) -> None:
        """Every service up, the arm ready and the master's engagement followed, moving.

        A master whose engagement the decision server refused (it began while the arm was
        not ready) is restarted, up to `attempts` times; each such recovery is recorded."""
        self.assert_no_crash()
        if not self.router.alive:
            self.cell.start_router()
            self.expected_down.discard("router")
        for name in ("arm", "force", "decision"):
            if not self.cell[name].alive:
                self.start(name)
        for name in ("arm", "force", "decision"):
            assert self.obs.node.alive.wait(name, START_TIMEOUT_S), (
                f"{name} never came up\n{self.diagnose()}"
            )
        master = self.cell[MASTER_ID]
        for attempt in range(attempts):
            self.wait_ready()
            if master.alive and self.mode() != "follow":
                master.stop()  # its engagement is held for good: a new one needs a restart
            if not master.alive:
                self.start(MASTER_ID)
            if wait_until(lambda: self.mode() == "follow", FOLLOW_TIMEOUT_S, 0.1):
                break
            self.recoveries.append(f"master not followed (attempt {attempt + 1}): {self.recent()}")
        else:
            raise AssertionError(
                f"the decision server never followed the master\n{self.diagnose()}"
            )
        moved = self.wait_motion(0.002, 5.0)
        assert moved, f"the arm does not move with the master\n{self.diagnose()}"

    def last_error(self) -> str:
        errors = [e.message for e in self.obs.events() if e.kind == "error"]
        return errors[-1] if errors else "?"

    def recent(self, n: int = 8) -> list[tuple[str, str, str]]:
        """The last events, for failure messages."""
        return [(e.source, e.kind, e.message[:100]) for e in self.obs.events()[-n:]]

    def diagnose(self) -> str:
        st = self.obs.latest_state()
        return (
            f"latest state: {st.status if st else None}; recoveries: {self.recoveries}\n"
            f"recent events: {self.recent(15)}\n{self.cell.logs()}"
        )

    def wait_motion(self, dist_m: float, timeout_s: float) -> bool:
        """Until the tool has moved `dist_m` from where it is now."""
        start = self.obs.n_states()
        st = self.obs.latest_state()
        assert st is not None
        p0 = np.asarray(st.tool_p)

        def moved() -> bool:
            states = self.obs.states(start)
            return any(float(np.linalg.norm(np.subtract(s.tool_p, p0))) > dist_m for s in states)

        return wait_until(moved, timeout_s, 0.02)

    def close(self) -> None:
        try:
            self.obs.close()
        finally:
            self.cell.close()


def path_length(states: list[RobotState]) -> float:
    """Length (m) of the tool point's path through `states`."""
    if len(states) < 2:
        return 0.0
    p = np.asarray([s.tool_p for s in states])
    return float(np.sum(np.linalg.norm(np.diff(p, axis=0), axis=1)))


def since(t0: float) -> float:
    """Milliseconds since the monotonic time `t0`."""
    return (time.monotonic() - t0) * 1e3
