"""Writing and reading MCAP files without Zenoh: layout, exact bytes, limits, split, cut files."""

from __future__ import annotations

import json
from dataclasses import dataclass, field
from pathlib import Path

import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from mcap.exceptions import EndOfFile
from mcap.reader import make_reader
from mcap.stream_reader import StreamReader

from services.bus import codec
from services.bus.errors import ConfigError
from services.bus.messages import ForceSample
from services.tools.record import schemas
from services.tools.record.archive import Recording
from services.tools.record.recorder import Inbox, McapSink, Received, RecorderConfig, part_path
from tests.tools.record.helpers import T0_NS, FakeClock, event, force, state, write_file

MIXED = [
    ("robot/force", force(1)),
    ("robot/state", state(1)),
    ("robot/force", force(2)),
    ("robot/events", event(1, "arm", "status", "ready")),
    ("robot/force", codec.pack({"seq": 3})),  # breaks the contract: raw only
    ("lab/other", codec.pack({"t_ns": T0_NS + 99, "note": "hi"})),
    ("lab/blob", b"\xc1not msgpack"),
]


def test_layout_two_channels_per_key_exact_raw_bytes_and_times(tmp_path: Path) -> None:
    path = tmp_path / "s.mcap"
    sink, written = write_file(path, MIXED, view3d=False)  # the 3D views: test_foxglove3d.py
    assert sink.stats.files == [path]
    with path.open("rb") as f:
        reader = make_reader(f, validate_crcs=True)
        summary = reader.get_summary()
        assert summary is not None and summary.statistics is not None
        topics = {c.topic: c for c in summary.channels.values()}
        schemas_by_id = summary.schemas
        msgs = list(reader.iter_messages(log_time_order=False))
    # raw channels: msgpack, no schema, metadata naming the key
    raw = topics["/raw/robot/force"]
    assert raw.message_encoding == "msgpack" and raw.schema_id == 0
    assert raw.metadata == {
        "key": "robot/force",
        "role": "raw",
        "type": "ForceSample",
        "encoding": "application/msgpack",
    }
    # view channels: JSON with the generated JSON Schema
    view = topics["robot/force"]
    assert view.message_encoding == "json"
    sch = schemas_by_id[view.schema_id]
    assert sch.name == "telerobot.ForceSample" and sch.encoding == "jsonschema"
    assert json.loads(sch.data) == schemas.message_schema(
        type(codec.decode(schemas.keys.FORCE.type, force(1)))
    )
    assert topics["lab/other"].schema_id == 0  # schemaless JSON
    assert "lab/blob" not in topics and "/raw/lab/blob" in topics
    # every message raw; a view for all but the rejected and the non-msgpack one
    raw_msgs = [(c.metadata["key"], m) for _, c, m in msgs if c.metadata["role"] == "raw"]
    assert [(k, m.data) for k, m in raw_msgs] == [(w.key, w.payload) for w in written]
    assert sum(1 for _, c, _ in msgs if c.metadata["role"] == "view") == len(MIXED) - 2
    assert summary.statistics.message_count == 2 * len(MIXED) - 2
    # log time = receive time, publish time = the message's t_ns (else the receive time)
    assert [m.log_time for _, m in raw_msgs] == [w.log_time_ns for w in written]
    assert [m.publish_time for _, m in raw_msgs] == [
        T0_NS + 1,
        T0_NS + 1,
        T0_NS + 2,
        T0_NS + 1,
        written[4].log_time_ns,
        T0_NS + 99,
        written[6].log_time_ns,
    ]
    st = sink.stats.key("robot/force")
    assert (st.written, st.no_view) == (3, 1)
    # the archive reads the raw channels back in receive order
    rec = Recording(path)
    back = list(rec.raw())
    assert [(r.key, r.payload, r.log_time_ns) for r in back] == [
        (w.key, w.payload, w.log_time_ns) for w in written
    ]
    assert not rec.truncated
    assert rec.metadata["telerobot.recording"]["raw_prefix"] == "/raw/"
    assert json.loads(rec.metadata["telerobot.stats"]["stats"])["written"] == len(MIXED)
    assert rec.raw_keys() == ["robot/force", "robot/state", "robot/events", "lab/other", "lab/blob"]


