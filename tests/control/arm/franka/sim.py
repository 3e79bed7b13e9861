"""franky-sim for the tests: the fault-injecting server (fault_sim.py) on a random loopback
address, started once per module that asks for it, and the skip when the wheels are missing."""

from __future__ import annotations

import importlib.util
import sys
from pathlib import Path

import pytest

from services.control.arm.franka.frankysim import FrankySim, loopback_host, start_franky_sim

FAULT_SIM = Path(__file__).with_name("fault_sim.py")

MISSING = [
    m for m in ("pylibfranka", "franky_sim", "ruckig") if importlib.util.find_spec(m) is None
]
needs_franky = pytest.mark.skipif(
    bool(MISSING),
    reason=f"not installed: {', '.join(MISSING)} (the dev extras: pip install -e .[dev])",
)


def start(host: str | None = None) -> FrankySim:
    """The fault-injecting franky-sim on `host` (default: a fresh loopback address)."""
    host = host or loopback_host()
    return start_franky_sim(host, [sys.executable, str(FAULT_SIM), "--hostname", host])
