"""One supervisor and one arm per cell: a second instance of a singleton service refuses to
start, naming the one that holds the cell, and the running one reports it (issue 42 item 2).
Another namespace is another cell."""

from __future__ import annotations

import threading

import pytest

from services.bus import keys
from services.bus.errors import AlreadyRunning
from services.bus.lifecycle import CONFIG_EXIT, SINGLETONS
from services.bus.messages import Event
from tests.bus.test_router import spawned, telerobot
from tests.conftest import Net, wait_until

DEADLINE_S = 30.0


def test_the_services_a_cell_runs_once() -> None:
    assert {"arm", "decision", "force", "vision"} <= SINGLETONS


def test_a_claim_is_refused_while_another_holds_the_service_and_the_holder_says_so(
    net: Net,
) -> None:
    holder = net.node("decision")
    holder.claim()
    holder.watch_claims()
    holder.announce()
    seen: list[Event] = []
    lock = threading.Lock()

    def on_event(ev: Event) -> None:
        with lock:
            seen.append(ev)

    net.node("console").subscribe(keys.EVENTS, on_event)
    second = net.node("decision")
    assert wait_until(lambda: second.alive.is_alive("decision"), DEADLINE_S)
    with pytest.raises(AlreadyRunning) as info:
        second.claim()
    assert "decision already runs in this cell" in str(info.value)
    assert "--ns" in str(info.value)

    def reported() -> bool:
        with lock:
            return any(
                e.source == "decision" and (e.data or {}).get("code") == "already_running"
                for e in seen
            )

    assert wait_until(reported, DEADLINE_S), "the running decision never said so"
    # a master is one per id: another id is another master
    net.node("master", instance="m1").announce()
    other = net.node("master", instance="m2")
    other.claim()
    twin = net.node("master", instance="m1")
    assert wait_until(lambda: twin.alive.is_alive("master/m1"), DEADLINE_S)
    with pytest.raises(AlreadyRunning):
        twin.claim()


def test_a_second_decision_process_exits_naming_the_running_one(net: Net) -> None:
    """As a lab meets it: `telerobot up sim` runs, and someone starts a decision by hand."""
    node = net.node("decision")
    node.announce()
    watcher = net.node("watcher")
    assert wait_until(lambda: watcher.alive.is_alive("decision"), DEADLINE_S)
    argv = telerobot("decision", "--connect", net.endpoint, "--mode", "peer")
    with spawned(argv) as child:
        assert child.wait(DEADLINE_S) == CONFIG_EXIT
        line = child.expect("telerobot decision:")
        assert "decision already runs in this cell" in line
    # in another namespace it is another cell: it starts
    with spawned([*argv, "--ns", "cell2"]) as child:
        child.expect(lambda s: "decision up" in s, DEADLINE_S)
