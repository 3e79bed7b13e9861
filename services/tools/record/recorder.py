"""Record every stream of a namespace to MCAP, without ever slowing the streams down.

Zenoh's callback only stamps the receive time and hands `(time, key, payload)` to a bounded
inbox; when the inbox is full the sample is dropped and counted, never waited for. One
writer thread turns each payload into its JSON view and its raw copy (schemas.py) and
writes them with `mcap.writer.Writer` in compressed chunks. Chunks are closed when they
reach `chunk_size_kb` and at least every `chunk_interval_s`, and each closed chunk is
flushed to the file, so a recorder killed outright leaves a file readable up to its last
chunk (archive.py reads it). `stop()` (Ctrl-C, SIGTERM) drains the inbox and finishes the
file with its summary and footer.

Limits: `max_size_mb` and `max_duration_s` end the recording, or with `split` start the
next part (FILE_000.mcap, FILE_001.mcap, …), each a complete MCAP file on its own.

The arm's description (`robot/arm/description`, cached by the arm for late subscribers) is
taken with Zenoh's history, so a recorder started after the arm still gets it: it is
recorded like any other key (when the key filter selects it) and gives the 3D views their
arm (foxglove3d.py: `/tf` from its URDF, `/robot_model`, `/robot_description`). With no
description, the file has no `/robot_model`; the stats (`arm_model` null, `robot_models` 0)
and the log say so.
"""

from __future__ import annotations

import json
import logging
import math
import threading
import time
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import IO, Any, Literal

import zenoh
import zenoh.ext
from mcap.writer import CompressionType, Writer

from services.bus import codec, keys
from services.bus.errors import ConfigError, ProtocolError
from services.bus.messages import ArmDescription
from services.bus.node import Node
from services.tools.record import foxglove3d, schemas

log = logging.getLogger("telerobot.record")

Compression = Literal["zstd", "lz4", "none"]
_COMPRESSION = {
    "zstd": CompressionType.ZSTD,
    "lz4": CompressionType.LZ4,
    "none": CompressionType.NONE,
}
FORMAT_VERSION = "1"
CONTRACT = "PROTOCOL.md v2"
DESCRIPTION_KEY = keys.ARM_DESCRIPTION.key
#: bytes an MCAP message record adds to its data (opcode, length, channel, seq, 2 times)
_RECORD_OVERHEAD = 1 + 8 + 2 + 4 + 8 + 8


@dataclass(frozen=True, slots=True)
class RecorderConfig:
    """What and how to record.

    output: the file (`session.mcap`); with `split`, parts `session_000.mcap`, ….
    keys: Zenoh key expressions to record (empty: everything, `**`).
    video: record `vision/stereo/*` (off: `--no-video`).
    ros: with no `keys`, record the ROS 2 view's copies of the streams too (`--ros`; by
        default a recording of everything leaves them out: they double the data).
    max_size_mb, max_duration_s: end the recording (or the part, with `split`) when
        reached; 0 = no limit.
    queue_len, queue_mb: the inbox bound, in samples and in payload megabytes.
    chunk_size_kb: a chunk is closed when its uncompressed size passes this.
    chunk_interval_s: a chunk is closed at least this often, bounding what a kill loses.
    """

    output: str
    keys: tuple[str, ...] = ()
    video: bool = True
    ros: bool = False
    max_size_mb: float = 0.0
    max_duration_s: float = 0.0
    split: bool = False
    queue_len: int = 50_000
    queue_mb: float = 256.0
    chunk_size_kb: int = 1024
    chunk_interval_s: float = 1.0
    compression: Compression = "zstd"
    view3d: bool = True
    """Also write what a 3D viewer draws (`foxglove3d.py`): `/tf`, `/robot_model`,
    `/robot_description`, `/workcell`."""

    def __post_init__(self) -> None:
        if not self.output.endswith(".mcap"):
            raise ConfigError("record.output", f"{self.output!r} must end in .mcap")
        for name in ("max_size_mb", "max_duration_s"):
            v = getattr(self, name)
            if not math.isfinite(v) or v < 0:
                raise ConfigError(f"record.{name}", "must be ≥ 0 (0 = no limit)")
        if self.split and not (self.max_size_mb or self.max_duration_s):
            raise ConfigError("record.split", "needs --max-size-mb or --max-duration-s")
        if self.queue_len < 1 or not self.queue_mb > 0:
            raise ConfigError("record.queue_len", "queue_len ≥ 1 and queue_mb > 0")
        if self.chunk_size_kb < 1 or not self.chunk_interval_s > 0:
            raise ConfigError("record.chunk_size_kb", "chunk_size_kb ≥ 1, chunk_interval_s > 0")
        if self.compression not in _COMPRESSION:
            raise ConfigError("record.compression", f"one of {', '.join(_COMPRESSION)}")
        schemas.key_matcher(self.keys)


