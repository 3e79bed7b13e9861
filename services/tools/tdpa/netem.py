"""A link you can make bad, for real: network namespaces whose traffic crosses an emulated
link with delay, jitter, loss and rate, built from the kernel's `tc netem` where it has one
and from the userspace delay line (`delayline.py`) where it has not.

With netem, two namespaces joined by a veth pair, shaped on both ends:

    operator 10.203.0.2/24 ─veth (netem both ways)─ 10.203.0.1/24 robot

Without it, a third namespace in the middle forwards between two /31 point-to-point veths
(RFC 3021), every packet through a TUN device that the delay line process reads and writes:

    operator 10.203.0.2/31 ─veth─ 10.203.0.3/31 line 10.203.0.0/31 ─veth─ 10.203.0.1/31 robot
                                         │ tl0 (TUN) ⇄ delayline │

In the line namespace a policy rule sends what arrives on either veth to a table whose only
route is `dev tl0`; what the delay line writes back arrives from tl0 and takes the main
table, which routes each /31 to its veth (ip_forward on, rp_filter off). The operator and the
robot each route the other's /31 via the line's address. The addresses are the same for
callers either way (`ROBOT_IP`, `OPERATOR_IP`) and exist only inside the namespaces, which
have no other interface but their loopback: nothing reaches any other network. The round trip
is split evenly: each direction is delayed `round_trip_ms / 2` ± jitter. The delay line keeps
each direction in order where netem with jitter would reorder (see delayline.py).

Run processes inside with `in_ns`. Needs root and iproute2, and either the netem qdisc or
/dev/net/tun; `unavailable()` says why not otherwise.
"""

from __future__ import annotations

import contextlib
import functools
import json
import os
import shutil
import subprocess
import sys
import time
from collections.abc import Iterator
from dataclasses import dataclass, field
from typing import Literal

from services.tools.cell.procs import Child
from services.tools.tdpa.delayline import DirectionShape

ROBOT_IP = "10.203.0.1"
OPERATOR_IP = "10.203.0.2"
LINE_ROBOT_SIDE_IP = "10.203.0.0"
"""The line namespace's address toward the robot (delay line only; /31 with ROBOT_IP)."""
LINE_OPERATOR_SIDE_IP = "10.203.0.3"
"""The line namespace's address toward the operator (delay line only; /31 with OPERATOR_IP)."""
ROBOT_NET = "10.203.0.0/31"
OPERATOR_NET = "10.203.0.2/31"
TUN_DEV = "tl0"
TUN_TABLE = "100"
"""The line namespace's routing table for what arrives on a veth: everything to tl0."""
START_TIMEOUT_S = 20.0
STOP_TIMEOUT_S = 5.0
CARRIER_TIMEOUT_S = 10.0
CARRIER_POLL_S = 0.02

Emulator = Literal["netem", "delayline"]


@dataclass(frozen=True, slots=True)
class LinkShape:
    """round_trip_ms (0 … 10000), jitter as a fraction of the one-way delay (0 … 1), loss
    per direction (0 … 1, excluded), rate_mbit (0: unlimited); seed draws the delay line's
    loss and jitter (netem draws its own)."""

    round_trip_ms: float = 0.0
    jitter: float = 0.0
    loss: float = 0.0
    rate_mbit: float = 0.0
    seed: int = 0
    queue_ms: float = 0.0
    """With a rate: the bottleneck's buffer in time each way (0: unbounded; delayline.py)."""

    def __post_init__(self) -> None:
        if not 0.0 <= self.round_trip_ms <= 10_000.0:
            raise ValueError("round_trip_ms must be within 0 … 10000")
        # Each direction's shape checks the rest (the same bounds for netem and the line).
        DirectionShape(
            self.round_trip_ms / 2.0, self.jitter, self.loss, self.rate_mbit, self.queue_ms
        )

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
            if self.queue_ms > 0.0:  # netem's limit is in packets: the buffer's of 1500 B
                packets = self.rate_mbit * 1e6 / 8 * self.queue_ms / 1e3 / 1500
                args += ["limit", str(max(1, round(packets)))]
        return args

    def delayline_args(self) -> list[str]:
        """The delay line's arguments (each applies to each direction)."""
        return [
            f"--delay-ms={self.round_trip_ms / 2.0!r}",
            f"--jitter={self.jitter!r}",
            f"--loss={self.loss!r}",
            f"--rate-mbit={self.rate_mbit!r}",
            f"--seed={self.seed}",
            *([f"--queue-ms={self.queue_ms!r}"] if self.queue_ms > 0.0 else []),
        ]


