"""The one module that knows bytes: strict msgpack encoding and validation (PROTOCOL.md §3).

A receiver ignores fields it does not know and rejects a message whose required fields are
missing, of the wrong type or size, or not finite, and a rotation that is not orthonormal or
is reflected. Every rejection is a `ProtocolError` that names the field. Encoding validates
too, so nothing that breaks the contract ever leaves a process of ours.

The schema is the dataclass annotations of `services.bus.messages`; method arguments are
checked with the same validators through `arg()`.
"""

from __future__ import annotations

import math
import types
import typing
from collections.abc import Callable, Mapping
from dataclasses import fields
from typing import Any, TypeVar, get_args, get_origin, get_type_hints

import msgpack
import numpy as np

from services.bus.errors import ProtocolError
from services.bus.messages import MAX_TEXT, MaxLen, Message, Range, Rotation, Size

M = TypeVar("M", bound=Message)
Validator = Callable[[str, Any], Any]

_MISSING = object()


def _number(name: str, v: Any) -> float:
    if isinstance(v, bool) or not isinstance(v, int | float):
        raise ProtocolError(name, f"expected a number, got {type(v).__name__}")
    f = float(v)
    if not math.isfinite(f):
        raise ProtocolError(name, f"not finite ({f})")
    return f


def _make_validator(tp: Any) -> Validator:
    """Build the validator for one annotation (Annotated, Literal, Optional, scalar, dict)."""
    meta: tuple[Any, ...] = ()
    if get_origin(tp) is typing.Annotated:
        tp, *rest = get_args(tp)
        meta = tuple(rest)
    size = next((m.n for m in meta if isinstance(m, Size)), None)
    rot = next((m for m in meta if isinstance(m, Rotation)), None)
    rng = next((m for m in meta if isinstance(m, Range)), None)
    max_len = next((m.n for m in meta if isinstance(m, MaxLen)), MAX_TEXT)
    origin = get_origin(tp)

    if origin is typing.Literal:
        allowed = get_args(tp)

        def literal(name: str, v: Any) -> Any:
            if not isinstance(v, str) or v not in allowed:
                raise ProtocolError(name, f"expected one of {list(allowed)}, got {v!r}")
            return v

        return literal
    if size is not None:
        n = size

        def seq(name: str, v: Any) -> tuple[float, ...]:
            if not isinstance(v, list | tuple):
                raise ProtocolError(name, f"expected {n} numbers, got {type(v).__name__}")
            if len(v) != n:
                raise ProtocolError(name, f"expected {n} numbers, got {len(v)}")
            out = tuple(_number(f"{name}[{i}]", x) for i, x in enumerate(v))
            if rot is not None:
                check_rotation(name, out, rot.tol)
            return out

        return seq
    if tp is bool:

        def boolean(name: str, v: Any) -> bool:
            if not isinstance(v, bool):
                raise ProtocolError(name, f"expected a bool, got {type(v).__name__}")
            return v

        return boolean
    if tp is int:
        lo, hi = (int(rng.lo), int(rng.hi)) if rng else (-(2**63), 2**64 - 1)

        def integer(name: str, v: Any) -> int:
            if isinstance(v, bool) or not isinstance(v, int):
                raise ProtocolError(name, f"expected an integer, got {type(v).__name__}")
            if not lo <= v <= hi:
                raise ProtocolError(name, f"{v} out of range [{lo}, {hi}]")
            return v

        return integer
    if tp is float:

        def number(name: str, v: Any) -> float:
            f = _number(name, v)
            if rng is not None and not rng.lo <= f <= rng.hi:
                raise ProtocolError(name, f"{f} out of range [{rng.lo}, {rng.hi}]")
            return f

        return number
    if tp is str:

        def text(name: str, v: Any) -> str:
            if not isinstance(v, str):
                raise ProtocolError(name, f"expected a string, got {type(v).__name__}")
            if len(v) > max_len:
                raise ProtocolError(name, f"longer than {max_len} characters")
            return v

        return text
    if tp is bytes:

        def binary(name: str, v: Any) -> bytes:
            if not isinstance(v, bytes | bytearray):
                raise ProtocolError(name, f"expected bytes, got {type(v).__name__}")
            if len(v) > max_len:
                raise ProtocolError(name, f"larger than {max_len} bytes")
            return bytes(v)

        return binary
    if origin is dict:

        def mapping(name: str, v: Any) -> dict[str, Any]:
            if not isinstance(v, dict) or not all(isinstance(k, str) for k in v):
                raise ProtocolError(name, "expected a map with string keys")
            return v

        return mapping
    raise TypeError(f"no validator for annotation {tp!r}")


def _unwrap_optional(tp: Any) -> tuple[Any, bool]:
    if get_origin(tp) in (typing.Union, types.UnionType):
        args = [a for a in get_args(tp) if a is not type(None)]
        if len(args) == 1 and len(get_args(tp)) == 2:
            return args[0], True
    return tp, False


