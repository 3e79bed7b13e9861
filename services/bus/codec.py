"""The one module that knows bytes: strict msgpack encoding and validation (PROTOCOL.md §3).

A receiver ignores fields it does not know and rejects a message whose required fields are
missing, of the wrong type or size, or not finite, and a rotation that is not orthonormal or
is reflected. Every rejection is a `ProtocolError` that names the field. Encoding validates
too, so nothing that breaks the contract ever leaves a process of ours.

The schema is the dataclass annotations of `services.bus.messages`, read once per class into
a table of `_Spec`s. Each spec has two validators:

- the *general* one (a closure per field, also behind `arg()` for method arguments), which
  accepts everything the contract allows (ints where floats are allowed, numpy floats, …) and
  raises the `ProtocolError` that explains a rejection;
- the *fast* one, compiled per message class at first use into one straight-line function
  (see `_compile`): exact-type checks only, no numpy, no string formatting, no exceptions. It
  either returns the validated message (or wire map) or None, and None sends the input to the
  general path, which decides. So the fast path only has to be right about what it accepts
  (tests/bus/test_codec_fastpath.py checks both against a reference implementation).
"""

from __future__ import annotations

import math
import reprlib
import types
import typing
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, fields
from typing import Any, Literal, TypeVar, get_args, get_origin, get_type_hints

import msgpack
import numpy as np

from services.bus.errors import ProtocolError
from services.bus.messages import MAX_TEXT, MaxLen, Message, Range, Rotation, Size
from services.geometry import ROTATION_TOL, rotation_defect

M = TypeVar("M", bound=Message)
Validator = Callable[[str, Any], Any]

_MISSING = object()
_INT_LO, _INT_HI = -(2**63), 2**64 - 1
"""The integers msgpack can carry."""


# --- the schema of one annotation -----------------------------------------------------


@dataclass(frozen=True, slots=True)
class _Spec:
    """What one annotation allows: `kind` plus that kind's bounds."""

    kind: Literal["literal", "vector", "bool", "int", "float", "str", "bytes", "map", "records"]
    allowed: tuple[Any, ...] = ()
    """literal: the allowed values."""
    n: int = 0
    """vector: the number of floats (the fewest, when `n_hi` is set)."""
    n_hi: int | None = None
    """vector: the most floats of a variable-length vector (None: exactly `n`)."""
    rotation_tol: float | None = None
    """vector of 9: a proper rotation within this ‖RᵀR − I‖."""
    lo: float | None = None
    hi: float | None = None
    """int, float: the range (int: msgpack's when None)."""
    max_len: int = MAX_TEXT
    """str, bytes: the largest length; records: the most maps."""


def _spec(tp: Any) -> _Spec:
    """Read one annotation (Annotated, Literal, scalar, dict) into a `_Spec`."""
    meta: tuple[Any, ...] = ()
    if get_origin(tp) is typing.Annotated:
        tp, *rest = get_args(tp)
        meta = tuple(rest)
    size_meta = next((m for m in meta if isinstance(m, Size)), None)
    size = None if size_meta is None else size_meta.n
    rot = next((m for m in meta if isinstance(m, Rotation)), None)
    rng = next((m for m in meta if isinstance(m, Range)), None)
    max_len = next((m.n for m in meta if isinstance(m, MaxLen)), MAX_TEXT)
    if get_origin(tp) is typing.Literal:
        return _Spec("literal", allowed=get_args(tp))
    if size_meta is not None and size is not None:
        return _Spec(
            "vector", n=size, n_hi=size_meta.hi, rotation_tol=None if rot is None else rot.tol
        )
    if tp is bool:
        return _Spec("bool")
    if tp is int:
        lo, hi = (int(rng.lo), int(rng.hi)) if rng else (_INT_LO, _INT_HI)
        return _Spec("int", lo=lo, hi=hi)
    if tp is float:
        return _Spec(
            "float", lo=None if rng is None else rng.lo, hi=None if rng is None else rng.hi
        )
    if tp is str:
        return _Spec("str", max_len=max_len)
    if tp is bytes:
        return _Spec("bytes", max_len=max_len)
    if get_origin(tp) is dict:
        return _Spec("map")
    if get_origin(tp) is tuple and get_args(tp)[:1] and get_origin(get_args(tp)[0]) is dict:
        return _Spec("records", max_len=max_len)
    raise TypeError(f"no validator for annotation {tp!r}")


