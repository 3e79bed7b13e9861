"""The teleop floor: the 1 kHz streams of teleoperation carried by bare zenoh-python
processes, in the same run as the CPU phases.

During 1 kHz teleoperation the router, the decision, the arm and the force service carry
these streams (sizes as measured on the bus, PUMA 560, 2026-12-04):

| stream | rate | bytes | from → to |
|---|---:|---:|---|
| `robot/cmd` | 1 kHz | 193 | the master → the decision |
| `robot/arm/target` | one per command | 195 | the decision → the arm |
| `robot/force` | 1 kHz | 141 | the force service → the decision, the master |
| `sim/arm/state` | 1 kHz | 351 | the workcell's loop (in the arm's process) → the force service |
| `robot/state` | 250 Hz | 506 | the arm → the decision, the force service |

Here one minimal process per role does only that — plain zenoh-python, one session,
robot/force's QoS on every stream (`floor.declare_floor_publisher`), no code of our
services: it sends its own streams on its own clock (`RateLoop`), puts each command on again
at once as the target (the decision's relay, inline in Zenoh's callback), and hands every
sample it takes to Python (its bytes taken, counted: each of our services must look at every
one — the decision watches every force sample). Keys are the bench's own
(`bench/floor/teleop/<stream>`), so no service receives them. The router plus these three is
the least CPU those four of ours can cost for teleoperation on this machine while each
process looks at every sample it takes; what the CPU phases' `core_pct` costs above it is
ours (decode and checks, the supervision, IK, the physics), not the bus's. The master's side
(the bench's own) is reported apart, as `bench_pct` is, never in the sum.

Run as `python -m services.tools.bench.teleop_floor ROLE --connect ENDPOINT` (the bench
spawns it like a service); on SIGTERM it prints one `teleop floor counts {json}` line:
what it took and sent, per stream, and over how many seconds.
"""

from __future__ import annotations

import argparse
import json
import re
import signal
import sys
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass
from types import FrameType
from typing import Any

import zenoh

from services.bus.rate import RateLoop
from services.tools.bench import cpu
from services.tools.bench.floor import declare_floor_publisher, floor_session
from services.tools.bench.procs import cpu_by_child
from services.tools.cell.procs import Child, Children, wait_log

Say = Callable[[str], None]

PREFIX = "bench/floor/teleop/"
UP = "teleop floor up"
COUNTS = "teleop floor counts "

STREAMS: dict[str, tuple[float, int]] = {
    "cmd": (1000.0, 193),
    "target": (0.0, 195),  # not on a clock: one per command
    "force": (1000.0, 141),
    "simstate": (1000.0, 351),
    "state": (250.0, 506),
}
"""Each stream's rate (Hz) and payload (bytes), as in the module docstring."""


@dataclass(frozen=True, slots=True)
class Role:
    """What one process carries: `takes` (each sample handed to Python), `sends` (on its own
    clock, at the stream's rate), `relays` ((in, out): each sample of `in` put on `out`)."""

    takes: tuple[str, ...] = ()
    sends: tuple[str, ...] = ()
    relays: tuple[tuple[str, str], ...] = ()


ROLES: dict[str, Role] = {
    "decision": Role(takes=("force", "state"), relays=(("cmd", "target"),)),
    "arm": Role(takes=("target",), sends=("state", "simstate")),
    "force": Role(takes=("simstate", "state"), sends=("force",)),
    "master": Role(takes=("force",), sends=("cmd",)),
}
"""In start order: the takers before the master's commands begin."""
COUNTED = ("router", "decision", "arm", "force")
"""The floor's `core_pct`: the processes the CPU phases' `core_pct` sums, bare."""


def key(stream: str) -> str:
    return PREFIX + stream


# --- the processes ---------------------------------------------------------------------------


def run_role(name: str, endpoint: str, mode: str, stop: threading.Event) -> dict[str, Any]:
    """Carry `name`'s streams until `stop`; what it took and sent, per stream."""
    role = ROLES[name]
    got = dict.fromkeys((*role.takes, *(i for i, _ in role.relays)), 0)
    sent = dict.fromkeys((*role.sends, *(o for _, o in role.relays)), 0)
    with floor_session(endpoint, mode) as session:
        pubs = {s: declare_floor_publisher(session, key(s)) for s in sent}
        subs = [session.declare_subscriber(key(s), _taker(got, s)) for s in role.takes]
        subs += [
            session.declare_subscriber(key(i), _relayer(got, sent, i, o, pubs[o]))
            for i, o in role.relays
        ]
        senders = [
            threading.Thread(target=_send, args=(pubs[s], s, sent, stop), daemon=True)
            for s in role.sends
        ]
        t0 = time.monotonic()
        print(f"{UP} {name}", flush=True)
        for t in senders:
            t.start()
        while not stop.wait(0.2):
            pass
        for t in senders:
            t.join(timeout=2.0)
        elapsed = time.monotonic() - t0
        for sub in subs:
            sub.undeclare()
    return {"role": name, "got": got, "sent": sent, "s": elapsed}


