"""The real `zenoh` command (PyPI zenoh-cli, a dev dependency) with our codec, as the design
card's live introspection: subscribe, get and put against running services.

An in-process router listens on a free loopback port; the force service (sim sensor) is a
client of it, as on the robot host; `zenoh --mode client --connect …` runs as a subprocess
and finds our codec through its entry points (setup.py). Every wait has a deadline.
"""

from __future__ import annotations

import json
import shutil
import sys
import threading
from collections.abc import Iterator
from pathlib import Path

import pytest
import zenoh

from services.bus import codec, keys, zenoh_cli_codec
from services.bus.config import Mode, NodeConfig
from services.bus.messages import IDENTITY_R, Event, ForceSample
from services.bus.node import Node
from services.control.force.config import ForceConfig
from services.control.force.service import ForceService
from tests.bus.test_router import spawned
from tests.conftest import free_port

pytest.importorskip("zenoh_cli", reason="zenoh-cli is a dev dependency: pip install -e '.[dev]'")

DEADLINE_S = 20.0
ZENOH = shutil.which("zenoh", path=str(Path(sys.executable).parent)) or "zenoh"


class Cell:
    """A router and the force service on loopback: a client of the router as on the robot
    host (robot.toml), or a peer connected to it as in the simulation profile (sim.toml)."""

    def __init__(self, service_mode: Mode = "client") -> None:
        self.endpoint = f"tcp/127.0.0.1:{free_port()}"
        self.router = Node("router", NodeConfig(mode="router", listen=(self.endpoint,)))
        self.force_node = Node("force", NodeConfig(mode=service_mode, connect=(self.endpoint,)))
        # 200 Hz is plenty to see a stream and keeps the test light on a shared machine.
        self.force = ForceService(self.force_node, ForceConfig(seed=3, period_ms=5.0))
        # The sim sensor senses once it knows where the tool is (robot/state from a arm).
        self.force.core.update_robot_state((0.5, 0.0, 0.5), IDENTITY_R, (0.5, 0.0, 0.7), IDENTITY_R)
        self.nodes: list[Node] = []

    def client(self, name: str) -> Node:
        return Node(name, NodeConfig(mode="client", connect=(self.endpoint,)))

    def zenoh(self, *args: str) -> list[str]:
        return [ZENOH, "--mode", "client", "--connect", self.endpoint, *args]

    def close(self) -> None:
        self.force.close()
        for n in [*self.nodes, self.force_node, self.router]:
            n.close()


@pytest.fixture
def cell(request: pytest.FixtureRequest) -> Iterator[Cell]:
    c = Cell(getattr(request, "param", "client"))
    try:
        yield c
    finally:
        c.close()


def json_line(line: str) -> dict[str, object]:
    try:
        value = json.loads(line)
    except json.JSONDecodeError:
        return {}
    return value if isinstance(value, dict) else {}


@pytest.mark.parametrize("cell", ["client", "peer"], indirect=True)
def test_subscribe_prints_decoded_force_samples(cell: Cell) -> None:
    argv = cell.zenoh("subscribe", "-k", "robot/force", "--decoder", "telerobot")
    seen = 0

    def fifth_sample(line: str) -> bool:
        nonlocal seen
        seen += "seq" in json_line(line)
        return seen >= 5

    with spawned(argv, merge_stderr=False) as child:
        child.expect(fifth_sample)
        rows = [json_line(s) for s in child.lines if "seq" in json_line(s)]
    assert len(rows) >= 5 and not any("Decoder" in e for e in child.errors)
    seqs = [r["seq"] for r in rows]
    assert seqs == sorted(seqs) and len(set(seqs)) == len(seqs)
    for r in rows:
        assert set(r) >= {"seq", "t_ns", "f", "c"} and "_rejected" not in r
        assert len(r["f"]) == 3 and len(r["c"]) == 3  # type: ignore[arg-type]


def test_subscribe_with_a_wildcard_and_the_key_in_the_line(cell: Cell) -> None:
    argv = cell.zenoh(
        "subscribe", "-k", "robot/**", "--decoder", "telerobot", "--line", "{key} {value}"
    )
    with spawned(argv, merge_stderr=False) as child:
        line = child.expect("robot/force ")
    key, _, value = line.partition(" ")
    assert key == "robot/force" and isinstance(json_line(value).get("seq"), int)


def test_get_calls_a_method_and_decodes_the_reply(cell: Cell) -> None:
    argv = cell.zenoh("get", "-s", "robot/force/rpc/sensor_status", "--decoder", "telerobot")
    with spawned(argv, merge_stderr=False) as child:
        assert child.wait(DEADLINE_S) == 0
        lines = child.rest()
    assert len(lines) == 1, (lines, child.errors)
    status = json.loads(lines[0])
    assert status["running"] is True and status["period_ms"] == 5.0
    assert status["sensor"] == "sim" and status["samples"] >= 0