class DelayLineProcess:
    """The delay line running in the line namespace, a cell layer `Child` whose lines are
    read; `start` (re)starts it with a shape. `runs` keeps the counts each run printed when
    it stopped, oldest first."""

    def __init__(self, ns: str) -> None:
        self.ns = ns
        self.runs: list[dict[str, int | str]] = []
        self._child: Child | None = None

    def start(self, how: LinkShape) -> None:
        """Stop the running delay line (if any) and start one with `how`; returns when it
        has said `ready`. Raises RuntimeError with its output when it does not."""
        self.stop()
        module = "services.tools.tdpa.delayline"
        options = [f"--dev={TUN_DEV}", f"--robot-net={ROBOT_NET}", *how.delayline_args()]
        argv = in_ns(self.ns, sys.executable, "-m", module, *options)
        self._child = child = Child(
            "delayline",
            argv,
            lines=True,
            errors_apart=True,
            own_group=False,
            stop_timeout_s=STOP_TIMEOUT_S,
        ).start()
        try:
            first = child.expect(lambda line: True, START_TIMEOUT_S).strip()
        except AssertionError:  # no line in time, or none before it ended
            first = ""
        if first != "ready":
            self.stop()
            raise RuntimeError(f"the delay line did not start: {self.runs.pop()}")

    def stop(self) -> None:
        """SIGTERM, SIGKILL after STOP_TIMEOUT_S; its counts appended to `runs` (or, when it
        printed none, {"error": …} with the end of its stderr)."""
        child, self._child = self._child, None
        if child is None:
            return
        code = child.stop()
        err = "\n".join(child.errors)
        lines = err.strip().splitlines()
        try:
            counts = json.loads(lines[-1]) if lines else None
        except json.JSONDecodeError:
            counts = None
        if not isinstance(counts, dict):
            counts = {"error": f"exit {code}: {err.strip()[-500:]}"}
        self.runs.append(counts)


@dataclass(frozen=True, slots=True)
class Link:
    """The namespaces of one link. With the delay line, `line` is the namespace in the
    middle and `delayline` its process; with netem both are empty."""

    operator: str
    robot: str
    operator_if: str
    robot_if: str
    emulator: Emulator = "netem"
    line: str = ""
    delayline: DelayLineProcess | None = field(default=None, compare=False)

    def namespaces(self) -> tuple[str, ...]:
        return tuple(ns for ns in (self.operator, self.line, self.robot) if ns)


def _run(*argv: str, check: bool = True) -> subprocess.CompletedProcess[str]:
    done = subprocess.run(argv, capture_output=True, text=True, timeout=30, check=False)
    if check and done.returncode != 0:
        raise RuntimeError(f"{' '.join(argv)}: {done.stderr.strip()[:300]}")
    return done


@functools.cache
def netem_refusal() -> str | None:
    """Why this kernel cannot shape with netem, or None: tried once per process on the
    loopback of a namespace made for the purpose (and deleted)."""
    if shutil.which("tc") is None:
        return "no `tc` (apt-get install iproute2)"
    ns = f"tdpa-probe-{os.getpid()}"
    try:
        _run("ip", "netns", "add", ns)
        tried = _run("ip", "netns", "exec", ns, "tc", "qdisc", "add", "dev", "lo", "root",
                     "netem", "delay", "1ms", check=False)  # fmt: skip
        if tried.returncode != 0:
            return f"tc netem refused: {tried.stderr.strip()[:200]}"
        return None
    except (RuntimeError, OSError, subprocess.SubprocessError) as e:
        return f"cannot try netem: {e}"
    finally:
        _run("ip", "netns", "delete", ns, check=False)


def tun_refusal() -> str | None:
    """Why the delay line cannot open a TUN device here, or None."""
    try:
        fd = os.open("/dev/net/tun", os.O_RDWR | os.O_CLOEXEC)
    except OSError as e:
        return f"no usable /dev/net/tun ({e.strerror}; modprobe tun)"
    os.close(fd)
    return None


def unavailable() -> str | None:
    """Why no link can be made here (neither netem nor the delay line), or None."""
    if not sys.platform.startswith("linux"):
        return "network namespaces are Linux only"
    if os.geteuid() != 0:
        return "needs root to create network namespaces"
    if shutil.which("ip") is None:
        return "no `ip` (apt-get install iproute2; `make system-deps`)"
    tun = tun_refusal()
    if tun is None:
        return None
    netem = netem_refusal()
    if netem is None:
        return None
    return f"neither netem ({netem}) nor the delay line ({tun})"


def shape(link: Link, how: LinkShape) -> None:
    """Set (or change) the shape: the netem qdisc on both ends, or the delay line restarted
    with it (what it held is lost, as on a link that went down for a moment)."""
    if link.delayline is not None:
        link.delayline.start(how)
        return
    for ns, ifname in ((link.operator, link.operator_if), (link.robot, link.robot_if)):
        _run("ip", "netns", "exec", ns, "tc", "qdisc", "replace", "dev", ifname, "root",
             "netem", *how.netem_args())  # fmt: skip


def _wait_carrier(ns: str, ifname: str) -> None:
    """Until the kernel reports the veth end up with a carrier: a new veth may stay
    NO-CARRIER for up to a second (link watch), and drops what it is given meanwhile."""
    deadline = time.monotonic() + CARRIER_TIMEOUT_S
    while True:
        shown = _run("ip", "-n", ns, "-o", "link", "show", "dev", ifname).stdout
        if "NO-CARRIER" not in shown and " state UP " in shown:
            return
        if time.monotonic() >= deadline:
            raise RuntimeError(f"{ifname} in {ns} not up after {CARRIER_TIMEOUT_S:g} s: {shown}")
        time.sleep(CARRIER_POLL_S)


