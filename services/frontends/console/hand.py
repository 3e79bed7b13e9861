"""The virtual master's hand, fed from the gizmo in the 3D scene.

The gizmo is the operator's hand: its pose (world) is sent as the hand pose of master
`<id>` (`robot/master/<id>/rpc/set_hand`, docs/protocol-extensions.md), which then runs the
same pipeline as a physical device (eq. 5, master-shift, robot/cmd → decision → arm).

Re-synchronising ("snap") is the physical operator's gesture: press the master-shift, put
the hand where the tool is, keep it pressed. The hand is then `parked` on the tool, and the
operator's first motion of the gizmo releases the master-shift there: the master starts a
new engagement at the tool pose, so with s_t = s_r = 1 and frame `world` the tool follows
the gizmo exactly. Nothing moves until the operator moves the gizmo, and nothing moves
while the gizmo is carried to the tool. The very first pose sent is always with the
master-shift pressed: a master that engaged before the console arrived never sees a jump.
"""

from __future__ import annotations

import logging
import threading
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from services.bus.errors import RpcError, Unavailable
from services.bus.messages import MasterState, vec
from services.bus.node import Node
from services.geometry import Array3, Mat3

log = logging.getLogger("telerobot.console")

Pose = tuple[Array3, Mat3]
SYNC_TIMEOUT_S = 1.0
"""How long a clutch step waits for the master to show it read the new hand."""
SAME_P_M = 1e-9


@dataclass(frozen=True, slots=True)
class ToolPose:
    """The arm's tool pose (world) and status, from the newest robot/state."""

    p: Array3
    R: Mat3
    status: str


def _same(m: MasterState, p: Array3) -> bool:
    return bool(np.max(np.abs(np.asarray(m.hand_p) - p)) <= SAME_P_M)


