"""A terminal jog for laptops: keys → hand velocity on the 6 axes.

Terminals report key presses, not releases, and auto-repeat a held key after a delay of
~0.5 s; so a press drives its axis at full speed for `hold_s` after the latest press, which
bridges the repeat delay and stops the hand shortly after the key is let go.

Key map (master frame: x right, y away from the operator, z up):

    w / s   +y / −y        ↑ / ↓   +y / −y
    d / a   +x / −x        → / ←   +x / −x
    r / f   +z / −z
    i / k   +rx / −rx      l / j   +ry / −ry      u / o   +rz / −rz
    space   master-shift on/off (starts ON: the slave holds until the first space)
    g       grip open/closed
    x       stop every axis now
"""

from __future__ import annotations

import os
import select
import sys
from collections.abc import Mapping
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

from services.control.master.config import positive, string
from services.control.master.device import (
    DeviceLost,
    DeviceNotFound,
    DeviceOptions,
    HandReading,
    MasterDevice,
)
from services.control.master.jog import HandIntegrator, RateScale
from services.control.master.status_line import StatusInfo, TerminalStatus

if TYPE_CHECKING:
    from services.control.master.config import MasterConfig

KEY_AXES: Mapping[str, tuple[int, float]] = {
    "d": (0, +1.0),
    "a": (0, -1.0),
    "right": (0, +1.0),
    "left": (0, -1.0),
    "w": (1, +1.0),
    "s": (1, -1.0),
    "up": (1, +1.0),
    "down": (1, -1.0),
    "r": (2, +1.0),
    "f": (2, -1.0),
    "i": (3, +1.0),
    "k": (3, -1.0),
    "l": (4, +1.0),
    "j": (4, -1.0),
    "u": (5, +1.0),
    "o": (5, -1.0),
}
"""Key → (axis index in tx, ty, tz, rx, ry, rz; direction)."""

CLUTCH_KEY = " "
GRIP_KEY = "g"
STOP_KEY = "x"
_ARROWS = {b"A": "up", b"B": "down", b"C": "right", b"D": "left"}


def parse_keys(data: bytes) -> list[str]:
    """Split raw terminal input into keys: single characters (lower-cased) and the arrow
    keys' escape sequences (ESC [ A…D → 'up', 'down', 'right', 'left'). Other escape
    sequences are dropped whole."""
    keys: list[str] = []
    i = 0
    while i < len(data):
        byte = data[i : i + 1]
        if byte == b"\x1b":
            if data[i + 1 : i + 2] in (b"[", b"O"):
                j = i + 2
                while j < len(data) and not 0x40 <= data[j] <= 0x7E:
                    j += 1
                final = data[j : j + 1]
                if final in _ARROWS and j == i + 2:
                    keys.append(_ARROWS[final])
                i = j + 1
            else:
                i += 1
            continue
        keys.append(byte.decode("latin-1").lower())
        i += 1
    return keys


@dataclass(frozen=True, slots=True)
class KeyAction:
    """What one key does: jog an axis, toggle the clutch or grip, stop, or nothing."""

    kind: str
    axis: int = -1
    direction: float = 0.0


def key_action(key: str) -> KeyAction:
    """The pure key → action mapping (see the module docstring)."""
    if key in KEY_AXES:
        axis, direction = KEY_AXES[key]
        return KeyAction("jog", axis, direction)
    if key == CLUTCH_KEY:
        return KeyAction("clutch")
    if key == GRIP_KEY:
        return KeyAction("grip")
    if key == STOP_KEY:
        return KeyAction("stop")
    return KeyAction("none")


class KeyJogState:
    """Clutch, grip and per-axis hold timers driven by key presses (pure: time is given)."""

    def __init__(self, hold_s: float = 0.5) -> None:
        if hold_s <= 0.0:
            raise ValueError("hold_s must be > 0")
        self.hold_s = hold_s
        self.clutch = True
        self.grip = 0.0
        self._direction = np.zeros(6)
        self._until_s = np.full(6, -np.inf)

    def press(self, key: str, t_s: float) -> KeyAction:
        """Apply one key pressed at time t_s (s)."""
        action = key_action(key)
        if action.kind == "jog":
            self._direction[action.axis] = action.direction
            self._until_s[action.axis] = t_s + self.hold_s
        elif action.kind == "clutch":
            self.clutch = not self.clutch
            self.stop()
        elif action.kind == "grip":
            self.grip = 1.0 - self.grip
        elif action.kind == "stop":
            self.stop()
        return action

    def stop(self) -> None:
        """Every axis to rest now."""
        self._until_s[:] = -np.inf

    def deflection(self, t_s: float) -> NDArray[np.float64]:
        """Deflections (tx … rz, each −1, 0 or +1) at time t_s."""
        return np.where(self._until_s > t_s, self._direction, 0.0)


