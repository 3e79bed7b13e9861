"""Running a task: the robot side in simulation, the operator's station, and one run.

- the robot side in simulation is `services.tools.cell.sim`'s `SimCell` (`light_cell`).
- `Station`: the operator's side: a master service with a virtual device (id `operator`),
  the scripted person at it, and what they see.
- `run_task()`: reset the workcell, run one scenario, and report its metrics.

Nodes come from a `NodeFactory(name, instance)` (`services.tools.cell.sim`), so the same
code runs on a private test network, on a headless in-process network, or against a running
system (`telerobot demo`).
"""

from __future__ import annotations

import contextlib
import logging
import time
from collections.abc import Callable
from dataclasses import asdict, replace

from services.bus.config import NodeConfig
from services.bus.errors import RpcError, Unavailable
from services.bus.node import Node
from services.bus.peers import Peers
from services.control.arm.model import DEFAULT_MODEL
from services.control.master.config import MasterConfig
from services.control.master.devices.virtual import VirtualMaster
from services.control.master.service import MasterService
from services.tools.cell.sim import READY_TIMEOUT_S, NodeFactory, SimCell, light_cell
from services.tools.tasks.metrics import RunRecorder, TaskReport
from services.tools.tasks.operator import (
    READY,
    Abort,
    DeviceLink,
    Observer,
    Operator,
    OperatorConfig,
    TaskFailed,
)
from services.tools.tasks.scenarios import SCENARIOS
from services.world.workcell.config import WorkcellConfig
from services.world.workcell.service import WorkcellService

log = logging.getLogger("telerobot.tasks")

MASTER_ID = "operator"


class Station:
    """The operator's station: a master service on a virtual device, the person and their
    eyes. The person moves the device's hand (in-process) and turns the station's knobs
    through the master's methods."""

    def __init__(
        self,
        make_node: NodeFactory,
        operator: OperatorConfig | None = None,
        master_id: str = MASTER_ID,
        master: MasterConfig | None = None,
        abort: Abort | None = None,
    ) -> None:
        self._closers: list[Callable[[], None]] = []
        cfg = master or MasterConfig(master_id=master_id, device="virtual", engage_on_start=False)
        try:
            self.device = VirtualMaster()
            self.master = MasterService(make_node("master", cfg.master_id), cfg, self.device)
            self._closers.append(self.master.close)
            self.node = make_node("tasks", None)
            self.eyes = Observer(self.node, cfg.master_id)
            self.recorder = RunRecorder(self.node)
            op_cfg = operator or OperatorConfig()
            if op_cfg.alignment != cfg.alignment:
                op_cfg = replace(op_cfg, alignment=cfg.alignment)
            link = DeviceLink(self.device, self.node, cfg.master_id)
            self.operator = Operator(link, self.eyes, op_cfg, abort)
        except BaseException:
            self.close()
            raise

    def close(self) -> None:
        for close in reversed(self._closers):
            close()
        self._closers.clear()


def run_task(task: int, station: Station, timeout_s: float = READY_TIMEOUT_S) -> TaskReport:
    """Reset the workcell, run scenario `task` with the station's operator, measure.

    Waits (within `timeout_s`) for a ready arm and for the workcell's state first. A run that
    fails (`TaskFailed`, an RPC error) is reported with `success` false and its `error`;
    the operator then lets go (the master-shift pressed), so the arm holds.
    """
    scenario = SCENARIOS[task]
    eyes, node = station.eyes, station.node
    if eyes.robot.wait(lambda s: s.status in READY, timeout_s) is None:
        last = eyes.robot.latest
        said = (
            "no robot/state arrived"
            if last is None
            else f"its last robot/state says {last.status!r}, seq {last.seq}"
        )
        if last is not None and last.status == "error":
            try:  # what the arm says of its error: the reason the operator has to act on
                why = node.call("arm", "status", {}, timeout_s=2.0).get("arm_error")
            except (RpcError, Unavailable):
                why = None
            if isinstance(why, str) and why:
                said += f" ({why[:200]})"
        raise TaskFailed(f"the arm is not ready within {timeout_s:g} s: {said}")
    try:
        node.call("workcell", "reset", {}, timeout_s)
    except (RpcError, Unavailable) as e:
        raise TaskFailed(f"the workcell simulation does not answer: {e}") from None
    after = time.time_ns()
    if eyes.scene.wait(lambda w: w.t_ns > after and w.held == "", timeout_s) is None:
        raise TaskFailed("no workcell/state after the reset")
    recorder = station.recorder
    op = station.operator
    recorder.start()
    error: str | None = None
    try:
        outcome = scenario.run(op)
    except (TaskFailed, RpcError, Unavailable) as e:
        error = str(e)
        outcome = None
        log.warning("task %d failed: %s", task, e)
        with contextlib.suppress(TaskFailed):
            op.press_clutch()
    elapsed = recorder.elapsed_s()
    force_n, torque_nm, interventions, events = recorder.finish()
    ws = eyes.scene.latest
    return TaskReport(
        task=task,
        name=scenario.name,
        success=outcome is not None and outcome.success,
        time_s=elapsed,
        measures=outcome.measures if outcome is not None else {},
        checks=outcome.checks if outcome is not None else {},
        force_peak_n=force_n,
        torque_peak_nm=torque_nm,
        interventions=interventions,
        events=events,
        operator={k: v for k, v in asdict(op.stats).items() if isinstance(v, int)},
        workcell=dict(ws.data or {}) if ws is not None else {},
        error=error,
        log=list(op.stats.log),
    )


def run_headless(
    task: int,
    operator: OperatorConfig | None = None,
    abort: Abort | None = None,
    model: str = DEFAULT_MODEL,
) -> TaskReport:
    """Task `task` on a private in-process network: SimCell (light settings, arm `model`)
    + Station."""
    net = Peers()
    cell: SimCell | None = None
    station: Station | None = None
    try:
        cell = light_cell(net.node, model)
        cell.start()
        station = Station(net.node, operator, abort=abort)
        return run_task(task, station)
    finally:
        if station is not None:
            station.close()
        if cell is not None:
            cell.close()
        net.close()


class Connected:
    """The task side of a running system (e.g. `telerobot up sim`): nodes that join it with
    `node_config`, a workcell service unless one is already alive, and a Station.
    Use as a context manager."""

    def __init__(
        self,
        node_config: NodeConfig,
        operator: OperatorConfig | None = None,
        abort: Abort | None = None,
        workcell_wait_s: float = 1.0,
    ) -> None:
        self.node_config = node_config
        self.nodes: list[Node] = []
        self.workcell: WorkcellService | None = None
        self.station: Station | None = None
        try:
            self.station = Station(self._node, operator, abort=abort)
            if not self.station.node.alive.wait("workcell", workcell_wait_s):
                self.workcell = WorkcellService(self._node("workcell", None), WorkcellConfig())
        except BaseException:
            self.close()
            raise

    def _node(self, name: str, instance: str | None) -> Node:
        n = Node(name, self.node_config, instance=instance)
        self.nodes.append(n)
        return n

    def run(self, task: int) -> TaskReport:
        assert self.station is not None
        return run_task(task, self.station)

    def __enter__(self) -> Connected:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def close(self) -> None:
        if self.station is not None:
            self.station.close()
            self.station = None
        if self.workcell is not None:
            self.workcell.close()
            self.workcell = None
        for n in reversed(self.nodes):
            n.close()
        self.nodes.clear()
