"""The teleop floor: its roles carry what the four 1 kHz processes carry, and the phase runs
them all through a real router (counts and values, never speed)."""

from __future__ import annotations

from pathlib import Path

import pytest

from services.tools.bench import teleop_floor
from services.tools.bench.teleop_floor import ROLES, STREAMS
from services.tools.cell.ports import free_port
from services.tools.cell.procs import Children, telerobot_argv, wait_log


def _senders(stream: str) -> list[str]:
    return [
        name
        for name, role in ROLES.items()
        if stream in role.sends or any(out == stream for _, out in role.relays)
    ]


def _takers(stream: str) -> list[str]:
    return [
        name
        for name, role in ROLES.items()
        if stream in role.takes or any(src == stream for src, _ in role.relays)
    ]


def test_every_stream_has_one_sender_and_its_services_as_takers() -> None:
    # who takes what, as in the running system (module docstring's table)
    assert {s: _senders(s) for s in STREAMS} == {
        "cmd": ["master"],
        "target": ["decision"],
        "force": ["force"],
        "simstate": ["arm"],
        "state": ["arm"],
    }
    assert {s: _takers(s) for s in STREAMS} == {
        "cmd": ["decision"],
        "target": ["arm"],
        "force": ["decision", "master"],
        "simstate": ["force"],
        "state": ["decision", "force"],
    }
    # the relayed stream has no clock of its own; every other one has its rate
    assert STREAMS["target"][0] == 0.0
    assert {s: r for s, (r, _) in STREAMS.items() if s != "target"} == {
        "cmd": 1000.0, "force": 1000.0, "simstate": 1000.0, "state": 250.0,
    }  # fmt: skip
    assert teleop_floor.COUNTED == ("router", "decision", "arm", "force")


def test_parse_counts_takes_the_last_line() -> None:
    out = (
        "teleop floor up arm\n"
        'teleop floor counts {"role": "arm", "got": {"target": 1}, "sent": {}, "s": 1.0}\n'
        'teleop floor counts {"role": "arm", "got": {"target": 7}, "sent": {}, "s": 2.0}\n'
    )
    assert teleop_floor.parse_counts(out) == {
        "role": "arm", "got": {"target": 7}, "sent": {}, "s": 2.0,
    }  # fmt: skip
    assert teleop_floor.parse_counts("teleop floor up arm\n") is None


@pytest.mark.timeout(120)
def test_the_phase_carries_every_stream_through_a_router(tmp_path: Path) -> None:
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    said: list[str] = []
    with Children(tmp_path) as kids:
        router = kids.spawn("router", telerobot_argv("router", "--listen", endpoint))
        wait_log(router, "router up", 60.0)
        fig = teleop_floor.phase_teleop_floor(kids, endpoint, 0.5, 1.0, 60.0, said.append)
        # every role stopped, the router left running
        assert set(kids.children) == {"router"}
    assert fig["na"] == {}
    assert set(fig["services"]) == {"router", "decision", "arm", "force"}
    assert fig["core_pct"] == pytest.approx(sum(fig["services"].values()))
    assert fig["master_pct"] >= 0.0 and fig["window_s"] >= 1.0
    rates = fig["rates_hz"]
    assert set(rates) == set(ROLES)
    # the decision put every command it took on again as a target, one for one
    assert rates["decision"]["cmd"] == rates["decision"]["target sent"] > 0
    for name, streams in (
        ("decision", ("force", "state")),
        ("arm", ("target",)),
        ("force", ("simstate", "state")),
        ("master", ("force",)),
    ):
        assert all(rates[name][s] > 0 for s in streams), (name, rates[name])
    assert said[-1].startswith("    teleop floor: router + decision + arm + force")
