"""The embedded router relaying between client sessions in separate processes.

Every process is spawned with subprocess (never forked: ZENOH_NOTES.md pitfall 3), its
output read line by line by a thread, and every wait is on a line with a deadline. Children
are always terminated in `finally`.
"""

from __future__ import annotations

import os
import queue
import re
import signal
import subprocess
import sys
import threading
import time
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from pathlib import Path

import pytest

from services.bus import keys
from services.bus.config import NodeConfig
from services.bus.errors import ConnectFailed
from services.bus.messages import ForceSample
from services.bus.node import Node
from tests.bus.test_node import wait_matched
from tests.conftest import free_port

REPO = Path(__file__).resolve().parents[2]
DEADLINE_S = 20.0


class ChildProcess:
    """A spawned child whose stdout+stderr lines are read by a thread, awaited with deadlines."""

    def __init__(self, argv: list[str], merge_stderr: bool = True) -> None:
        env = {**os.environ, "PYTHONUNBUFFERED": "1", "PYTHONPATH": str(REPO)}
        self.argv = argv
        self.proc = subprocess.Popen(
            argv,
            cwd=REPO,
            env=env,
            stdin=subprocess.DEVNULL,
            stdout=subprocess.PIPE,
            stderr=subprocess.STDOUT if merge_stderr else subprocess.PIPE,
            text=True,
            bufsize=1,
        )
        self.lines: list[str] = []
        #: stderr lines when not merged into stdout (diagnostics for failed assertions)
        self.errors: list[str] = []
        self._queue: queue.Queue[str | None] = queue.Queue()
        self._readers = [threading.Thread(target=self._read, daemon=True)]
        if not merge_stderr:
            self._readers.append(threading.Thread(target=self._read_errors, daemon=True))
        for t in self._readers:
            t.start()

    def _read(self) -> None:
        assert self.proc.stdout is not None
        for line in self.proc.stdout:
            self._queue.put(line.rstrip("\n"))
        self._queue.put(None)

    def _read_errors(self) -> None:
        assert self.proc.stderr is not None
        for line in self.proc.stderr:
            self.errors.append(line.rstrip("\n"))

    def expect(self, pred: Callable[[str], bool] | str, timeout_s: float = DEADLINE_S) -> str:
        """The first line so far or to come that satisfies `pred` (or starts with it).

        Lines already read count too: children print in their own order.
        """
        test = pred if callable(pred) else (lambda s, p=pred: s.startswith(p))
        for line in self.lines:
            if test(line):
                return line
        deadline = time.monotonic() + timeout_s
        while True:
            left = deadline - time.monotonic()
            if left <= 0:
                raise AssertionError(
                    f"no line matching {pred!r} from {self.argv[:4]}: {self.lines} {self.errors}"
                )
            try:
                got = self._queue.get(timeout=left)
            except queue.Empty:
                continue
            if got is None:
                self._queue.put(None)
                raise AssertionError(f"{self.argv[:4]} ended: {self.lines} {self.errors}")
            self.lines.append(got)
            if test(got):
                return got

    def rest(self, timeout_s: float = DEADLINE_S) -> list[str]:
        """Every remaining line, once the child has closed its output."""
        deadline = time.monotonic() + timeout_s
        while True:
            try:
                line = self._queue.get(timeout=max(deadline - time.monotonic(), 0.01))
            except queue.Empty as e:
                raise AssertionError(f"{self.argv[:4]} still writing: {self.lines}") from e
            if line is None:
                self._queue.put(None)
                return self.lines
            self.lines.append(line)

    def wait(self, timeout_s: float = DEADLINE_S) -> int:
        return self.proc.wait(timeout=timeout_s)

    def stop(self) -> None:
        """SIGTERM, then SIGKILL if it does not go within the deadline."""
        if self.proc.poll() is None:
            self.proc.send_signal(signal.SIGTERM)
            try:
                self.proc.wait(timeout=5.0)
            except subprocess.TimeoutExpired:
                self.proc.kill()
                self.proc.wait(timeout=5.0)
        for t in self._readers:
            t.join(timeout=5.0)
        for pipe in (self.proc.stdout, self.proc.stderr):
            if pipe is not None:  # closed here, never left to the collector (a warning)
                pipe.close()


@contextmanager
def spawned(argv: list[str], merge_stderr: bool = True) -> Iterator[ChildProcess]:
    child = ChildProcess(argv, merge_stderr)
    try:
        yield child
    finally:
        child.stop()


def telerobot(*args: str) -> list[str]:
    return [sys.executable, "-m", "services.tools.cli.main", *args]


# A client-mode session that counts ForceSamples and prints what it got.
COUNTER = r"""
import sys, threading
from services.bus import keys
from services.bus.config import NodeConfig
from services.bus.node import Node

endpoint, n = sys.argv[1], int(sys.argv[2])
cond, seqs = threading.Condition(), []

def on_force(m):
    with cond:
        seqs.append(m.seq)
        cond.notify_all()

with Node("counter", NodeConfig(mode="client", connect=(endpoint,))) as node:
    node.subscribe(keys.FORCE, on_force)
    node.announce()
    print("ready", flush=True)
    with cond:
        cond.wait_for(lambda: len(seqs) >= n, timeout=15)
        got = list(seqs)
    print("count", len(got), flush=True)
    print("seqs", ",".join(map(str, got)), flush=True)
"""

# A client-mode session that publishes N ForceSamples once the counter is there.
PUBLISHER = r"""
import sys, time
from services.bus import keys
from services.bus.config import NodeConfig
from services.bus.messages import ForceSample
from services.bus.node import Node

endpoint, n = sys.argv[1], int(sys.argv[2])
with Node("force", NodeConfig(mode="client", connect=(endpoint,))) as node:
    pub = node.publisher(keys.FORCE)
    assert node.alive.wait("counter", 30), "counter never came up"
    deadline = time.monotonic() + 30
    # the router must have told us about the counter's subscriber before the first put
    while not pub._pub.matching_status.matching:
        assert time.monotonic() < deadline, "no matching subscriber"
        time.sleep(0.005)
    for i in range(1, n + 1):
        pub.put(ForceSample(seq=i, t_ns=time.time_ns(), f=(i, 0.0, -1.0), c=(0.0, 0.0, 0.0)))
    print("sent", n, flush=True)
    # stay connected until the counter is done, so nothing in flight is cut off
    while node.alive.is_alive("counter") and time.monotonic() < deadline:
        time.sleep(0.01)
"""


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
            pub = a.publisher(keys.FORCE)
            wait_matched(pub)
            for i in range(1, 21):
                pub.put(ForceSample(seq=i, t_ns=i, f=(0.0, 0.0, 0.0), c=(0.0, 0.0, 0.0)))
            assert sub.wait_count(20, DEADLINE_S)
            assert sub.latest is not None and sub.latest.seq == 20
        finally:
            b.close()
            a.close()


def test_router_refuses_a_lease_above_2000_ms() -> None:
    with spawned(telerobot("router", "--listen", "tcp/127.0.0.1:1", "--lease-ms", "5000")) as r:
        assert r.wait() == 2
        assert any("zenoh.lease_ms" in line for line in r.rest())
