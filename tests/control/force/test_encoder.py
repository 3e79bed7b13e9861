"""The dedicated ForceSample encoder writes exactly the codec's bytes, and refuses as it does."""

from __future__ import annotations

import math

import pytest
from hypothesis import given
from hypothesis import strategies as st

from services.bus import codec
from services.bus.errors import ProtocolError
from services.bus.messages import ForceSample
from services.control.force.config import ForceConfig
from services.control.force.encoder import ForceSampleEncoder
from services.control.force.service import ForceService

count = st.integers(0, 2**63 - 1)
num = st.floats(allow_nan=False, allow_infinity=False) | st.integers(-(2**40), 2**40)
v3 = st.tuples(num, num, num)
v6 = st.tuples(num, num, num, num, num, num)


@given(count, count, v3, v3, st.none() | v6, st.sampled_from([None, True]))
def test_bytes_are_the_codecs(
    seq: int, t_ns: int, f: tuple, c: tuple, raw: tuple | None, estimate: bool | None
) -> None:
    ref = codec.encode(ForceSample(seq=seq, t_ns=t_ns, f=f, c=c, raw=raw, estimate=estimate))
    assert ForceSampleEncoder().encode(seq, t_ns, f, c, raw, estimate) == ref
    back = codec.decode(ForceSample, ref)
    assert (back.seq, back.t_ns, back.f, back.c) == (
        seq,
        t_ns,
        tuple(map(float, f)),
        tuple(map(float, c)),
    )


@pytest.mark.parametrize(
    ("args", "field"),
    [
        ((-1, 0, (0.0,) * 3, (0.0,) * 3, None), "seq"),
        ((2**63, 0, (0.0,) * 3, (0.0,) * 3, None), "seq"),
        ((1, True, (0.0,) * 3, (0.0,) * 3, None), "t_ns"),
        ((1, 0, (0.0, math.nan, 0.0), (0.0,) * 3, None), "f"),
        ((1, 0, (0.0,) * 3, (math.inf, 0.0, 0.0), None), "c"),
        ((1, 0, (0.0,) * 3, (0.0,) * 3, (0.0,) * 5 + (math.nan,)), "raw"),
        ((1, 0, (0.0,) * 2, (0.0,) * 3, None), "f"),
        ((1, 0, (0.0,) * 3, (0.0,) * 3, (0.0,) * 5), "raw"),
    ],
)
def test_refuses_what_the_codec_refuses(args: tuple, field: str) -> None:
    with pytest.raises(ProtocolError) as e:
        ForceSampleEncoder().encode(*args)
    assert e.value.field == field


def test_huge_but_finite_values_are_not_mistaken_for_infinite() -> None:
    f = (1e308, 1e308, 0.0)  # their sum overflows; each is finite
    ref = codec.encode(ForceSample(seq=1, t_ns=2, f=f, c=(0.0,) * 3))
    assert ForceSampleEncoder().encode(1, 2, f, (0.0,) * 3) == ref


def test_the_service_publishes_the_codecs_bytes(net) -> None:  # type: ignore[no-untyped-def]
    svc = ForceService(net.node("force"), ForceConfig(autostart=False))
    try:
        s = ForceSample(seq=7, t_ns=123, f=(1.0, -2.0, 0.5), c=(0.0, 0.1, -0.2), raw=(1.0,) * 6)
        assert svc.encode_sample(s) == codec.encode(
            ForceSample(seq=7, t_ns=123, f=s.f, c=s.c, raw=s.raw)
        )
    finally:
        svc.close()
