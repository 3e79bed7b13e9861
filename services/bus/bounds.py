"""Physical bounds: every magnitude an input may carry, with its unit, in one table.

A value can be a valid float and still absurd: `dp = [1e308, 0, 0]` is finite, and the
arithmetic it meets (a rotation, a norm, a sum) overflows to inf or NaN. Every entry of a
service (a stream, a method argument, a configuration key) checks its magnitudes against
this table **before** any such arithmetic, and refuses what is outside with an error that
names the field and the bound. The bounds are generous for the arms we ship (the tool point
within 1.9 m of the world origin, tool ≤ 1 m; `position_m` ±5 m) and tight enough that no
product of two in-bound values can overflow.

Sizes: a payload or a method's arguments above `MAX_PAYLOAD_BYTES` are refused before
they are decoded (stereo frames have their own cap, `MAX_FRAME_BYTES`), and no reply,
event or log line repeats more than `MAX_ECHO_CHARS` of what it refuses.
"""

from __future__ import annotations

import math
import reprlib
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import NoReturn

from services.bus.errors import ConfigError, ErrorCode, RpcError

MAX_PAYLOAD_BYTES = 64 * 1024
"""A message on any key but the stereo frames, or one call's arguments (bytes)."""
MAX_ECHO_CHARS = 160
"""The longest piece of a refused input (or of a message about it) a reply, event or log
line may carry."""


@dataclass(frozen=True, slots=True)
class Bound:
    """A closed interval [lo, hi] in `unit`; `what` says what it bounds, for people."""

    lo: float
    hi: float
    unit: str
    what: str


#: name → bound. Names are the kinds of quantity; a field says which kind it is.
BOUNDS: dict[str, Bound] = {
    "displacement_m": Bound(0.0, 2.0, "m", "a motion since an engagement, or one relative move"),
    "position_m": Bound(-5.0, 5.0, "m", "a point in the world frame, per axis"),
    "tool_offset_m": Bound(0.0, 1.0, "m", "the tool point's distance from the flange"),
    "distance_m": Bound(0.0, 2.0, "m", "a travel or a height"),
    "direction": Bound(1e-6, 1e6, "", "the length of a direction before it is normalised"),
    "speed_m_s": Bound(0.0, 2.0, "m/s", "a tool speed"),
    "rot_speed_rad_s": Bound(0.0, 10.0, "rad/s", "a tool turn rate"),
    "joint_speed_rad_s": Bound(0.0, 10.0, "rad/s", "a joint speed"),
    "joint_accel_rad_s2": Bound(0.0, 100.0, "rad/s²", "a joint acceleration"),
    "joint_rad": Bound(-2.0 * math.pi, 2.0 * math.pi, "rad", "a joint angle"),
    "force_n": Bound(0.0, 5000.0, "N", "a force threshold"),
    "torque_nm": Bound(0.0, 500.0, "N·m", "a moment threshold"),
    "stiffness_n_m": Bound(1.0, 1e8, "N/m", "a stiffness"),
    "stiffness_nm_rad": Bound(1e-3, 1e6, "N·m/rad", "a rotational stiffness"),
    "admittance_m_n_s": Bound(0.0, 1.0, "m/(N·s)", "an admittance gain"),
    "admittance_rad_nm_s": Bound(0.0, 10.0, "rad/(N·m·s)", "a rotational admittance gain"),
    "timeout_s": Bound(0.0, 3600.0, "s", "a timeout"),
    "duration_s": Bound(0.0, 3600.0, "s", "a duration"),
    "period_ms": Bound(0.1, 1000.0, "ms", "a sampling or loop period"),
    "watchdog_ms": Bound(1.0, 60_000.0, "ms", "a watchdog or staleness window"),
    "rate_hz": Bound(1.0, 10_000.0, "Hz", "a loop or stream rate"),
    "fraction": Bound(0.0, 1.0, "", "a fraction"),
}


