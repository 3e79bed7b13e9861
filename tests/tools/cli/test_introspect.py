"""`telerobot topic|call|alive` as a user runs them: a subprocess against an in-process service.

The service is the first node of a private loopback network (it listens); the CLI connects
to it with `--connect`. Output is parsed as JSON lines; every wait has a deadline.
"""

from __future__ import annotations

import contextlib
import json
import signal
import threading
from collections.abc import Iterator
from typing import Any

import msgpack
import pytest

from services.bus import codec, keys, zenoh_cli_codec
from services.bus.errors import RpcError
from services.bus.messages import IDENTITY_R, ForceSample, OperatorCommand
from services.bus.node import Node
from services.tools.cli.introspect import decode_sample
from tests.bus.test_router import ChildProcess, spawned, telerobot
from tests.conftest import Net

DEADLINE_S = 20.0


def force(seq: int) -> ForceSample:
    return ForceSample(
        seq=seq, t_ns=1_000 + seq, f=(float(seq), -float(seq), 0.5), c=(0.0, 0.0, 1.0)
    )


class Streamer:
    """Publishes ForceSamples (seq 1, 2, …) at ~200 Hz from a thread until stopped."""

    def __init__(self, node: Node) -> None:
        self.pub = node.publisher(keys.FORCE)
        self.stop = threading.Event()
        self.seq = 0
        self.thread = threading.Thread(target=self._run, daemon=True)
        self.thread.start()

    def _run(self) -> None:
        while not self.stop.wait(0.005):  # pacing, not synchronisation
            self.seq += 1
            self.pub.put(force(self.seq))

    def close(self) -> None:
        self.stop.set()
        self.thread.join(5.0)


@pytest.fixture
def service(net: Net) -> Iterator[Node]:
    """The in-process 'arm' service every CLI run connects to."""
    node = net.node("arm")

    def status(args: dict[str, Any]) -> dict[str, Any]:
        return {"status": "ready", "q": [0.0, 1.5, -1.5, 0.0, 0.0, 0.0], "args": args}

    def limit(args: dict[str, Any]) -> dict[str, Any]:
        raise RpcError("limit", "joint 3 beyond 45°")

    node.serve("arm", {"status": status, "limit": limit})
    node.announce()
    yield node


def json_lines(child: ChildProcess) -> list[Any]:
    return [json.loads(line) for line in child.rest()]


def run_cli(net: Net, *args: str) -> tuple[int, list[Any]]:
    """Run `telerobot ARGS --connect <net>` to the end: exit code and JSON stdout lines."""
    with spawned(telerobot(*args, "--connect", net.endpoint), merge_stderr=False) as child:
        code = child.wait(DEADLINE_S)
        return code, json_lines(child)


# --- topic echo / hz / list -------------------------------------------------------------


def test_topic_echo_prints_decoded_samples(net: Net, service: Node) -> None:
    streamer = Streamer(service)
    try:
        code, rows = run_cli(
            net, "topic", "echo", "robot/force", "--count", "5", "--timeout", str(DEADLINE_S)
        )
    finally:
        streamer.close()
    assert code == 0 and len(rows) == 5
    seqs = [r["seq"] for r in rows]
    assert seqs == sorted(seqs) and len(set(seqs)) == 5
    for r in rows:
        assert r == {
            "seq": r["seq"],
            "t_ns": 1_000 + r["seq"],
            "f": [float(r["seq"]), -float(r["seq"]), 0.5],
            "c": [0.0, 0.0, 1.0],
            "raw": None,
            "estimate": None,
        }


def test_topic_echo_with_a_wildcard_names_keys_and_shows_rejections(
    net: Net, service: Node
) -> None:
    pub = service.publisher(keys.CMD)
    stop = threading.Event()

    def garbage() -> None:
        while not stop.wait(0.01):
            pub.put_bytes(b"\xc1not msgpack")

    t = threading.Thread(target=garbage, daemon=True)
    t.start()
    try:
        code, rows = run_cli(net, "topic", "echo", "robot/**", "--count", "2", "--timeout", "20")
    finally:
        stop.set()
        t.join(5.0)
    assert code == 0 and len(rows) == 2
    for r in rows:
        assert r["_key"] == "robot/cmd"
        assert r["_rejected"].startswith("payload: not valid msgpack")