class HandLink:
    """Sends the gizmo pose to the master from a thread of its own (latest wins).

    Callers (the page's callbacks, the button actions) only store and notify: `set_gizmo`,
    `set_shift`, `resync`, `hold`. The link's thread runs the clutch cycle and sends.

    link states (`state`): `waiting` (no pose sent yet), `parked` (on the tool, clutched until
    the gizmo moves while the robot is ready), `engaged`, `master-shift` (the operator's),
    `holding` (clutched by the console during `home` and after an e-stop, until the next
    resync), `error`.
    """

    def __init__(
        self,
        node: Node,
        master_id: str,
        master_state: Callable[[Callable[[MasterState], bool], float], MasterState | None],
        tool_pose: Callable[[], ToolPose | None],
        place_gizmo: Callable[[Array3, Mat3], None],
        rpc_timeout_s: float = 2.0,
    ) -> None:
        self.node = node
        self.master_id = master_id
        self.service = f"master/{master_id}"
        self._wait_master = master_state
        self._tool_pose = tool_pose
        self._place_gizmo = place_gizmo
        self.rpc_timeout_s = rpc_timeout_s
        self._cond = threading.Condition()
        self._gizmo: Pose | None = None
        self._version = 0
        self._shift = False
        self._held: str | None = None
        self._resync = False
        self._stop = False
        self._synced = False
        self._sent: tuple[Pose, bool] | None = None
        self.state = "waiting"
        self.error: str | None = None
        self.sent = 0
        self.resyncs = 0
        self._thread = threading.Thread(target=self._run, name="console-hand", daemon=True)
        self._thread.start()

    # --- any thread: store and notify -----------------------------------------------------
    def set_gizmo(self, p: Array3, R: Mat3) -> None:
        """The gizmo moved (world pose)."""
        with self._cond:
            self._gizmo = (p, R)
            self._version += 1
            self._cond.notify_all()

    def release(self) -> None:
        """The operator let go of the gizmo: the hand stays where it is, clutched (parked
        there), so the master disengages cleanly instead of streaming a still hand, and the
        next drag engages afresh from that pose (no jump, no watchdog)."""
        with self._cond:
            if self._held is None:
                self._held = "parked"
                self._version += 1
                self._cond.notify_all()

    def set_shift(self, pressed: bool) -> None:
        """The operator's master-shift (clutch) checkbox."""
        with self._cond:
            self._shift = pressed
            self._version += 1
            self._cond.notify_all()

    def hold(self) -> None:
        """Clutch on behalf of the console (before `home`, on e-stop) until the next resync."""
        with self._cond:
            self._held = "holding"
            self._version += 1
            self._cond.notify_all()

    def resync(self) -> None:
        """Snap the gizmo to the tool, clutched: the hand is `parked` there."""
        with self._cond:
            self._resync = True
            self._cond.notify_all()

    def wait(self, pred: Callable[[HandLink], bool], timeout_s: float) -> bool:
        """Block until `pred(self)` holds (checked at each change of state), or the deadline."""
        with self._cond:
            return self._cond.wait_for(lambda: pred(self), timeout_s)

    def _set_state(self, state: str) -> None:
        with self._cond:
            self.state = state
            self._cond.notify_all()

    @property
    def synced(self) -> bool:
        with self._cond:
            return self._synced

    def close(self) -> None:
        with self._cond:
            self._stop = True
            self._cond.notify_all()
        self._thread.join(timeout=2.0)

    # --- the link's thread ----------------------------------------------------------------
    def _run(self) -> None:
        seen = -1
        while True:
            with self._cond:
                while not self._stop and not self._resync and self._version == seen:
                    self._cond.wait(0.5)
                if self._stop:
                    return
                resync, self._resync = self._resync, False
                seen = self._version
                gizmo, shift, held, synced = self._gizmo, self._shift, self._held, self._synced
            try:
                if resync:
                    self._do_resync()
                elif synced and gizmo is not None:
                    self._follow(gizmo, shift, held)
            except (RpcError, Unavailable) as e:
                self.error = f"{self.service}: {e}"
                self._set_state("error")
                log.warning("virtual master: %s", e)

    def _send(self, pose: Pose, clutch: bool) -> None:
        if self._sent is not None and self._sent[1] == clutch:
            last = self._sent[0]
            if np.array_equal(last[0], pose[0]) and np.array_equal(last[1], pose[1]):
                return
        self.node.call(
            self.service,
            "set_hand",
            {"p": list(vec(pose[0])), "R": list(vec(pose[1])), "clutch": clutch},
            self.rpc_timeout_s,
        )
        self._sent = (pose, clutch)
        self.sent += 1
        self.error = None

    def _follow(self, gizmo: Pose, shift: bool, held: str | None) -> None:
        moved = self._sent is not None and not (
            np.array_equal(self._sent[0][0], gizmo[0])
            and np.array_equal(self._sent[0][1], gizmo[1])
        )
        if held == "parked" and not shift and self._sent is not None and moved:
            tool = self._tool_pose()
            if tool is not None and tool.status in ("ready", "moving"):
                # The operator moves the gizmo: release the master-shift where the hand was
                # parked (the tool pose), so the engagement starts there, then follow.
                parked = self._sent[0]
                self._send(parked, False)
                if self._wait_master(lambda m: m.active and _same(m, parked[0]), SYNC_TIMEOUT_S):
                    with self._cond:
                        if self._held == "parked":
                            self._held = held = None
                else:
                    raise RpcError("internal", "the master did not engage")
        self._send(gizmo, shift or held is not None)
        self._set_state("master-shift" if shift else held or "engaged")

    def _do_resync(self) -> None:
        tool = self._tool_pose()
        if tool is None:
            self._set_state("waiting")
            return
        target: Pose = (np.asarray(tool.p, dtype=float), np.asarray(tool.R, dtype=float))
        here = self._sent[0] if self._sent is not None else target
        # 1. press the master-shift where the hand is, and see the master disengage
        self._send(here, True)
        if self._wait_master(lambda m: not m.active and _same(m, here[0]), SYNC_TIMEOUT_S) is None:
            raise RpcError("internal", "the master did not take the master-shift")
        # 2. carry the hand (and the gizmo) to the tool, keep it clutched there: parked
        self._place_gizmo(target[0], target[1])
        with self._cond:
            self._gizmo = target
            self._held = "parked"
            shift = self._shift
        self._send(target, True)
        if self._wait_master(lambda m: _same(m, target[0]), SYNC_TIMEOUT_S) is None:
            raise RpcError("internal", "the master did not read the new hand pose")
        with self._cond:
            self._synced = True
        self.resyncs += 1
        self._set_state("master-shift" if shift else "parked")
