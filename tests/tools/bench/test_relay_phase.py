"""The two-hop floor's figures, on hand-made probe records (counts and values)."""

from __future__ import annotations

import pytest

from services.tools.bench.relay_phase import relay_figures, relay_key


def test_figures_count_only_the_timed_samples_and_their_loss() -> None:
    # seqs 1–3 were the route set-up; 4–13 timed (10 sent), 7 lost; each back 2 ms after its stamp
    records = [(t * 1_000_000 + 2_000_000, (s, t * 1_000_000)) for t, s in enumerate(range(1, 14))]
    records = [r for r in records if r[1][0] != 7]
    fig = relay_figures(100.0, 10, 3, records)
    assert fig["sent"] == 10 and fig["received"] == 9
    assert fig["loss"]["lost"] == 1
    assert fig["latency_ms"]["p50"] == pytest.approx(2.0)
    assert fig["latency_ms"]["max"] == pytest.approx(2.0)
    assert fig["sent_rate_hz"] == 100.0


def test_nothing_back_is_all_lost() -> None:
    fig = relay_figures(1000.0, 5, 0, [])
    assert fig["received"] == 0 and fig["loss"]["lost"] == 5


def test_keys_name_the_rate() -> None:
    assert relay_key(100.0) == "baseline_zenoh_relay_100hz"
    assert relay_key(1000.0) == "baseline_zenoh_relay_1000hz"
