"""A subscriber process for tests/bus/test_starvation.py: our Node on the given router, its
callbacks made late (sleeps) and its CPU taken by busy threads; it checks every stereo
frame's checksum and prints one JSON line of counts when told to stop (stdin closes)."""

from __future__ import annotations

import hashlib
import json
import random
import sys
import threading
import time

from services.bus import keys
from services.bus.config import NodeConfig
from services.bus.messages import StereoFrame
from services.bus.node import Node


def main() -> None:
    endpoint, shared_memory = sys.argv[1], sys.argv[2] == "shm"
    node = Node(
        "starved",
        NodeConfig(connect=(endpoint,), listen=("tcp/127.0.0.1:0",), shared_memory=shared_memory),
    )
    counts = {"frames": 0, "corrupt": 0}
    lock = threading.Lock()

    def on_frame(f: StereoFrame) -> None:
        if random.random() < 0.1:
            time.sleep(0.2)  # a callback that runs late
        ok = hashlib.sha1(f.data[20:]).digest() == f.data[:20]
        with lock:
            counts["frames"] += 1
            counts["corrupt"] += not ok

    frames = node.subscribe(keys.STEREO_L, on_frame)
    force = node.subscribe(keys.FORCE)
    stop = threading.Event()

    def hog() -> None:
        x = 0
        while not stop.is_set():
            for i in range(100_000):
                x += i

    for _ in range(3):
        threading.Thread(target=hog, daemon=True).start()
    node.announce()
    print("ready", flush=True)
    sys.stdin.read()  # until the test closes our stdin
    stop.set()
    with lock:
        out = {
            **counts,
            "frames_rejected": frames.rejected,
            "force": force.received,
            "force_rejected": force.rejected,
        }
    print(json.dumps(out), flush=True)
    node.close()


if __name__ == "__main__":
    main()
