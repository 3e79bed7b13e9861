"""Process lifecycle: SIGINT/SIGTERM become a stop flag, so every service runs its `finally`."""

from __future__ import annotations

import faulthandler
import logging
import signal
import threading
from types import FrameType

#: after a stop signal, a process that has not exited by then dumps every thread's stack
#: to stderr and exits (status 1): an exit hang is reported, never left running.
EXIT_GRACE_S = 15.0


class Shutdown:
    """Set on SIGINT or SIGTERM (installed from the main thread). `wait()` sleeps until then.

    Services poll `is_set()` in their loops and leave through their `finally` blocks, which
    hold the arm and close the Zenoh session. A signal also arms a last-resort timer: a
    process still there `grace_s` (default `EXIT_GRACE_S`) later prints every thread's
    stack and exits. A process whose orderly stop takes longer by design (the launcher
    stops its children one by one) raises `grace_s` before any signal can come.
    """

    def __init__(self, install: bool = True, grace_s: float = EXIT_GRACE_S) -> None:
        self._event = threading.Event()
        self.signal: int | None = None
        self.grace_s = grace_s
        if install and threading.current_thread() is threading.main_thread():
            signal.signal(signal.SIGINT, self._handle)
            signal.signal(signal.SIGTERM, self._handle)

    def _handle(self, signum: int, frame: FrameType | None) -> None:
        self.signal = signum
        if not self._event.is_set():
            faulthandler.dump_traceback_later(self.grace_s, exit=True)
        self._event.set()

    def set(self) -> None:
        self._event.set()

    def is_set(self) -> bool:
        return self._event.is_set()

    def wait(self, timeout_s: float | None = None) -> bool:
        return self._event.wait(timeout_s)


def setup_logging(name: str, verbose: bool = False) -> logging.Logger:
    """One log format for every service: time, level, service, message."""
    logging.basicConfig(
        level=logging.DEBUG if verbose else logging.INFO,
        format=f"%(asctime)s %(levelname)-7s {name}: %(message)s",
    )
    return logging.getLogger(f"telerobot.{name}")
