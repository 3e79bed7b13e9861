"""`wait_until`: poll a condition to a deadline, with an answer that says what it waited for.

The one waiting helper of the tools and the tests (never a bare sleep as synchronisation):
for state with no condition to wait on — a process's output, a port, a status on the bus.
"""

from __future__ import annotations

import time
from collections.abc import Callable


class Waited:
    """What `wait_until` saw: truthy iff the condition held before the deadline.

    Its repr names the condition and the deadline, so a bare `assert wait_until(...)`
    fails with a message that says what never happened (and `assert not wait_until(...)`
    says what happened when it should not have).
    """

    __slots__ = ("elapsed_s", "held", "timeout_s", "what")

    def __init__(self, held: bool, what: str, timeout_s: float, elapsed_s: float) -> None:
        self.held, self.what = held, what
        self.timeout_s, self.elapsed_s = timeout_s, elapsed_s

    def __bool__(self) -> bool:
        return self.held

    def __repr__(self) -> str:
        if self.held:
            return f"<{self.what} held after {self.elapsed_s:.2f} s>"
        return f"<timed out: {self.what} still false after {self.timeout_s:g} s>"


def _describe(pred: Callable[[], object]) -> str:
    """A name for a condition: its function name, or where a lambda was written."""
    code = getattr(pred, "__code__", None)
    name = getattr(pred, "__qualname__", None) or repr(pred)
    if code is None or name.rpartition(".")[2] != "<lambda>":
        return name
    return f"lambda at {code.co_filename.rpartition('/')[2]}:{code.co_firstlineno}"


def wait_until(
    pred: Callable[[], object],
    timeout_s: float = 10.0,
    poll_s: float = 0.005,
    *,
    what: str | None = None,
) -> Waited:
    """Poll `pred` until it holds or `timeout_s` passes.

    Use as `assert wait_until(cond, 5.0, what="the arm at rest")`: the answer is truthy iff
    `pred` held, and a failure names `what` (or the condition) and the deadline. In the
    tests the deadline is generous on purpose (two shared, loaded cores); it bounds a
    failure, it never measures speed.
    """
    start = time.monotonic()
    deadline = start + timeout_s
    while not pred():
        if time.monotonic() >= deadline:
            # One last look: a poll that slept past the deadline must not miss a late truth.
            held = bool(pred())
            return Waited(held, what or _describe(pred), timeout_s, time.monotonic() - start)
        time.sleep(poll_s)
    return Waited(True, what or _describe(pred), timeout_s, time.monotonic() - start)
