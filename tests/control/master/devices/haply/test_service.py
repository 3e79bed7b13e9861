"""The master station with `--device haply` against the fake Inverse Service, over Zenoh:
what reaches robot/cmd (eq. 5 through the dead-man), what reaches the Inverse3 (forces), and
what a dropped WebSocket does (hold, reconnect, engage afresh)."""

from __future__ import annotations

import math
import subprocess
import sys
import threading
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass

import numpy as np
import pytest

from services.bus import keys
from services.bus.messages import Event, ForceSample, OperatorCommand, RobotState
from services.control.master.config import MasterConfig
from services.control.master.devices.haply.backend import HaplyMaster, HaplyOptions
from services.control.master.devices.haply.fake import FakeInverseService, HandPose
from services.control.master.service import MasterService
from services.geometry import rot_z
from services.tools.cell.procs import telerobot_argv
from services.tools.cli.main import main as telerobot
from tests.bus.test_router import spawned
from tests.conftest import Net, free_port, wait_until

pytestmark = pytest.mark.system


ALIGN = rot_z(math.pi / 2)
"""Master x (operator's right) onto slave +y: hand-right moves the tool along +y."""
SCALE_T = 0.5
HOME = (0.0, -0.12, 0.15)


def haply_master(net: Net, fake: FakeInverseService, **config: float) -> MasterService:
    """Master `h1` on the fake's Inverse3: s_t = 0.5, A = Rz(90°)."""
    cfg = MasterConfig(
        master_id="h1",
        device="haply",
        options=HaplyOptions(haply_url=fake.url),
        scale_t=SCALE_T,
        alignment=tuple(ALIGN.reshape(9)),
        **config,  # type: ignore[arg-type]
    )
    return MasterService(net.node("master", instance="h1"), cfg)


@dataclass
class Station:
    fake: FakeInverseService
    master: MasterService
    commands: list[OperatorCommand]
    events: list[Event]
    node_lock: threading.Lock

    def cmds(self) -> list[OperatorCommand]:
        with self.node_lock:
            return list(self.commands)

    def evs(self) -> list[Event]:
        with self.node_lock:
            return list(self.events)

    def last(self) -> OperatorCommand | None:
        cmds = self.cmds()
        return cmds[-1] if cmds else None

    def engaged(self) -> bool:
        last = self.last()
        return last is not None and last.active


@pytest.fixture
def station(net: Net) -> Iterator[Station]:
    with FakeInverseService(pose=HandPose(cursor_m=HOME)) as fake:
        observer = net.node("observer")
        lock = threading.Lock()
        commands: list[OperatorCommand] = []
        events: list[Event] = []

        def keep(store: list) -> Callable[[object], None]:
            def on_message(msg: object) -> None:
                with lock:
                    store.append(msg)

            return on_message

        observer.subscribe(keys.CMD, keep(commands))
        observer.subscribe(keys.EVENTS, keep(events))
        master = haply_master(net, fake, force_ramp_s=0.2)
        try:
            yield Station(fake, master, commands, events, lock)
        finally:
            master.close()


def slide_x(distance_m: float, duration_s: float, a: bool = True) -> Callable[[float], HandPose]:
    """The cursor slides from HOME along +x at constant speed, then stays."""

    def motion(t_s: float) -> HandPose:
        x = distance_m * min(t_s / duration_s, 1.0)
        return HandPose((HOME[0] + x, HOME[1], HOME[2]), a=a)

    return motion


def engage(s: Station) -> int:
    """Release `a` (until the master has read it), then press and hold it; the engagement
    number the master started."""
    s.fake.set_pose(a=False)
    seen = s.fake.messages
    assert wait_until(lambda: s.fake.messages > seen + 2)
    s.fake.set_pose(a=True)
    assert wait_until(s.engaged), "holding a never engaged"
    last = s.last()
    assert last is not None
    return last.engage


