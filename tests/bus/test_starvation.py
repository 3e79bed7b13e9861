"""A subscriber starved of CPU never reads another message's bytes (issue: services rejected
their own well-formed messages under load).

The cause, reproduced here: Zenoh's implicit shared-memory transport (on by default in the
PyPI wheel) puts payloads of 3 KB or more between local processes in buffers from a pool the
publisher reuses once the reader's watchdog stops confirming them; a starved reader whose
callback runs late then decodes whatever was written there since. Our nodes turn it off
(`NodeConfig.shared_memory`). The subscriber here is a separate process, frozen with
SIGSTOP again and again while large checksummed frames and small force samples stream.
"""

from __future__ import annotations

import hashlib
import json
import os
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

import pytest

from services.bus import keys
from services.bus.config import NodeConfig
from services.bus.messages import ForceSample, StereoFrame
from tests.conftest import Net

pytestmark = pytest.mark.timeout(120)

REPO = Path(__file__).resolve().parents[2]
FREEZES = 12


def test_node_config_turns_shared_memory_off() -> None:
    cfg = NodeConfig().to_zenoh()
    assert json.loads(cfg.get_json("transport/shared_memory/enabled")) is False
    assert (
        json.loads(
            NodeConfig(shared_memory=True).to_zenoh().get_json("transport/shared_memory/enabled")
        )
        is True
    )


def test_a_starved_subscriber_never_reads_another_messages_bytes(net: Net) -> None:
    pub_node = net.node("vision")
    endpoint = net.endpoint
    child = subprocess.Popen(
        [sys.executable, "-m", "tests.bus.starved_subscriber", endpoint, "tcp"],
        cwd=REPO,
        stdin=subprocess.PIPE,
        stdout=subprocess.PIPE,
        text=True,
    )
    try:
        assert child.stdout is not None and child.stdin is not None
        assert child.stdout.readline().strip() == "ready"
        assert pub_node.alive.wait("starved", 30.0)
        frames, force = pub_node.publisher(keys.STEREO_L), pub_node.publisher(keys.FORCE)
        done = threading.Event()
        sent = {"frames": 0}

        def stream() -> None:
            i = 0
            while not done.is_set():
                i += 1
                body = os.urandom(20_000) + i.to_bytes(8, "little")
                frames.put(
                    StereoFrame(
                        seq=i,
                        t_ns=time.time_ns(),
                        eye="l",
                        width=64,
                        height=48,
                        encoding="jpeg",
                        data=hashlib.sha1(body).digest() + body,
                    )
                )
                sent["frames"] += 1
                for k in range(5):
                    force.put(ForceSample(5 * i + k, time.time_ns(), (1.0, 2.0, 3.0), (0.0,) * 3))
                done.wait(0.002)

        t = threading.Thread(target=stream, daemon=True)
        t.start()
        for _ in range(FREEZES):  # the reader starved outright: frozen, thawed, frozen …
            done.wait(0.5)
            os.kill(child.pid, signal.SIGSTOP)
            done.wait(0.3)
            os.kill(child.pid, signal.SIGCONT)
        done.set()
        t.join(5.0)
        out, _ = child.communicate("", timeout=60.0)
        counts = json.loads(out.strip().splitlines()[-1])
    finally:
        if child.poll() is None:
            os.kill(child.pid, signal.SIGCONT)
            child.kill()
            child.wait()
    assert counts["frames"] > 50 and counts["force"] > 250, counts
    assert counts["corrupt"] == 0, counts
    assert counts["frames_rejected"] == 0 and counts["force_rejected"] == 0, counts