def test_topic_echo_gets_the_cached_arm_description_published_before_it_came(
    net: Net, service: Node
) -> None:
    from services.bus.messages import ArmDescription
    from services.control.arm.model import load_model

    fields = load_model("ur5e").description()
    service.publisher(keys.ARM_DESCRIPTION, cache=1).put(ArmDescription(seq=3, t_ns=7, **fields))
    code, rows = run_cli(
        net, "topic", "echo", "robot/arm/description", "--count", "1", "--timeout", "20"
    )
    assert code == 0 and len(rows) == 1
    got = rows[0]
    assert (got["seq"], got["model"], got["n"]) == (3, "ur5e", 6)
    assert [j["name"] for j in got["joints"]] == list(load_model("ur5e").joint_names)


def test_topic_echo_times_out_with_exit_1(net: Net, service: Node) -> None:
    code, rows = run_cli(net, "topic", "echo", "robot/state", "--count", "1", "--timeout", "0.5")
    assert code == 1 and rows == []


def test_topic_hz_reports_a_rate(net: Net, service: Node) -> None:
    streamer = Streamer(service)
    try:
        code, rows = run_cli(net, "topic", "hz", "robot/force", "--window", "0.5", "--reports", "2")
    finally:
        streamer.close()
    assert code == 0 and len(rows) == 2
    assert rows[-1]["key"] == "robot/force" and rows[-1]["window_s"] == 0.5
    assert rows[-1]["samples"] > 1 and rows[-1]["rate_hz"] > 0


def test_topic_list_shows_keys_with_their_types(net: Net, service: Node) -> None:
    streamer = Streamer(service)
    other = service.session.declare_publisher("lab/notes")
    stop = threading.Event()

    def notes() -> None:
        while not stop.wait(0.02):
            other.put(codec.pack({"n": 1}))

    t = threading.Thread(target=notes, daemon=True)
    t.start()
    try:
        code, rows = run_cli(net, "topic", "list", "--json", "--duration", "1")
    finally:
        stop.set()
        t.join(5.0)
        streamer.close()
    assert code == 0 and len(rows) == 1
    by_key = {r["key"]: r for r in rows[0]}
    assert by_key["robot/force"]["type"] == "ForceSample"
    assert by_key["robot/force"]["rate_hz"] > 0
    assert by_key["lab/notes"]["type"] == "?"


def test_topic_list_text_aligns_its_columns_to_the_longest_key(net: Net, service: Node) -> None:
    """The ROS bridge's keys run to ~190 characters: the columns widen with them."""
    long_key = "ros2/" + "x" * 185
    pub = service.session.declare_publisher(long_key)
    stop = threading.Event()

    def notes() -> None:
        while not stop.wait(0.02):
            pub.put(codec.pack({"n": 1}))

    t = threading.Thread(target=notes, daemon=True)
    t.start()
    try:
        argv = telerobot("topic", "list", "--duration", "1", "--connect", net.endpoint)
        with spawned(argv, merge_stderr=False) as child:
            assert child.wait(DEADLINE_S) == 0
            lines = list(child.rest())
    finally:
        stop.set()
        t.join(5.0)
    header, rows = lines[0], lines[1:]
    assert header.startswith("KEY" + " " * (len(long_key) - 2)) and [
        r for r in rows if long_key in r
    ]
    type_col = header.index("TYPE")
    assert all(len(r) > type_col and r[type_col - 1] == " " for r in rows)


# --- call ----------------------------------------------------------------------------


def test_call_pretty_indents_the_reply(net: Net, service: Node) -> None:
    argv = telerobot(
        "call", "arm", "status", "--pretty", "--timeout", "10", "--connect", net.endpoint
    )
    with spawned(argv, merge_stderr=False) as child:
        assert child.wait(DEADLINE_S) == 0
        text = "\n".join(child.rest())
    assert text.startswith("{\n  ") and json.loads(text)["status"] == "ready"


