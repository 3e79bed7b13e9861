"""The Haply Inverse Service's simulation channel (JSON over a WebSocket), as pure functions.

What the service sends (docs.haply.co, "WebSocket Protocol" and "Simulation Channel",
service 3.5; see docs/master.md for each message's source and what we could not confirm):

- On connect, one *inventory*: `session_id` and, per device type, a list of devices, each
  `{"device_id", "config", "state", "status"}`. Later *state updates* have the same lists
  without `config`, exactly one per message the client sends.
- `inverse3[i].state.cursor_position {x, y, z}`: the cursor in m, Haply's right-handed frame
  (+x right, +y forward, away from the operator, +z up).
- `wireless_verse_grip[i].state.orientation {w, x, y, z}`: the grip's unit quaternion in the
  same frame; `.state.buttons {a, b, c}`: booleans.

What the client sends: `{"inverse3": [{"device_id", "commands": {"set_cursor_force":
{"values": {x, y, z}}}}]}` (N, same frame), optionally with a one-shot `"session":
{"configure": {...}}` on the first message.

Everything received is checked before use: a frame that is not JSON, misses a field we use,
has a wrong type, a NaN or an infinity, an absurd magnitude or too many devices raises
`ProtocolError` naming the field; fields we do not use are ignored.
"""

from __future__ import annotations

import json
import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import NDArray

from services.bus.errors import ProtocolError

DEFAULT_URL = "ws://localhost:10001"
"""The Inverse Service's simulation channel on the operator's machine (its default port)."""

MAX_MESSAGE_BYTES = 256 * 1024
"""Largest frame accepted. An inventory of a few devices is a few kB."""

MAX_POSITION_M = 1.0
"""A cursor farther than this from the device origin on any axis is absurd: the Inverse3
reaches about ±0.2 m."""

QUATERNION_NORM_TOL = 0.1
"""A grip quaternion whose norm is off 1 by more than this is refused, not renormalised:
the service quantises its components (norms of 0.9998 are normal), garbage is farther off."""

MAX_DEVICES = 16
"""More devices of one type in a frame than this is refused as a hostile frame."""

MAX_ID_CHARS = 64

BUTTONS = ("a", "b", "c")
"""VerseGrip buttons; bit i of `GripState.buttons` is BUTTONS[i]."""

GRIP_LIST = "wireless_verse_grip"
INVERSE3_LIST = "inverse3"


@dataclass(frozen=True, slots=True)
class CursorState:
    """One Inverse3's cursor: `position_m` (x, y, z) in m, Haply frame."""

    device_id: str
    position_m: tuple[float, float, float]


@dataclass(frozen=True, slots=True)
class GripState:
    """One wireless VerseGrip: unit quaternion `orientation_wxyz` (Haply frame) and the
    buttons as a bitmask (bit 0 = a, bit 1 = b, bit 2 = c)."""

    device_id: str
    orientation_wxyz: tuple[float, float, float, float]
    buttons: int


@dataclass(frozen=True, slots=True)
class ServiceFrame:
    """What we use of one inventory or state update."""

    session_id: int | None
    inverse3: tuple[CursorState, ...]
    grips: tuple[GripState, ...]

    def cursor(self, device_id: str) -> CursorState | None:
        """The Inverse3 `device_id` in this frame, or None."""
        return next((c for c in self.inverse3 if c.device_id == device_id), None)

    def grip(self, device_id: str) -> GripState | None:
        """The VerseGrip `device_id` in this frame, or None."""
        return next((g for g in self.grips if g.device_id == device_id), None)


def _reject_constant(name: str) -> Any:
    # Python's json reads NaN, Infinity and -Infinity, which JSON does not allow.
    raise ProtocolError("frame", f"non-finite number {name}")


def _mapping(value: object, field: str) -> Mapping[str, Any]:
    if not isinstance(value, dict):
        raise ProtocolError(field, f"must be an object, got {type(value).__name__}")
    return value


def _number(value: object, field: str, bound: float) -> float:
    if isinstance(value, bool) or not isinstance(value, int | float):
        raise ProtocolError(field, f"must be a number, got {type(value).__name__}")
    x = float(value)
    if not math.isfinite(x):
        raise ProtocolError(field, "must be finite")
    if abs(x) > bound:
        raise ProtocolError(field, f"{x:.3g} is beyond ±{bound:g}")
    return x


def _components(value: object, field: str, names: str, bound: float) -> tuple[float, ...]:
    m = _mapping(value, field)
    return tuple(_number(m.get(k), f"{field}.{k}", bound) for k in names)


