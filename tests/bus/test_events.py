"""The bus's event rate limiter: one per key per interval, a global cap, nothing lost."""

from __future__ import annotations

import pytest
from hypothesis import given
from hypothesis import strategies as st

from services.bus.events import EventLimiter


def test_one_per_key_per_interval_and_the_next_says_how_many_were_held() -> None:
    lim = EventLimiter(1.0)
    assert lim.allow("a", 0.0) == 0
    assert [lim.allow("a", t) for t in (0.1, 0.5, 0.99)] == [None, None, None]
    assert lim.held("a") == 3
    assert lim.allow("b", 0.5) == 0  # keys are independent
    assert lim.allow("a", 1.0) == 3
    assert lim.held("a") == 0
    assert lim.allow("a", 1.5) is None
    assert lim.allow("a", 2.0) == 1


def test_per_second_cap_over_all_keys() -> None:
    lim = EventLimiter(1.0, per_s=2)
    assert [lim.allow(k, 0.0) for k in "abc"] == [0, 0, None]
    assert lim.allow("d", 0.5) is None
    assert lim.allow("c", 1.0) == 1  # a new one-second window
    assert lim.allow("d", 1.0) == 1
    assert lim.allow("e", 1.0) is None


def test_uses_its_clock_when_no_time_is_given() -> None:
    now = [10.0]
    lim = EventLimiter(0.5, clock_s=lambda: now[0])
    assert lim.allow("k") == 0
    assert lim.allow("k") is None
    now[0] = 10.5
    assert lim.allow("k") == 1


def test_max_keys_forgets_the_least_recent_key() -> None:
    lim = EventLimiter(1.0, max_keys=2)
    assert [lim.allow(k, 0.0) for k in "ab"] == [0, 0]
    assert lim.allow("a", 0.5) is None
    assert lim.allow("c", 0.5) == 0  # "a" (let through first) is forgotten, held count too
    assert lim.held("a") == 0
    assert lim.allow("a", 0.6) == 0  # a forgotten key starts afresh; "b" is forgotten now
    assert lim.allow("c", 0.7) is None  # still remembered
    assert lim.allow("b", 0.7) == 0


@pytest.mark.parametrize(
    ("interval_s", "per_s", "max_keys"),
    [(-1.0, None, None), (float("nan"), None, None), (1.0, 0, None), (1.0, None, 0)],
)
def test_bad_settings_are_refused(
    interval_s: float, per_s: int | None, max_keys: int | None
) -> None:
    with pytest.raises(ValueError):
        EventLimiter(interval_s, per_s, max_keys=max_keys)


@given(
    st.lists(st.tuples(st.sampled_from("abc"), st.floats(0.0, 0.7)), max_size=60),
    st.floats(0.0, 2.0),
    st.none() | st.integers(1, 4),
)
def test_every_event_is_sent_or_counted_once(
    steps: list[tuple[str, float]], interval_s: float, per_s: int | None
) -> None:
    lim = EventLimiter(interval_s, per_s)
    t, sent, told = 0.0, dict.fromkeys("abc", 0), dict.fromkeys("abc", 0)
    last: dict[str, float] = {}
    for key, dt in steps:
        t += dt
        r = lim.allow(key, t)
        if r is not None:
            assert key not in last or t - last[key] >= interval_s
            last[key] = t
            sent[key] += 1
            told[key] += r
    for k in "abc":
        n = sum(1 for key, _ in steps if key == k)
        assert sent[k] + told[k] + lim.held(k) == n