def test_call_prints_the_reply(net: Net, service: Node) -> None:
    code, rows = run_cli(net, "call", "arm", "status", '{"verbose": true}', "--timeout", "10")
    assert code == 0
    assert rows == [
        {"status": "ready", "q": [0.0, 1.5, -1.5, 0.0, 0.0, 0.0], "args": {"verbose": True}}
    ]


def test_call_error_prints_the_code_and_exits_1(net: Net, service: Node) -> None:
    code, rows = run_cli(net, "call", "arm", "limit", "--timeout", "10")
    assert code == 1 and rows == [{"error": "limit", "message": "joint 3 beyond 45°"}]


def test_call_unknown_method_is_bad_request(net: Net, service: Node) -> None:
    code, rows = run_cli(net, "call", "arm", "fly", "--timeout", "10")
    assert code == 1 and rows[0]["error"] == "bad_request"


def test_call_without_a_service_is_unavailable_exit_2(net: Net, service: Node) -> None:
    code, rows = run_cli(net, "call", "force", "sensor_status", "--timeout", "1")
    assert code == 2 and len(rows) == 1 and rows[0]["error"] == "unavailable"


@pytest.mark.parametrize("args", ["{not json", "[1, 2]"])
def test_call_with_bad_arguments_is_bad_request(net: Net, service: Node, args: str) -> None:
    code, rows = run_cli(net, "call", "arm", "status", args)
    assert code == 1 and rows[0]["error"] == "bad_request"


# --- alive ---------------------------------------------------------------------------


def test_alive_lists_the_tokens(net: Net, service: Node) -> None:
    master = net.node("master", instance="m1")
    master.announce()
    assert service.alive.wait("master/m1", DEADLINE_S)
    code, rows = run_cli(net, "alive", "--json", "--timeout", "1.5")
    assert code == 0 and rows == [["arm", "master/m1"]]


def test_a_config_error_exits_2_naming_the_key(net: Net) -> None:
    with spawned(telerobot("alive", "--lease-ms", "9000"), merge_stderr=False) as child:
        assert child.wait(DEADLINE_S) == 2
        child.rest()
        assert any("zenoh.lease_ms" in line for line in child.errors)


# --- the zenoh-cli codec -------------------------------------------------------------


def test_zenoh_cli_codec_round_trips_a_contract_message() -> None:
    sample = force(7)
    text = json.dumps(codec.jsonable(sample))
    payload = zenoh_cli_codec.encode("robot/force", text)
    assert codec.decode(ForceSample, payload) == sample
    assert json.loads(zenoh_cli_codec.decode("robot/force", payload)) == json.loads(text)
    # Typed by the key even under a namespace.
    assert json.loads(zenoh_cli_codec.decode("cell2/robot/force", payload)) == json.loads(text)


def test_zenoh_cli_codec_shows_other_msgpack_as_json() -> None:
    payload = zenoh_cli_codec.encode("lab/notes", '{"a": [1, 2.5], "b": "x"}')
    assert msgpack.unpackb(payload) == {"a": [1, 2.5], "b": "x"}
    assert json.loads(zenoh_cli_codec.decode("lab/notes", payload)) == {"a": [1, 2.5], "b": "x"}
    assert json.loads(zenoh_cli_codec.decode("x/y", codec.pack({"d": b"abc"}))) == {
        "d": "<3 bytes>"
    }


def test_zenoh_cli_codec_shows_a_rejection_instead_of_failing() -> None:
    bad = codec.pack({"seq": 1, "t_ns": 1, "f": [0, 0], "c": [0, 0, 0]})
    shown = json.loads(zenoh_cli_codec.decode("robot/force", bad))
    assert shown["_rejected"].startswith("f: expected 3 numbers")
    cmd = OperatorCommand(1, 2, "m", 0, True, "world", (0.0, 0.0, 0.0), IDENTITY_R)
    shown = json.loads(zenoh_cli_codec.decode("cell9/robot/cmd", codec.encode(cmd)))
    assert shown["master"] == "m" and shown["dR"] == list(IDENTITY_R)
    assert decode_sample("robot/force", b"\xff\xfe")["_raw"] == "<2 bytes>"