@dataclass(frozen=True, slots=True)
class KeyboardOptions(DeviceOptions):
    """`device = "keyboard"`: its `[master]` keys.

    port: the terminal to read ("" = standard input).
    sensitivity: multiplier on the jog speeds, > 0.
    """

    port: str = ""
    sensitivity: float = 1.0

    def __post_init__(self) -> None:
        string(self, "port")
        positive(self, "sensitivity")

    def build(self, config: MasterConfig) -> MasterDevice:
        return KeyboardMaster(self.port or None, sensitivity=self.sensitivity)


class KeyboardMaster:
    """Keyboard jog as a `MasterDevice` (reads a tty without blocking; no force display).

    tty_path: the terminal to read (None: this process's stdin). fd: an already open file
    descriptor to read instead (tests pass a pty). The terminal is put in cbreak mode while
    open (keys arrive without Enter, Ctrl-C still works) and restored on close().
    status_fd: where the one-line status goes (`show_status`; default: standard error).
    """

    def __init__(
        self,
        tty_path: str | None = None,
        *,
        fd: int | None = None,
        sensitivity: float = 1.0,
        speed_m_s: float = 0.05,
        rate_rad_s: float = 0.3,
        hold_s: float = 0.5,
        status_fd: int | None = None,
    ) -> None:
        self._tty_path = tty_path
        self._status = TerminalStatus(sys.stderr.fileno() if status_fd is None else status_fd)
        self._given_fd = fd
        self._fd: int | None = None
        self._owns_fd = False
        self._saved_attrs: list[Any] | None = None
        self._rates = RateScale(speed_m_s * sensitivity, rate_rad_s * sensitivity)
        self._state = KeyJogState(hold_s)
        self._hand = HandIntegrator()
        self._t_s = 0.0

    @property
    def name(self) -> str:
        return "keyboard"

    @property
    def can_display_force(self) -> bool:
        return False

    def open(self) -> None:
        import termios
        import tty

        if self._given_fd is not None:
            self._fd = self._given_fd
        elif self._tty_path is not None:
            try:
                self._fd = os.open(self._tty_path, os.O_RDONLY | os.O_NONBLOCK)
            except OSError as exc:
                raise DeviceNotFound(f"cannot open terminal {self._tty_path}: {exc}") from exc
            self._owns_fd = True
        else:
            self._fd = sys.stdin.fileno()
        if os.isatty(self._fd):
            self._saved_attrs = termios.tcgetattr(self._fd)
            tty.setcbreak(self._fd)
        self._state = KeyJogState(self._state.hold_s)
        self._hand.reset()
        self._t_s = 0.0

    def read(self, dt_s: float) -> HandReading:
        if self._fd is None:
            raise DeviceLost("keyboard is not open")
        self._t_s += max(float(dt_s), 0.0)
        while select.select([self._fd], [], [], 0.0)[0]:
            try:
                data = os.read(self._fd, 1024)
            except BlockingIOError:
                break
            if not data:
                break
            for key in parse_keys(data):
                self._state.press(key, self._t_s)
        if not self._state.clutch:
            v, w = self._rates.twist(self._state.deflection(self._t_s))
            self._hand.step(v, w, dt_s)
        p, R = self._hand.pose
        return HandReading(p, R, self._state.clutch, self._state.grip, 0)

    def display_force(self, f: ArrayLike, c: ArrayLike) -> None:
        """A keyboard cannot push back: nothing to do."""

    def show_status(self, info: StatusInfo) -> None:
        """The station's status on the terminal, one line (see status_line.py)."""
        self._status.show(info)

    def close(self) -> None:
        if self._fd is None:
            return
        if self._saved_attrs is not None:
            import termios

            termios.tcsetattr(self._fd, termios.TCSADRAIN, self._saved_attrs)
            self._saved_attrs = None
        if self._owns_fd:
            os.close(self._fd)
        self._fd = None
        self._owns_fd = False
