"""A whole sim session — arm, force, decision and a scripted master — recorded, checked with
the mcap library, replayed byte for byte into fresh subscribers, and reported."""

from __future__ import annotations

import io
import itertools
import json
import signal
import threading
import time
from collections import defaultdict
from collections.abc import Iterator
from contextlib import redirect_stderr, redirect_stdout
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pytest
import zenoh
from mcap.decoder import DecoderFactory
from mcap.reader import make_reader
from mcap.records import Schema

from services.bus import codec, keys
from services.bus.messages import Event, RobotState
from services.control.arm.config import ArmConfig
from services.control.arm.service import ArmService
from services.control.decision.config import DecisionConfig
from services.control.decision.service import DecisionService
from services.control.force.config import ForceConfig
from services.control.force.service import ForceService
from services.control.master.config import MasterConfig
from services.control.master.devices.scripted import ScriptedOptions
from services.control.master.service import MasterService
from services.tools.cli.main import main as telerobot
from services.tools.record import schemas
from services.tools.record.archive import Recording
from services.tools.record.recorder import Recorder, RecorderConfig, RecorderStats
from services.tools.record.replay import Replayer, ReplayOptions
from services.tools.record.report import analyze
from tests.conftest import Net, wait_until
from tests.tools.record.helpers import conforms

pytestmark = pytest.mark.system

SESSION_KEYS = {
    "robot/cmd",
    "robot/arm/target",
    "robot/arm/description",
    "robot/state",
    "robot/force",
    "robot/events",
    "master/state",
    "master/feedback",
}


@dataclass(frozen=True)
class Session:
    path: Path
    stats: RecorderStats


@pytest.fixture(scope="module")
def session(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Session]:
    path = tmp_path_factory.mktemp("session") / "session.mcap"
    net = Net()
    services: list[object] = []
    try:
        rec = Recorder(net.node("record"), RecorderConfig(output=str(path), chunk_interval_s=0.2))
        services.append(ArmService(net.node("arm"), ArmConfig(sim_calibration_s=0.05)))
        services.append(ForceService(net.node("force"), ForceConfig()))
        services.append(DecisionService(net.node("decision"), DecisionConfig()))
        op = net.node("operator")
        state = op.subscribe(keys.STATE)
        op.call("decision", "connect", {}, timeout_s=10.0)
        op.call("decision", "initialize", {"wait": True}, timeout_s=20.0)
        assert state.wait_for(lambda s: s.status == "ready", 20.0) is not None
        cmds = op.subscribe(keys.ARM_TARGET)
        services.append(
            MasterService(
                net.node("master", instance="m1"),
                MasterConfig(master_id="m1", device="scripted", options=ScriptedOptions("circle")),
            )
        )
        assert cmds.wait_count(300, 30.0), "the decision server never forwarded commands"
    finally:
        for svc in reversed(services):
            svc.close()  # type: ignore[attr-defined]
    stats = rec.stop()
    net.close()
    yield Session(path, stats)


def test_the_recording_is_valid_mcap_with_every_stream(session: Session) -> None:
    assert session.stats.dropped == 0 and session.stats.error == ""
    assert set(session.stats.keys) >= SESSION_KEYS

    class JsonDecoder(DecoderFactory):
        def decoder_for(self, message_encoding: str, schema: Schema | None):  # type: ignore[no-untyped-def]
            return json.loads if message_encoding == "json" else None

    with session.path.open("rb") as f:
        reader = make_reader(f, validate_crcs=True, decoder_factories=[JsonDecoder()])
        summary = reader.get_summary()
        assert summary is not None and summary.statistics is not None
        counts: dict[str, int] = defaultdict(int)
        checked: set[str] = set()
        n = 0
        for schema, channel, message in reader.iter_messages():
            n += 1
            counts[channel.topic] += 1
            assert message.log_time >= message.publish_time - 5_000_000_000
            if channel.message_encoding == "json" and channel.topic not in checked:
                checked.add(channel.topic)
                assert schema is not None and schema.encoding == "jsonschema"
                doc = json.loads(message.data)
                assert conforms(json.loads(schema.data), doc) == []
        decoded = sum(1 for _ in reader.iter_decoded_messages(topics=["robot/state"]))
    assert n == summary.statistics.message_count
    assert {
        c.topic: summary.statistics.channel_message_counts[i] for i, c in summary.channels.items()
    } == counts
    for key in SESSION_KEYS:
        assert counts[key] == counts[schemas.raw_topic(key)] == session.stats.keys[key].written
    assert decoded == counts["robot/state"]
    assert checked == SESSION_KEYS | {"/tf", "/robot_model", "/robot_description"}
    assert counts["/tf"] == counts["robot/state"]
    # the arm described itself once (at start-up), the recorder already listening
    assert counts["robot/arm/description"] == 1
    assert counts["/robot_model"] == counts["/robot_description"] == 1
    assert session.stats.arm_model == "puma560" and session.stats.robot_models == 1