def _build_netem(link: Link) -> None:
    _run("ip", "link", "add", link.operator_if, "netns", link.operator, "type", "veth",
         "peer", link.robot_if, "netns", link.robot)  # fmt: skip
    for ns, ifname, ip in (
        (link.operator, link.operator_if, OPERATOR_IP),
        (link.robot, link.robot_if, ROBOT_IP),
    ):
        _run("ip", "-n", ns, "addr", "add", f"{ip}/24", "dev", ifname)
        _run("ip", "-n", ns, "link", "set", ifname, "up")


def _build_delayline(link: Link, line_op_if: str, line_robot_if: str) -> None:
    _run("ip", "link", "add", link.operator_if, "netns", link.operator, "type", "veth",
         "peer", line_op_if, "netns", link.line)  # fmt: skip
    _run("ip", "link", "add", link.robot_if, "netns", link.robot, "type", "veth",
         "peer", line_robot_if, "netns", link.line)  # fmt: skip
    for ns, ifname, ip in (
        (link.operator, link.operator_if, OPERATOR_IP),
        (link.line, line_op_if, LINE_OPERATOR_SIDE_IP),
        (link.line, line_robot_if, LINE_ROBOT_SIDE_IP),
        (link.robot, link.robot_if, ROBOT_IP),
    ):
        _run("ip", "-n", ns, "addr", "add", f"{ip}/31", "dev", ifname)
        _run("ip", "-n", ns, "link", "set", ifname, "up")
    _run("ip", "-n", link.operator, "route", "add", ROBOT_NET, "via", LINE_OPERATOR_SIDE_IP)
    _run("ip", "-n", link.robot, "route", "add", OPERATOR_NET, "via", LINE_ROBOT_SIDE_IP)
    # A persistent TUN, so the routes through it survive a restart of the delay line.
    _run("ip", "-n", link.line, "tuntap", "add", "dev", TUN_DEV, "mode", "tun")
    _run("ip", "-n", link.line, "link", "set", TUN_DEV, "txqueuelen", "10000", "up")
    # Written through /proc/sys (a namespace's own inside `ip netns exec`): no procps needed.
    settings = {
        "net/ipv4/ip_forward": 1,
        "net/ipv6/conf/all/disable_ipv6": 1,
        "net/ipv6/conf/default/disable_ipv6": 1,
    }
    for ifname in ("all", "default", "lo", line_op_if, line_robot_if, TUN_DEV):
        settings[f"net/ipv4/conf/{ifname}/rp_filter"] = 0
        settings[f"net/ipv4/conf/{ifname}/send_redirects"] = 0
    script = "".join(f"echo {v} > /proc/sys/{k} && " for k, v in settings.items()) + "true"
    _run("ip", "netns", "exec", link.line, "sh", "-c", script)
    _run("ip", "-n", link.line, "route", "add", "default", "dev", TUN_DEV, "table", TUN_TABLE)
    for ifname in (line_op_if, line_robot_if):
        _run("ip", "-n", link.line, "rule", "add", "iif", ifname, "lookup", TUN_TABLE)


@contextlib.contextmanager
def netem_link(
    how: LinkShape, tag: str | None = None, emulator: Emulator | None = None
) -> Iterator[Link]:
    """The namespaces, joined and shaped, for the duration of the block; always removed (the
    delay line stopped first; deleting a namespace deletes its veth ends and TUN). netem when
    the kernel has it, the delay line otherwise, or the `emulator` asked for. Raises
    RuntimeError with the command's message when a step is refused."""
    tag = tag or str(os.getpid() % 100000)
    names = (f"tdpa-{tag}-operator", f"tdpa-{tag}-robot", f"tdo{tag}", f"tdr{tag}")
    if emulator is None:
        emulator = "netem" if netem_refusal() is None else "delayline"
    if emulator == "netem":
        link = Link(*names)
    else:
        line = f"tdpa-{tag}-line"
        link = Link(*names, emulator="delayline", line=line, delayline=DelayLineProcess(line))
    try:
        for ns in link.namespaces():
            _run("ip", "netns", "add", ns)
            _run("ip", "-n", ns, "link", "set", "lo", "up")
        if link.delayline is None:
            _build_netem(link)
            veths = [(link.operator, link.operator_if), (link.robot, link.robot_if)]
        else:
            _build_delayline(link, f"tlo{tag}", f"tlr{tag}")
            veths = [(link.operator, link.operator_if), (link.line, f"tlo{tag}"),
                     (link.line, f"tlr{tag}"), (link.robot, link.robot_if)]  # fmt: skip
        shape(link, how)
        for ns, ifname in veths:
            _wait_carrier(ns, ifname)
        yield link
    finally:
        if link.delayline is not None:
            link.delayline.stop()
        for ns in link.namespaces():
            _run("ip", "netns", "delete", ns, check=False)


def in_ns(ns: str, *argv: str) -> list[str]:
    """argv run inside namespace ns (a Python module or script: `sys.executable` first)."""
    return ["ip", "netns", "exec", ns, *argv]
