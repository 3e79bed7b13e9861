"""What the bench does on the bus: record streams with their arrival times, decode video,
drive commands as a master, and time method calls.

Arrival times are `time.time_ns()` taken first thing in the Zenoh callback, on the same
clock as the senders' `t_ns` (one machine). Callbacks only stamp, decode the small message
and append (ZENOH_NOTES.md pitfall 6); JPEG decoding runs on a worker thread of its own.
"""

from __future__ import annotations

import queue
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any, Generic, TypeVar

import zenoh

from services.bus import codec
from services.bus.errors import ProtocolError, RpcError, Unavailable
from services.bus.keys import CMD, STEREO_L, STEREO_R, Topic
from services.bus.messages import IDENTITY_R, Message, OperatorCommand, StereoFrame
from services.bus.node import Node
from services.bus.rate import RateLoop

M = TypeVar("M", bound=Message)


class StreamProbe(Generic[M]):
    """Records `(arrival_ns, extract(msg))` for every valid message on `topic` between
    `start()` and `stop()`; invalid payloads are only counted."""

    def __init__(self, node: Node, topic: Topic[M], extract: Callable[[M], tuple[Any, ...]]):
        self.node = node
        self.topic = topic
        self.extract = extract
        self.records: list[tuple[int, tuple[Any, ...]]] = []
        self.rejected = 0
        self._lock = threading.Lock()
        self._handle: Any = None

    def start(self) -> StreamProbe[M]:
        self._handle = self.node.subscribe_raw(self.topic.key, self._on_sample)
        return self

    def _on_sample(self, sample: zenoh.Sample) -> None:
        rx_ns = time.time_ns()
        try:
            msg = codec.decode(self.topic.type, sample.payload.to_bytes())
        except ProtocolError:
            with self._lock:
                self.rejected += 1
            return
        row = (rx_ns, self.extract(msg))
        with self._lock:
            self.records.append(row)

    def count(self) -> int:
        with self._lock:
            return len(self.records)

    def snapshot(self) -> list[tuple[int, tuple[Any, ...]]]:
        """A copy of the records so far, in arrival order."""
        with self._lock:
            return list(self.records)

    def newest(self) -> tuple[int, tuple[Any, ...]] | None:
        with self._lock:
            return self.records[-1] if self.records else None

    def wait_count(self, n: int, timeout_s: float) -> bool:
        """Poll until `n` records are in (a deadline, not a sleep: True when reached)."""
        deadline = time.monotonic() + timeout_s
        while self.count() < n:
            if time.monotonic() >= deadline:
                return False
            time.sleep(0.01)
        return True

    def stop(self) -> list[tuple[int, tuple[Any, ...]]]:
        """Undeclare and return the records in arrival order."""
        if self._handle is not None:
            self._handle.undeclare()
            self._handle = None
        with self._lock:
            return list(self.records)


@dataclass(frozen=True, slots=True)
class FrameRecord:
    """One stereo frame as the bench saw it: arrival, and the end of its JPEG decoding."""

    eye: str
    seq: int
    t_ns: int
    rx_ns: int
    decoded_ns: int
    nbytes: int
    width: int
    height: int


class VideoProbe:
    """Subscribes both eyes; a worker decodes every frame (cv2.imdecode) and records when
    the decoded image was ready — the operator's station's "capture → on screen" minus
    display."""

    def __init__(self, node: Node) -> None:
        self.node = node
        self.frames: list[FrameRecord] = []
        self.decode_errors = 0
        self.rejected = 0
        self._queue: queue.SimpleQueue[tuple[int, bytes] | None] = queue.SimpleQueue()
        self._handles: list[Any] = []
        self._worker: threading.Thread | None = None
        self._lock = threading.Lock()

    def start(self) -> VideoProbe:
        self._worker = threading.Thread(target=self._decode_loop, name="bench-video", daemon=True)
        self._worker.start()
        for topic in (STEREO_L, STEREO_R):
            self._handles.append(self.node.subscribe_raw(topic.key, self._on_sample))
        return self

    def _on_sample(self, sample: zenoh.Sample) -> None:
        self._queue.put((time.time_ns(), sample.payload.to_bytes()))

    def _decode_loop(self) -> None:
        import cv2
        import numpy as np

        while True:
            item = self._queue.get()
            if item is None:
                return
            rx_ns, payload = item
            try:
                msg = codec.decode(StereoFrame, payload)
            except ProtocolError:
                with self._lock:
                    self.rejected += 1
                continue
            if msg.encoding == "jpeg":
                img = cv2.imdecode(np.frombuffer(msg.data, np.uint8), cv2.IMREAD_COLOR)
                ok = img is not None and img.shape[:2] == (msg.height, msg.width)
            else:
                ok = len(msg.data) == msg.width * msg.height * 3
            done_ns = time.time_ns()
            with self._lock:
                if not ok:
                    self.decode_errors += 1
                    continue
                self.frames.append(
                    FrameRecord(
                        msg.eye,
                        msg.seq,
                        msg.t_ns,
                        rx_ns,
                        done_ns,
                        len(msg.data),
                        msg.width,
                        msg.height,
                    )
                )

    def count(self, eye: str | None = None) -> int:
        with self._lock:
            return sum(1 for f in self.frames if eye is None or f.eye == eye)

    def wait_frames(self, n: int, timeout_s: float) -> bool:
        """Poll until both eyes have `n` decoded frames (True) or the deadline (False)."""
        deadline = time.monotonic() + timeout_s
        while min(self.count("l"), self.count("r")) < n:
            if time.monotonic() >= deadline:
                return False
            time.sleep(0.02)
        return True

    def stop(self) -> list[FrameRecord]:
        """Undeclare, let the worker finish the frames already received, return them."""
        for h in self._handles:
            h.undeclare()
        self._handles.clear()
        self._queue.put(None)
        if self._worker is not None:
            self._worker.join(timeout=10.0)
        with self._lock:
            return list(self.frames)


