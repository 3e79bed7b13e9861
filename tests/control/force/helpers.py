"""Helpers for the force tests: recording callbacks, rotations."""

from __future__ import annotations

import threading
from collections.abc import Callable
from typing import Any

import numpy as np
from numpy.typing import NDArray

from services.control.force.sensors import ForceSensor, Reading
from services.geometry import R_from_wxyz, rot_x, rot_y, rot_z
from tests.conftest import wait_until

DEADLINE_S = 10.0


def drain_until(
    sensor: ForceSensor, cond: Callable[[], object], timeout_s: float = DEADLINE_S
) -> Reading | None:
    """Read continuously (as the sampler would) until cond() holds; the last reading."""
    last: list[Reading | None] = [None]

    def step() -> bool:
        r = sensor.read()
        if r is not None:
            last[0] = r
        return bool(cond())

    assert wait_until(step, timeout_s, what="the sensor's condition")
    return last[0]


class Events:
    """An EventSink that records (kind, message, data), safe from any thread."""

    def __init__(self) -> None:
        self._lock = threading.Lock()
        self.items: list[tuple[str, str, dict[str, Any]]] = []

    def __call__(self, kind: str, message: str, data: dict[str, Any]) -> None:
        with self._lock:
            self.items.append((kind, message, data))

    def kinds(self) -> list[str]:
        with self._lock:
            return [k for k, _, _ in self.items]

    def of(self, kind: str) -> list[tuple[str, str, dict[str, Any]]]:
        with self._lock:
            return [e for e in self.items if e[0] == kind]


def rot(axis: str, angle: float) -> NDArray[np.float64]:
    """Elementary rotation about x, y or z (rad)."""
    return {"x": rot_x, "y": rot_y}.get(axis, rot_z)(angle)


def quat_to_R(q: tuple[float, float, float, float]) -> NDArray[np.float64]:
    """A rotation from any non-zero quaternion (w, x, y, z)."""
    return R_from_wxyz(q)