@pytest.mark.parametrize(
    ("key", "plain"),
    [
        ("robot/cmd", "robot/cmd"),
        ("cell2/robot/cmd", "robot/cmd"),
        ("a/b/vision/stereo/l", "vision/stereo/l"),
        ("cell2/master/state", "master/state"),
        ("cell2/alive/arm", "alive/arm"),
        ("lab/notes", "lab/notes"),
        ("myrobot/x", "myrobot/x"),
    ],
)
def test_zenoh_cli_codec_strips_a_namespace(key: str, plain: str) -> None:
    assert zenoh_cli_codec._plain_key(key) == plain


def test_ctrl_c_on_a_waiting_motion_call_stops_the_motion(net: Net) -> None:
    """`telerobot call decision move_relative '{…, "wait": true}'`, then Ctrl-C: the motion
    it started is stopped (the service's `stop`), one line says so, no traceback."""
    import signal

    node = net.node("decision")
    started, stopped = threading.Event(), threading.Event()

    def move_relative(args: dict[str, Any]) -> dict[str, Any]:
        started.set()
        stopped.wait(DEADLINE_S)  # a motion with "wait": true, until it is stopped
        return {"status": "stopped"}

    def stop(args: dict[str, Any]) -> dict[str, Any]:
        stopped.set()
        return {"status": "ready"}

    node.serve("decision", {"move_relative": move_relative, "stop": stop})
    node.announce()
    argv = telerobot(
        "call", "decision", "move_relative", '{"dp": [-0.3, 0, -0.1], "wait": true}',
        "--timeout", "60", "--connect", net.endpoint,
    )  # fmt: skip
    # A child inherits an ignored SIGINT (POSIX: a non-interactive shell's `cmd &` runs it
    # with SIGINT ignored, and `nohup make test &` hands that down to pytest), and Python
    # then keeps ignoring it, as a program started so should: Ctrl-C is tested with it at
    # its default. A handler of ours is reset to the default at exec.
    with contextlib.ExitStack() as stack:
        previous = signal.signal(signal.SIGINT, signal.default_int_handler)
        try:
            child = stack.enter_context(spawned(argv))
        finally:
            signal.signal(signal.SIGINT, previous)
        assert started.wait(DEADLINE_S), "the call never reached the service"
        child.proc.send_signal(signal.SIGINT)
        assert child.wait(DEADLINE_S) == 130
        out = "\n".join(child.rest())
    assert stopped.is_set(), "Ctrl-C left the motion running"
    assert "Traceback" not in out and "KeyboardInterrupt" not in out, out
    reply = json.loads(out.strip().splitlines()[-1])
    assert reply["error"] == "interrupted" and "was stopped" in reply["message"]


def test_without_a_reachable_router_the_tools_say_so_and_exit_non_zero() -> None:
    """`telerobot alive` / `topic list` with no router used to print nothing and exit 0."""
    from tests.conftest import free_port

    nowhere = f"tcp/127.0.0.1:{free_port()}"
    for args in (("alive", "--timeout", "1"), ("topic", "list", "--duration", "1")):
        with spawned(telerobot(*args, "--connect", nowhere), merge_stderr=True) as child:
            assert child.wait(DEADLINE_S) == 1
            lines = child.rest()
        text = "\n".join(lines)
        assert f"no Zenoh router or peer reachable at {nowhere}" in text, text
        assert "Traceback" not in text


def test_a_service_that_cannot_connect_says_why_in_one_line() -> None:
    """A service waits for its router (a station may be switched on before the robot host):
    one line with the endpoint, the cause and what to check, no traceback; SIGTERM ends
    the wait cleanly. A tool that runs to completion fails at once (test_lifecycle)."""
    from tests.conftest import free_port

    nowhere = f"tcp/127.0.0.1:{free_port()}"
    argv = telerobot("decision", "--mode", "client", "--connect", nowhere)
    with spawned(argv, merge_stderr=True) as child:
        waiting = child.expect(lambda s: "Trying again" in s)
        child.proc.send_signal(signal.SIGTERM)
        assert child.wait(DEADLINE_S) == 0
        lines = [line for line in child.rest() if line.strip()]
    assert lines == [waiting, lines[-1]], lines
    assert f"decision: cannot connect to {nowhere}: Unable to" in waiting
    assert "Is the router up" in waiting
    assert lines[-1].endswith("decision: decision stopped before its router answered")