_REPR = reprlib.Repr()
_REPR.maxlevel = 3
_REPR.maxstring = _REPR.maxother = _REPR.maxlong = MAX_ECHO_CHARS // 2


def short(text: object, limit: int = MAX_ECHO_CHARS) -> str:
    """`text` as a string of at most `limit` characters (…and how much was cut). Anything
    but a string is shown by a bounded repr: a value nested 1000 deep or 10 MB long costs
    no more than a short one."""
    s = text if isinstance(text, str) else _REPR.repr(text)
    if len(s) <= limit:
        return s
    return f"{s[:limit]}… ({len(s) - limit} more characters)"


def out_of_bounds(field: str, value: float, kind: str) -> str | None:
    """Why `value` is outside the bound of `kind` (None if inside): names the field."""
    b = BOUNDS[kind]
    if math.isfinite(value) and b.lo <= value <= b.hi:
        return None
    unit = f" {b.unit}" if b.unit else ""
    return f"{field}: {value:.6g}{unit} is outside [{b.lo:g}, {b.hi:g}]{unit} ({b.what})"


def refuse(why: str, code: ErrorCode) -> NoReturn:
    """Raise the refusal, RpcError(code); `why` starts with the field's name. (A value out
    of bounds does not break the wire contract, so it is no ProtocolError.)"""
    raise RpcError(code, why)


def check(field: str, value: float, kind: str, code: ErrorCode = "bad_request") -> float:
    """`value` if it lies within the bound of `kind`, else refused (`refuse`)."""
    why = out_of_bounds(field, value, kind)
    if why is not None:
        refuse(why, code)
    return value


def norm_out_of_bounds(field: str, v: Sequence[float], kind: str) -> str | None:
    """Why the length of vector `v` is outside the bound of `kind` (None if inside),
    without overflowing: every component is checked first, so the squares stay finite."""
    b = BOUNDS[kind]
    limit = max(abs(b.lo), abs(b.hi))
    for i, x in enumerate(v):
        if not math.isfinite(x) or abs(x) > limit:
            return f"{field}[{i}]: {x:.6g} exceeds {limit:g} {b.unit} ({b.what})".rstrip()
    return out_of_bounds(f"|{field}|", math.sqrt(math.fsum(x * x for x in v)), kind)


def check_norm(
    field: str, v: Sequence[float], kind: str, code: ErrorCode = "bad_request"
) -> Sequence[float]:
    """`v` if its length lies within the bound of `kind`, else RpcError(code)."""
    why = norm_out_of_bounds(field, v, kind)
    if why is not None:
        refuse(why, code)
    return v


def each_out_of_bounds(field: str, v: Sequence[float], kind: str) -> str | None:
    """Why a component of `v` is outside the bound of `kind` (None if all are inside)."""
    for i, x in enumerate(v):
        why = out_of_bounds(f"{field}[{i}]", x, kind)
        if why is not None:
            return why
    return None


def check_each(
    field: str, v: Sequence[float], kind: str, code: ErrorCode = "bad_request"
) -> Sequence[float]:
    """`v` if every component lies within the bound of `kind`, else RpcError(code)."""
    why = each_out_of_bounds(field, v, kind)
    if why is not None:
        refuse(why, code)
    return v


def check_config(section: str, cfg: object, kinds: Mapping[str, str]) -> None:
    """Every field named in `kinds` of a configuration (a number, or a tuple of numbers
    checked one by one) lies within its bound, else ConfigError naming `section.field`."""
    for name, kind in kinds.items():
        value = getattr(cfg, name)
        items = value if isinstance(value, tuple | list) else (value,)
        for i, x in enumerate(items):
            field = (
                name if len(items) == 1 and not isinstance(value, tuple | list) else f"{name}[{i}]"
            )
            if isinstance(x, bool) or not isinstance(x, int | float):
                raise ConfigError(f"{section}.{name}", f"{field} must be a number")
            why = out_of_bounds(field, float(x), kind)
            if why is not None:
                raise ConfigError(f"{section}.{name}", why)
