"""The embedded router relaying between client sessions in separate processes.

Every process is spawned with subprocess (never forked: ZENOH_NOTES.md pitfall 3), its
output read line by line by a thread, and every wait is on a line with a deadline. Children
are always terminated in `finally`.
"""

from __future__ import annotations

import re
import signal
import subprocess
import sys
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from pathlib import Path

import pytest

from services.bus import codec, keys
from services.bus.config import NodeConfig
from services.bus.errors import ConnectFailed
from services.bus.messages import ForceSample
from services.bus.node import Node
from services.tools.cell.procs import Child
from services.tools.cell.procs import telerobot_argv as telerobot
from tests.bus.test_node import wait_matched
from tests.conftest import free_port, lossless

REPO = Path(__file__).resolve().parents[2]
DEADLINE_S = 20.0


class ChildProcess(Child):
    """The cell layer's `Child`, started at once the way these tests spawn: from the
    repository with it on PYTHONPATH, standard input closed, in our process group (signals
    to its pid), its lines read by a thread (standard error among them, or apart in
    `errors`) and awaited with `DEADLINE_S` unless told."""

    proc: subprocess.Popen[bytes]  # started in __init__

    def __init__(self, argv: list[str], merge_stderr: bool = True) -> None:
        super().__init__(
            Path(argv[0]).name,
            argv,
            lines=True,
            errors_apart=not merge_stderr,
            cwd=REPO,
            env={"PYTHONPATH": str(REPO)},
            stdin=subprocess.DEVNULL,
            own_group=False,
        )
        self.start()

    def expect(self, pred: Callable[[str], bool] | str, timeout_s: float = DEADLINE_S) -> str:
        return super().expect(pred, timeout_s)

    def rest(self, timeout_s: float = DEADLINE_S) -> list[str]:
        return super().rest(timeout_s)

    def wait(self, timeout_s: float = DEADLINE_S) -> int:
        return self.proc.wait(timeout=timeout_s)


@contextmanager
def spawned(argv: list[str], merge_stderr: bool = True) -> Iterator[ChildProcess]:
    child = ChildProcess(argv, merge_stderr)
    try:
        yield child
    finally:
        child.stop()


# A client-mode session that counts ForceSamples and prints what it got.
COUNTER = r"""
import sys, threading
from services.bus import keys
from services.bus.config import NodeConfig
from services.bus.node import Node

endpoint, n = sys.argv[1], int(sys.argv[2])
cond, seqs = threading.Condition(), []

def on_event(m):
    with cond:
        seqs.append(m.seq)
        cond.notify_all()

with Node("counter", NodeConfig(mode="client", connect=(endpoint,))) as node:
    node.subscribe(keys.EVENTS, on_event)
    node.announce()
    print("ready", flush=True)
    with cond:
        cond.wait_for(lambda: len(seqs) >= n, timeout=15)
        got = list(seqs)
    print("count", len(got), flush=True)
    print("seqs", ",".join(map(str, got)), flush=True)
"""

# A client-mode session that publishes N events once the counter is there: a reliable key
# (the latest-wins streams are best-effort, keys.py: a starved router may drop some of theirs).
PUBLISHER = r"""
import sys, time
from services.bus import keys
from services.bus.config import NodeConfig
from services.bus.messages import Event
from services.bus.node import Node

endpoint, n = sys.argv[1], int(sys.argv[2])
with Node("force", NodeConfig(mode="client", connect=(endpoint,))) as node:
    pub = node.publisher(keys.EVENTS)
    assert node.alive.wait("counter", 30), "counter never came up"
    deadline = time.monotonic() + 30
    # the router must have told us about the counter's subscriber before the first put
    while not pub._pub.matching_status.matching:
        assert time.monotonic() < deadline, "no matching subscriber"
        time.sleep(0.005)
    for i in range(1, n + 1):
        pub.put(Event(seq=i, t_ns=time.time_ns(), source="force", kind="status", message="n"))
    print("sent", n, flush=True)
    # stay connected until the counter is done, so nothing in flight is cut off
    while node.alive.is_alive("counter") and time.monotonic() < deadline:
        time.sleep(0.01)
"""


def test_a_spawned_child_that_ignores_sigterm_is_killed_on_leaving() -> None:
    stubborn = (
        "import signal, time\n"
        "signal.signal(signal.SIGTERM, signal.SIG_IGN)\n"
        "print('ignoring SIGTERM', flush=True)\n"
        "time.sleep(60)\n"
    )
    with spawned([sys.executable, "-c", stubborn]) as child:
        child.expect("ignoring SIGTERM")
        child.stop_timeout_s = 0.5
    assert child.proc.returncode == -signal.SIGKILL


def test_router_relays_between_client_processes() -> None:
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    n = 300
    with spawned(telerobot("router", "--listen", endpoint)) as router:
        line = router.expect("router up")
        assert endpoint in line
        with (
            spawned([sys.executable, "-c", COUNTER, endpoint, str(n)]) as counter,
            spawned([sys.executable, "-c", PUBLISHER, endpoint, str(n)]) as publisher,
        ):
            counter.expect("ready")
            publisher.expect(f"sent {n}")
            assert counter.expect("count") == f"count {n}"
            seqs = counter.expect("seqs").split(" ", 1)[1]
            assert [int(s) for s in seqs.split(",")] == list(range(1, n + 1))
            assert counter.wait() == 0
            assert publisher.wait() == 0
        router.proc.send_signal(signal.SIGTERM)
        assert router.wait() == 0


def test_a_client_cannot_open_without_its_router() -> None:
    """Client sessions only talk through a router: with none listening, a client cannot open
    (so the relay above really went through the router)."""
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    with pytest.raises(ConnectFailed, match="Unable to connect"):
        Node("force", NodeConfig(mode="client", connect=(endpoint,))).close()


def test_router_honours_a_json5_config_file(tmp_path: Path) -> None:
    port = free_port()
    cfg = tmp_path / "router.json5"
    cfg.write_text(
        "{\n"
        "  // only the file says where to listen\n"
        f'  listen: {{ endpoints: ["tcp/127.0.0.1:{port}"] }},\n'
        "}\n"
    )
    endpoint = f"tcp/127.0.0.1:{port}"
    with spawned(telerobot("router", "--zenoh-config", str(cfg))) as router:
        line = router.expect("router up")
        assert re.search(r"listen=\[\]", line), line  # no listen flag: the file's endpoint
        a = Node("force", NodeConfig(mode="client", connect=(endpoint,)))
        b = Node("watch", NodeConfig(mode="client", connect=(endpoint,)))
        try:
            sub = b.subscribe(keys.FORCE)
            b.announce()
            assert a.alive.wait("watch", DEADLINE_S)
            wait_matched(a.publisher(keys.FORCE))
            put = lossless(a, keys.FORCE)  # the router's forwarding is under test, not loss
            for i in range(1, 21):
                put(codec.encode(ForceSample(seq=i, t_ns=i, f=(0.0,) * 3, c=(0.0,) * 3)))
            assert sub.wait_count(20, DEADLINE_S)
            assert sub.latest is not None and sub.latest.seq == 20
        finally:
            b.close()
            a.close()


def test_router_refuses_a_lease_above_2000_ms() -> None:
    with spawned(telerobot("router", "--listen", "tcp/127.0.0.1:1", "--lease-ms", "5000")) as r:
        assert r.wait() == 2
        assert any("zenoh.lease_ms" in line for line in r.rest())