def test_config_is_checked() -> None:
    with pytest.raises(ConfigError) as err:
        RecorderConfig(output="x.bag")
    assert err.value.key == "record.output"
    with pytest.raises(ConfigError) as err:
        RecorderConfig(output="x.mcap", split=True)
    assert err.value.key == "record.split"
    with pytest.raises(ConfigError):
        RecorderConfig(output="x.mcap", max_size_mb=-1)
    with pytest.raises(ConfigError):
        RecorderConfig(output="x.mcap", keys=("a//b",))
    assert part_path("/d/session.mcap", 3) == Path("/d/session_003.mcap")


def test_a_size_limit_ends_the_recording_with_a_complete_file(tmp_path: Path) -> None:
    path = tmp_path / "s.mcap"
    items = [("robot/force", force(i)) for i in range(1, 5001)]
    sink, written = write_file(path, items, flush_every=100, max_size_mb=0.05, chunk_size_kb=8)
    assert sink.ended and 0 < len(written) < len(items)
    assert path.stat().st_size < 0.05e6 + 20_000  # the limit plus the summary, roughly
    with path.open("rb") as f:
        summary = make_reader(f).get_summary()
    assert summary is not None and summary.statistics is not None
    assert summary.statistics.message_count == 2 * len(written)


def test_split_rotates_into_complete_parts_by_size_and_by_time(tmp_path: Path) -> None:
    out = tmp_path / "s.mcap"
    items = [("robot/force", force(i)) for i in range(1, 3001)]
    sink, written = write_file(
        out, items, flush_every=50, max_size_mb=0.03, split=True, chunk_size_kb=8
    )
    files = sink.stats.files
    assert len(written) == len(items)
    assert len(files) >= 3 and files[0] == part_path(out, 0) and files[2] == part_path(out, 2)
    seqs = []
    for p in files:
        rec = Recording(p)
        seqs += [codec.decode(ForceSample, m.payload).seq for m in rec.raw()]
        assert not rec.truncated
        with p.open("rb") as f:
            assert make_reader(f).get_summary() is not None  # each part stands alone
    assert seqs == list(range(1, 3001))

    clock = FakeClock()
    sink = McapSink(
        RecorderConfig(output=str(tmp_path / "t.mcap"), max_duration_s=1.0, split=True),
        monotonic_s=clock,
    )
    for i in range(1, 31):
        clock.now_s = i * 0.1  # 3 s of messages, 10 per second
        assert sink.write(Received(T0_NS + i, "robot/force", force(i)))
    clock.now_s = 4.0
    assert sink.tick()  # time passes without messages: a new part all the same
    sink.close()
    counts = [sum(1 for _ in Recording(p).raw()) for p in sink.stats.files]
    assert counts == [9, 10, 10, 1, 0]  # a part holds [start, start + 1 s)


def test_a_duration_limit_without_split_ends_even_when_nothing_arrives(tmp_path: Path) -> None:
    clock = FakeClock()
    sink = McapSink(
        RecorderConfig(output=str(tmp_path / "d.mcap"), max_duration_s=2.0), monotonic_s=clock
    )
    assert sink.write(Received(T0_NS, "robot/force", force(1)))
    clock.now_s = 1.0
    assert sink.tick()
    clock.now_s = 2.0
    assert not sink.tick() and sink.ended
    assert not sink.write(Received(T0_NS + 1, "robot/force", force(2)))
    assert [m.payload for m in Recording(tmp_path / "d.mcap").raw()] == [force(1)]


def test_inbox_refuses_instead_of_blocking_and_is_bounded_by_bytes() -> None:
    box = Inbox(max_items=3, max_bytes=1000)
    assert all(box.put(Received(i, "k", b"x" * 10)) for i in range(3))
    assert not box.put(Received(3, "k", b"x"))
    assert [r.log_time_ns for r in box.take(0.0)] == [0, 1, 2]
    assert box.put(Received(4, "k", b"x" * 900))
    assert not box.put(Received(5, "k", b"x" * 200))  # over the byte bound
    assert box.put(Received(6, "k", b"x" * 100))
    box.close()
    assert not box.put(Received(7, "k", b""))
    assert [r.log_time_ns for r in box.take(10.0)] == [4, 6]  # no wait once closed


