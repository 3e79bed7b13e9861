"""Metrics of a task run: what the run achieved and what it took, from the bus.

`RunRecorder` listens during a run (robot/force, robot/events, workcell/state) and asks the
decision server for its intervention counters before and after. `TaskReport` is one run's
result: success, time, the task's measures (final pose error, blocks stacked, max tilt and
liquid spilled), force peaks, the supervisor's interventions, events by kind, what the
operator did, and the workcell's counters; printed as JSON or as a table.
"""

from __future__ import annotations

import json
import math
import threading
import time
from dataclasses import asdict, dataclass, field
from typing import Any

import numpy as np

from services.bus import keys
from services.bus.errors import RpcError, Unavailable
from services.bus.messages import Event, ForceSample
from services.bus.node import Node
from services.control.decision.notices import INTERVENTIONS

STATUS_TIMEOUT_S = 3.0


@dataclass(frozen=True, slots=True)
class TaskReport:
    """One run of a task (units in the names).

    measures: the task's own figures (see services.tools.tasks.scenarios); checks: each success
    criterion and whether it held; interventions: the decision server's intervention
    counters over the run (watchdog, lease, limit, contact, estop, rejected, busy);
    events: robot/events over the run, by "source:kind" ("source:kind/reason" for an
    intervention that gives one; events are rate-limited, counters are not); operator:
    what the person did;
    workcell: the simulation's counters (grasps, missed, releases, collisions, toppled,
    max_penetration_mm). `error`: why the run stopped early, if it did.
    """

    task: int
    name: str
    success: bool
    time_s: float
    measures: dict[str, Any]
    checks: dict[str, bool]
    force_peak_n: float
    torque_peak_nm: float
    interventions: dict[str, int]
    events: dict[str, int]
    operator: dict[str, int]
    workcell: dict[str, Any]
    error: str | None = None
    log: list[str] = field(default_factory=list)

    def to_dict(self) -> dict[str, Any]:
        return asdict(self)

    def to_json(self, indent: int | None = 2) -> str:
        return json.dumps(self.to_dict(), indent=indent, default=_jsonable)

    def table(self) -> str:
        """A human-readable summary, one figure a line."""
        rows: list[tuple[str, str]] = [
            ("task", f"{self.task}: {self.name}"),
            (
                "result",
                "SUCCESS" if self.success else f"FAILED{': ' + self.error if self.error else ''}",
            ),
            ("time", f"{self.time_s:.1f} s"),
        ]
        rows += [(k, _fmt(v)) for k, v in self.measures.items()]
        rows += [(f"check {k}", "ok" if v else "FAILED") for k, v in self.checks.items()]
        rows += [
            ("force peak", f"{self.force_peak_n:.2f} N"),
            ("torque peak", f"{self.torque_peak_nm:.3f} N·m"),
            (
                "interventions",
                ", ".join(f"{k} {v}" for k, v in self.interventions.items() if v) or "none",
            ),
            ("operator", ", ".join(f"{k} {v}" for k, v in self.operator.items())),
            ("workcell", ", ".join(f"{k} {_fmt(v)}" for k, v in self.workcell.items())),
            ("events", ", ".join(f"{k} {v}" for k, v in sorted(self.events.items())) or "none"),
        ]
        width = max(len(k) for k, _ in rows)
        return "\n".join(f"{k.ljust(width)}  {v}" for k, v in rows)


def _fmt(v: Any) -> str:
    if isinstance(v, float):
        return f"{v:.3g}" if abs(v) < 1e4 else f"{v:.0f}"
    return str(v)


def _jsonable(obj: Any) -> Any:
    if isinstance(obj, np.generic):
        return obj.item()
    if isinstance(obj, np.ndarray):
        return obj.tolist()
    raise TypeError(f"cannot encode {type(obj).__name__}")


class RunRecorder:
    """Listens to a run on `node`: force peaks, events, and the decision's counters.

    Callbacks only fold numbers in (peaks, counts) under a lock. `start()` zeroes them and
    reads the decision's counters; `finish()` reads them again and returns the differences.
    """

    def __init__(self, node: Node) -> None:
        self.node = node
        self._lock = threading.Lock()
        self._recording = False
        self._force_peak = 0.0
        self._torque_peak = 0.0
        self._events: dict[str, int] = {}
        self.event_log: list[Event] = []
        self._t0 = 0.0
        self._counters0: dict[str, int] = {}
        node.subscribe(keys.FORCE, self._on_force)
        node.subscribe(keys.EVENTS, self._on_event)

    def _on_force(self, s: ForceSample) -> None:
        if not self._recording:
            return
        f = math.sqrt(s.f[0] ** 2 + s.f[1] ** 2 + s.f[2] ** 2)
        c = math.sqrt(s.c[0] ** 2 + s.c[1] ** 2 + s.c[2] ** 2)
        with self._lock:
            self._force_peak = max(self._force_peak, f)
            self._torque_peak = max(self._torque_peak, c)

    def _on_event(self, ev: Event) -> None:
        if not self._recording:
            return
        key = f"{ev.source}:{ev.kind}"
        reason = (ev.data or {}).get("reason")
        if ev.kind in INTERVENTIONS and ev.kind != "lease" and isinstance(reason, str):
            key += f"/{reason}"
        with self._lock:
            self._events[key] = self._events.get(key, 0) + 1
            self.event_log.append(ev)

    def decision_counters(self) -> dict[str, int]:
        """The decision server's intervention counters now (empty if it does not answer)."""
        try:
            st = self.node.call("decision", "status", {}, STATUS_TIMEOUT_S)
        except (RpcError, Unavailable):
            return {}
        raw = st.get("interventions", {})
        return {k: int(raw.get(k, 0)) for k in INTERVENTIONS} if isinstance(raw, dict) else {}

    def start(self) -> None:
        self._counters0 = self.decision_counters()
        with self._lock:
            self._force_peak = self._torque_peak = 0.0
            self._events = {}
            self.event_log = []
            self._recording = True
        self._t0 = time.monotonic()

    def elapsed_s(self) -> float:
        return time.monotonic() - self._t0

    def finish(self) -> tuple[float, float, dict[str, int], dict[str, int]]:
        """Stop; (force peak N, torque peak N·m, interventions over the run, events)."""
        with self._lock:
            self._recording = False
            peaks = (self._force_peak, self._torque_peak)
            events = dict(self._events)
        after = self.decision_counters()
        interventions = {k: after.get(k, 0) - self._counters0.get(k, 0) for k in INTERVENTIONS}
        return peaks[0], peaks[1], interventions, events