def test_get_with_arguments_through_the_encoder(cell: Cell) -> None:
    argv = cell.zenoh(
        "get",
        "-s",
        "robot/force/rpc/sensor_config",
        "--encoder",
        "telerobot",
        "-v",
        '{"period_ms": 4.0}',
        "--decoder",
        "telerobot",
    )
    with spawned(argv, merge_stderr=False) as child:
        assert child.wait(DEADLINE_S) == 0
        lines = child.rest()
    assert len(lines) == 1 and json.loads(lines[0])["period_ms"] == 4.0, (lines, child.errors)
    assert cell.force.core.rpc_sensor_status({})["period_ms"] == 4.0


def test_put_sends_a_contract_message(cell: Cell) -> None:
    listener = cell.client("listener")
    cell.nodes.append(listener)
    events = listener.subscribe(keys.EVENTS)
    event = {"seq": 41, "t_ns": 7, "source": "zenoh-cli", "kind": "data", "message": "hello"}
    argv = cell.zenoh(
        "put", "-k", "robot/events", "--encoder", "telerobot", "-v", json.dumps(event)
    )
    with spawned(argv, merge_stderr=False) as child:
        assert child.wait(DEADLINE_S) == 0, child.errors
    got = events.wait_for(lambda e: e.source == "zenoh-cli", DEADLINE_S)
    assert got == Event(seq=41, t_ns=7, source="zenoh-cli", kind="data", message="hello")


def test_put_of_a_broken_message_fails_loudly_and_sends_nothing(cell: Cell) -> None:
    listener = cell.client("listener")
    cell.nodes.append(listener)
    raw: list[bytes] = []
    arrived = threading.Event()

    def on_cmd(sample: zenoh.Sample) -> None:
        raw.append(sample.payload.to_bytes())
        arrived.set()

    listener.subscribe_raw("robot/cmd", on_cmd)
    bad = {"seq": 1, "t_ns": 1, "master": "m", "engage": 1, "active": True, "frame": "world"}
    bad |= {"dp": [0.0, 0.0], "dR": [1, 0, 0, 0, 1, 0, 0, 0, 1]}
    argv = cell.zenoh("put", "-k", "robot/cmd", "--encoder", "telerobot", "-v", json.dumps(bad))
    with spawned(argv, merge_stderr=False) as child:
        assert child.wait(DEADLINE_S) != 0
        child.rest()
    assert any("not a valid OperatorCommand: dp" in e for e in child.errors), child.errors
    # A good message put after it arrives; the bad one never did (order on one key).
    good = {**bad, "seq": 2, "dp": [0.0, 0.0, 0.01]}
    argv = cell.zenoh("put", "-k", "robot/cmd", "--encoder", "telerobot", "-v", json.dumps(good))
    with spawned(argv, merge_stderr=False) as child:
        assert child.wait(DEADLINE_S) == 0, child.errors
    assert arrived.wait(DEADLINE_S)
    assert len(raw) == 1 and json.loads(zenoh_cli_codec.decode("robot/cmd", raw[0]))["seq"] == 2


def test_the_codec_takes_a_key_expr_as_zenoh_cli_passes_it() -> None:
    sample = ForceSample(seq=3, t_ns=9, f=(1.0, 2.0, 3.0), c=(0.0, 0.0, 0.5))
    payload = zenoh_cli_codec.encode(
        zenoh.KeyExpr("cell2/robot/force"),
        json.dumps({"seq": 3, "t_ns": 9, "f": [1.0, 2.0, 3.0], "c": [0.0, 0.0, 0.5]}),
    )
    assert codec.decode(ForceSample, payload) == sample
    shown = json.loads(zenoh_cli_codec.decode(zenoh.KeyExpr("cell2/robot/force"), payload))
    assert shown == {
        "seq": 3,
        "t_ns": 9,
        "f": [1.0, 2.0, 3.0],
        "c": [0.0, 0.0, 0.5],
        "raw": None,
        "estimate": None,
    }


@pytest.mark.parametrize(
    ("key", "value", "message"),
    [
        ("robot/force", "{seq: 1}", "telerobot encoder: not JSON"),
        ("lab/x", "[1, 2]", "the value must be a JSON object"),
        ("robot/force", '{"seq": 1, "t_ns": 1, "f": [0, 0], "c": [0, 0, 0]}', "ForceSample: f"),
    ],
)
def test_the_encoder_refuses_what_would_break_the_contract(
    key: str, value: str, message: str
) -> None:
    with pytest.raises(ValueError, match=message):
        zenoh_cli_codec.encode(key, value)
