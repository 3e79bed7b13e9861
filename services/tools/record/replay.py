"""`telerobot replay FILE.mcap`: republish a recording on its original keys, byte for byte.

Each raw message (`/raw/<key>`) is published on `<key>` — in the replaying node's namespace
— with the contract's encoding and the key's QoS, at its recorded receive time scaled by
`--speed` (0: as fast as possible), in the order it was received. So the console and the
services can be run against a real session. Before the first message the replayer waits
(up to `--wait-s`) until every key it will publish has a subscriber, so nothing is lost to
routes not yet set up. See docs/record.md.

A recording holds the cell's own keys (robot/state, robot/events, …): published into a cell
where the live services run, old states and events would mix with theirs. So the replayer
refuses to start while any of LIVE_SERVICES is alive in its namespace, unless told
`--into-live`; and it marks everything it sends with the Zenoh attachment `REPLAY_MARK`
(and announces itself as `alive/replay`), so a subscriber can tell replayed from live.
"""

from __future__ import annotations

import argparse
import json
import logging
import math
import sys
import threading
import time
from collections import Counter
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Protocol

import zenoh

from services.bus import keys, streams
from services.bus.config import LOCAL_ROUTER, add_node_args, node_config
from services.bus.errors import ConfigError
from services.bus.lifecycle import Shutdown, setup_logging
from services.bus.node import Node
from services.tools.record import schemas
from services.tools.record.archive import Recording

log = logging.getLogger("telerobot.replay")

MAX_SLEEP_S = 0.05
MATCH_POLL_S = 0.01
LIVE_SERVICES = ("arm", "decision", "force", "vision", "workcell")
"""The services whose keys a recording replays: alive, they are a live cell."""
REPLAY_MARK = b"replay"
"""The Zenoh attachment on every sample the replayer sends."""
LIVE_QUERY_S = 1.0


def live_services(node: Node, timeout_s: float = LIVE_QUERY_S) -> list[str]:
    """Which of LIVE_SERVICES hold `alive/<service>` in `node`'s namespace (a liveliness
    query: every reachable session answers)."""
    found = set()
    for r in node.session.liveliness().get(f"{keys.ALIVE_PREFIX}/**", timeout=timeout_s):
        if r.ok is None:
            continue
        name = str(r.ok.key_expr).split("/")[1]
        if name in LIVE_SERVICES:
            found.add(name)
    return sorted(found)


@dataclass(frozen=True, slots=True)
class ReplayOptions:
    """speed: time scale (2.0 = twice as fast; 0 = no waiting between messages).
    loop: start again at the end until stopped.
    keys: Zenoh key expressions to replay (empty: all).
    wait_s: before starting, wait up to this long for a subscriber on every key."""

    speed: float = 1.0
    loop: bool = False
    keys: tuple[str, ...] = ()
    wait_s: float = 1.0

    def __post_init__(self) -> None:
        if not math.isfinite(self.speed) or self.speed < 0:
            raise ConfigError("replay.speed", "must be ≥ 0 (0: as fast as possible)")
        if not math.isfinite(self.wait_s) or self.wait_s < 0:
            raise ConfigError("replay.wait_s", "must be ≥ 0")
        schemas.key_matcher(self.keys)


@dataclass
class ReplayStats:
    """What a replay published: per key, the passes made, and files found cut short."""

    published: Counter[str] = field(default_factory=Counter)
    passes: int = 0
    truncated: list[str] = field(default_factory=list)
    unmatched: list[str] = field(default_factory=list)
    duration_s: float = 0.0

    def as_dict(self) -> dict[str, Any]:
        return {
            "published": dict(sorted(self.published.items())),
            "total": sum(self.published.values()),
            "passes": self.passes,
            "truncated": self.truncated,
            "unmatched": self.unmatched,
            "duration_s": round(self.duration_s, 3),
        }


class StopFlag(Protocol):
    """`threading.Event` or `services.bus.lifecycle.Shutdown`."""

    def is_set(self) -> bool: ...

    def wait(self, timeout: float | None = None, /) -> bool: ...


def recorded_keys(paths: Sequence[str | Path], select: Callable[[str], bool]) -> list[str]:
    """The keys of the raw channels in `paths` that `select` accepts, in first-seen order."""
    seen: dict[str, None] = {}
    for p in paths:
        for k in Recording(Path(p)).raw_keys():
            if select(k):
                seen.setdefault(k, None)
    return list(seen)