def _device_id(entry: Mapping[str, Any], field: str) -> str:
    value = entry.get("device_id")
    if not isinstance(value, str) or not 0 < len(value) <= MAX_ID_CHARS:
        raise ProtocolError(f"{field}.device_id", f"must be a string of 1 … {MAX_ID_CHARS}")
    return value


def _entries(frame: Mapping[str, Any], key: str) -> Sequence[Any]:
    value = frame.get(key, [])
    if not isinstance(value, list):
        raise ProtocolError(key, "must be a list")
    if len(value) > MAX_DEVICES:
        raise ProtocolError(key, f"{len(value)} devices, at most {MAX_DEVICES}")
    return value


def _cursor(entry: object, field: str) -> CursorState:
    e = _mapping(entry, field)
    state = _mapping(e.get("state"), f"{field}.state")
    x, y, z = _components(
        state.get("cursor_position"), f"{field}.state.cursor_position", "xyz", MAX_POSITION_M
    )
    return CursorState(_device_id(e, field), (x, y, z))


def _grip(entry: object, field: str) -> GripState:
    e = _mapping(entry, field)
    state = _mapping(e.get("state"), f"{field}.state")
    w, x, y, z = _components(state.get("orientation"), f"{field}.state.orientation", "wxyz", 2.0)
    norm = math.sqrt(w * w + x * x + y * y + z * z)
    if abs(norm - 1.0) > QUATERNION_NORM_TOL:
        raise ProtocolError(f"{field}.state.orientation", f"norm {norm:.3g} is not 1")
    # A grip that reports no buttons has none pressed: the dead-man stays released.
    pressed = _mapping(state.get("buttons", {}), f"{field}.state.buttons")
    mask = 0
    for bit, name in enumerate(BUTTONS):
        value = pressed.get(name, False)
        if not isinstance(value, bool):
            raise ProtocolError(f"{field}.state.buttons.{name}", "must be true or false")
        mask |= int(value) << bit
    return GripState(_device_id(e, field), (w / norm, x / norm, y / norm, z / norm), mask)


def parse_frame(data: str | bytes, max_bytes: int = MAX_MESSAGE_BYTES) -> ServiceFrame:
    """Decode and check one frame from the service (inventory or state update).

    Raises ProtocolError (with the offending field) for anything we cannot trust.
    """
    if len(data) > max_bytes:
        raise ProtocolError("frame", f"{len(data)} bytes, at most {max_bytes}")
    try:
        text = data.decode("utf-8") if isinstance(data, bytes) else data
        frame = json.loads(text, parse_constant=_reject_constant)
    except ProtocolError:
        raise
    except (ValueError, RecursionError) as e:  # bad JSON, bad UTF-8, 10⁵-digit integers, nesting
        raise ProtocolError("frame", f"not JSON: {str(e)[:120]}") from None
    top = _mapping(frame, "frame")
    session = top.get("session_id")
    if session is not None and (
        isinstance(session, bool) or not isinstance(session, int) or not 0 <= session < 2**53
    ):
        raise ProtocolError("session_id", "must be an integer ≥ 0")
    cursors = tuple(
        _cursor(e, f"{INVERSE3_LIST}[{i}]") for i, e in enumerate(_entries(top, INVERSE3_LIST))
    )
    grips = tuple(_grip(e, f"{GRIP_LIST}[{i}]") for i, e in enumerate(_entries(top, GRIP_LIST)))
    return ServiceFrame(session, cursors, grips)


def force_message(
    inverse3_id: str,
    force_n: Sequence[float] | NDArray[np.float64],
    session_configure: Mapping[str, Any] | None = None,
) -> str:
    """The client message that sets the cursor force of `inverse3_id` to `force_n` (N, Haply
    frame), with an optional one-shot `session.configure` block. ValueError if not finite."""
    fx, fy, fz = (float(v) for v in force_n)
    if not (math.isfinite(fx) and math.isfinite(fy) and math.isfinite(fz)):
        raise ValueError("force must be finite")
    message: dict[str, Any] = {
        INVERSE3_LIST: [
            {
                "device_id": inverse3_id,
                "commands": {"set_cursor_force": {"values": {"x": fx, "y": fy, "z": fz}}},
            }
        ]
    }
    if session_configure:
        message["session"] = {"configure": dict(session_configure)}
    return json.dumps(message, separators=(",", ":"))