def test_replay_republishes_the_same_bytes_in_the_same_order_per_key(
    session: Session,
) -> None:
    recorded: dict[str, list[bytes]] = defaultdict(list)
    first_ns = last_ns = None
    for m in Recording(session.path).raw():
        recorded[m.key].append(m.payload)
        first_ns = first_ns or m.log_time_ns
        last_ns = m.log_time_ns
    total = sum(len(v) for v in recorded.values())
    got: dict[str, list[bytes]] = defaultdict(list)
    lock = threading.Lock()
    done = threading.Event()

    def on_sample(sample: zenoh.Sample) -> None:
        with lock:
            got[str(sample.key_expr)].append(sample.payload.to_bytes())
            if sum(len(v) for v in got.values()) >= total:
                done.set()

    net = Net()
    try:
        net.node("console").subscribe_raw("**", on_sample)
        stats = Replayer(net.node("replay"), [session.path], ReplayOptions(speed=1.0)).run()
        assert done.wait(10.0), f"{sum(len(v) for v in got.values())} of {total} arrived"
    finally:
        net.close()
    assert stats.unmatched == [] and stats.passes == 1
    assert dict(stats.published) == {k: len(v) for k, v in recorded.items()}
    for key, payloads in recorded.items():
        assert got[key] == payloads, key
    assert set(got) == set(recorded)
    # at recorded timing: never faster than the session itself
    assert first_ns is not None and last_ns is not None
    assert stats.duration_s >= (last_ns - first_ns) / 1e9


def test_replay_filters_keys_and_loops_until_stopped(session: Session) -> None:
    events = [m.payload for m in Recording(session.path).raw() if m.key == "robot/events"]
    assert events
    got: list[tuple[str, bytes]] = []
    stop = threading.Event()

    def on_sample(sample: zenoh.Sample) -> None:
        got.append((str(sample.key_expr), sample.payload.to_bytes()))
        if len(got) >= 2 * len(events):
            stop.set()

    net = Net()
    try:
        net.node("console").subscribe_raw("**", on_sample)
        stats = Replayer(
            net.node("replay"),
            [session.path],
            ReplayOptions(speed=0.0, loop=True, keys=("robot/events",)),
        ).run(stop)
    finally:
        net.close()
    assert stats.passes >= 2 and set(stats.published) == {"robot/events"}
    assert {k for k, _ in got} == {"robot/events"}
    assert [p for _, p in got[: 2 * len(events)]] == events + events


def test_the_report_matches_the_recording_and_draws_the_plots(
    session: Session, tmp_path: Path
) -> None:
    msgs = list(Recording(session.path).raw())
    report = analyze([session.path])
    assert report.messages == len(msgs) and report.truncated == []
    assert report.recorder is not None and report.recorder["dropped"] == 0
    for key in SESSION_KEYS:
        mine = [m for m in msgs if m.key == key]
        k = report.key(key)
        assert k.count == len(mine) and k.rejected == 0
        if len(mine) > 1:  # the description comes once
            span_s = (mine[-1].log_time_ns - mine[0].log_time_ns) / 1e9
            assert k.rate_hz == pytest.approx((len(mine) - 1) / span_s)
        else:
            assert k.rate_hz == 0.0
        topic = keys.topic_for(key)
        assert topic is not None
        decoded = [codec.decode(topic.type, m.payload) for m in mine]
        lat = [(m.log_time_ns - d.t_ns) / 1e6 for m, d in zip(mine, decoded, strict=True)]
        assert k.publish_to_record_ms is not None and k.publish_to_record_ms.mean == pytest.approx(
            np.mean(lat)
        )
        assert k.publish_to_record_ms.max == pytest.approx(max(lat))
        by_sender: dict[str, list[int]] = defaultdict(list)
        for d in decoded:
            sender = getattr(d, "source", None) or getattr(d, "master", "") or ""
            by_sender[sender].append(d.seq)
        missing = sum(
            max(0, b - a - 1) for s in by_sender.values() for a, b in itertools.pairwise(s)
        )
        assert k.missing == missing and k.senders == len(by_sender)
    events = [codec.decode(Event, m.payload) for m in msgs if m.key == "robot/events"]
    assert [(e.source, e.kind, e.message) for e in report.events] == [
        (e.source, e.kind, e.message) for e in events
    ]
    assert any(e.kind == "status" and e.source == "arm" for e in report.events)
    states = [codec.decode(RobotState, m.payload) for m in msgs if m.key == "robot/state"]
    assert len(report.traces.tool_p) == sum(s.status in ("ready", "moving") for s in states)
    assert len(report.traces.force_f) == report.key("robot/force").count
    assert report.tracking_mm is not None and report.tracking_mm.n > 0
    assert len(report.traces.targets["robot/arm/target"][0]) > 0

    out = io.StringIO()
    with redirect_stdout(out):
        assert telerobot(["report", str(session.path), "--plots", str(tmp_path)]) == 0
    text = out.getvalue()
    for key in SESSION_KEYS:
        row = next(line for line in text.splitlines() if line.startswith(key + " "))
        assert str(report.key(key).count) in row.split()
    assert "status: ready" in text
    import cv2

    for name in ("force.png", "path.png"):
        p = tmp_path / name
        assert p.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
        img = cv2.imread(str(p))
        assert img is not None and img.shape[0] > 300 and img.shape[1] > 600
        assert (img < 128).any() and (img == 255).mean() > 0.5  # ink on a white page

    out = io.StringIO()
    with redirect_stdout(out):
        assert telerobot(["report", str(session.path), "--json"]) == 0
    data = json.loads(out.getvalue())
    assert data["messages"] == report.messages
    assert {k["key"]: k["count"] for k in data["keys"]} == {k.key: k.count for k in report.keys}


