"""The passivity figures (robot/passivity/master and /slave, docs/passivity.md) in a recording:
recorded from a live publisher with their JSON Schema (Foxglove plots the energies), listed
by the report, and replayed byte for byte."""

from __future__ import annotations

import json
import threading
import time
from pathlib import Path

import pytest
import zenoh
from mcap.reader import make_reader

from services.bus import codec, keys
from services.bus.messages import PassivityState
from services.tools.record import schemas
from services.tools.record.archive import Recording
from services.tools.record.recorder import Recorder, RecorderConfig
from services.tools.record.replay import Replayer, ReplayOptions
from services.tools.record.report import analyze, format_report, write_plots
from tests.conftest import Net, wait_until
from tests.tools.record.helpers import conforms

PER_SIDE = 40
SCHEMA = "telerobot.PassivityState"


def figures(side: str, k: int) -> PassivityState:
    """The k-th message of a side: energies that grow with k, the slave acting from k = 30;
    the master runs a rotational port too."""
    acting = side == "slave" and k >= 30
    rot = side == "master"
    return PassivityState(
        seq=k,
        t_ns=time.time_ns(),
        master="m1",
        engage=2,
        side=side,  # type: ignore[arg-type]
        enabled=True,
        e_in=0.01 * k if side == "master" else 0.005 * k,
        e_out=0.002 * k,
        dissipated_j=0.001 * (k - 29) if acting else 0.0,
        gain=2.5e-4 if acting else 0.0,
        active_steps=k - 29 if acting else 0,
        rot_e_in=0.004 * k if rot else None,
        rot_e_out=0.001 * k if rot else None,
    )


def _record(net: Net, path: Path) -> dict[str, list[PassivityState]]:
    """Record both sides' figures from a live publisher; the master skips seq 20 (a gap)."""
    rec = Recorder(net.node("record"), RecorderConfig(output=str(path), chunk_interval_s=0.2))
    pubnode = net.node("tdpa")
    probe = pubnode.session.declare_publisher(keys.PASSIVITY_SLAVE.key)
    try:
        assert wait_until(lambda: bool(probe.matching_status.matching), 10.0)
    finally:
        probe.undeclare()
    pubs = {
        "master": pubnode.publisher(keys.PASSIVITY_MASTER),
        "slave": pubnode.publisher(keys.PASSIVITY_SLAVE),
    }
    # The figures are best effort (latest wins): a burst on a starved host may lose some, as
    # it would on a link. The recorder is under test here, not the bus, so each is sent once
    # the one before it is in, and re-sent if it was lost (never after it arrived).
    sent: dict[str, list[PassivityState]] = {"master": [], "slave": []}
    total = 0
    for k in range(1, PER_SIDE + 1):
        for side, pub in pubs.items():
            if side == "master" and k == 20:
                continue
            msg = figures(side, k)
            sent[side].append(msg)
            total += 1
            for _ in range(3):
                pub.put(msg)
                if wait_until(lambda n=total: rec.stats().received >= n, 5.0):
                    break
            assert rec.stats().received == total, rec.stats().as_dict()
    stats = rec.stop()
    assert stats.dropped == 0 and stats.written == total and stats.error == ""
    return sent