def test_holding_a_moves_the_tool_by_the_scaled_aligned_motion_and_releasing_holds(
    station: Station,
) -> None:
    s = station
    assert wait_until(lambda: len(s.cmds()) > 5)
    assert not any(c.active for c in s.cmds()), "engaged before the dead-man was held"
    k = engage(s)
    first = next(c for c in s.cmds() if c.engage == k)
    assert first.active and first.dp == (0.0, 0.0, 0.0)

    s.fake.set_motion(slide_x(0.04, 0.5))
    want = SCALE_T * ALIGN @ np.array([0.04, 0.0, 0.0])  # 2 cm along the tool's +y
    if not wait_until(lambda: np.allclose(s.last().dp, want, atol=1e-9)):  # type: ignore[union-attr]
        tail = [(c.engage, c.active, c.dp) for c in s.cmds()[-5:]]
        engages = sorted({c.engage for c in s.cmds()})
        pytest.fail(
            f"dp never reached {want}: last {tail}; engagements {engages}; "
            f"events {[(e.kind, e.message[:120]) for e in s.evs()[-8:]]}; "
            f"device {getattr(s.master.device, 'stats', None)}"
        )
    moving = [np.array(c.dp) for c in s.cmds() if c.engage == k and c.active]
    assert all(abs(dp[0]) < 1e-12 and abs(dp[2]) < 1e-12 for dp in moving)
    assert all(0.0 <= dp[1] <= want[1] + 1e-12 for dp in moving)

    # Release a, then slide the cursor 4 cm back: the slave must not move.
    s.fake.set_motion(None)
    s.fake.set_pose(a=False, cursor_m=(HOME[0] + 0.04, HOME[1], HOME[2]))
    assert wait_until(lambda: not s.engaged())
    n = len(s.cmds())
    s.fake.set_motion(slide_x(-0.04, 0.3, a=False))
    assert wait_until(lambda: s.master.teleop.state().hand_p[0] == pytest.approx(HOME[0] - 0.04))
    after = s.cmds()[n:]
    assert len(after) > 10 and not any(c.active for c in after)
    assert all(np.allclose(c.dp, want) for c in after)  # the last values, never a jump back


@dataclass
class ForceSource:
    """Publishes a constant tool force and a robot state with tool_R = I, like the force
    and arm services would, until stopped."""

    net: Net
    force_n: tuple[float, float, float]

    def __post_init__(self) -> None:
        self._stop = threading.Event()
        node = self.net.node("force-source")
        self._force = node.publisher(keys.FORCE)
        self._state = node.publisher(keys.STATE)
        self._thread = threading.Thread(target=self._run, daemon=True)
        self._thread.start()

    def _run(self) -> None:
        eye = (1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0)
        seq = 0
        deadline = time.monotonic() + 60.0  # bounded, whatever happens to the test
        while not self._stop.wait(0.005) and time.monotonic() < deadline:
            seq += 1
            t_ns = time.time_ns()
            self._force.put(ForceSample(seq, t_ns, self.force_n, (0.0, 0.0, 0.0)))
            self._state.put(
                RobotState(
                    seq, t_ns, "ready", (0.0,) * 6, (0.5, 0.0, 0.5), eye, (0.5, 0.0, 0.7), eye, 0, 0
                )
            )

    def stop(self) -> None:
        self._stop.set()
        self._thread.join(timeout=2.0)


def test_forces_arrive_every_tick_finite_clipped_ramped_and_zero_when_released(
    station: Station, net: Net
) -> None:
    s = station
    source = ForceSource(net, (0.0, 20.0, 0.0))  # 20 N along the tool's +y
    try:
        assert wait_until(lambda: s.master._stale is False)
        assert wait_until(lambda: s.fake.forces_received > 20)
        assert all(r.force_n == (0.0, 0.0, 0.0) for r in s.fake.forces)  # not engaged yet

        n0 = s.fake.forces_received
        engage(s)
        # Aᵀ maps the slave's +y back onto the operator's +x; 20 N is cut to 3 N.
        assert wait_until(lambda: s.fake.forces[-1].force_n == pytest.approx((3.0, 0.0, 0.0)))
        mags = [math.hypot(*r.force_n) for r in s.fake.forces_since(n0)]
        assert all(math.isfinite(m) and m <= 3.0 + 1e-9 for m in mags)
        ramp = [m for m in mags if 0.0 < m < 3.0 - 1e-9]
        assert len(ramp) >= 3, "no ramp-in"
        assert ramp == sorted(ramp)

        # One force message per command tick — the force rate is the master's rate — but
        # for the ticks a loaded machine left two messages unanswered (counted, skipped).
        def counts() -> tuple[int, int, int]:
            stats = s.master._status()["device_stats"]
            return s.master.ticks, stats["forces_sent"], stats["skipped"]

        ticks0, sent0, skipped0 = counts()
        assert wait_until(lambda: s.master.ticks >= ticks0 + 100, timeout_s=30.0)
        ticks1, sent1, skipped1 = counts()
        assert abs((sent1 - sent0) + (skipped1 - skipped0) - (ticks1 - ticks0)) <= 2
        assert wait_until(lambda: s.fake.forces_received >= sent1)

        s.fake.set_pose(a=False)
        assert wait_until(lambda: s.fake.forces[-1].force_n == (0.0, 0.0, 0.0))
        m = s.fake.forces_received
        assert wait_until(lambda: s.fake.forces_received >= m + 20)
        assert all(r.force_n == (0.0, 0.0, 0.0) for r in s.fake.forces_since(m))
        assert all(math.hypot(*r.force_n) <= 3.0 + 1e-9 for r in s.fake.forces)
    finally:
        source.stop()