def test_telerobot_replay_command(session: Session) -> None:
    events = [m.payload for m in Recording(session.path).raw() if m.key == "robot/events"]
    got: list[bytes] = []
    net = Net()
    handlers = {s: signal.getsignal(s) for s in (signal.SIGINT, signal.SIGTERM)}
    try:
        net.node("console").subscribe_raw("robot/**", lambda s: got.append(s.payload.to_bytes()))
        out = io.StringIO()
        with redirect_stdout(out):
            rc = telerobot(
                [
                    "replay",
                    str(session.path),
                    "--connect",
                    net.endpoint,
                    "--speed",
                    "0",
                    "--keys",
                    "robot/events",
                    "--wait-s",
                    "5",
                ]
            )
        assert rc == 0
        deadline = time.monotonic() + 10.0
        while len(got) < len(events) and time.monotonic() < deadline:
            time.sleep(0.01)
    finally:
        for s, h in handlers.items():
            signal.signal(s, h)
        net.close()
    result = json.loads(out.getvalue())
    assert result["published"] == {"robot/events": len(events)} and result["unmatched"] == []
    assert got == events


def test_the_live_arm_s_transforms_reproduce_its_tool_pose(session: Session) -> None:
    """Over the real arm's states: each /tf message (from the arm's description) composes
    (world → … → tool) to the tool pose of the robot/state it was derived from, within
    1e-9, and its flange is the PUMA's closed-form FK of the recorded q."""
    from services.control.arm.puma560 import Puma560

    from .test_foxglove3d import _compose

    kin = Puma560()
    with session.path.open("rb") as f:
        reader = make_reader(f)
        pairs: dict[int, dict[str, bytes]] = defaultdict(dict)
        for _, channel, message in reader.iter_messages(topics=["robot/state", "/tf"]):
            pairs[message.log_time].setdefault(channel.topic, message.data)
    checked = 0
    for both in pairs.values():
        if len(both) != 2:
            continue
        st = json.loads(both["robot/state"])
        tfs = json.loads(both["/tf"])["transforms"]
        if len(tfs) == 2:
            continue  # a state before the description arrived: its own poses only
        poses = _compose(tfs)
        assert np.allclose(poses["tool"][0], st["tool_p"], atol=1e-9)
        assert np.allclose(poses["tool"][1], np.reshape(st["tool_R"], (3, 3)), atol=1e-9)
        assert np.allclose(poses["flange"][0], kin.fk_flange(st["q"]).translation, atol=1e-9)
        assert np.allclose(poses["flange"][0], st["flange_p"], atol=1e-9)
        checked += 1
    assert checked > 10


def test_replay_refuses_a_live_cell_unless_told_and_marks_what_it_sends(
    session: Session,
) -> None:
    """Issue 42 item 7: `replay` into a running system republished old robot/events and
    robot/state on the live keys, unmarked. Now it refuses (exit 2, naming the live
    services) while an arm or decision is alive in its namespace; `--into-live` replays,
    and every sample carries the attachment `replay`."""
    events = [m.payload for m in Recording(session.path).raw() if m.key == "robot/events"]
    got: list[tuple[bytes, bytes | None]] = []
    lock = threading.Lock()
    net = Net()
    handlers = {s: signal.getsignal(s) for s in (signal.SIGINT, signal.SIGTERM)}

    def on_sample(s: zenoh.Sample) -> None:
        mark = None if s.attachment is None else s.attachment.to_bytes()
        with lock:
            got.append((s.payload.to_bytes(), mark))

    def replay(*extra: str) -> tuple[int, str]:
        err = io.StringIO()
        out = io.StringIO()
        with redirect_stdout(out), redirect_stderr(err):
            args = ["--connect", net.endpoint, "--speed", "0", "--keys", "robot/events"]
            rc = telerobot(["replay", str(session.path), *args, "--wait-s", "5", *extra])
        return rc, err.getvalue()

    try:
        net.node("arm").announce()  # a live arm in this namespace
        net.node("console").subscribe_raw("robot/events", on_sample)
        rc, err = replay()
        assert rc == 2 and "refused: arm run in this namespace" in err and "--into-live" in err
        assert got == []  # nothing was published
        rc, _ = replay("--into-live")
        assert rc == 0
        assert wait_until(lambda: len(got) >= len(events), 10.0)
    finally:
        for s, h in handlers.items():
            signal.signal(s, h)
        net.close()
    assert [p for p, _ in got] == events
    assert {m for _, m in got} == {b"replay"}
