"""The bench's tests: register the `slow` marker of the full smoke run."""

from __future__ import annotations

import pytest


def pytest_configure(config: pytest.Config) -> None:
    config.addinivalue_line(
        "markers", "slow: runs the whole `telerobot bench --quick` (TELEROBOT_BENCH_SMOKE=1)"
    )
