"""franky-sim as a subprocess: an independent implementation of libfranka's network protocol
(server version 10, TCP 1337, UDP state at 1 kHz of its own clock, the hand on 1338) with
MuJoCo and an FR3 inside, on a loopback address. For the tests, the bench and a person
trying the libfranka driver without a robot (docs/franka.md).

It must run in a process of its own: pylibfranka deadlocks with it in the same process
(both keep the interpreter lock while they wait), and `franky` and `pylibfranka` cannot be
imported together. Its MuJoCo simulator is the one that works here (`--simulator mujoco`;
the default crashes); it runs slower than real time on a loaded machine rather than miss
cycles, so whoever drives it asserts order, counts and positions, never timing.
"""

from __future__ import annotations

import contextlib
import os
import random
import select
import shutil
import subprocess
import sys
import time
from pathlib import Path
from typing import IO

READY_LINE = "Connect to the server using '"
START_TIMEOUT_S = 60.0


class FrankySim:
    """A running franky-sim (or a script that speaks like it); `host` is its address."""

    def __init__(self, argv: list[str], host: str, timeout_s: float = START_TIMEOUT_S) -> None:
        self.argv = argv
        self.proc = subprocess.Popen(
            argv,
            stdin=subprocess.PIPE,
            stdout=subprocess.PIPE,
            stderr=subprocess.STDOUT,
            text=True,
            bufsize=1,
        )
        self.host = host
        self.output: list[str] = []
        out: IO[str] = self.proc.stdout  # type: ignore[assignment]
        deadline = time.monotonic() + timeout_s
        while True:
            left = deadline - time.monotonic()
            if left <= 0 or self.proc.poll() is not None:
                self.kill()
                raise RuntimeError(
                    f"franky-sim did not start on {host}: " + " | ".join(self.output[-5:])
                )
            r, _, _ = select.select([out], [], [], min(left, 0.5))
            if not r:
                continue
            line = out.readline()
            self.output.append(line.rstrip())
            if READY_LINE in line:
                self.host = line.split(READY_LINE, 1)[1].split("'", 1)[0]
                break

    def send(self, line: str) -> None:
        """A line to the process's stdin (the fault-injecting test server reads it)."""
        stdin: IO[str] = self.proc.stdin  # type: ignore[assignment]
        stdin.write(line.rstrip("\n") + "\n")
        stdin.flush()

    @property
    def alive(self) -> bool:
        return self.proc.poll() is None

    def kill(self) -> None:
        """SIGKILL: the robot vanishes mid-whatever (no goodbye on the wire)."""
        if self.proc.poll() is None:
            self.proc.kill()
        self.proc.wait(10.0)
        close_pipes(self.proc)

    def close(self) -> None:
        if self.proc.poll() is None:
            self.proc.terminate()
            with contextlib.suppress(subprocess.TimeoutExpired):
                self.proc.wait(5.0)
        self.kill()


def close_pipes(proc: subprocess.Popen[str]) -> None:
    """Close a child's stdin and stdout (it has ended, or is about to)."""
    for f in (proc.stdin, proc.stdout):
        if f is not None:
            with contextlib.suppress(OSError):
                f.close()


def loopback_host() -> str:
    """A random 127.x.y.z address (not 127.0.0.x): franky-sim binds 1337 and 1338 on it, so
    concurrent runs do not meet."""
    r = random.Random(os.getpid() ^ time.monotonic_ns())
    return f"127.{r.randint(16, 250)}.{r.randint(0, 255)}.{r.randint(1, 254)}"


def franky_sim_argv(host: str) -> list[str]:
    """franky-sim's command line: MuJoCo, on `host`."""
    exe = shutil.which("franky-sim") or str(Path(sys.executable).with_name("franky-sim"))
    return [exe, "--simulator", "mujoco", "--hostname", host]


def start_franky_sim(host: str | None = None, argv: list[str] | None = None) -> FrankySim:
    """franky-sim on `host` (default: a random loopback address), started and ready."""
    host = host or loopback_host()
    return FrankySim(argv or franky_sim_argv(host), host)
