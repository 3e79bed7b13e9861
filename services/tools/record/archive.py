"""Reading recordings back: the raw payloads, in the order they were received.

Replay and report read the raw channels (`/raw/<key>`, msgpack) sequentially, in file
order, which is the recorder's receive order. Reading is sequential rather than through the
summary so that a recording whose recorder was killed — no summary, no footer, maybe half a
chunk at the end — still yields every message up to its last complete chunk; `truncated`
then says so. Chunk CRCs are checked, so a damaged chunk is never read as data.
"""

from __future__ import annotations

import struct
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from pathlib import Path

import zstandard
from mcap.exceptions import McapError
from mcap.reader import make_reader
from mcap.records import Channel, Message, Metadata
from mcap.stream_reader import StreamReader

from services.tools.record.schemas import RAW_ENCODING, ROLE_RAW

#: what a cut-off or damaged tail raises inside the mcap library
_TRUNCATION_ERRORS = (McapError, struct.error, ValueError, EOFError, zstandard.ZstdError)


@dataclass(frozen=True, slots=True)
class Recorded:
    """One message as received: bus key (no namespace), receive time (`log_time_ns`), the
    sender's `t_ns` (`publish_time_ns`; the receive time when the payload had none), and the
    exact payload bytes."""

    key: str
    log_time_ns: int
    publish_time_ns: int
    payload: bytes


@dataclass
class Recording:
    """One MCAP file of ours. Iterate `raw()`; afterwards `truncated`, `metadata` and
    `channels` describe what was read."""

    path: Path
    truncated: bool = False
    error: str = ""
    metadata: dict[str, dict[str, str]] = field(default_factory=dict)
    channels: dict[int, Channel] = field(default_factory=dict)

    def raw(self, select: Callable[[str], bool] | None = None) -> Iterator[Recorded]:
        """Every raw message (of the keys `select` accepts), in file order."""
        raw_channels: dict[int, str] = {}
        with self.path.open("rb") as f:
            records = StreamReader(f, validate_crcs=True).records
            while True:
                try:
                    record = next(records)
                except StopIteration:
                    return
                except _TRUNCATION_ERRORS as e:
                    self.truncated = True
                    self.error = f"{type(e).__name__}: {e}"
                    return
                if isinstance(record, Message):
                    key = raw_channels.get(record.channel_id)
                    if key is not None and (select is None or select(key)):
                        yield Recorded(key, record.log_time, record.publish_time, record.data)
                elif isinstance(record, Channel):
                    self.channels[record.id] = record
                    if (
                        record.message_encoding == RAW_ENCODING
                        and record.metadata.get("role") == ROLE_RAW
                    ):
                        raw_channels[record.id] = record.metadata["key"]
                elif isinstance(record, Metadata):
                    self.metadata[record.name] = dict(record.metadata)

    def raw_keys(self) -> list[str]:
        """The keys of the raw channels, in first-seen order: from the summary when the file
        has one, else by reading it through."""
        summary = None
        try:
            with self.path.open("rb") as f:
                summary = make_reader(f).get_summary()
        except _TRUNCATION_ERRORS:
            summary = None
        if summary is None:
            for _ in self.raw(lambda _key: False):
                pass
            channels = self.channels
        else:
            channels = summary.channels
        return [
            c.metadata["key"]
            for _, c in sorted(channels.items())
            if c.message_encoding == RAW_ENCODING and c.metadata.get("role") == ROLE_RAW
        ]