def part_path(output: str | Path, index: int) -> Path:
    """`session.mcap`, part 3 → `session_003.mcap`."""
    p = Path(output)
    return p.with_name(f"{p.stem}_{index:03d}{p.suffix}")


@dataclass(frozen=True, slots=True)
class Received:
    """One sample as the callback saw it: receive time (time.time_ns()), key, payload.
    `record` False: not to be recorded, only read (an arm description outside the key
    filter, still needed by the 3D views)."""

    log_time_ns: int
    key: str
    payload: bytes
    record: bool = True


@dataclass
class KeyStats:
    """Per-key counters: received by the callback, dropped (inbox full), written, and
    `no_view` (written raw only: rejected by the codec or not msgpack)."""

    received: int = 0
    dropped: int = 0
    written: int = 0
    no_view: int = 0
    bytes: int = 0


@dataclass
class RecorderStats:
    """The recorder's counters. Zenoh's threads add keys and count `received`/`dropped`;
    the writer thread counts the rest; `key()` and `snapshot()` take the lock."""

    keys: dict[str, KeyStats] = field(default_factory=dict)
    files: list[Path] = field(default_factory=list)
    error: str = ""
    arm_model: str = ""
    """The model of the newest arm description received ("": none arrived)."""
    robot_models: int = 0
    """`/robot_model` messages written (one per description and file; 0: the recording has
    no arm model, see `arm_model`)."""
    lock: threading.Lock = field(default_factory=threading.Lock, repr=False, compare=False)

    def key(self, key: str) -> KeyStats:
        with self.lock:
            st = self.keys.get(key)
            if st is None:
                st = self.keys[key] = KeyStats()
            return st

    def snapshot(self) -> RecorderStats:
        """A copy that no other thread changes."""
        with self.lock:
            return RecorderStats(
                {k: KeyStats(**vars(v)) for k, v in self.keys.items()},
                list(self.files),
                self.error,
                self.arm_model,
                self.robot_models,
            )

    @property
    def received(self) -> int:
        return sum(k.received for k in self.keys.values())

    @property
    def dropped(self) -> int:
        return sum(k.dropped for k in self.keys.values())

    @property
    def written(self) -> int:
        return sum(k.written for k in self.keys.values())

    def as_dict(self) -> dict[str, Any]:
        """JSON-able totals and per-key counters (call on a snapshot)."""
        return {
            "received": self.received,
            "dropped": self.dropped,
            "written": self.written,
            "keys": {k: vars(v).copy() for k, v in sorted(self.keys.items())},
            "files": [str(f) for f in self.files],
            "error": self.error,
            "arm_model": self.arm_model or None,
            "robot_models": self.robot_models,
        }


class Inbox:
    """A bounded hand-over from Zenoh's threads to the writer: `put` never blocks; it
    refuses (returns False) when `max_items` samples or `max_bytes` of payload wait."""

    def __init__(self, max_items: int, max_bytes: int) -> None:
        self._items: deque[Received] = deque()
        self._bytes = 0
        self._max_items = max_items
        self._max_bytes = max_bytes
        self._cond = threading.Condition()
        self._closed = False

    def put(self, item: Received) -> bool:
        with self._cond:
            n = len(item.payload)
            if self._closed or len(self._items) >= self._max_items:
                return False
            if self._bytes + n > self._max_bytes and self._items:
                return False
            self._items.append(item)
            self._bytes += n
            self._cond.notify()
            return True

    def take(self, timeout_s: float) -> list[Received]:
        """Everything waiting (possibly nothing after `timeout_s`)."""
        with self._cond:
            if not self._items and not self._closed:
                self._cond.wait(timeout_s)
            out = list(self._items)
            self._items.clear()
            self._bytes = 0
            return out

    def close(self) -> None:
        """Refuse further samples; `take` returns what is left without waiting."""
        with self._cond:
            self._closed = True
            self._cond.notify_all()

    @property
    def closed(self) -> bool:
        return self._closed

    def __len__(self) -> int:
        with self._cond:
            return len(self._items)


