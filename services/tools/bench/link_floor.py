"""The floor of `telerobot bench link`: bare Zenoh over the same emulated link, no services.

Before each condition's services start, two bare Zenoh sessions cross the same link with the
same transport and the same TLS files: the robot side (listening, as the router does) sends a
force-sized sample (`SIZE` bytes, robot/force's QoS: best effort, REAL_TIME, express) at
`DOWN_HZ`, the station sends a command-sized one at `UP_HZ`, each stamped with `time.time_ns()`
(the namespaces share the host's clock). What arrives, and how old, is what the transport
itself allows on that link: the system's figures in the same row are to be read against it.
A row whose floor already misses a target is the transport's limit, not the system's.

    python -m services.tools.bench.link_floor peer robot|station ENDPOINT ZENOH_FILE SECONDS
"""

from __future__ import annotations

import json
import sys
import threading
import time
from typing import Any

DOWN_HZ = 1000.0
"""robot/force's rate at the robot host."""
UP_HZ = 500.0
"""The station's command rate (link.py `--rate-hz` default)."""
SIZE = 150
"""Bytes per sample: a ForceSample with `raw` (143 B of msgpack) or an OperatorCommand."""
FLOOR_S = 6.0
"""Streamed each way by default (`--floor-s`), after SETTLE_S for the sessions to meet."""
SETTLE_S = 2.0
KEY_DOWN = "bench/floor/down"
KEY_UP = "bench/floor/up"


def summary(ages_ms: list[float], sent: int) -> dict[str, Any]:
    """Delivered share and age quantiles of one direction (the bench's own percentiles)."""
    from services.tools.bench.stats import summarize

    ages = summarize(ages_ms).as_dict()
    return {
        "sent": sent,
        "received": len(ages_ms),
        "delivered_pct": 100.0 * len(ages_ms) / sent if sent else None,
        "age_p50_ms": ages["p50"],
        "age_p99_ms": ages["p99"],
    }


def peer(role: str, ep: str, zenoh_file: str, seconds: float = FLOOR_S) -> dict[str, Any]:
    """One side's run: stream its direction, receive the other's; its received ages."""
    import zenoh

    from services.bus import keys
    from services.bus.config import NodeConfig
    from services.bus.node import open_session
    from services.bus.streams import publisher_qos

    robot = role == "robot"
    cfg = NodeConfig(
        mode="peer",
        listen=(ep,) if robot else (),
        connect=() if robot else (ep,),
        zenoh_config=zenoh_file,
    )
    session = open_session(cfg)
    ages: list[float] = []
    lock = threading.Lock()

    def on_sample(s: zenoh.Sample) -> None:
        t = int.from_bytes(bytes(s.payload)[:8], "little")
        with lock:
            ages.append((time.time_ns() - t) / 1e6)

    session.declare_subscriber(KEY_UP if robot else KEY_DOWN, on_sample)
    qos = publisher_qos(keys.FORCE)
    pub = session.declare_publisher(KEY_DOWN if robot else KEY_UP, **qos)
    if robot:
        print("ready", flush=True)
    time.sleep(SETTLE_S)  # pacing: both sides' declarations cross the link before streaming
    hz = DOWN_HZ if robot else UP_HZ
    n = int(seconds * hz)
    pad = b"\0" * (SIZE - 8)
    nxt = time.perf_counter()
    for _ in range(n):
        pub.put(time.time_ns().to_bytes(8, "little") + pad)
        nxt += 1.0 / hz
        delay = nxt - time.perf_counter()
        if delay > 0:
            time.sleep(delay)
    time.sleep(SETTLE_S)  # pacing: what is still in flight lands
    session.close()
    with lock:
        got = list(ages)
    return {"role": role, "sent": n, "ages_ms": got}


def run(
    link: Any, ep: str, router_file: str, client_file: str, seconds: float = FLOOR_S
) -> dict[str, Any]:
    """Both sides over `link` (netem.Link) for `seconds`; {down: …, up: …} or {error: …}."""
    import subprocess

    from services.tools.tdpa.netem import in_ns

    argv = [sys.executable, "-m", __name__, "peer"]
    timeout = SETTLE_S * 2 + seconds + 60.0
    with subprocess.Popen(
        in_ns(link.robot, *argv, "robot", ep, router_file, str(seconds)),
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
    ) as robot:
        assert robot.stdout is not None
        if robot.stdout.readline().strip() != "ready":
            robot.kill()
            return {"error": f"the robot side did not start: {robot.communicate()[1][-600:]}"}
        station = subprocess.run(
            in_ns(link.operator, *argv, "station", ep, client_file, str(seconds)),
            capture_output=True,
            text=True,
            timeout=timeout,
            check=False,
        )
        r_out, r_err = robot.communicate(timeout=timeout)
    if robot.returncode != 0 or station.returncode != 0:
        return {"error": (r_err + station.stderr).strip()[-600:]}
    r = json.loads(r_out.strip().splitlines()[-1])
    s = json.loads(station.stdout.strip().splitlines()[-1])
    return {
        "down": summary(s["ages_ms"], r["sent"]),
        "up": summary(r["ages_ms"], s["sent"]),
        "down_hz": DOWN_HZ,
        "up_hz": UP_HZ,
        "size_b": SIZE,
    }


def main(argv: list[str]) -> int:
    if len(argv) != 5 or argv[0] != "peer" or argv[1] not in ("robot", "station"):
        print(__doc__, file=sys.stderr)
        return 2
    print(json.dumps(peer(argv[1], argv[2], argv[3], float(argv[4]))), flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