CATCH_UP_S = 0.005
"""How far behind its schedule the command driver catches up instead of skipping ticks."""


class CommandDriver:
    """The bench as a master (`alive/master/<id>` is the node's token): streams
    OperatorCommands on `robot/cmd` whose `dp` encodes each command's index, so it can be
    told apart after the decision re-sequences (see `stream`)."""

    def __init__(self, node: Node, master_id: str) -> None:
        self.node = node
        self.master_id = master_id
        self._pub = node.publisher(CMD)
        # Seeded from the wall clock like the masters: a rerun counts upwards.
        wall = time.time_ns()
        self._seq = wall // 1_000
        self._engage = wall // 1_000_000

    def _put(self, k: int, step_m: float, active: bool) -> int:
        self._seq += 1
        t_ns = time.time_ns()
        self._pub.put(
            OperatorCommand(
                seq=self._seq,
                t_ns=t_ns,
                master=self.master_id,
                engage=self._engage,
                active=active,
                frame="world",
                dp=(k * step_m, 0.0, 0.0),
                dR=IDENTITY_R,
            )
        )
        return t_ns

    def stream(
        self,
        rate_hz: float,
        duration_s: float,
        step_m: float,
        held: Callable[[int], bool] | None = None,
        release: int = 5,
    ) -> CommandRun:
        """Stream active commands k = 0, 1, … at `rate_hz` for `duration_s`, then `release`
        inactive ones (the decision holds and frees the lease).

        Within an engagement started at command k0, command k carries dp_x = (k − k0)·step_m:
        the decision rebases every engagement on the tool pose of its start. When
        `held(start_ns)` says the decision stopped following the engagement that began at
        start_ns (a watchdog hold, a refusal), the next command starts a new engagement, as
        an operator would engage again.
        """
        run = CommandRun([], [])
        # A tick woken late is sent at once (up to CATCH_UP_S behind) rather than skipped:
        # the phase sends `rate_hz` on average, as a device's servo clock would.
        loop = RateLoop(rate_hz, late_tolerance=max(1.0, CATCH_UP_S * rate_hz))
        end = time.monotonic() + duration_s
        k = k0 = 0
        while time.monotonic() < end:
            if not run.starts or (held is not None and held(run.starts[-1][0])):
                self._engage += 1
                k0 = k
                t_ns = self._put(k - k0, step_m, True)
                run.starts.append((t_ns, k0))
            else:
                t_ns = self._put(k - k0, step_m, True)
            run.sent.append((k, t_ns))
            k += 1
            loop.sleep()
        for _ in range(release):
            self._put(max(k - 1 - k0, 0), step_m, False)
            loop.sleep()
        return run


@dataclass(frozen=True, slots=True)
class CommandRun:
    """What `CommandDriver.stream` sent: (k, t_ns) per active command, and (t_ns of its first
    command, k0) per engagement."""

    sent: list[tuple[int, int]]
    starts: list[tuple[int, int]]


@dataclass(frozen=True, slots=True)
class CallTimes:
    """Round trips (ms) of the calls that got a reply, and the failures by kind
    (`unavailable`: no reply within the timeout; otherwise the error code)."""

    ms: list[float]
    failures: dict[str, int]


def time_calls(node: Node, service: str, method: str, n: int, timeout_s: float = 5.0) -> CallTimes:
    """`n` sequential calls of `service.method` with no arguments. A call that fails is
    counted, not timed, and the series goes on: one lost reply must not end the run."""
    out: list[float] = []
    failures: dict[str, int] = {}
    for i in range(n + 1):
        t0 = time.perf_counter()
        try:
            node.call(service, method, {}, timeout_s)
            failure = None
        except Unavailable:
            failure = "unavailable"
        except RpcError as e:
            failure = e.code
        if i == 0:  # the first call only warms up: liveliness known, routes declared
            continue
        if failure is None:
            out.append((time.perf_counter() - t0) * 1e3)
        else:
            failures[failure] = failures.get(failure, 0) + 1
    return CallTimes(out, failures)
