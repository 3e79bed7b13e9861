"""Arguments of the PUMA proxy's methods and fields of its streamed commands: validation.

Every value a caller sends is checked here before any arithmetic (PROTOCOL.md §4 conventions):
a bad one raises `RpcError("bad_request")` naming the field, and is never echoed in full
(`short`).
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from typing import Any, Literal, get_args

import numpy as np
from numpy.typing import NDArray

from services.bus.bounds import short
from services.bus.errors import RpcError
from services.geometry import rotation_problem

Vec = NDArray[np.float64]
RelFrame = Literal["world", "wrist", "tool"]
REL_FRAMES: tuple[str, ...] = get_args(RelFrame)


def is_number(x: Any) -> bool:
    return isinstance(x, int | float) and not isinstance(x, bool)


def opt_vector(args: Mapping[str, Any], key: str, n: int) -> Vec | None:
    """`args[key]` as n finite floats, None if absent, or RpcError("bad_request") naming it."""
    if args.get(key) is None:
        return None
    value = args[key]
    if not isinstance(value, list | tuple) or len(value) != n:
        raise RpcError("bad_request", f"{key}: expected {n} numbers, got {short(value, 80)}")
    if not all(is_number(x) for x in value):
        raise RpcError("bad_request", f"{key}: every element must be a number")
    arr = np.array(value, dtype=np.float64)
    if not np.all(np.isfinite(arr)):
        raise RpcError("bad_request", f"{key}: not finite")
    return arr


def arg_vector(args: Mapping[str, Any], key: str, n: int) -> Vec:
    """`args[key]` as n finite floats, or RpcError("bad_request") naming the field."""
    v = opt_vector(args, key, n)
    if v is None:
        raise RpcError("bad_request", f"{key}: missing ({n} numbers)")
    return v


def opt_rotation(args: Mapping[str, Any], key: str) -> Vec | None:
    """`args[key]` as a rotation from 9 floats row-major, None if absent, or
    RpcError("bad_request") naming the field."""
    flat = opt_vector(args, key, 9)
    if flat is None:
        return None
    R = flat.reshape(3, 3)
    why = rotation_problem(R)
    if why is not None:
        raise RpcError("bad_request", f"{key}: {why}")
    return R


def arg_rotation(args: Mapping[str, Any], key: str) -> Vec:
    R = opt_rotation(args, key)
    if R is None:
        raise RpcError("bad_request", f"{key}: missing (9 numbers, row-major)")
    return R


def opt_frame(args: Mapping[str, Any], key: str = "frame") -> RelFrame | None:
    """`args[key]` as world | wrist | tool, None if absent, or RpcError("bad_request")."""
    value = args.get(key)
    if value is None:
        return None
    if value == "world" or value == "wrist" or value == "tool":
        return value
    raise RpcError(
        "bad_request", f"{key}: must be one of {', '.join(REL_FRAMES)}, got {short(value, 40)}"
    )


def arg_config(args: Mapping[str, Any], key: str = "config") -> str | None:
    c = args.get(key)
    if c is None:
        return None
    if not (isinstance(c, str) and len(c) == 3 and c[0] in "rl" and c[1] in "ud" and c[2] in "pm"):
        raise RpcError("bad_request", f"{key}: must be 3 letters r|l, u|d, p|m, got {short(c, 40)}")
    return c


def arg_fraction(args: Mapping[str, Any], key: str) -> float:
    x = args.get(key)
    if x is None:
        return 1.0
    if not is_number(x) or not math.isfinite(x) or not 0.0 < x <= 1.0:
        raise RpcError("bad_request", f"{key}: must be a number in (0, 1], got {short(x, 40)}")
    return float(x)


def too_long(v: Vec, max_norm: float) -> bool:
    """‖v‖ > max_norm, without overflowing on absurd values (plain floats: it checks every
    streamed command)."""
    x: list[float] = np.asarray(v, dtype=np.float64).reshape(-1).tolist()
    return max(map(abs, x), default=0.0) > max_norm or math.hypot(*x) > max_norm