def check_rotation(name: str, r: tuple[float, ...], tol: float = 1e-6) -> None:
    """Reject a non-orthonormal (‖RᵀR − I‖ > tol) or reflected (det R < 0) rotation."""
    R = np.asarray(r, dtype=float).reshape(3, 3)
    with np.errstate(over="ignore", invalid="ignore"):  # huge entries: err is inf, rejected
        err = float(np.linalg.norm(R.T @ R - np.eye(3)))
    if not err <= tol:
        raise ProtocolError(name, f"not a rotation: ‖RᵀR − I‖ = {err:.3g} > {tol:g}")
    if np.linalg.det(R) < 0:
        raise ProtocolError(name, "reflection: det R < 0")


class _Schema:
    __slots__ = ("cls", "entries")

    def __init__(self, cls: type[Message]) -> None:
        hints = get_type_hints(cls, include_extras=True)
        self.cls = cls
        self.entries: list[tuple[str, Validator, bool]] = []
        for f in fields(cls):
            inner, optional = _unwrap_optional(hints[f.name])
            self.entries.append((f.name, _make_validator(inner), optional))


_SCHEMAS: dict[type[Message], _Schema] = {}


def _schema(cls: type[Message]) -> _Schema:
    s = _SCHEMAS.get(cls)
    if s is None:
        s = _SCHEMAS[cls] = _Schema(cls)
    return s


def from_fields(cls: type[M], data: Mapping[str, Any]) -> M:
    """Validate a decoded map against `cls`; unknown fields are ignored (§ conventions)."""
    values: dict[str, Any] = {}
    for name, validate, optional in _schema(cls).entries:
        v = data.get(name, _MISSING)
        if v is _MISSING or v is None:
            if optional:
                values[name] = None
                continue
            raise ProtocolError(name, "missing" if v is _MISSING else "is nil")
        values[name] = validate(name, v)
    return cls(**values)


def to_fields(msg: Message) -> dict[str, Any]:
    """The validated wire map of `msg` (tuples as lists, None optionals left out)."""
    out: dict[str, Any] = {}
    for name, validate, optional in _schema(type(msg)).entries:
        v = getattr(msg, name)
        if v is None:
            if optional:
                continue
            raise ProtocolError(name, "missing")
        v = validate(name, v)
        out[name] = list(v) if isinstance(v, tuple) else v
    return out


def encode(msg: Message) -> bytes:
    """msgpack bytes of `msg`, after checking it against the contract."""
    return pack(to_fields(msg))


def decode(cls: type[M], payload: bytes) -> M:
    """The message of type `cls` in `payload`; raises ProtocolError naming the bad field."""
    data = unpack(payload)
    if not isinstance(data, dict):
        raise ProtocolError("payload", f"expected a msgpack map, got {type(data).__name__}")
    return from_fields(cls, data)


def pack(obj: Any) -> bytes:
    """msgpack with string keys and binary type, the contract's encoding."""
    return msgpack.packb(obj, use_bin_type=True, default=_default)


def unpack(payload: bytes) -> Any:
    """Decode msgpack; any malformed input becomes a ProtocolError on `payload`."""
    try:
        return msgpack.unpackb(payload, raw=False, strict_map_key=True)
    except (ValueError, TypeError, msgpack.ExtraData, msgpack.FormatError) as e:
        raise ProtocolError("payload", f"not valid msgpack ({e})") from None
    except msgpack.StackError:
        raise ProtocolError("payload", "nested too deeply") from None


def _default(obj: Any) -> Any:
    if isinstance(obj, np.ndarray):
        return obj.tolist()
    if isinstance(obj, np.generic):
        return obj.item()
    raise TypeError(f"cannot encode {type(obj).__name__}")


def arg(args: Mapping[str, Any], name: str, annotation: Any, default: Any = _MISSING) -> Any:
    """Validate method argument `name` against a messages.py annotation (e.g. `Vec3`, `Rot`).

    Missing → `default` when given, else ProtocolError; the codec's rules apply otherwise.
    """
    v = args.get(name, _MISSING)
    if v is _MISSING or v is None:
        if default is not _MISSING:
            return default
        raise ProtocolError(name, "missing")
    inner, _ = _unwrap_optional(annotation)
    return _validator_for(inner)(name, v)


_ARG_VALIDATORS: dict[Any, Validator] = {}


def _validator_for(annotation: Any) -> Validator:
    try:
        return _ARG_VALIDATORS[annotation]
    except KeyError:
        v = _ARG_VALIDATORS[annotation] = _make_validator(annotation)
        return v
    except TypeError:  # unhashable annotation
        return _make_validator(annotation)


def jsonable(obj: Any, max_bytes: int = 32) -> Any:
    """A JSON-friendly view of a decoded payload: bytes summarized, numbers kept."""
    if isinstance(obj, Message):
        obj = {f.name: getattr(obj, f.name) for f in fields(obj)}
    if isinstance(obj, dict):
        return {str(k): jsonable(v, max_bytes) for k, v in obj.items()}
    if isinstance(obj, list | tuple):
        return [jsonable(v, max_bytes) for v in obj]
    if isinstance(obj, bytes | bytearray):
        return f"<{len(obj)} bytes>"
    if isinstance(obj, float) and not math.isfinite(obj):
        return str(obj)
    return obj
