"""Shared fixtures of the master station's tests."""

from __future__ import annotations

import time
from collections.abc import Callable

import pytest

Waiter = Callable[..., bool]


def _wait_until(condition: Callable[[], bool], timeout_s: float = 3.0) -> bool:
    """Poll `condition` until it holds or the deadline passes; its final value."""
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        if condition():
            return True
        time.sleep(0.002)
    return condition()


@pytest.fixture
def wait_until() -> Waiter:
    """wait_until(condition, timeout_s=3.0) -> bool: wait on a condition with a deadline."""
    return _wait_until
