"""Shared pieces of the recording tests: sample messages, a JSON Schema checker, file writers."""

from __future__ import annotations

import math
import time
from collections.abc import Callable, Iterable, Sequence
from pathlib import Path
from typing import Any

import pinocchio as pin
from numpy.typing import ArrayLike

from services.bus import codec, keys
from services.bus.messages import (
    IDENTITY_R,
    ArmDescription,
    Event,
    ForceSample,
    OperatorCommand,
    RobotState,
)
from services.control.arm.model import ArmModel
from services.tools.record.recorder import McapSink, Received, RecorderConfig
from tests.conftest import ready_state

T0_NS = 1_700_000_000_000_000_000


def force(seq: int, t_ns: int | None = None, fz: float = 1.0) -> bytes:
    return codec.encode(
        ForceSample(seq=seq, t_ns=t_ns or T0_NS + seq, f=(0.0, 0.0, fz), c=(0.0, 0.0, 0.0))
    )


def state(seq: int, p: Sequence[float] = (0.5, 0.0, 0.6), status: str = "ready") -> bytes:
    return codec.encode(
        RobotState(
            seq=seq,
            t_ns=T0_NS + seq,
            status=status,  # type: ignore[arg-type]
            q=(0.0,) * 6,
            tool_p=tuple(p),
            tool_R=IDENTITY_R,
            flange_p=tuple(p),
            flange_R=IDENTITY_R,
            engage=0,
            cmd_seq=0,
        )
    )


def description(
    model: ArmModel,
    seq: int = 1,
    tool_p: Sequence[float] | None = None,
    tool_R: Sequence[float] | None = None,
) -> bytes:
    """The arm's robot/arm/description as the arm service publishes it (its default tool,
    or the one given)."""
    desc = model.description(
        None if tool_p is None else tuple(tool_p),  # type: ignore[arg-type]
        None if tool_R is None else tuple(tool_R),  # type: ignore[arg-type]
    )
    return codec.encode(ArmDescription(seq=seq, t_ns=T0_NS + seq, **desc))


def arm_state(seq: int, q: ArrayLike, oMe: pin.SE3, eMt: pin.SE3) -> bytes:
    """A robot/state at joints q whose flange is at oMe and tool at oMe·eMt."""
    return codec.encode(ready_state(seq, T0_NS + seq, q, oMe * eMt, oMe))


def command(seq: int, engage: int, dp: Sequence[float], active: bool = True) -> bytes:
    return codec.encode(
        OperatorCommand(
            seq=seq,
            t_ns=T0_NS + seq,
            master="m1",
            engage=engage,
            active=active,
            frame="world",
            dp=tuple(dp),
            dR=IDENTITY_R,
        )
    )


def event(seq: int, source: str, kind: str, message: str) -> bytes:
    return codec.encode(
        Event(seq=seq, t_ns=T0_NS + seq, source=source, kind=kind, message=message, data=None)
    )


class FakeClock:
    """Monotonic seconds under the test's control."""

    def __init__(self) -> None:
        self.now_s = 0.0

    def __call__(self) -> float:
        return self.now_s


def write_file(
    path: Path,
    items: Iterable[tuple[str, bytes]],
    flush_every: int = 0,
    **config: Any,
) -> tuple[McapSink, list[Received]]:
    """Write `(key, payload)` items with a McapSink (log times 1 ms apart); closing a chunk
    every `flush_every` items when given. Returns the (closed) sink and what was written."""
    clock = FakeClock()
    sink = McapSink(
        RecorderConfig(output=str(path), **config), monotonic_s=clock, clock_ns=time.time_ns
    )
    written: list[Received] = []
    for i, (key, payload) in enumerate(items):
        item = Received(T0_NS + i * 1_000_000, key, payload)
        if not sink.write(item):
            break
        written.append(item)
        if flush_every and (i + 1) % flush_every == 0:
            sink.flush()
    sink.close()
    return sink, written


def conforms(schema: dict[str, Any], doc: Any, where: str = "$") -> list[str]:
    """The ways `doc` breaks `schema` (the JSON Schema subset schemas.py emits); [] if none."""
    errors: list[str] = []
    t = schema.get("type")
    checks: dict[str, Callable[[Any], bool]] = {
        "object": lambda v: isinstance(v, dict),
        "array": lambda v: isinstance(v, list),
        "string": lambda v: isinstance(v, str),
        "boolean": lambda v: isinstance(v, bool),
        "integer": lambda v: isinstance(v, int) and not isinstance(v, bool),
        "number": lambda v: isinstance(v, int | float) and not isinstance(v, bool),
    }
    if t is not None and not checks[t](doc):
        return [f"{where}: expected {t}, got {type(doc).__name__}"]
    if "enum" in schema and doc not in schema["enum"]:
        errors.append(f"{where}: {doc!r} not in {schema['enum']}")
    if t == "number" and not math.isfinite(doc):
        errors.append(f"{where}: not finite")
    if "minimum" in schema and doc < schema["minimum"]:
        errors.append(f"{where}: below minimum")
    if "maximum" in schema and doc > schema["maximum"]:
        errors.append(f"{where}: above maximum")
    if "maxLength" in schema and len(doc) > schema["maxLength"]:
        errors.append(f"{where}: too long")
    if t == "array":
        if len(doc) < schema.get("minItems", 0) or len(doc) > schema.get("maxItems", 1 << 62):
            errors.append(f"{where}: {len(doc)} items")
        for i, v in enumerate(doc):
            errors += conforms(schema.get("items", {}), v, f"{where}[{i}]")
    if t == "object":
        for name in schema.get("required", []):
            if name not in doc:
                errors.append(f"{where}.{name}: missing")
        props: dict[str, Any] | None = schema.get("properties")
        for name, v in doc.items():
            if props is None:
                break  # a free-form object
            if name not in props:
                errors.append(f"{where}.{name}: not in the schema")
            else:
                errors += conforms(props[name], v, f"{where}.{name}")
    return errors


def topic_keys() -> list[str]:
    return [t.key for t in keys.TOPICS]