def test_passivity_figures_are_recorded_with_their_schema_reported_and_replayed(
    net: Net, tmp_path: Path
) -> None:
    path = tmp_path / "tdpa.mcap"
    sent = _record(net, path)
    topic_of = {"master": keys.PASSIVITY_MASTER.key, "slave": keys.PASSIVITY_SLAVE.key}

    # The view channels: JSON under the telerobot.PassivityState JSON Schema, values as sent.
    with path.open("rb") as fh:
        reader = make_reader(fh, validate_crcs=True)
        views: dict[str, list[dict[str, object]]] = {k: [] for k in topic_of.values()}
        for schema, channel, message in reader.iter_messages(topics=list(views)):
            assert schema is not None and schema.name == SCHEMA
            assert schema.encoding == "jsonschema" and channel.message_encoding == "json"
            assert channel.metadata["type"] == "PassivityState"
            doc = json.loads(message.data)
            assert conforms(json.loads(schema.data), doc) == []
            assert message.publish_time == doc["t_ns"]
            views[channel.topic].append(doc)
    for side, key in topic_of.items():
        assert [codec.from_fields(PassivityState, d) for d in views[key]] == sent[side]
    slave = views[keys.PASSIVITY_SLAVE.key]
    assert [d["e_in"] for d in slave[:3]] == [0.005, 0.01, 0.015]
    assert [d["active_steps"] for d in slave[-3:]] == [9, 10, 11]
    schema_doc = schemas.json_schema(SCHEMA)
    assert {"e_in", "e_out", "dissipated_j", "gain", "active_steps"} <= set(schema_doc["required"])
    assert schema_doc["properties"]["side"]["enum"] == ["master", "slave"]

    # The raw channels: the exact payloads.
    raw: dict[str, list[bytes]] = {k: [] for k in topic_of.values()}
    for m in Recording(path).raw():
        raw[m.key].append(m.payload)
    for side, key in topic_of.items():
        assert raw[key] == [codec.encode(m) for m in sent[side]]

    # The report lists both keys: count, rate, the master's one missing seq; no stall is
    # counted on these streams (they pause whenever nobody is engaged).
    report = analyze([path])
    master_r, slave_r = report.key(topic_of["master"]), report.key(topic_of["slave"])
    assert (master_r.type, master_r.count, slave_r.count) == ("PassivityState", 39, 40)
    assert master_r.rate_hz > 0 and slave_r.rate_hz > 0 and master_r.rejected == 0
    assert (master_r.seq_gaps, master_r.missing, master_r.gaps) == (1, 1, 1)
    assert (slave_r.seq_gaps, slave_r.gaps, slave_r.stalls) == (0, 0, 0)
    assert master_r.senders == 1 and slave_r.senders == 1
    assert [len(report.traces.passivity[s][0]) for s in ("master", "slave")] == [39, 40]
    assert report.traces.passivity["slave"][1][-1] == pytest.approx((0.2, 0.08, 0.011))
    # The master's rotational port, in its own trace; the slave runs none.
    assert set(report.traces.passivity_rot) == {"master"}
    assert report.traces.passivity_rot["master"][1][-1] == pytest.approx((0.16, 0.04))
    written = write_plots(report, tmp_path / "plots")
    assert [p.name for p in written] == ["force.png", "path.png", "passivity.png"]
    import cv2

    img = cv2.imread(str(written[-1]))
    assert img is not None and img.shape[0] > 600  # one panel per port
    assert (img < 128).any() and (img == 255).mean() > 0.5
    text = format_report(report)
    assert "robot/passivity/master PassivityState" in text
    assert "robot/passivity/slave" in text

    # Replay: both keys are republished byte for byte, in order, as their topic's QoS.
    got: dict[str, list[bytes]] = {k: [] for k in topic_of.values()}
    lock = threading.Lock()
    replay_net = Net()
    try:
        listener = replay_net.node("console")

        def keep(sample: zenoh.Sample) -> None:
            with lock:
                got[str(sample.key_expr)].append(sample.payload.to_bytes())

        listener.subscribe_raw("robot/passivity/*", keep)
        stats = Replayer(
            replay_net.node("replay"), [path], ReplayOptions(speed=0.0, wait_s=5.0)
        ).run()
        total = sum(len(v) for v in raw.values())
        assert wait_until(lambda: sum(len(v) for v in got.values()) >= total, 10.0)
    finally:
        replay_net.close()
    assert stats.unmatched == [] and dict(stats.published) == {k: len(v) for k, v in raw.items()}
    assert got == raw


def test_a_passivity_payload_out_of_bounds_is_kept_raw_only(tmp_path: Path) -> None:
    """An energy that breaks the contract (negative) gets no view, as any rejected message."""
    bad = codec.to_fields(figures("master", 3)) | {"e_in": -1.0}
    payload = codec.pack(bad)
    assert schemas.view(keys.PASSIVITY_MASTER.key, payload) is None
    good = schemas.view(keys.PASSIVITY_MASTER.key, codec.encode(figures("slave", 3)))
    assert good is not None and good.schema == SCHEMA


@pytest.mark.parametrize("key", [keys.PASSIVITY_MASTER.key, keys.PASSIVITY_SLAVE.key])
def test_the_passivity_keys_are_contract_topics(key: str) -> None:
    topic = keys.topic_for(key)
    assert topic is not None and topic.type is PassivityState
    assert schemas.schema_name(key) == SCHEMA
