"""Nobody watching, no work: the console without a browser sleeps and subscribes to no video
(so vision renders nothing), wakes for a browser, and takes robot/force downsampled by
Zenoh itself. A browser here is `support.FakeBrowser`, a websocket client as viser counts them."""

from __future__ import annotations

import time
from collections.abc import Iterator
from dataclasses import dataclass
from typing import Any

import numpy as np
import pytest

from services.bus import keys
from services.bus.config import NodeConfig
from services.bus.messages import ForceSample, VisionStats
from services.bus.node import Node, Subscription
from services.bus.rate import RateLoop
from services.control.master.config import MasterConfig
from services.control.master.service import MasterService
from services.control.vision.config import VisionConfig
from services.control.vision.service import VisionService
from services.frontends.console.__main__ import console_node_config, master_node_config
from services.frontends.console.app import Console
from services.frontends.console.config import ConsoleConfig
from services.frontends.console.mirror import BusMirror
from services.world.workcell.messages import WORKCELL_STATE

from .support import FakeBrowser, ready_state, wait_until

pytestmark = [pytest.mark.system, pytest.mark.timeout(120)]

TOOL_P = (0.5, 0.1, 0.6)


@dataclass
class Cell:
    console: Console
    vision: VisionService
    stats: Subscription[VisionStats]

    def captured(self) -> int:
        return int(self.vision.pipeline.stats()["captured"])

    def idle_waits(self) -> int:
        return int(self.vision.pipeline.stats()["idle_waits"])

    def two_stats_periods(self) -> None:
        """A clock that is not a sleep: two more vision/stats messages (1 Hz)."""
        n = self.stats.received
        assert self.stats.wait_count(n + 2, 10.0), "vision/stats stopped flowing"


@pytest.fixture
def cell(net: Any) -> Iterator[Cell]:
    closers: list[Any] = []
    try:
        watcher = net.node("watcher")
        stats = watcher.subscribe(keys.VISION_STATS)
        vision = VisionService(net.node("vision"), VisionConfig(width=160, height=120, fps=20.0))
        closers.append(vision)
        console = Console(net.node("console"), ConsoleConfig(port=0, shadows=False))
        closers.append(console)
        yield Cell(console, vision, stats)
    finally:
        for c in reversed(closers):
            c.close()


def test_without_a_browser_the_console_sleeps_and_vision_renders_nothing(cell: Cell) -> None:
    console = cell.console
    assert wait_until(lambda: cell.idle_waits() == 1), "vision never went to sleep"
    cell.two_stats_periods()
    assert console.viewers == 0 and console.ticks == 0, "the GUI thread ran for nobody"
    assert console.mirror.watching == (False, False)
    assert cell.captured() == 0, "vision rendered for nobody"

    # A browser: the page streams are subscribed, vision wakes, frames reach the page.
    with FakeBrowser(console.port) as browser:
        assert wait_until(lambda: console.viewers == 1)
        assert wait_until(lambda: console.mirror.watching == (True, True))
        assert wait_until(lambda: console.frames_shown >= 3, 20.0), "no video on the page"
        assert cell.captured() > 0 and browser.received > 0

    # It leaves: everything stops again, and stays stopped.
    assert wait_until(lambda: console.viewers == 0)
    assert wait_until(lambda: console.mirror.watching == (False, False))
    assert wait_until(lambda: cell.idle_waits() == 2), "vision kept rendering"
    ticks, captured, shown = console.ticks, cell.captured(), console.frames_shown
    cell.two_stats_periods()
    assert (console.ticks, cell.captured(), console.frames_shown) == (ticks, captured, shown)

    # Another browser: live again at once.
    with FakeBrowser(console.port):
        assert wait_until(lambda: console.frames_shown > shown, 20.0)
    assert console.gui_errors == 0


def test_video_off_drops_the_subscription_and_vision_sleeps(cell: Cell) -> None:
    console = cell.console
    with FakeBrowser(console.port):
        assert wait_until(lambda: console.frames_shown >= 1, 20.0)
        console._set_view("off")
        assert wait_until(lambda: console.mirror.watching == (True, False))
        assert wait_until(lambda: cell.vision.pipeline.stats()["idle"]), "vision kept rendering"
        ticks = console.ticks
        assert wait_until(lambda: console.ticks > ticks), "the page itself stays live"
        console._set_view("left")
        shown = console.frames_shown
        assert wait_until(lambda: console.frames_shown > shown, 20.0)


def test_the_last_browser_leaving_clutches_an_engaged_hand(net: Any) -> None:
    """An engagement does not outlive its operator: the hand is clutched when the page
    closes, and parked on the tool (not engaged) when a page comes back."""
    closers: list[Any] = []
    try:
        arm = net.node("arm")
        closers.append(
            MasterService(
                net.node("master", instance="console"),
                MasterConfig(master_id="console", device="virtual", engage_on_start=False),
            )
        )
        console = Console(net.node("console"), ConsoleConfig(port=0, shadows=False))
        closers.append(console)
        arm.publisher(keys.STATE).put(ready_state(1, TOOL_P))
        assert console.mirror.state.wait_for(lambda s: True, 10.0) is not None
        hand = console.hand
        with FakeBrowser(console.port):
            assert hand.wait(lambda h: h.state == "parked", 10.0), (hand.state, hand.error)
            hand.set_gizmo(np.array(TOOL_P) + np.array([0.0, 0.0, 0.02]), np.eye(3))
            assert hand.wait(lambda h: h.state == "engaged", 10.0), (hand.state, hand.error)
            assert console.mirror.wait_master("console", lambda m: m.active, 5.0)
        assert hand.wait(lambda h: h.state == "holding", 10.0), (hand.state, hand.error)
        assert console.mirror.wait_master("console", lambda m: not m.active, 5.0)
        resyncs = hand.resyncs
        with FakeBrowser(console.port):
            assert hand.wait(lambda h: h.state == "parked" and h.resyncs > resyncs, 10.0)
            assert console.mirror.wait_master("console", lambda m: not m.active, 5.0)
    finally:
        for c in reversed(closers):
            c.close()