def _unwrap_optional(tp: Any) -> tuple[Any, bool]:
    if get_origin(tp) in (typing.Union, types.UnionType):
        args = [a for a in get_args(tp) if a is not type(None)]
        if len(args) == 1 and len(get_args(tp)) == 2:
            return args[0], True
    return tp, False


# --- rotations ----------------------------------------------------------------------


def check_rotation(name: str, r: Sequence[float], tol: float = ROTATION_TOL) -> None:
    """Reject a non-orthonormal (‖RᵀR − I‖ > tol) or reflected (det R < 0) rotation."""
    err, det = rotation_defect(r)
    if not err <= tol:  # NaN (opposite infinities in a product) is rejected too
        raise ProtocolError(name, f"not a rotation: ‖RᵀR − I‖ = {err:.3g} > {tol:g}")
    if not det >= 0.0:
        raise ProtocolError(name, "reflection: det R < 0")


# --- the general validators (and the error messages) ------------------------------------


def _shown(v: Any) -> str:
    """A short repr for an error message, whatever `v` is (huge ints, huge lists)."""
    try:
        return reprlib.repr(v)
    except ValueError:  # an int too long to print (sys.set_int_max_str_digits)
        return f"an int of {v.bit_length()} bits" if isinstance(v, int) else type(v).__name__


def _float_or_reason(v: Any) -> tuple[float, str | None]:
    """`v` as a finite float, or why it is not one (the reason is formatted only then)."""
    if isinstance(v, bool) or not isinstance(v, int | float):
        return math.nan, f"expected a number, got {type(v).__name__}"
    try:
        f = float(v)
    except OverflowError:
        return math.nan, "not finite (an int beyond the float range)"
    if not math.isfinite(f):
        return f, f"not finite ({f})"
    return f, None


def _number(name: str, v: Any) -> float:
    f, why = _float_or_reason(v)
    if why is not None:
        raise ProtocolError(name, why)
    return f


def _general(s: _Spec) -> Validator:
    """The validator of one `_Spec`: returns the field's value or raises ProtocolError."""
    if s.kind == "literal":
        allowed = s.allowed

        def literal(name: str, v: Any) -> Any:
            if not isinstance(v, str) or v not in allowed:
                raise ProtocolError(name, f"expected one of {list(allowed)}, got {_shown(v)}")
            return v

        return literal
    if s.kind == "vector":
        n, hi, tol = s.n, s.n_hi, s.rotation_tol
        want = f"{n}" if hi is None else f"{n} … {hi}"

        def vector(name: str, v: Any) -> tuple[float, ...]:
            if not isinstance(v, list | tuple):
                raise ProtocolError(name, f"expected {want} numbers, got {type(v).__name__}")
            if (len(v) != n) if hi is None else not n <= len(v) <= hi:
                raise ProtocolError(name, f"expected {want} numbers, got {len(v)}")
            out: list[float] = []
            for i, x in enumerate(v):
                f, why = _float_or_reason(x)
                if why is not None:
                    raise ProtocolError(f"{name}[{i}]", why)
                out.append(f)
            if tol is not None:
                check_rotation(name, out, tol)
            return tuple(out)

        return vector
    if s.kind == "bool":

        def boolean(name: str, v: Any) -> bool:
            if not isinstance(v, bool):
                raise ProtocolError(name, f"expected a bool, got {type(v).__name__}")
            return v

        return boolean
    if s.kind == "int":
        lo, hi = int(_INT_LO if s.lo is None else s.lo), int(_INT_HI if s.hi is None else s.hi)

        def integer(name: str, v: Any) -> int:
            if isinstance(v, bool) or not isinstance(v, int):
                raise ProtocolError(name, f"expected an integer, got {type(v).__name__}")
            if not lo <= v <= hi:
                raise ProtocolError(name, f"{_shown(v)} out of range [{lo}, {hi}]")
            return v

        return integer
    if s.kind == "float":
        flo, fhi = s.lo, s.hi

        def number(name: str, v: Any) -> float:
            f = _number(name, v)
            if flo is not None and fhi is not None and not flo <= f <= fhi:
                raise ProtocolError(name, f"{f} out of range [{flo}, {fhi}]")
            return f

        return number
    if s.kind == "str":
        max_len = s.max_len

        def text(name: str, v: Any) -> str:
            if not isinstance(v, str):
                raise ProtocolError(name, f"expected a string, got {type(v).__name__}")
            if len(v) > max_len:
                raise ProtocolError(name, f"longer than {max_len} characters")
            return v

        return text
    if s.kind == "bytes":
        max_bytes = s.max_len

        def binary(name: str, v: Any) -> bytes:
            if not isinstance(v, bytes | bytearray):
                raise ProtocolError(name, f"expected bytes, got {type(v).__name__}")
            if len(v) > max_bytes:
                raise ProtocolError(name, f"larger than {max_bytes} bytes")
            return bytes(v)

        return binary

    def mapping(name: str, v: Any) -> dict[str, Any]:
        if not isinstance(v, dict) or not all(isinstance(k, str) for k in v):
            raise ProtocolError(name, "expected a map with string keys")
        return v

    if s.kind == "records":
        most = s.max_len

        def records(name: str, v: Any) -> tuple[dict[str, Any], ...]:
            if not isinstance(v, list | tuple):
                raise ProtocolError(name, f"expected a list of maps, got {type(v).__name__}")
            if len(v) > most:
                raise ProtocolError(name, f"more than {most} maps")
            return tuple(mapping(f"{name}[{i}]", x) for i, x in enumerate(v))

        return records
    return mapping


