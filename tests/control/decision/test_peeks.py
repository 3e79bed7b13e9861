"""Peek: the other services' status kept for the decision's `status`, refreshed behind."""

from __future__ import annotations

import threading
from typing import Any, cast

from services.bus.errors import RpcError, Unavailable
from services.bus.node import Node
from services.control.decision.peeks import Peek
from tests.conftest import wait_until


class FakeNode:
    """`alive.is_alive` and `call`: each call answers {"n": how many calls so far}."""

    def __init__(self) -> None:
        self.alive = self
        self.up = True
        self.n = 0
        self.fail: Exception | None = None
        self.gate = threading.Event()
        self.gate.set()
        self.lock = threading.Lock()

    def is_alive(self, name: str) -> bool:
        return self.up

    def call(self, service: str, method: str, args: dict[str, Any], timeout_s: float) -> Any:
        assert (service, method, args) == ("arm", "status", {})
        self.gate.wait(5.0)
        if self.fail is not None:
            raise self.fail
        with self.lock:
            self.n += 1
            return {"n": self.n}


def peek(node: FakeNode, **kw: float) -> Peek:
    return Peek(cast(Node, node), "arm", "status", 1.0, **kw)


def test_kept_while_young_refreshed_behind_when_older() -> None:
    node = FakeNode()
    p = peek(node, refresh_s=3600.0, max_age_s=3600.0)
    assert p.get() == {"n": 1, "age_ms": 0.0}  # none kept: asked and waited for
    again = p.get()
    assert again["n"] == 1 and again["age_ms"] >= 0.0 and node.n == 1  # kept
    p.refresh_s = 0.0  # everything is old enough to refresh now
    node.gate.clear()  # the refresh hangs: callers still get the kept reply at once
    assert p.get()["n"] == 1
    assert p.get()["n"] == 1  # one refresh under way, not two
    node.gate.set()
    assert wait_until(lambda: p.get()["n"] == 2)
    assert node.n <= 3 and p.calls == node.n


def test_too_old_is_asked_again_and_waited_for() -> None:
    node = FakeNode()
    p = peek(node, refresh_s=0.0, max_age_s=0.0)
    assert [p.get()["n"] for _ in range(3)] == [1, 2, 3]


def test_a_service_not_alive_is_reported_at_once_and_forgotten() -> None:
    node = FakeNode()
    p = peek(node, refresh_s=3600.0, max_age_s=3600.0)
    assert p.get()["n"] == 1
    node.up = False
    assert p.get() == {"error": "unavailable", "message": "the arm service is not running"}
    node.up = True
    assert p.get()["n"] == 2  # nothing kept from before


def test_errors_are_maps_and_nothing_is_kept() -> None:
    node = FakeNode()
    p = peek(node, refresh_s=3600.0, max_age_s=3600.0)
    node.fail = RpcError("not_ready", "calibrating")
    assert p.get() == {"error": "not_ready", "message": "calibrating"}
    node.fail = Unavailable("no reply in 1 s")
    assert p.get() == {"error": "unavailable", "message": "no reply in 1 s"}
    node.fail = None
    assert p.get() == {"n": 1, "age_ms": 0.0}


def test_without_waiting_a_peek_answers_only_from_what_it_keeps() -> None:
    node = FakeNode()
    p = peek(node, refresh_s=3600.0, max_age_s=3600.0)
    assert p.get(wait=False) is None and node.n == 0  # nothing kept: not asked
    assert p.get() == {"n": 1, "age_ms": 0.0}
    assert p.get(wait=False)["n"] == 1  # type: ignore[index]  # kept and young
    p.max_age_s = 0.0
    assert wait_until(lambda: p.get(wait=False) is None)  # too old: it would ask again
    assert node.n == 1
    node.up = False
    assert p.get(wait=False) == {
        "error": "unavailable",
        "message": "the arm service is not running",
    }
