"""One line of status for a master driven from a terminal (the keyboard jog).

The operator must see at a glance whether the slave follows: engaged or in master-shift
(the keyboard starts in master-shift), the scale and frame, the grip, and the decision
server's last word about this master (a hold, a refusal, a limit) — with what to do about
it. `render` is pure; `TerminalStatus` writes it in place (carriage return, no newline) at
most `rate_hz` times a second and only when it changed, or as a plain line when the output
is not a terminal.
"""

from __future__ import annotations

import os
import time
from dataclasses import dataclass

from services.bus.bounds import short

KEYS_HINT = "wasd rf move · ijkl uo turn · space engage · g grip · x stop"
WIDTH = 120


@dataclass(frozen=True, slots=True)
class StatusInfo:
    """What the line shows. `notice` is the decision's last word about this master (kind,
    message), or None."""

    device: str
    engaged: bool
    scale_t: float
    scale_r: float
    frame: str
    grip: float | None
    notice: tuple[str, str] | None = None


#: what an operator does about each kind of intervention the decision reports
ADVICE: dict[str, str] = {
    "watchdog": "held: engage again (space twice)",
    "lease": "another master leads, or this engagement was held: engage again",
    "limit": "a limit held the motion back",
    "contact": "contact: motion into it stopped",
    "estop": "E-STOP latched: reset it first",
    "busy": "a task runs: wait or cancel it",
    "rejected": "refused: engage again",
}


def render(info: StatusInfo, width: int = WIDTH) -> str:
    """The status line (at most `width` characters)."""
    mode = "ENGAGED" if info.engaged else "SHIFT: slave holds"
    grip = "" if info.grip is None else f" · grip {'closed' if info.grip >= 0.5 else 'open'}"
    parts = [mode, f"scale {info.scale_t:.2f}/{info.scale_r:.2f} · {info.frame}{grip}"]
    if info.notice is not None:
        kind, message = info.notice
        parts.append(f"{ADVICE.get(kind, kind)} ({short(message, 60)})")
    else:
        parts.append(KEYS_HINT)
    return " | ".join(parts)[:width]


class TerminalStatus:
    """Writes the line to file descriptor `fd`: in place on a terminal, as whole lines (on
    change, at most once a second) elsewhere."""

    def __init__(self, fd: int, rate_hz: float = 5.0) -> None:
        self._fd = fd
        self._tty = os.isatty(fd)
        self._period_s = 1.0 / rate_hz if self._tty else 1.0
        self._last_s = -1e9
        self._last = ""

    def show(self, info: StatusInfo, now_s: float | None = None) -> bool:
        """Write the line if it changed and the rate allows; whether it was written."""
        now = time.monotonic() if now_s is None else now_s
        line = render(info)
        if line == self._last or now - self._last_s < self._period_s:
            return False
        self._last, self._last_s = line, now
        text = f"\r{line:<{WIDTH}}" if self._tty else f"{line}\n"
        try:
            os.write(self._fd, text.encode())
        except OSError:
            return False
        return True
