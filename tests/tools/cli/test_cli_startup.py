"""The CLI answers at once and always ends (issue 23 item 10; item 8's `call master status`).

"At once" is held by what is imported, not by wall-clock time: `--help`, `--version` and a
bad `call` argument must not load Zenoh, numpy, OpenCV or Pinocchio (seconds on a loaded
machine). Each case runs in a fresh interpreter and reports `sys.modules`.
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import threading
from typing import Any

import pytest

from services.bus.node import Node
from services.tools.cli import main as cli_main
from tests.bus.test_router import REPO, spawned, telerobot
from tests.conftest import Net
from tests.tools.cli.test_introspect import Streamer

DEADLINE_S = 20.0
HEAVY = ("zenoh", "numpy", "cv2", "pinocchio")

PROBE = r"""
import contextlib, io, json, sys
argv, preload = json.loads(sys.argv[1]), sys.argv[2]
if preload:
    __import__(preload)
from services.tools.cli.main import main
out = io.StringIO()
with contextlib.redirect_stdout(out), contextlib.redirect_stderr(io.StringIO()):
    try:
        code = main(argv)
    except SystemExit as e:
        code = e.code
heavy = sorted({m.split(".")[0] for m in sys.modules} & set(json.loads(sys.argv[3])))
print(json.dumps({"code": code, "heavy": heavy, "out": out.getvalue()}))
"""


def probe(argv: list[str], preload: str = "") -> dict[str, Any]:
    """Run `telerobot ARGV` in a fresh interpreter: exit code, heavy modules loaded, stdout."""
    done = subprocess.run(
        [sys.executable, "-c", PROBE, json.dumps(argv), preload, json.dumps(HEAVY)],
        cwd=REPO,
        capture_output=True,
        text=True,
        timeout=60,
    )
    assert done.returncode == 0, done.stderr
    result: dict[str, Any] = json.loads(done.stdout.splitlines()[-1])
    return result


@pytest.mark.parametrize(
    "argv",
    [
        ["--help"],
        ["alive", "--help"],
        ["call", "--help"],
        ["topic", "echo", "--help"],
        ["topic", "hz", "--help"],
        ["topic", "list", "--help"],
    ],
)
def test_help_loads_no_heavy_module(argv: list[str]) -> None:
    r = probe(argv)
    assert r["code"] == 0 and r["heavy"] == []
    assert r["out"].startswith("usage: telerobot")


def test_version_loads_no_heavy_module() -> None:
    r = probe(["--version"])
    assert r["code"] == 0 and r["heavy"] == []
    assert r["out"] == f"telerobot {cli_main.version()}\n"


@pytest.mark.parametrize(
    ("args", "message"),
    [("{not json", "arguments: Expecting property name"), ("[1, 2]", "must be a JSON object")],
)
def test_a_bad_call_argument_fails_before_zenoh(args: str, message: str) -> None:
    r = probe(["call", "arm", "move_relative", args])
    assert r["code"] == 1 and r["heavy"] == []
    reply = json.loads(r["out"])
    assert reply["error"] == "bad_request" and reply["message"].find(message) >= 0


def test_the_probe_sees_a_heavy_import() -> None:
    """The control: the same probe reports Zenoh and numpy when they are loaded."""
    r = probe(["--help"], preload="services.bus.node")
    assert r["code"] == 0 and {"zenoh", "numpy"} <= set(r["heavy"])


def _options(parser: argparse.ArgumentParser, path: str) -> list[tuple[str, argparse.Action]]:
    found = []
    for action in parser._actions:
        if isinstance(action, argparse._SubParsersAction):
            for name, child in action.choices.items():
                found += _options(child, f"{path} {name}")
        elif not isinstance(action, argparse._HelpAction):
            found.append((path, action))
    return found


def test_every_option_and_argument_has_help() -> None:
    actions = _options(cli_main.build_parser(cli_main._available()), "telerobot")
    names = {f"{path} {a.dest}" for path, a in actions}
    assert {"telerobot call timeout", "telerobot topic hz duration", "telerobot version"} <= names
    missing = [f"{path} {a.option_strings or a.dest}" for path, a in actions if not a.help]
    assert missing == []


# --- against a service ------------------------------------------------------------------


def run(net: Net, *args: str) -> tuple[int, list[Any], list[str]]:
    """`telerobot ARGS --connect <net>` to the end: exit code, JSON stdout lines, stderr."""
    with spawned(telerobot(*args, "--connect", net.endpoint), merge_stderr=False) as child:
        code = child.wait(DEADLINE_S)
        rows = [json.loads(line) for line in child.rest()]
    return code, rows, child.errors


@pytest.fixture
def service(net: Net) -> Node:
    node = net.node("arm")
    node.serve("arm", {"status": lambda args: {"status": "ready"}})
    node.announce()
    return node


def test_echo_on_a_silent_key_says_so_and_ends(net: Net, service: Node) -> None:
    code, rows, errors = run(
        net, "topic", "echo", "robot/state", "--hint-after", "0.3", "--timeout", "1.5"
    )
    assert code == 1 and rows == []
    assert [e.split("…")[0] for e in errors if "no sample" in e] == [
        "telerobot: no sample on robot/state yet",
        "telerobot: no sample on robot/state in 1.5 s",
    ]


def test_hz_ends_after_its_duration(net: Net, service: Node) -> None:
    streamer = Streamer(service)
    try:
        code, rows, _ = run(net, "topic", "hz", "robot/force", "--window", "0.5", "--duration", "1")
    finally:
        streamer.close()
    assert code == 0 and 1 <= len(rows) <= 2
    assert rows[-1]["key"] == "robot/force" and rows[-1]["total"] > 0


def test_hz_ends_after_count_samples(net: Net, service: Node) -> None:
    streamer = Streamer(service)
    try:
        code, rows, _ = run(
            net, "topic", "hz", "robot/force", "--count", "20", "--duration", "0", "--window", "60"
        )
    finally:
        streamer.close()
    assert code == 0 and len(rows) == 1 and rows[0]["total"] >= 20 and rows[0]["samples"] >= 20


def test_hz_on_a_silent_key_exits_1(net: Net, service: Node) -> None:
    code, rows, errors = run(net, "topic", "hz", "robot/state", "--duration", "0.5")
    assert code == 1 and any("no sample on robot/state in" in e for e in errors)
    assert [r["total"] for r in rows] == [0]


def serve_master(net: Net, master_id: str) -> Node:
    node = net.node("master", instance=master_id)
    node.serve(f"master/{master_id}", {"status": lambda args: {"master": master_id}})
    node.announce()
    return node


def test_call_a_role_calls_its_single_instance(net: Net, service: Node) -> None:
    serve_master(net, "master")
    code, rows, _ = run(net, "call", "master", "status", "--timeout", "10")
    assert (code, rows) == (0, [{"master": "master"}])
    code, rows, _ = run(net, "call", "master/master", "status", "--timeout", "10")
    assert (code, rows) == (0, [{"master": "master"}])


def test_call_a_role_with_several_instances_names_them(net: Net, service: Node) -> None:
    serve_master(net, "m1")
    serve_master(net, "m2")
    assert service.alive.wait("master/m1", DEADLINE_S) and service.alive.wait("master/m2", 20)
    code, rows, _ = run(net, "call", "master", "status", "--timeout", "10")
    assert code == 1 and len(rows) == 1 and rows[0]["error"] == "bad_request"
    assert "master/m1, master/m2" in rows[0]["message"]
    code, rows, _ = run(net, "call", "master/m2", "status", "--timeout", "10")
    assert (code, rows) == (0, [{"master": "m2"}])


def test_call_an_absent_service_lists_who_is_alive(net: Net, service: Node) -> None:
    code, rows, _ = run(net, "call", "decision", "status", "--timeout", "1")
    assert code == 2 and rows[0]["error"] == "unavailable"
    assert rows[0]["message"].endswith("alive: arm")


def test_call_that_times_out_says_the_request_may_be_running(net: Net) -> None:
    node = net.node("arm")
    release = threading.Event()
    started = threading.Event()

    def slow(args: dict[str, Any]) -> dict[str, Any]:
        started.set()
        release.wait(DEADLINE_S)
        return {}

    node.serve("arm", {"move_joints": slow})
    node.announce()
    try:
        code, rows, _ = run(net, "call", "arm", "move_joints", "--timeout", "1")
    finally:
        release.set()
    assert started.is_set() and code == 2 and len(rows) == 1
    assert rows[0]["error"] == "timed_out" and "may still be running" in rows[0]["message"]


def test_a_call_that_never_reaches_the_service_says_nothing_ran(net: Net) -> None:
    """What a call dropped by the router's ACL looks like from the caller: the service is
    alive, yet no queryable answers. Not "timed out, may still be running": nothing ran."""
    node = net.node("arm")
    node.announce()  # alive, but serving no methods at all
    code, rows, _ = run(net, "call", "arm", "move_joints", "--timeout", "1")
    assert code == 2 and len(rows) == 1 and rows[0]["error"] == "unavailable"
    assert "never reached it, so nothing ran" in rows[0]["message"]
    assert "access control" in rows[0]["message"]
