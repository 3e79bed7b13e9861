"""The page shows a latched e-stop (#23 item 9): the E-STOP button says so, Reset is offered
only then and calls the decision server's `reset`, "ready" is not green meanwhile; and a
loading indicator lists what the page still waits for until it has arrived. Checked through
what a browser receives (`FakeBrowser(decode=True)`), against a stand-in decision server."""

from __future__ import annotations

import threading
from collections.abc import Iterator
from dataclasses import dataclass
from typing import Any

import pytest

from services.bus import keys
from services.bus.node import Node
from services.frontends.console.app import Console
from services.frontends.console.config import ConsoleConfig

from .support import FakeBrowser, gui_uuid, ready_state, wait_until

pytestmark = [pytest.mark.system, pytest.mark.timeout(120)]


class Decision:
    """The decision server's `status` and `reset`, as far as the page uses them."""

    def __init__(self, node: Node) -> None:
        self.latched = False
        self.resets = 0
        self._lock = threading.Lock()
        node.serve("decision", {"status": self.status, "reset": self.reset})
        node.announce()

    def status(self, args: dict[str, Any]) -> dict[str, Any]:
        with self._lock:
            return {"mode": "estop" if self.latched else "hold", "estop": self.latched}

    def reset(self, args: dict[str, Any]) -> dict[str, Any]:
        with self._lock:
            was, self.latched = self.latched, False
            self.resets += 1
        return {"was_latched": was}


@dataclass
class Page:
    console: Console
    decision: Decision
    robot: Node


@pytest.fixture
def page(net: Any) -> Iterator[Page]:
    console = Console(
        net.node("console"),
        ConsoleConfig(port=0, shadows=False, gui_rate_hz=20.0, status_period_s=0.1),
    )
    try:
        yield Page(console, Decision(net.node("decision")), net.node("arm"))
    finally:
        console.close()


def test_the_page_shows_the_latch_and_offers_reset(page: Page) -> None:
    console = page.console
    state_pub = page.robot.publisher(keys.STATE)
    with FakeBrowser(console.port, decode=True) as browser:
        estop = gui_uuid(browser, "E-STOP")
        reset = gui_uuid(browser, "Reset e-stop")
        status = gui_uuid(browser, 'id="tr-loading"')
        panel = gui_uuid(browser, 'id="tr-robot-status"')
        assert "waiting for robot state" in browser.gui(status)["content"]

        # Nothing but the decision server and a robot state: the page loads (no force or
        # vision service to wait for) and the indicator goes.
        seq = 0

        def robot_ready() -> bool:
            nonlocal seq
            seq += 1
            state_pub.put(ready_state(seq, (0.55, 0.0, 0.65)))
            return console.loaded

        assert wait_until(robot_ready, 20.0, poll_s=0.05), browser.gui(status)
        assert wait_until(lambda: browser.gui(status).get("visible") is False, 10.0)
        assert wait_until(lambda: browser.gui(reset).get("disabled") is True, 10.0), (
            "Reset offered with no latch"
        )

        page.decision.latched = True
        assert wait_until(lambda: browser.gui(estop).get("label") == "E-STOP — LATCHED", 10.0)
        assert wait_until(lambda: browser.gui(reset).get("disabled") is False, 10.0)
        assert wait_until(
            lambda: 'data-estop="latched"' in str(browser.gui(panel)["content"]), 10.0
        )
        assert 'data-status="ready"' in str(
            browser.gui(panel)["content"]
        ) and "#1a7f37" not in _robot(str(browser.gui(panel)["content"]))

        # Reset, as the button does it: the decision's `reset`, then the page clears.
        console._submit("reset", console._do_reset)
        assert wait_until(lambda: page.decision.resets == 1, 10.0)
        assert wait_until(lambda: console.last_action == "reset: cleared", 10.0)
        assert wait_until(lambda: browser.gui(estop).get("label") == "E-STOP", 10.0)
        assert wait_until(lambda: browser.gui(reset).get("disabled") is True, 10.0)
        assert wait_until(lambda: 'data-estop="clear"' in str(browser.gui(panel)["content"]), 10.0)
        assert console.gui_errors == 0


def _robot(panel: str) -> str:
    """The robot's status element of the panel (its colour says ready); the element must be
    there, or a check that a colour is absent from it would hold for any markup."""
    start = panel.find('id="tr-robot-status"')
    end = panel.find("</b>", start)
    assert start >= 0 and end > start, f"no robot status element in the panel: {panel[:300]}"
    return panel[start:end]