class Replayer:
    """Republishes recordings through `node`. `run()` blocks until done or `stop` is set."""

    def __init__(
        self, node: Node, paths: Sequence[str | Path], options: ReplayOptions | None = None
    ) -> None:
        self.node = node
        self.paths = [Path(p) for p in paths]
        for p in self.paths:
            if not p.is_file():
                raise ConfigError("replay.file", f"no such file {str(p)!r}")
        self.options = options or ReplayOptions()
        self._select = schemas.key_matcher(self.options.keys)
        self._puts: dict[str, Callable[[bytes], None]] = {}

    def _publisher(self, key: str) -> Callable[[bytes], None]:
        """The put of `key`: the contract's encoding and the key's priority, but reliable and
        blocking whatever the live stream's delivery (keys.py): a replay is for looking at
        a session, so it loses nothing (it never runs faster than asked)."""
        put = self._puts.get(key)
        if put is None:
            topic = keys.topic_for(key)
            qos = {} if topic is None else streams.publisher_qos(topic)
            qos |= {
                "reliability": zenoh.Reliability.RELIABLE,
                "congestion_control": zenoh.CongestionControl.BLOCK,
            }
            raw = self.node.session.declare_publisher(
                key, encoding=zenoh.Encoding(keys.ENCODING), **qos
            )

            def put(payload: bytes, raw: Any = raw) -> None:
                raw.put(payload, attachment=REPLAY_MARK)

            self._puts[key] = put
        return put

    def _wait_for_subscribers(self, names: Sequence[str], stop: StopFlag) -> list[str]:
        """Wait until each key has a subscriber (or `wait_s` passes); the keys without."""
        probes = {k: self.node.session.declare_publisher(k) for k in names}
        deadline = time.monotonic() + self.options.wait_s
        try:
            while True:
                missing = [k for k, p in probes.items() if not _matching(p)]
                if not missing or time.monotonic() >= deadline or stop.is_set():
                    return missing
                stop.wait(MATCH_POLL_S)
        finally:
            for p in probes.values():
                p.undeclare()

    def run(self, stop: StopFlag | None = None) -> ReplayStats:
        """Replay (every pass, with `loop`); returns what was published."""
        stop = stop if stop is not None else threading.Event()
        stats = ReplayStats()
        names = recorded_keys(self.paths, self._select)
        for k in names:
            self._publisher(k)
        if self.options.wait_s > 0 and names:
            stats.unmatched = self._wait_for_subscribers(names, stop)
            if stats.unmatched:
                log.info("no subscriber yet on %s", ", ".join(stats.unmatched))
        started = time.monotonic()
        while not stop.is_set():
            self._one_pass(stop, stats)
            stats.passes += 1
            if not self.options.loop or not names:
                break
        stats.duration_s = time.monotonic() - started
        return stats

    def _one_pass(self, stop: StopFlag, stats: ReplayStats) -> None:
        speed = self.options.speed
        t0_s = time.perf_counter()
        log0_ns: int | None = None
        for path in self.paths:
            rec = Recording(path)
            for m in rec.raw(self._select):
                if stop.is_set():
                    return
                if log0_ns is None:
                    log0_ns = m.log_time_ns
                if speed > 0:
                    due_s = t0_s + (m.log_time_ns - log0_ns) / 1e9 / speed
                    while (left := due_s - time.perf_counter()) > 0:
                        if stop.wait(min(left, MAX_SLEEP_S)):
                            return
                self._publisher(m.key)(m.payload)
                stats.published[m.key] += 1
            if rec.truncated and str(path) not in stats.truncated:
                log.warning("%s ends early (%s): replayed up to its last chunk", path, rec.error)
                stats.truncated.append(str(path))


def _matching(pub: Any) -> bool:
    # zenoh-python 1.x returns a MatchingStatus object; older stubs say bool.
    status = pub.matching_status
    return bool(getattr(status, "matching", status))


def parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="telerobot replay", description=__doc__)
    add_node_args(p)
    p.add_argument("files", nargs="+", metavar="FILE.mcap", help="recording (or its parts)")
    p.add_argument("--speed", type=float, default=1.0, help="time scale; 0 = no waiting")
    p.add_argument("--loop", action="store_true", help="start again at the end")
    p.add_argument(
        "--keys",
        action="append",
        default=[],
        metavar="KEYEXPR",
        help="replay only keys in this Zenoh key expression, e.g. 'robot/**' (repeatable; "
        "default: all)",
    )
    p.add_argument("--wait-s", type=float, default=1.0, help="wait for subscribers up to this long")
    p.add_argument(
        "--into-live",
        action="store_true",
        help="publish even though the cell's services run in this namespace (their live "
        "robot/state and events then mix with the recording's, marked `replay`)",
    )
    p.add_argument("--verbose", "-v", action="store_true", help="debug logging")
    return p


def main(argv: list[str] | None = None) -> int:
    args = parser().parse_args(argv)
    setup_logging("replay", args.verbose)
    options = ReplayOptions(
        speed=args.speed, loop=args.loop, keys=tuple(args.keys), wait_s=args.wait_s
    )
    cfg = node_config(args, connect=(LOCAL_ROUTER,))
    stop = Shutdown()
    with Node("replay", cfg) as node:
        live = live_services(node)
        if live and not args.into_live:
            print(
                f"replay: refused: {', '.join(live)} run in this namespace — replaying would "
                "publish the recording's old robot/state and events on their live keys. Stop "
                "them, replay into another namespace (--ns replay), or pass --into-live.",
                file=sys.stderr,
            )
            return 2
        if live:
            log.warning("replaying into a live cell (%s): samples marked 'replay'", ", ".join(live))
        node.announce()
        stats = Replayer(node, args.files, options).run(stop)
    print(json.dumps(stats.as_dict()))
    return 0


if __name__ == "__main__":
    sys.exit(main())