@settings(max_examples=200, deadline=None)
@given(
    max_items=st.integers(1, 8),
    max_bytes=st.integers(1, 400),
    ops=st.lists(st.one_of(st.integers(0, 150), st.none()), max_size=60),
)
def test_inbox_bounds_hold_and_order_is_kept_for_any_sequence_of_puts_and_takes(
    max_items: int, max_bytes: int, ops: list[int | None]
) -> None:
    """The recorder's hand-over never grows past its bounds (one oversized sample may pass
    into an empty inbox, so no sample is unrecordable), refuses exactly when a bound would
    be passed, and hands over what it accepted in order."""
    box = Inbox(max_items, max_bytes)
    waiting: list[int] = []
    accepted: list[int] = []
    taken: list[int] = []
    for i, op in enumerate(ops):
        if op is None:
            taken += [r.log_time_ns for r in box.take(0.0)]
            waiting = []
            continue
        fits = len(waiting) < max_items and (sum(waiting) + op <= max_bytes or not waiting)
        assert box.put(Received(i, "k", b"x" * op)) == fits
        if fits:
            waiting.append(op)
            accepted.append(i)
        assert len(box) == len(waiting) <= max_items
    taken += [r.log_time_ns for r in box.take(0.0)]
    assert taken == accepted


# --- a recorder killed mid-file --------------------------------------------------------------
@dataclass(frozen=True)
class Chunked:
    """A file of 400 messages in chunks of 25, and the end offset of every chunk."""

    path: Path
    payloads: list[bytes] = field(repr=False)
    ends: list[int] = field(repr=False)


@pytest.fixture(scope="module")
def chunked(tmp_path_factory: pytest.TempPathFactory) -> Chunked:
    path = tmp_path_factory.mktemp("cut") / "full.mcap"
    items = [("robot/force", force(i)) for i in range(1, 401)]
    write_file(path, items, flush_every=25)
    with path.open("rb") as f:
        summary = make_reader(f).get_summary()
    assert summary is not None
    ends = sorted(c.chunk_start_offset + c.chunk_length for c in summary.chunk_indexes)
    assert len(ends) == 16
    return Chunked(path, [p for _, p in items], ends)


@settings(
    max_examples=120, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture]
)
@given(cut_frac=st.floats(0.0, 1.0))
def test_a_cut_file_reads_as_a_prefix_up_to_its_last_complete_chunk(
    chunked: Chunked,
    cut_frac: float,
    tmp_path_factory: pytest.TempPathFactory,
) -> None:
    """Whatever byte a kill stops the file at, reading never fails and yields exactly the
    messages in order, at least all those of the chunks completed before the cut."""
    path, payloads, ends = chunked.path, chunked.payloads, chunked.ends
    data = path.read_bytes()
    cut = int(cut_frac * len(data))
    cut_path = tmp_path_factory.getbasetemp() / "cut.mcap"
    cut_path.write_bytes(data[:cut])
    rec = Recording(cut_path)
    got = [m.payload for m in rec.raw()]
    assert got == payloads[: len(got)]
    complete = sum(1 for e in ends if e <= cut)
    assert len(got) >= complete * 25
    assert rec.truncated == (cut < len(data))


def test_the_mcap_stream_reader_also_reads_a_cut_file_up_to_the_cut(
    chunked: Chunked, tmp_path: Path
) -> None:
    cut_path = tmp_path / "cut.mcap"
    cut_path.write_bytes(chunked.path.read_bytes()[: chunked.ends[5]])
    n = 0
    with cut_path.open("rb") as f, pytest.raises(EndOfFile):
        for record in StreamReader(f, validate_crcs=True).records:
            n += type(record).__name__ == "Message"
    assert n == 2 * 6 * 25  # six complete chunks, view + raw per message