class McapSink:
    """Writes received samples into one MCAP file, or a series of parts. No Zenoh: the
    writer thread drives it, and tests can too.

    `write()` returns False once a limit has ended the recording (without `split`).
    """

    def __init__(
        self,
        config: RecorderConfig,
        ns: str = "",
        stats: RecorderStats | None = None,
        clock_ns: Callable[[], int] = time.time_ns,
        monotonic_s: Callable[[], float] = time.monotonic,
    ) -> None:
        self.config = config
        self.ns = ns
        self.stats = stats if stats is not None else RecorderStats()
        self._clock_ns = clock_ns
        self._monotonic_s = monotonic_s
        self._part = -1
        self._file: IO[bytes] | None = None
        self._writer: Writer | None = None
        self._schemas: dict[str, int] = {}
        self._channels: dict[tuple[str, str], int] = {}
        self._sequence: dict[int, int] = {}
        self._part_start_s = 0.0
        self._last_flush_s = 0.0
        self._pos = 0
        self._pending = 0
        self._arm: foxglove3d.ArmView | None = None
        """The arm of the newest description, over the whole recording (all parts)."""
        self._arm_written = False
        """This part has the current arm's /robot_model."""
        self._states_without_arm = 0
        """robot/states of this part derived with no arm description."""
        self._spills = foxglove3d.Spills(foxglove3d.SCENE)
        """Puddles of spilled liquid, over the whole recording (all parts)."""
        self.derive_errors = 0
        self.ended = False
        self._open_part()

    # --- files ---------------------------------------------------------------------------
    def _open_part(self) -> None:
        self._part += 1
        path = part_path(self.config.output, self._part) if self.config.split else None
        path = path or Path(self.config.output)
        path.parent.mkdir(parents=True, exist_ok=True)
        self._file = path.open("wb")
        self._writer = Writer(
            self._file,
            chunk_size=self.config.chunk_size_kb * 1024,
            compression=_COMPRESSION[self.config.compression],
        )
        self._writer.start(profile="", library="telerobot record")
        self._writer.add_metadata(
            "telerobot.recording",
            {
                "format": FORMAT_VERSION,
                "contract": CONTRACT,
                "ns": self.ns,
                "keys": " ".join(self.config.keys) or "**",
                "video": str(self.config.video).lower(),
                "ros": str(self.config.ros).lower(),
                "part": str(self._part),
                "started_ns": str(self._clock_ns()),
                "raw_prefix": schemas.RAW_PREFIX,
            },
        )
        self._schemas.clear()
        self._channels.clear()
        self._sequence.clear()
        self._arm_written = False
        self._states_without_arm = 0
        self._part_start_s = self._last_flush_s = self._monotonic_s()
        self._pos = self._file.tell()
        self._pending = 0
        with self.stats.lock:
            self.stats.files.append(path)
        log.info("recording to %s", path)

    def _finish_part(self) -> None:
        if self._writer is None or self._file is None:
            return
        if self.config.view3d and self._states_without_arm and not self._arm_written:
            log.warning(
                "%s: no arm description (robot/arm/description) arrived: recorded without "
                "/robot_model; /tf holds world → flange → tool only",
                self._file.name,
            )
        self._writer.add_metadata(
            "telerobot.stats",
            {
                "ended_ns": str(self._clock_ns()),
                "part": str(self._part),
                "stats": json.dumps(self.stats.snapshot().as_dict()),
            },
        )
        self._writer.finish()
        self._file.close()
        self._writer = None
        self._file = None

    def close(self) -> None:
        """Finish the current part (summary, footer). Idempotent."""
        self._finish_part()
        self.ended = True

    # --- writing ---------------------------------------------------------------------------
    def _schema_id(self, name: str) -> int:
        assert self._writer is not None
        sid = self._schemas.get(name)
        if sid is None:
            doc = foxglove3d.SCHEMAS.get(name) or schemas.json_schema(name)
            data = json.dumps(doc, ensure_ascii=False).encode()
            sid = self._writer.register_schema(name, schemas.SCHEMA_ENCODING, data)
            self._schemas[name] = sid
        return sid

    def _channel(self, key: str, role: str, schema: str) -> int:
        assert self._writer is not None
        cid = self._channels.get((key, schema if role == schemas.ROLE_VIEW else role))
        if cid is not None:
            return cid
        topic = keys.topic_for(key)
        meta = {"key": key, "role": role, "type": topic.type.name if topic else ""}
        if role == schemas.ROLE_RAW:
            meta["encoding"] = keys.ENCODING
            cid = self._writer.register_channel(
                schemas.raw_topic(key), schemas.RAW_ENCODING, 0, meta
            )
            self._channels[(key, role)] = cid
        else:
            sid = self._schema_id(schema) if schema else 0
            cid = self._writer.register_channel(key, schemas.VIEW_ENCODING, sid, meta)
            self._channels[(key, schema)] = cid
        return cid

    def _add(self, channel_id: int, item: Received, publish_ns: int, data: bytes) -> None:
        assert self._writer is not None
        seq = self._sequence[channel_id] = (self._sequence.get(channel_id, 0) + 1) % 2**32
        self._writer.add_message(
            channel_id=channel_id,
            log_time=item.log_time_ns,
            data=data,
            publish_time=publish_ns,
            sequence=seq,
        )
        self._pending += len(data) + _RECORD_OVERHEAD

    def write(self, item: Received) -> bool:
        """Write one sample (raw copy and view). False when the recording has ended."""
        if self.ended:
            return False
        if self._limit_reached() and not self._rotate():
            return False
        if item.key == DESCRIPTION_KEY:
            self._description(item)
        if not item.record:
            self._model_due(item)
            return True
        st = self.stats.key(item.key)
        v = schemas.view(item.key, item.payload)
        t_ns = v.t_ns if v is not None else schemas.stamp(item.payload)
        publish_ns = t_ns if t_ns is not None else item.log_time_ns
        self._add(self._channel(item.key, schemas.ROLE_RAW, ""), item, publish_ns, item.payload)
        if v is None:
            st.no_view += 1
        else:
            cid = self._channel(item.key, schemas.ROLE_VIEW, v.schema)
            self._add(cid, item, publish_ns, schemas.dumps(v.document))
        self._model_due(item)
        if v is not None and self.config.view3d:
            self._derive(item, v, publish_ns)
        st.written += 1
        st.bytes += len(item.payload)
        return True

    def _derived_channel(self, topic: str, schema: str, key: str) -> int:
        assert self._writer is not None
        cid = self._channels.get((topic, foxglove3d.ROLE_DERIVED))
        if cid is None:
            meta = {"key": key, "role": foxglove3d.ROLE_DERIVED, "type": schema}
            cid = self._writer.register_channel(
                topic, schemas.VIEW_ENCODING, self._schema_id(schema), meta
            )
            self._channels[(topic, foxglove3d.ROLE_DERIVED)] = cid
        return cid

    def _description(self, item: Received) -> None:
        """A robot/arm/description: the arm the 3D views draw from now on (when it differs
        from the one they draw)."""
        try:
            desc = codec.decode(ArmDescription, item.payload)
        except ProtocolError as e:
            self.derive_errors += 1
            log.warning("ignored an arm description that does not check out: %s", e)
            return
        with self.stats.lock:
            self.stats.arm_model = desc.model
        if not self.config.view3d:
            return
        old = self._arm.description if self._arm is not None else None
        if old is not None and _same_arm(old, desc):
            return
        try:
            self._arm = foxglove3d.ArmView(desc)
        except (ConfigError, ProtocolError, ValueError, KeyError, TypeError, RuntimeError) as e:
            self._arm = None
            self.derive_errors += 1
            log.warning("cannot draw the arm %r of its description: %s", desc.model, e)
            return
        self._arm_written = False
        log.info("arm %s (%d joints): /tf and /robot_model from its URDF", desc.model, desc.n)

    def _model_due(self, item: Received) -> None:
        """Write the current arm's model if this part does not have it yet."""
        if self.config.view3d and self._arm is not None and not self._arm_written:
            self._write_model(item)

    def _derive(self, item: Received, v: schemas.View, publish_ns: int) -> None:
        """The 3D views of a robot/state or workcell/state (`foxglove3d.py`)."""
        assert self._writer is not None
        if item.key not in (keys.STATE.key, foxglove3d.WORKCELL_KEY):
            return
        try:
            if item.key == keys.STATE.key:
                if self._arm is None:
                    if not self._states_without_arm:
                        log.info("robot/state with no arm description yet: /tf of its poses")
                    self._states_without_arm += 1
                tf = foxglove3d.frame_transforms(v.document, self._arm)
                out = [(foxglove3d.TF_TOPIC, foxglove3d.FRAME_TRANSFORMS, tf)]
            else:
                update = foxglove3d.workcell_update(v.document, spills=self._spills)
                out = [(foxglove3d.WORKCELL_TOPIC, foxglove3d.SCENE_UPDATE, update)]
        except (ProtocolError, ValueError, KeyError, TypeError) as e:
            self.derive_errors += 1
            log.debug("no 3D view of %s: %s", item.key, e)
            return
        for topic, schema, body in out:
            cid = self._derived_channel(topic, schema, item.key)
            self._add(cid, item, publish_ns, schemas.dumps(body))

    def _write_model(self, item: Received) -> None:
        """The current arm, at `item`'s receive time: its URDF with the tool link (attached,
        and on /robot_description) and its visuals locked to the link frames
        (/robot_model)."""
        assert self._writer is not None and self._arm is not None
        arm, t_ns = self._arm, item.log_time_ns
        self._writer.add_attachment(
            t_ns, t_ns, arm.urdf_name, foxglove3d.URDF_MEDIA_TYPE, arm.urdf.encode()
        )
        cid = self._derived_channel(
            foxglove3d.DESCRIPTION_TOPIC, foxglove3d.STRING, DESCRIPTION_KEY
        )
        self._add(cid, item, t_ns, schemas.dumps(foxglove3d.robot_description(arm)))
        cid = self._derived_channel(
            foxglove3d.MODEL_TOPIC, foxglove3d.SCENE_UPDATE, DESCRIPTION_KEY
        )
        self._add(cid, item, t_ns, schemas.dumps(foxglove3d.robot_model(t_ns, arm)))
        self._arm_written = True
        with self.stats.lock:
            self.stats.robot_models += 1
        if arm.visuals_error:
            log.warning("%s drawn without its visuals: %s", arm.urdf_name, arm.visuals_error)

    def tick(self) -> bool:
        """Close the chunk when `chunk_interval_s` has passed; apply the limits even when
        nothing arrives. False when the recording has ended."""
        if self.ended:
            return False
        now = self._monotonic_s()
        if now - self._last_flush_s >= self.config.chunk_interval_s:
            self.flush()
        return not (self._limit_reached() and not self._rotate())

    def flush(self) -> None:
        """Close the chunk in progress and push it to the file."""
        if self._writer is not None and self._file is not None:
            self._writer.flush()
            self._pos = self._file.tell()
            self._pending = 0
        self._last_flush_s = self._monotonic_s()

    def size_bytes(self) -> int:
        """The current part's size: written so far plus the open chunk (uncompressed)."""
        if self._file is not None:
            pos = self._file.tell()
            if pos != self._pos:  # the writer closed a full chunk on its own
                self._pos, self._pending = pos, 0
        return self._pos + self._pending

    def _limit_reached(self) -> bool:
        cfg = self.config
        if cfg.max_size_mb and self.size_bytes() >= cfg.max_size_mb * 1e6:
            return True
        return bool(
            cfg.max_duration_s and self._monotonic_s() - self._part_start_s >= cfg.max_duration_s
        )

    def _rotate(self) -> bool:
        self._finish_part()
        if not self.config.split:
            self.ended = True
            log.info("limit reached: recording ended")
            return False
        self._open_part()
        return True


