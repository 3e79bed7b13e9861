"""The robot side in simulation, in one process: `SimCell` and its light settings.

Each service runs on a node of its own as separate processes would, built in the order each
needs the one before: arm (simulated arm, at home), workcell (the cell's MuJoCo physics, of a
given `Scene`, which the arm's joints and the wrist are part of; with the arm on
`sim_physics = "embedded"`, the default `light_arm`, the two share an `ArmChannel` in memory
as in the sim profile's arm process), force (simulated wrist) and decision. Used by the
tests, by the tasks (`python -m services.tools.tasks --headless`), by the bench and by the
link bench's robot side (`services.tools.tdpa.link_bench`, which starts it through the
decision server instead of `start()`).

Nodes come from a `NodeFactory(name, instance)`, so the same code runs on a private test
network or a headless in-process network.
"""

from __future__ import annotations

from collections.abc import Callable

from services.bus.errors import TelerobotError
from services.bus.node import Node
from services.control.arm.config import ArmConfig
from services.control.arm.model import DEFAULT_MODEL
from services.control.arm.service import ArmService
from services.control.decision.config import DecisionConfig
from services.control.decision.service import DecisionService
from services.control.force.config import ForceConfig
from services.control.force.service import ForceService
from services.tools.cell.wait import wait_until
from services.world.workcell.channel import ArmChannel
from services.world.workcell.config import WorkcellConfig
from services.world.workcell.scene import Scene
from services.world.workcell.service import WorkcellService

NodeFactory = Callable[[str, str | None], Node]
READY_TIMEOUT_S = 30.0


class CellNotReady(TelerobotError):
    """The simulated arm did not report ready within the deadline."""


class SimCell:
    """Arm, workcell, force and decision services in this process (see the module doc), on
    nodes from `make_node` (the arm's first: on a `Peers` network it is the one that listens).

    `scene`: the workcell's (default its `default_scene()`). `start()` connects and
    initializes the arm and waits until `robot/state` says ready. `close()` stops them in
    reverse order (the decision holds the arm first).
    """

    def __init__(
        self,
        make_node: NodeFactory,
        *,
        arm: ArmConfig | None = None,
        force: ForceConfig | None = None,
        decision: DecisionConfig | None = None,
        workcell: WorkcellConfig | None = None,
        scene: Scene | None = None,
    ) -> None:
        self._closers: list[Callable[[], None]] = []
        arm = arm or ArmConfig()
        # the arm on the cell's physics in memory, as the sim profile runs it (embedded)
        channel = ArmChannel() if arm.sim_physics == "embedded" else None
        try:
            self.arm = ArmService(make_node("arm", None), arm, channel=channel)
            self._closers.append(self.arm.close)
            self.workcell = WorkcellService(
                make_node("workcell", None),
                workcell or WorkcellConfig(),
                scene=scene,
                channel=channel,
            )
            self._closers.append(self.workcell.close)
            self.force = ForceService(make_node("force", None), force or ForceConfig())
            self._closers.append(self.force.close)
            self.decision = DecisionService(
                make_node("decision", None), decision or DecisionConfig()
            )
            self._closers.append(self.decision.close)
        except BaseException:
            self.close()
            raise

    def start(self, timeout_s: float = READY_TIMEOUT_S) -> None:
        """Connect and initialize the arm (as `arm --autostart` does), wait until ready."""
        proxy = self.arm.proxy
        proxy.rpc_connect({})
        proxy.rpc_initialize({})
        if not wait_until(lambda: proxy.status == "ready", timeout_s, 0.01):
            raise CellNotReady(f"the arm did not become ready (status {proxy.status})")

    def close(self) -> None:
        for close in reversed(self._closers):
            close()
        self._closers.clear()


def light_arm(model: str = DEFAULT_MODEL) -> ArmConfig:
    """The simulated arm `model` on the workcell's physics (embedded: handed over in memory,
    as the sim profile does), with a short calibration."""
    return ArmConfig(model=model, sim_calibration_s=0.05, sim_physics="embedded")


LIGHT_FORCE = ForceConfig(seed=7, period_ms=2.0)
"""The simulated wrist at 500 Hz without the final spin."""


def light_cell(make_node: NodeFactory, model: str = DEFAULT_MODEL) -> SimCell:
    """A SimCell of arm `model` with settings that keep it light on a small shared host
    (tests, headless runs): `light_arm`, `LIGHT_FORCE`, and watchdogs that catch a service
    that is really gone rather than a busy CPU."""
    return SimCell(
        make_node,
        arm=light_arm(model),
        force=LIGHT_FORCE,
        decision=DecisionConfig(watchdog_ms=500.0, state_stale_ms=1000.0, stale_ms=500.0),
    )