def _make_validator(tp: Any) -> Validator:
    """The general validator of one annotation (Annotated, Literal, scalar, dict)."""
    return _general(_spec(tp))


# --- the fast path: one compiled function per message class ------------------------------


def _check_source(s: _Spec, v: str, k: int, consts: dict[str, Any]) -> list[str]:
    """Lines that `return None` unless local `v` meets `s` exactly (leaving its value in `v`).

    `k` (the field's index) names the temporaries (`_k_i`, `_sk`), which cannot clash with a
    field's `v_<name>`.

    Exact types only (`type(x) is float`): anything else (ints in float fields, numpy floats,
    bytearrays, subclasses) is left to the general path, which accepts or explains it.
    """
    fail = "return None"
    if s.kind == "literal":
        consts[f"allowed_{k}"] = frozenset(s.allowed)
        return [f"if type({v}) is not str or {v} not in allowed_{k}: {fail}"]
    if s.kind == "records":
        return [fail]  # rare (the arm's description): the general path checks it
    if s.kind == "vector" and s.n_hi is not None:
        lines = [
            f"if type({v}) is not tuple and type({v}) is not list: {fail}",
            f"if not {s.n} <= len({v}) <= {s.n_hi}: {fail}",
            f"for _x{k} in {v}:",
            f"    if type(_x{k}) is not float: {fail}",
            f"_s{k} = sum({v})",
            f"if _s{k} - _s{k} != 0.0: {fail}",
            f"if type({v}) is list: {v} = tuple({v})",
        ]
        return lines
    if s.kind == "vector":
        xs = [f"_{k}_{i}" for i in range(s.n)]
        lines = [
            f"if type({v}) is not tuple and type({v}) is not list or len({v}) != {s.n}: {fail}",
            f"{', '.join(xs)}, = {v}",
            "if " + " or ".join(f"type({x}) is not float" for x in xs) + f": {fail}",
            # A NaN or an infinity anywhere makes the sum non-finite (so does an overflowing
            # sum of finite values: the general path then accepts it).
            f"_s{k} = {' + '.join(xs)}",
            f"if _s{k} - _s{k} != 0.0: {fail}",
            f"if type({v}) is list: {v} = ({', '.join(xs)},)",
        ]
        if s.rotation_tol is not None:
            consts["rotation_defect"] = rotation_defect
            lines += [
                f"_err, _det = rotation_defect({v})",
                f"if not (_err <= {s.rotation_tol!r} and _det >= 0.0): {fail}",
            ]
        return lines
    if s.kind == "bool":
        return [f"if {v} is not True and {v} is not False: {fail}"]
    if s.kind == "int":
        return [f"if type({v}) is not int or not {s.lo!r} <= {v} <= {s.hi!r}: {fail}"]
    if s.kind == "float":
        lines = [f"if type({v}) is not float or {v} - {v} != 0.0: {fail}"]
        if s.lo is not None and s.hi is not None:
            lines.append(f"if not {float(s.lo)!r} <= {v} <= {float(s.hi)!r}: {fail}")
        return lines
    if s.kind == "str":
        return [f"if type({v}) is not str or len({v}) > {s.max_len}: {fail}"]
    if s.kind == "bytes":
        return [f"if type({v}) is not bytes or len({v}) > {s.max_len}: {fail}"]
    return [
        f"if type({v}) is not dict: {fail}",
        f"for _key in {v}:",
        f"    if type(_key) is not str: {fail}",
    ]