def test_a_dropped_connection_holds_reconnects_and_engages_again_without_a_jump(
    station: Station,
) -> None:
    s = station
    k = engage(s)
    s.fake.set_motion(slide_x(0.02, 0.3))
    assert wait_until(lambda: s.last().dp[1] == pytest.approx(0.01))  # type: ignore[union-attr]
    n = len(s.cmds())

    s.fake.drop()
    assert wait_until(lambda: any(not c.active for c in s.cmds()[n:]))
    assert wait_until(lambda: any("lost" in e.message for e in s.evs() if e.kind == "error"))
    held = [c for c in s.cmds()[n:] if not c.active]
    assert held[0].engage == k and held[0].dp[1] == pytest.approx(0.01)  # the slave holds

    # Back within 5 s by itself; the operator, still holding a, is not re-engaged.
    assert wait_until(lambda: s.fake.connections == 2, timeout_s=5.0)
    assert wait_until(lambda: any("back" in e.message for e in s.evs()))
    m = len(s.cmds())
    assert wait_until(lambda: len(s.cmds()) > m + 20)
    assert not any(c.active for c in s.cmds()[m:])

    # Release and press again: a new engagement from where the hand is now, dp = 0.
    s.fake.set_motion(None)
    s.fake.set_pose(a=False, cursor_m=(HOME[0] + 0.05, HOME[1], HOME[2]))
    seen = s.fake.messages
    assert wait_until(lambda: s.fake.messages > seen + 2)  # the master read the release
    m = len(s.cmds())
    s.fake.set_pose(a=True)
    assert wait_until(lambda: any(c.active for c in s.cmds()[m:]))
    again = next(c for c in s.cmds()[m:] if c.active)
    assert again.engage > k and again.dp == (0.0, 0.0, 0.0)
    assert s.master._status()["reopens"] == 1


def test_a_service_that_stays_down_is_retried_with_back_off_and_the_master_stays_up(
    station: Station,
) -> None:
    s = station
    s.fake.set_down(True)
    assert wait_until(lambda: s.fake.refused >= 3, timeout_s=10.0)
    n = len(s.cmds())
    assert wait_until(lambda: len(s.cmds()) > n + 20)  # still commanding: holding
    assert not any(c.active for c in s.cmds()[n:])
    s.fake.set_down(False)
    assert wait_until(lambda: s.master._status()["device_ok"], timeout_s=5.0)
    assert engage(s) > 0


def test_hostile_frames_are_counted_reported_and_move_nothing(station: Station) -> None:
    s = station
    engage(s)
    dp = s.last().dp  # type: ignore[union-attr]
    s.fake.inject(
        '{"inverse3": [{"device_id": "049D", "state": {"cursor_position": '
        '{"x": 1e308, "y": 0, "z": 0}}}]}',
        "NaN",
        "{",
        "[" * 5000,
    )
    assert wait_until(lambda: any(e.kind == "rejected" and "device" in e.message for e in s.evs()))
    assert wait_until(lambda: s.master._status()["device_stats"]["rejected"] >= 4)
    assert all(c.dp == dp for c in s.cmds() if c.active)


def test_a_bad_haply_url_fails_at_start_up_naming_the_key(
    capsys: pytest.CaptureFixture[str],
) -> None:
    assert telerobot(["master", "--device", "haply", "--haply-url", "http://localhost:1"]) == 2
    assert "master.haply_url" in capsys.readouterr().err


def test_no_inverse_service_at_start_up_exits_with_a_clear_message() -> None:
    port, zport = free_port(), free_port()
    proc = subprocess.run(
        [
            sys.executable,
            "-m",
            "services.tools.cli.main",
            "master",
            "--device",
            "haply",
            "--haply-url",
            f"ws://127.0.0.1:{port}",
            "--listen",
            f"tcp/127.0.0.1:{zport}",
        ],
        capture_output=True,
        text=True,
        timeout=60,
    )
    assert proc.returncode == 2
    assert f"no Haply Inverse Service at ws://127.0.0.1:{port}" in proc.stderr


def test_the_fake_runs_by_hand_and_the_backend_drives_it() -> None:
    port = free_port()
    with spawned(telerobot_argv("haply-fake", "--port", str(port)), merge_stderr=False) as fake:
        assert f"ws://127.0.0.1:{port}" in fake.expect(lambda _: True)
        device = HaplyMaster(f"ws://127.0.0.1:{port}")
        device.open()
        try:  # the scripted operator holds a for most of its cycle
            assert wait_until(lambda: not device.read(0.01).clutch, timeout_s=10.0)
        finally:
            device.close()
        fake.proc.terminate()
        assert fake.wait(10.0) == 0
