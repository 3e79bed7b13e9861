"""A link you can make bad, for real: two network namespaces joined by a veth pair, with
`tc netem` delay, jitter, loss and rate on both ends.

    operator 10.203.0.2 ─veth (netem both ways)─ 10.203.0.1 robot

The addresses exist only inside the two namespaces, which have no other interface but their
loopback: nothing reaches any other network. The round trip is split evenly: each end delays
what it sends by `round_trip_ms / 2` ± jitter. Run processes inside with `in_ns`. Needs root
and iproute2 (`ip`, `tc` with the netem qdisc); `unavailable()` says why not otherwise.
"""

from __future__ import annotations

import contextlib
import os
import shutil
import subprocess
import sys
from collections.abc import Iterator
from dataclasses import dataclass

ROBOT_IP = "10.203.0.1"
OPERATOR_IP = "10.203.0.2"


@dataclass(frozen=True, slots=True)
class LinkShape:
    """round_trip_ms (0 … 10000), jitter as a fraction of the one-way delay (0 … 1), loss
    per direction (0 … 1, excluded), rate_mbit (0: unlimited)."""

    round_trip_ms: float = 0.0
    jitter: float = 0.0
    loss: float = 0.0
    rate_mbit: float = 0.0

    def __post_init__(self) -> None:
        if not 0.0 <= self.round_trip_ms <= 10_000.0:
            raise ValueError("round_trip_ms must be within 0 … 10000")
        if not 0.0 <= self.jitter <= 1.0:
            raise ValueError("jitter must be within 0 … 1")
        if not 0.0 <= self.loss < 1.0:
            raise ValueError("loss must be within 0 … 1 (excluded)")
        if not 0.0 <= self.rate_mbit <= 100_000.0:
            raise ValueError("rate_mbit must be within 0 … 100000")

    def netem_args(self) -> list[str]:
        """The `tc qdisc … netem` arguments of one direction."""
        one_way = self.round_trip_ms / 2.0
        args = ["delay", f"{one_way:.3f}ms"]
        if self.jitter > 0.0 and one_way > 0.0:
            args += [f"{self.jitter * one_way:.3f}ms", "distribution", "normal"]
        if self.loss > 0.0:
            args += ["loss", f"{100.0 * self.loss:.4f}%"]
        if self.rate_mbit > 0.0:
            args += ["rate", f"{self.rate_mbit:g}mbit"]
        return args


@dataclass(frozen=True, slots=True)
class Link:
    operator: str
    robot: str
    operator_if: str
    robot_if: str


def unavailable() -> str | None:
    """Why namespaces with netem cannot be made here, or None."""
    if not sys.platform.startswith("linux"):
        return "network namespaces are Linux only"
    if os.geteuid() != 0:
        return "needs root to create network namespaces"
    for tool in ("ip", "tc"):
        if shutil.which(tool) is None:
            return f"no `{tool}` (apt-get install iproute2)"
    return None


def _run(*argv: str, check: bool = True) -> subprocess.CompletedProcess[str]:
    done = subprocess.run(argv, capture_output=True, text=True, timeout=30, check=False)
    if check and done.returncode != 0:
        raise RuntimeError(f"{' '.join(argv)}: {done.stderr.strip()[:300]}")
    return done


def shape(link: Link, how: LinkShape) -> None:
    """Set (or change) the netem qdisc on both ends."""
    for ns, ifname in ((link.operator, link.operator_if), (link.robot, link.robot_if)):
        _run("ip", "netns", "exec", ns, "tc", "qdisc", "replace", "dev", ifname, "root",
             "netem", *how.netem_args())  # fmt: skip


@contextlib.contextmanager
def netem_link(how: LinkShape, tag: str | None = None) -> Iterator[Link]:
    """The two namespaces, joined and shaped, for the duration of the block; always removed
    (deleting a namespace deletes its veth end and the peer). Raises RuntimeError with the
    command's message when a step is refused."""
    tag = tag or str(os.getpid() % 100000)
    link = Link(f"tdpa-{tag}-operator", f"tdpa-{tag}-robot", f"tdo{tag}", f"tdr{tag}")
    try:
        _run("ip", "netns", "add", link.operator)
        _run("ip", "netns", "add", link.robot)
        _run("ip", "link", "add", link.operator_if, "netns", link.operator, "type", "veth",
             "peer", link.robot_if, "netns", link.robot)  # fmt: skip
        for ns, ifname, ip in (
            (link.operator, link.operator_if, OPERATOR_IP),
            (link.robot, link.robot_if, ROBOT_IP),
        ):
            _run("ip", "-n", ns, "addr", "add", f"{ip}/24", "dev", ifname)
            _run("ip", "-n", ns, "link", "set", ifname, "up")
            _run("ip", "-n", ns, "link", "set", "lo", "up")
        shape(link, how)
        yield link
    finally:
        for ns in (link.operator, link.robot):
            _run("ip", "netns", "delete", ns, check=False)


def in_ns(ns: str, *argv: str) -> list[str]:
    """argv run inside namespace ns (a Python module or script: `sys.executable` first)."""
    return ["ip", "netns", "exec", ns, *argv]