def _force(seq: int) -> ForceSample:
    return ForceSample(seq=seq, t_ns=time.time_ns(), f=(0.0, 0.0, 1.0), c=(0.0, 0.0, 0.0))


@pytest.mark.parametrize("ns", ["", "cell2"])
def test_the_console_session_takes_robot_force_downsampled_by_zenoh(make_net: Any, ns: str) -> None:
    net = make_net(ns)
    force = net.node("force")  # listens; the others connect to it
    ds_node = Node("console", console_node_config(net.config(), ConsoleConfig(port=0)))
    net.nodes.append(ds_node)
    downsampled = ds_node.subscribe(keys.FORCE)
    plain = net.node("plain").subscribe(keys.FORCE)
    pub = force.publisher(keys.FORCE)

    def routed() -> bool:
        pub.put(_force(1))
        return downsampled.wait_count(1, 0.05) and plain.wait_count(1, 0.05)

    assert wait_until(routed), "no route to the subscribers"
    d0, p0 = downsampled.received, plain.received
    sent = 2000
    rate = RateLoop(1000.0)
    for seq in range(1, sent + 1):
        pub.put(_force(seq))
        rate.sleep()
    # Nearly every sample reaches the plain subscriber (robot/force is best-effort, keys.py:
    # a loaded host may drop one, superseded by the next; Zenoh's downsampling is what cuts
    # the console's)...
    assert plain.wait_count(p0 + int(0.95 * sent), 20.0), plain.received - p0
    got = downsampled.received - d0
    # ...and only a fraction reaches the console's, whatever the machine's load made of
    # the publisher's rate: Zenoh dropped the rest before any Python ran.
    assert 5 <= got <= sent // 4, got


def test_session_configs_carry_the_downsampling_rules() -> None:
    base = NodeConfig(connect=("tcp/127.0.0.1:7447",), downsampling=(("x/y", 5.0),))
    cfg = console_node_config(base, ConsoleConfig(gui_rate_hz=20.0, force_rate_hz=50.0))
    assert cfg.downsampling == (
        ("x/y", 5.0),
        (keys.FORCE.key, 50.0),
        (keys.STATE.key, 40.0),
        (keys.ARM_TARGET.key, 40.0),
        (WORKCELL_STATE.key, 40.0),
        (keys.PASSIVITY_MASTER.key, 40.0),
        (keys.PASSIVITY_SLAVE.key, 40.0),
    )
    m = master_node_config(base, 100.0)
    assert m.downsampling == (("x/y", 5.0), (keys.FORCE.key, 100.0), (keys.STATE.key, 100.0))
    assert master_node_config(base).downsampling == base.downsampling


@pytest.mark.parametrize("rule", [("", 10.0), ("/a", 10.0), ("a", 0.0), ("a", float("nan"))])
def test_bad_downsampling_rules_are_config_errors(rule: tuple[str, float]) -> None:
    from services.bus.errors import ConfigError

    with pytest.raises(ConfigError) as err:
        NodeConfig(downsampling=(rule,))
    assert err.value.key == "zenoh.downsampling"


def test_a_mirror_without_a_page_decodes_no_force(net: Any) -> None:
    """BusMirror alone (as the hand link's tests use it) subscribes to the force only while
    a page is watched."""
    force = net.node("force")
    mirror = BusMirror(net.node("console"), events=5, force_capacity=100)
    pub = force.publisher(keys.FORCE)
    mirror.watch_page(True)
    assert mirror.watching == (True, False)

    def seen() -> bool:
        pub.put(_force(1))
        return mirror.latest_force() is not None

    assert wait_until(seen, poll_s=0.02)
    assert len(mirror.force) >= 1
    mirror.watch_page(False)
    assert mirror.latest_force() is None and mirror.watching == (False, False)


def test_a_bad_video_frame_is_rejected_when_it_would_be_shown(net: Any) -> None:
    vision = net.node("vision")
    node = net.node("console")
    mirror = BusMirror(node, events=5, force_capacity=100)
    mirror.watch_video(True)
    pub = vision.publisher(keys.STEREO_L)

    def arrived() -> bool:
        pub.put_bytes(b"\xc1")  # not msgpack
        return mirror.frame_counts()[0] > 0

    assert wait_until(arrived, poll_s=0.02)
    assert node.rejected.get(keys.STEREO_L.key, 0) == 0, "decoded before it was needed"
    assert mirror.frame("l") is None and mirror.frame("r") is None
    assert node.rejected[keys.STEREO_L.key] == 1
    mirror.watch_video(False)
    assert mirror.watching == (False, False) and mirror.frame("l") is None