def _taker(got: dict[str, int], stream: str) -> Callable[[zenoh.Sample], None]:
    def on_sample(sample: zenoh.Sample) -> None:
        sample.payload.to_bytes()
        got[stream] += 1

    return on_sample


def _relayer(
    got: dict[str, int], sent: dict[str, int], src: str, dst: str, pub: zenoh.Publisher
) -> Callable[[zenoh.Sample], None]:
    def on_sample(sample: zenoh.Sample) -> None:
        got[src] += 1
        pub.put(sample.payload.to_bytes())
        sent[dst] += 1

    return on_sample


def _send(pub: zenoh.Publisher, stream: str, sent: dict[str, int], stop: threading.Event) -> None:
    rate_hz, size = STREAMS[stream]
    payload = bytes(size)
    loop = RateLoop(rate_hz)
    while not stop.is_set():
        pub.put(payload)
        sent[stream] += 1
        loop.sleep()


def role_argv(name: str, endpoint: str, mode: str = "client") -> list[str]:
    return [sys.executable, "-m", "services.tools.bench.teleop_floor", name,
            "--connect", endpoint, "--mode", mode]  # fmt: skip


def parse_counts(output: str) -> dict[str, Any] | None:
    """The counts line a role printed when it stopped (None: it printed none)."""
    found = re.findall(re.escape(COUNTS) + r"(\{.*\})", output)
    return json.loads(found[-1]) if found else None


# --- the phase -------------------------------------------------------------------------------


def phase_teleop_floor(
    kids: Children, endpoint: str, settle_s: float, window_s: float, timeout_s: float, say: Say
) -> dict[str, Any]:
    """Every role as a child of `kids` (the router among them, named `router`), `settle_s`
    to set routes up, a `window_s` CPU window, every role stopped: % of one core per process
    (`services`), their sum over `COUNTED` (`core_pct`), the master's apart (`master_pct`),
    and each role's rate per stream over its life (`rates_hz`). A stream that never arrived
    where it should is named in `na`. ChildFailed (a role or the router died) or
    TimeoutError (a role did not come up): nothing measured, every role stopped."""
    say(
        f"[teleop_floor] teleoperation's streams between bare Zenoh processes "
        f"({', '.join(ROLES)}) for {window_s:g} s …"
    )
    started: dict[str, Child] = {}
    try:
        for name in ROLES:
            started[name] = kids.spawn(f"floor-{name}", role_argv(name, endpoint))
            wait_log(started[name], UP, timeout_s)
        # Route set-up and the senders at their rates are not what the window measures.
        time.sleep(settle_s)
        a, t0 = cpu_by_child(kids), time.monotonic()
        time.sleep(window_s)  # the window's length is the measurement itself
        b, t1 = cpu_by_child(kids), time.monotonic()
        kids.check("router", *(f"floor-{n}" for n in started))  # ChildFailed: not measured
    finally:
        for name in reversed(tuple(started)):
            kids.stop(f"floor-{name}")
    pct = cpu.percent_of_core(a, b, t1 - t0)
    services = {n: pct[n if n == "router" else f"floor-{n}"] for n in COUNTED}
    fig: dict[str, Any] = {
        "window_s": t1 - t0,
        "services": services,
        "core_pct": sum(services.values()),
        "master_pct": pct["floor-master"],
        "rates_hz": {},
        "na": {},
    }
    for name, child in started.items():
        counts = parse_counts(child.output())
        if counts is None or counts["s"] <= 0:
            fig["na"][name] = "printed no counts"
            continue
        both = {**counts["got"], **{f"{s} sent": n for s, n in counts["sent"].items()}}
        fig["rates_hz"][name] = {s: n / counts["s"] for s, n in both.items()}
        silent = [s for s, n in counts["got"].items() if n == 0]
        if silent:
            fig["na"][name] = f"took nothing on {', '.join(silent)}"
    say(
        f"    teleop floor: router + decision + arm + force {fig['core_pct']:.1f} % of one "
        "core; " + ", ".join(f"{k} {v:.1f}" for k, v in services.items())
    )
    return fig


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(
        prog="python -m services.tools.bench.teleop_floor", description=__doc__
    )
    p.add_argument("role", choices=list(ROLES))
    p.add_argument("--connect", required=True, metavar="ENDPOINT")
    p.add_argument("--mode", choices=["client", "peer"], default="client")
    args = p.parse_args(argv)
    stop = threading.Event()

    def on_signal(signum: int, frame: FrameType | None) -> None:
        stop.set()

    signal.signal(signal.SIGTERM, on_signal)
    signal.signal(signal.SIGINT, on_signal)
    counts = run_role(args.role, args.connect, args.mode, stop)
    print(COUNTS + json.dumps(counts), flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
