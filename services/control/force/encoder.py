"""The ForceSample's bytes, written directly: the codec's output without its generic path.

`ForceSampleEncoder.encode` gives exactly `codec.encode(ForceSample(...))` (a msgpack map
with the fields in declaration order, ints in their shortest form, floats as float64),
checked by tests/control/force/test_encoder.py against `services.bus.codec`, without building a
dataclass or running the codec's generic validation. It checks what the codec would: `seq`
and `t_ns` integers in [0, 2⁶³), `f` and `c` 3 finite floats, `raw` 6 or None; a bad value
raises the codec's ProtocolError naming the field.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import msgpack

from services.bus.errors import ProtocolError

_COUNT_MAX = 2**63 - 1


def _finite(name: str, v: Sequence[float]) -> None:
    for x in v:
        if not math.isfinite(x):
            raise ProtocolError(name, "not finite")


class ForceSampleEncoder:
    """ForceSample → bytes. Holds a msgpack `Packer`: one encoder per thread."""

    __slots__ = ("_pack",)

    def __init__(self) -> None:
        self._pack = msgpack.Packer(use_bin_type=True).pack

    def encode(
        self,
        seq: int,
        t_ns: int,
        f: Sequence[float],
        c: Sequence[float],
        raw: Sequence[float] | None = None,
        estimate: bool | None = None,
    ) -> bytes:
        """The msgpack bytes of ForceSample(seq, t_ns, f, c, raw, estimate) (PROTOCOL.md §3;
        `estimate`, an extension, only when true)."""
        if type(seq) is not int or not 0 <= seq <= _COUNT_MAX:
            raise ProtocolError("seq", f"expected an integer within 0…{_COUNT_MAX}")
        if type(t_ns) is not int or not 0 <= t_ns <= _COUNT_MAX:
            raise ProtocolError("t_ns", f"expected an integer within 0…{_COUNT_MAX}")
        if len(f) != 3:
            raise ProtocolError("f", "expected 3 numbers")
        if len(c) != 3:
            raise ProtocolError("c", "expected 3 numbers")
        f = (float(f[0]), float(f[1]), float(f[2]))
        c = (float(c[0]), float(c[1]), float(c[2]))
        # One test for the usual case: a sum is finite only if every term is (or overflowed).
        total = f[0] + f[1] + f[2] + c[0] + c[1] + c[2]
        if raw is None:
            if not math.isfinite(total):
                _finite("f", f)
                _finite("c", c)
            if estimate:
                return self._pack({"seq": seq, "t_ns": t_ns, "f": f, "c": c, "estimate": True})
            return self._pack({"seq": seq, "t_ns": t_ns, "f": f, "c": c})
        if len(raw) != 6:
            raise ProtocolError("raw", "expected 6 numbers")
        raw = (
            float(raw[0]),
            float(raw[1]),
            float(raw[2]),
            float(raw[3]),
            float(raw[4]),
            float(raw[5]),
        )
        total += raw[0] + raw[1] + raw[2] + raw[3] + raw[4] + raw[5]
        if not math.isfinite(total):
            _finite("f", f)
            _finite("c", c)
            _finite("raw", raw)
        if estimate:
            return self._pack(
                {"seq": seq, "t_ns": t_ns, "f": f, "c": c, "raw": raw, "estimate": True}
            )
        return self._pack({"seq": seq, "t_ns": t_ns, "f": f, "c": c, "raw": raw})