def _setter(cls: type, name: str) -> Callable[[Any, Any], None] | None:
    """The slot's own setter (bypasses the frozen __setattr__), or None if not a slot."""
    for klass in cls.__mro__:
        if name in klass.__dict__:
            d = klass.__dict__[name]
            return d.__set__ if isinstance(d, types.MemberDescriptorType) else None
    return None


def _compile(
    cls: type[Message], entries: list[tuple[str, _Spec, bool]]
) -> tuple[Callable[[Mapping[str, Any]], Any], Callable[[Any], dict[str, Any] | None], str]:
    """(from_map, to_map, source): the fast decoder and encoder of `cls`, straight-line code.

    Python has no JIT: a loop calling one closure per field costs ~0.2 µs a field, the
    `RobotState` budget is 8 µs for 15 fields, two rotations and msgpack; so, as `dataclasses`
    does for `__init__`, the per-class code is generated once from the field table. Names in
    the source are `v_<field>`; constants come in through `consts`, never as text.
    A decoded message is built by setting its slots directly (no `__init__`: ~1 µs saved on
    15 fields); a class with `__post_init__` or without slots goes through its constructor.
    """
    consts: dict[str, Any] = {"cls": cls, "new": object.__new__}
    setters = {name: _setter(cls, name) for name, _, _ in entries}
    direct = all(setters.values()) and not hasattr(cls, "__post_init__")
    required = [name for name, _, optional in entries if not optional]
    # A missing required field is a KeyError (free when absent), a nil one fails its check.
    dec = ["def from_map(d):", "    try:"]
    dec += [f"        v_{name} = d[{name!r}]" for name in required]
    dec += ["    except KeyError:", "        return None", "    get = d.get"]
    dec += [f"    v_{name} = get({name!r})" for name, _, optional in entries if optional]
    enc = ["def to_map(m):"]
    enc += [f"    v_{name} = m.{name}" for name, _, _ in entries]
    checks = []
    for k, (name, spec, optional) in enumerate(entries):
        lines = _check_source(spec, f"v_{name}", k, consts)
        if optional:
            checks += [f"    if v_{name} is not None:"] + [f"        {line}" for line in lines]
        else:
            checks += [f"    {line}" for line in lines]
    dec += checks
    enc += checks
    if direct:
        dec.append("    o = new(cls)")
        for name, _, _ in entries:
            consts[f"set_{name}"] = setters[name]
            dec.append(f"    set_{name}(o, v_{name})")
        dec.append("    return o")
    else:
        dec.append("    return cls(" + ", ".join(f"{n}=v_{n}" for n, _, _ in entries) + ")")
    lead = 0
    while lead < len(entries) and not entries[lead][2]:
        lead += 1
    enc.append("    out = {" + ", ".join(f"{n!r}: v_{n}" for n, _, _ in entries[:lead]) + "}")
    for name, _, optional in entries[lead:]:
        line = f"out[{name!r}] = v_{name}"
        enc.append(f"    if v_{name} is not None: {line}" if optional else f"    {line}")
    enc.append("    return out")
    source = "\n".join(dec + enc) + "\n"
    namespace = dict(consts)
    exec(compile(source, f"<codec fast path {cls.__name__}>", "exec"), namespace)
    return namespace["from_map"], namespace["to_map"], source


