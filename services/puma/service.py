"""The `puma` service on the bus: IProxyRobot at robot/puma/rpc, `robot/state`, `robot/puma/cmd`.

One control thread owns the arm (franka-node's rule): it applies the newest command from
`robot/puma/cmd`, ticks the proxy at `control_rate_hz` and publishes `robot/state` at
`state_rate_hz`. The command subscription only stores the newest command (latest-wins);
methods run on the node's worker pool and only plan under the proxy's lock. Every exit path
(close, a crash of the loop, SIGTERM through `__main__`) holds the arm.
"""

from __future__ import annotations

import logging
import threading
import time
from typing import Any

import numpy as np

from services.bus import codec, keys
from services.bus.messages import OperatorCommand, RobotState, mat3
from services.bus.node import Node
from services.bus.rate import RateLoop
from services.puma.arm import open_arm
from services.puma.config import PumaConfig
from services.puma.mapping import TeleopInput
from services.puma.proxy import PumaProxy

log = logging.getLogger("telerobot.puma")

#: methods that start a motion and so accept `"wait": true`
MOTIONS = ("move_joints", "move_pose", "move_relative", "home")
WAIT_TIMEOUT_S = 120.0


class PumaService:
    """Runs the PUMA proxy on the bus; `close()` holds the arm and disconnects it."""

    def __init__(self, node: Node, config: PumaConfig, arm: Any = None) -> None:
        self.node = node
        self.config = config
        self.arm = (
            arm if arm is not None else open_arm(config.arm, config.port, **config.arm_options())
        )
        self.proxy = PumaProxy(self.arm, config, self._emit)
        self._state_pub = node.publisher(keys.STATE)
        self._state_seq = 0
        self._cmd_lock = threading.Lock()
        self._pending: OperatorCommand | None = None
        self._stop = threading.Event()
        node.subscribe(keys.PUMA_CMD, self._on_command)
        methods: dict[str, Any] = {
            name: getattr(self.proxy, f"rpc_{name}")
            for name in (
                "status",
                "connect",
                "initialize",
                "set_tool",
                "set_frame",
                "stop",
                "estop",
                "fk",
                "ik",
                "limits",
            )
        }
        for name in MOTIONS:
            methods[name] = self._motion_method(name)
        node.serve("puma", methods)
        self._thread = threading.Thread(target=self._loop, name="puma-control", daemon=True)
        self._thread.start()
        node.announce()

    def _emit(self, kind: str, message: str, data: dict[str, Any]) -> None:
        self.node.event(kind, message, data)

    # --- commands (latest wins; applied by the control thread) ------------------------
    def _on_command(self, cmd: OperatorCommand) -> None:
        with self._cmd_lock:
            self._pending = cmd

    def _apply_pending(self) -> None:
        with self._cmd_lock:
            cmd, self._pending = self._pending, None
        if cmd is None:
            return
        ti = TeleopInput(
            seq=cmd.seq,
            engage=cmd.engage,
            active=cmd.active,
            frame=cmd.frame,
            dp=np.asarray(cmd.dp),
            dR=mat3(cmd.dR),
        )
        self.proxy.on_command(ti, cmd.t_ns, cmd.grip)

    # --- the control loop -------------------------------------------------------------
    def _loop(self) -> None:
        rate = RateLoop(self.config.control_rate_hz, on_late=self._on_late)
        state_every = max(1, round(self.config.control_rate_hz / self.config.state_rate_hz))
        dt = 1.0 / self.config.control_rate_hz
        ticks = 0
        try:
            while not self._stop.is_set():
                self._apply_pending()
                self.proxy.tick(dt)
                if ticks % state_every == 0:
                    self._publish_state()
                ticks += 1
                rate.sleep()
        except Exception as e:  # the loop must never die silently with the arm moving
            log.exception("control loop failed")
            self.node.event("error", f"puma control loop failed: {e}", {"code": "internal"})
            self.proxy.rpc_stop({})
            raise

    def _publish_state(self) -> None:
        st = self.proxy.state()
        self._state_seq += 1
        st["engage"] = max(0, int(st["engage"]))
        st["cmd_seq"] = max(0, int(st["cmd_seq"]))
        self._state_pub.put(RobotState(seq=self._state_seq, t_ns=time.time_ns(), **st))

    def _on_late(self, late_s: float, n_late: int) -> None:
        log.warning("control loop late by %.1f ms (%d late ticks)", late_s * 1e3, n_late)

    # --- methods ----------------------------------------------------------------------
    def _motion_method(self, name: str) -> Any:
        rpc = getattr(self.proxy, f"rpc_{name}")

        def handler(args: dict[str, Any]) -> dict[str, Any]:
            wait = codec.arg(args, "wait", bool, False)
            timeout_s = codec.arg(args, "timeout_s", float, WAIT_TIMEOUT_S)
            reply: dict[str, Any] = rpc(args)
            if not wait:
                return reply
            return {**reply, **self.proxy.wait_motion(int(reply["motion"]), timeout_s)}

        return handler

    def close(self) -> None:
        self._stop.set()
        self._thread.join(timeout=2.0)
        self.proxy.close()
