"""The other services' status as the decision's `status` shows it: kept, refreshed behind.

`status` is the operator's one look at the whole system (the console asks twice a second).
Asking the arm and the force service each time put two round trips, and their handlers,
inside every call (4–7 ms against a 1 ms floor). A `Peek` keeps the last reply of one
nested call: a service that is not alive is reported at once (`unavailable`, from
liveliness); a reply younger than `max_age_s` is returned as it is, with `age_ms`, and one
older than `refresh_s` starts one refresh in the background for the next caller; with
none, or one too old, the call is made and waited for, as before — or, with `wait=False`
(the decision's `status` tried in Zenoh's callback), not made: None. The live parts of
`status` (robot/state, robot/force, the supervisor) never come from here; `stamped` and
`read_sample` turn their newest samples into `status` entries.
"""

from __future__ import annotations

import threading
import time
from dataclasses import fields
from typing import Any

from services.bus.errors import RpcError, Unavailable
from services.bus.messages import ForceSample, RobotState
from services.bus.node import Node

#: a kept reply older than this is refreshed in the background for the next caller
REFRESH_S = 0.1
#: a kept reply older than this is not shown: the call is made and waited for
MAX_AGE_S = 1.0


class Peek:
    """One nested call (`service`.`method` with no arguments), its last reply kept."""

    def __init__(
        self,
        node: Node,
        service: str,
        method: str,
        timeout_s: float,
        refresh_s: float = REFRESH_S,
        max_age_s: float = MAX_AGE_S,
    ) -> None:
        self.node = node
        self.service = service
        self.method = method
        self.timeout_s = timeout_s
        self.refresh_s = refresh_s
        self.max_age_s = max_age_s
        self._lock = threading.Lock()
        self._reply: dict[str, Any] | None = None
        self._at = 0.0
        self._refreshing = False
        self.calls = 0

    def get(self, wait: bool = True) -> dict[str, Any] | None:
        """The reply (with `age_ms` when kept), or an error map: status never fails for it.
        None if the call would have to be made and `wait` is False."""
        if not self.node.alive.is_alive(self.service):
            with self._lock:
                self._reply = None
            return {"error": "unavailable", "message": f"the {self.service} service is not running"}
        now = time.monotonic()
        with self._lock:
            reply, age = self._reply, now - self._at
            stale = reply is None or age > self.max_age_s
            kick = not stale and age > self.refresh_s and not self._refreshing
            if kick:
                self._refreshing = True
        if stale:
            return self._call() if wait else None
        if kick:
            threading.Thread(target=self._refresh, name="decision-peek", daemon=True).start()
        assert reply is not None
        return {**reply, "age_ms": round(age * 1e3, 3)}

    def _call(self) -> dict[str, Any]:
        self.calls += 1
        try:
            reply = self.node.call(self.service, self.method, {}, self.timeout_s)
        except RpcError as e:
            return {"error": e.code, "message": e.message}
        except Unavailable as e:
            return {"error": "unavailable", "message": str(e)}
        with self._lock:
            self._reply, self._at = reply, time.monotonic()
        return {**reply, "age_ms": 0.0}

    def _refresh(self) -> None:
        try:
            self._call()
        finally:
            with self._lock:
                self._refreshing = False


def read_sample(got: dict[str, Any]) -> dict[str, Any] | None:
    """A `sensor_read` reply as status's `force` entry (age from its `t_ns`), or None."""
    if "error" in got or not isinstance(got.get("t_ns"), int):
        return None
    return {**got, "age_ms": max(time.time_ns() - got["t_ns"], 0) / 1e6, "via": "sensor_read"}


def stamped(
    item: tuple[RobotState, int] | tuple[ForceSample, int] | None, now_ns: int
) -> dict[str, Any] | None:
    if item is None:
        return None
    msg, rx_ns = item
    # Decoded by the codec: finite numbers, flat tuples, no bytes (jsonable's cases).
    names = _STATE_FIELDS if isinstance(msg, RobotState) else _FORCE_FIELDS
    out: dict[str, Any] = {
        name: list(v) if isinstance(v, tuple) else v
        for name in names
        for v in (getattr(msg, name),)
    }
    out["age_ms"] = (now_ns - rx_ns) / 1e6
    return out


_STATE_FIELDS = tuple(f.name for f in fields(RobotState))
_FORCE_FIELDS = tuple(f.name for f in fields(ForceSample))