class _Schema:
    __slots__ = ("cls", "entries", "fast_from", "fast_to", "source", "tuples")

    def __init__(self, cls: type[Message]) -> None:
        hints = get_type_hints(cls, include_extras=True)
        self.cls = cls
        specs: list[tuple[str, _Spec, bool]] = []
        self.entries: list[tuple[str, Validator, bool]] = []
        for f in fields(cls):
            inner, optional = _unwrap_optional(hints[f.name])
            spec = _spec(inner)
            specs.append((f.name, spec, optional))
            self.entries.append((f.name, _general(spec), optional))
        self.fast_from, self.fast_to, self.source = _compile(cls, specs)
        # msgpack arrays may arrive as tuples (no copy to a tuple later) unless a free-form
        # map field would then hold tuples where its sender put lists.
        self.tuples = all(spec.kind not in ("map", "records") for _, spec, _ in specs)


_SCHEMAS: dict[type[Message], _Schema] = {}


def _schema(cls: type[Message]) -> _Schema:
    s = _SCHEMAS.get(cls)
    if s is None:
        s = _SCHEMAS[cls] = _Schema(cls)
    return s


# --- the public codec -----------------------------------------------------------------


def from_fields(cls: type[M], data: Mapping[str, Any]) -> M:
    """Validate a decoded map against `cls`; unknown fields are ignored (§ conventions)."""
    msg = _schema(cls).fast_from(data)
    if msg is not None:
        return typing.cast(M, msg)
    return _general_from_fields(cls, data)


def _general_from_fields(cls: type[M], data: Mapping[str, Any]) -> M:
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


def _wire(msg: Message) -> dict[str, Any]:
    """The validated wire map of `msg`, vectors as tuples (msgpack packs them as arrays)."""
    schema = _schema(type(msg))
    out = schema.fast_to(msg)
    if out is not None:
        return out
    out = {}
    for name, validate, optional in schema.entries:
        v = getattr(msg, name)
        if v is None:
            if optional:
                continue
            raise ProtocolError(name, "missing")
        out[name] = validate(name, v)
    return out


def to_fields(msg: Message) -> dict[str, Any]:
    """The validated wire map of `msg` (tuples as lists, None optionals left out)."""
    return {k: list(v) if isinstance(v, tuple) else v for k, v in _wire(msg).items()}


def encode(msg: Message) -> bytes:
    """msgpack bytes of `msg`, after checking it against the contract."""
    wire = _wire(msg)
    try:
        return pack(wire)
    except (TypeError, ValueError, OverflowError) as e:  # e.g. a huge int in a free-form map
        for name, v in wire.items():
            try:
                pack(v)
            except (TypeError, ValueError, OverflowError):
                raise ProtocolError(name, f"cannot be encoded ({e})") from None
        raise


def decode(cls: type[M], payload: bytes) -> M:
    """The message of type `cls` in `payload`; raises ProtocolError naming the bad field."""
    schema = _schema(cls)
    data = unpack(payload, lists=not schema.tuples)
    if type(data) is dict:
        msg = schema.fast_from(data)
        if msg is not None:
            return typing.cast(M, msg)
    # The error path (or a foreign peer's ints): decoded again with lists, so messages read
    # "got list" as the sender would expect.
    data = unpack(payload)
    if type(data) is not dict:
        raise ProtocolError("payload", f"expected a msgpack map, got {type(data).__name__}")
    return _general_from_fields(cls, data)


def pack(obj: Any) -> bytes:
    """msgpack with string keys and binary type, the contract's encoding."""
    return msgpack.packb(obj, use_bin_type=True, default=_default)


def unpack(payload: bytes, lists: bool = True) -> Any:
    """Decode msgpack, arrays as lists (or tuples); malformed input: ProtocolError on `payload`."""
    try:
        return msgpack.unpackb(payload, raw=False, strict_map_key=True, use_list=lists)
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
