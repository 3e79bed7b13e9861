"""Helpers for the force tests: recording callbacks, rotations."""

from __future__ import annotations

import threading
from collections.abc import Callable
from typing import Any

import numpy as np
from numpy.typing import NDArray

from services.force.sensors import ForceSensor, Reading
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
    c, s = np.cos(angle), np.sin(angle)
    if axis == "x":
        return np.array([[1, 0, 0], [0, c, -s], [0, s, c]])
    if axis == "y":
        return np.array([[c, 0, s], [0, 1, 0], [-s, 0, c]])
    return np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]])


def quat_to_R(q: tuple[float, float, float, float]) -> NDArray[np.float64]:
    """A rotation from any non-zero quaternion (w, x, y, z)."""
    w, x, y, z = np.asarray(q, dtype=float) / np.linalg.norm(q)
    return np.array(
        [
            [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
            [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
            [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)],
        ]
    )