def _same_arm(a: ArmDescription, b: ArmDescription) -> bool:
    """The same arm with the same tool: nothing for the 3D views to change."""
    return (a.model, a.urdf, a.base_frame, a.flange_frame, a.eMt) == (
        b.model,
        b.urdf,
        b.base_frame,
        b.flange_frame,
        b.eMt,
    )


class Recorder:
    """Records the bus that `node` sees into MCAP (see the module docstring).

    Starts at construction; `stop()` drains and finishes the file(s) and returns the final
    stats. `ended` is set when the recording is over: stopped, a limit reached without
    `split`, or a write error (then `stats().error` says which).
    """

    def __init__(self, node: Node, config: RecorderConfig) -> None:
        self.node = node
        self.config = config
        self.ended = threading.Event()
        self._stats = RecorderStats()
        self._select = schemas.key_matcher(config.keys, config.video, config.ros)
        self._inbox = Inbox(config.queue_len, int(config.queue_mb * 1e6))
        self._sink = McapSink(config, node.config.ns, self._stats)
        self._stopped = False
        patterns = config.keys or ("**",)
        # One subscription per expression; a key inside several is taken by the first only,
        # so overlapping expressions never record a sample twice.
        owners = [schemas.key_matcher(patterns[:i]) if i else None for i in range(len(patterns))]
        # The arm's description has a subscription of its own, with the history its
        # publisher caches, so that a recorder started after the arm gets the current one:
        # the ones for the key expressions leave that key to it.
        self._record_description = self._select(DESCRIPTION_KEY)
        self._own_description = config.view3d or self._record_description
        self._description_seen: set[str] = set()
        self._subs: list[Any] = [
            node.subscribe_raw(k, self._receiver(owners[i])) for i, k in enumerate(patterns)
        ]
        if self._own_description:
            # Zenoh's advanced subscriber, raw (the bytes as they came, and no `rejected`
            # event published as Node.subscribe(history=True) would): Node offers no raw
            # subscriber with history.
            sub = zenoh.ext.declare_advanced_subscriber(
                node.session,
                DESCRIPTION_KEY,
                self._on_description,
                history=zenoh.ext.HistoryConfig(detect_late_publishers=True),
            )
            self._subs.append(sub)
        self._thread = threading.Thread(target=self._run, name="record-writer", daemon=True)
        self._thread.start()

    def _receiver(
        self, taken_earlier: Callable[[str], bool] | None
    ) -> Callable[[zenoh.Sample], None]:
        def on_sample(sample: zenoh.Sample) -> None:
            now = time.time_ns()
            key = str(sample.key_expr)
            if key == DESCRIPTION_KEY and self._own_description:
                return  # taken by the description's own subscription
            if taken_earlier is None or not taken_earlier(key):
                self._on_sample(now, key, sample)

        return on_sample

    def _on_description(self, sample: zenoh.Sample) -> None:
        # Zenoh's thread. A sample both live and from the publisher's cache (a publisher
        # detected late) is the same sample, with the same timestamp: taken once.
        now = time.time_ns()
        if sample.kind != zenoh.SampleKind.PUT:
            return
        stamp = sample.timestamp
        if stamp is not None:
            with self._stats.lock:
                if str(stamp) in self._description_seen:
                    return
                self._description_seen.add(str(stamp))
        if self._record_description:
            self._on_sample(now, DESCRIPTION_KEY, sample)
        else:
            self._inbox.put(Received(now, DESCRIPTION_KEY, sample.payload.to_bytes(), False))

    def _on_sample(self, now: int, key: str, sample: zenoh.Sample) -> None:
        # Zenoh's thread: stamp, filter, hand over. Never block on the writer.
        if sample.kind != zenoh.SampleKind.PUT or not self._select(key):
            return
        ok = self._inbox.put(Received(now, key, sample.payload.to_bytes()))
        if not ok and self._inbox.closed:
            return
        st = self._stats.key(key)
        with self._stats.lock:
            st.received += 1
            st.dropped += 0 if ok else 1

    def _run(self) -> None:
        # The only thread that touches the sink.
        sink = self._sink
        try:
            live = True
            while live:
                items = self._inbox.take(min(0.05, self.config.chunk_interval_s))
                for it in items:
                    if not sink.write(it):
                        live = False
                        break
                live = live and sink.tick()
                if self._inbox.closed and not items and len(self._inbox) == 0:
                    break
        except OSError as e:  # disk full, file gone: the recording is over; say why
            log.error("recording failed: %s", e)
            with self._stats.lock:
                self._stats.error = f"{type(e).__name__}: {e}"
        finally:
            self._inbox.close()
            try:
                sink.close()
            except OSError as e:
                with self._stats.lock:
                    self._stats.error = self._stats.error or f"{type(e).__name__}: {e}"
            self.ended.set()

    def stats(self) -> RecorderStats:
        """A consistent copy of the counters."""
        return self._stats.snapshot()

    @property
    def files(self) -> list[Path]:
        return self.stats().files

    def stop(self, timeout_s: float = 30.0) -> RecorderStats:
        """Stop receiving, write what is queued, finish the file. Idempotent."""
        if not self._stopped:
            self._stopped = True
            for sub in self._subs:
                try:
                    sub.undeclare()
                except zenoh.ZError:
                    log.debug("undeclare failed (session closed)", exc_info=True)
            self._inbox.close()
        self._thread.join(timeout_s)
        return self.stats()
