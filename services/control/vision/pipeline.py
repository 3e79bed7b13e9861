"""The stereo streaming pipeline: capture → encode → publish, dropping frames, never queueing.

Three threads joined by `LatestSlot`s, one-item mailboxes where a new item replaces one not
yet taken. A slow stage therefore makes the stage before it drop pairs (counted), and video
latency stays bounded by one pair per stage whatever the network or the encoder do: the
operator sees the newest pair, never a backlog (the paper's 17 fps stereo stream shared the
LAN with force and commands; here `vision/**` is also sent at DATA_LOW with DROP).

Timing: capture runs at the fixed rate `config.fps`; a tick later than one period is
skipped rather than caught up (counted as `late_ticks`). Both eyes of a pair share `seq`
(the pair number, counting captured pairs, so gaps mean drops) and `t_ns`, the LEFT eye's
capture time; the left→right capture skew is measured and reported in the statistics.

Nobody watching, no work: while `set_watched(False)` (the service follows Zenoh's matching
status of its keys) nothing is grabbed, encoded or published; the camera's `keep_alive()`
keeps a device's queue fresh, or the capture thread sleeps until someone watches.
"""

from __future__ import annotations

import math
import threading
import time
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any, Generic, TypeVar

import numpy as np

from services.control.vision.adapt import Level
from services.control.vision.camera import Camera, Image, StereoPair
from services.control.vision.config import VisionConfig

T = TypeVar("T")

Fields = dict[str, Any]
PublishFn = Callable[[Fields, Fields], None]
"""publish(left_fields, right_fields): the StereoFrame fields (PROTOCOL.md §3) of a pair."""
EmitFn = Callable[[str, str, dict[str, Any]], None]
"""emit(kind, message, data): an Event for `robot/events` (kind "error", "status", …)."""

STATS_WINDOW = 300
"""Samples kept for the percentiles in `stats()` (10 s at 30 fps)."""
FPS_WINDOW_S = 2.0


class LatestSlot(Generic[T]):
    """A one-item mailbox between two threads: `put` replaces an item not yet taken.

    `dropped` counts the replaced items. Nothing ever waits in it but the newest item, so
    memory and latency stay bounded whatever the speed of the consumer.
    """

    def __init__(self) -> None:
        self._cond = threading.Condition()
        self._item: T | None = None
        self._full = False
        self._closed = False
        self.put_count = 0
        self.taken = 0
        self.dropped = 0

    def put(self, item: T) -> bool:
        """Store `item`; returns True when it replaced (dropped) an untaken one."""
        with self._cond:
            replaced = self._full
            if replaced:
                self.dropped += 1
            self._item, self._full = item, True
            self.put_count += 1
            self._cond.notify()
            return replaced

    def take(self, timeout_s: float) -> T | None:
        """The newest item, waiting up to `timeout_s`; None on timeout or once closed."""
        with self._cond:
            if not self._full and not self._closed:
                self._cond.wait(timeout_s)
            if not self._full:
                return None
            item, self._item, self._full = self._item, None, False
            self.taken += 1
            return item

    @property
    def pending(self) -> int:
        """1 when an item waits, else 0."""
        return int(self._full)

    def close(self) -> None:
        """Wake every waiter; later `take`s return the pending item, then None at once."""
        with self._cond:
            self._closed = True
            self._cond.notify_all()


@dataclass(frozen=True, slots=True)
class _Captured:
    seq: int
    pair: StereoPair


@dataclass(frozen=True, slots=True)
class _Encoded:
    seq: int
    t_ns: int
    left: Fields
    right: Fields


def encode_image(img: Image, encoding: str, jpeg_quality: int = 80) -> bytes:
    """The `data` of a StereoFrame: JPEG bytes, or for "bgr8" the raw rows (H·W·3 bytes)."""
    if encoding == "bgr8":
        return np.ascontiguousarray(img).tobytes()
    import cv2

    ok, buf = cv2.imencode(".jpg", img, [cv2.IMWRITE_JPEG_QUALITY, int(jpeg_quality)])
    if not ok:
        raise ValueError(f"JPEG encoding failed for an image of shape {img.shape}")
    return buf.tobytes()


def scaled(img: Image, scale: float) -> Image:
    """`img` resized by `scale` (area averaging: no aliasing); itself at 1."""
    if scale == 1.0:
        return img
    import cv2

    h, w = img.shape[:2]
    size = (max(16, round(w * scale)), max(16, round(h * scale)))
    return np.asarray(cv2.resize(img, size, interpolation=cv2.INTER_AREA), dtype=np.uint8)


def frame_fields(
    seq: int,
    t_ns: int,
    eye: str,
    img: Image,
    data: bytes,
    encoding: str,
    pair: StereoPair,
    scale: float = 1.0,
) -> Fields:
    """The StereoFrame fields (PROTOCOL.md §3) of one eye; `scale`: how the image was
    resized from the camera's (the intrinsics follow it)."""
    k = pair.intrinsics
    sx = img.shape[1] / pair.width if scale != 1.0 else 1.0
    sy = img.shape[0] / pair.height if scale != 1.0 else 1.0
    return {
        "seq": seq,
        "t_ns": t_ns,
        "eye": eye,
        "width": int(img.shape[1]),
        "height": int(img.shape[0]),
        "encoding": encoding,
        "data": data,
        "fx": float(k.fx) * sx,
        "fy": float(k.fy) * sy,
        # pixel centres: (c + ½)·s − ½ maps the camera's principal point onto the resized grid
        "cx": (float(k.cx) + 0.5) * sx - 0.5,
        "cy": (float(k.cy) + 0.5) * sy - 0.5,
        "baseline": float(pair.baseline_m),
    }


class StereoPipeline:
    """Captures pairs from `camera` at `config.fps`, encodes them (`config.encoding`) and
    hands each pair to `publish(left_fields, right_fields)`; reports camera trouble through
    `emit(kind, message, data)`.

    Only the capture thread touches the camera (it opens it, grabs, closes it). A camera
    that raises on open/grab is reported once with `emit("error", …)`, closed, and reopened
    every `config.reopen_s`; one that returns None for `stall_s` is reported the same way;
    when pairs flow again, `emit("status", "… recovered", …)`. Nothing here stops the
    pipeline but `stop()`. `publish` runs on the publish thread; if it raises, the pair is
    counted in `publish_errors` and reported once until a publish succeeds.
    """

    def __init__(
        self,
        camera: Camera,
        config: VisionConfig,
        publish: PublishFn,
        emit: EmitFn,
        stall_s: float = 1.0,
        watched: bool = True,
    ) -> None:
        self.camera = camera
        self.config = config
        self._publish = publish
        self._emit = emit
        self._dead_after = max(3, math.ceil(stall_s * config.fps))
        self._stop = threading.Event()
        self._to_encode: LatestSlot[_Captured] = LatestSlot()
        self._to_publish: LatestSlot[_Encoded] = LatestSlot()
        self._threads: list[threading.Thread] = []
        self._lock = threading.Lock()
        # Whether anyone watches the stream (set by `set_watched`); the capture thread
        # sleeps on this condition while nobody does.
        self._watch = threading.Condition()
        self._watched = watched
        self._kept_alive = 0
        self._idle_waits = 0
        # Counters: each written by one thread, read under the lock by stats().
        self._seq = 0
        self._captured = 0
        self._encoded = 0
        self._published = 0
        self._late_ticks = 0
        self._grab_errors = 0
        self._grab_misses = 0
        self._misses = 0
        self._encode_errors = 0
        self._encode_failing = False
        self._publish_errors = 0
        self._emit_errors = 0
        self._camera_ok = False
        self._camera_failing = False
        self._publish_failing = False
        self._size = (config.width, config.height)
        # The video's level (adapt.py): quality, size and rate; the encoder and the capture
        # thread read it at each pair, `set_level` changes it.
        self._level = Level(config.jpeg_quality, 1.0, 1)
        self._last_published_seq = -1
        self._grab_ms: deque[float] = deque(maxlen=STATS_WINDOW)
        self._encode_ms: deque[float] = deque(maxlen=STATS_WINDOW)
        self._publish_ms: deque[float] = deque(maxlen=STATS_WINDOW)
        self._skew_ms: deque[float] = deque(maxlen=STATS_WINDOW)
        self._latency_ms: deque[float] = deque(maxlen=STATS_WINDOW)
        self._bytes: deque[int] = deque(maxlen=STATS_WINDOW)
        self._capture_times: deque[float] = deque(maxlen=STATS_WINDOW)
        self._publish_times: deque[float] = deque(maxlen=STATS_WINDOW)

    # -- lifecycle -------------------------------------------------------------------------

    def start(self) -> None:
        """Start the three threads (the camera is opened by the capture thread)."""
        if self._threads:
            raise RuntimeError("pipeline already started")
        for name, target in (
            ("capture", self._capture_loop),
            ("encode", self._encode_loop),
            ("publish", self._publish_loop),
        ):
            th = threading.Thread(target=target, name=f"vision-{name}", daemon=True)
            self._threads.append(th)
        for th in self._threads:
            th.start()

    def stop(self, timeout_s: float = 5.0) -> None:
        """Stop the threads and close the camera; `publish` is not called once this returns
        (unless a publish call is stuck past `timeout_s`)."""
        self._stop.set()
        with self._watch:
            self._watch.notify_all()
        self._to_encode.close()
        self._to_publish.close()
        deadline = time.monotonic() + timeout_s
        for th in self._threads:
            th.join(max(0.0, deadline - time.monotonic()))

    def set_watched(self, watched: bool) -> None:
        """Whether anyone watches the stream (e.g. Zenoh's matching status of its keys).
        While nobody does, nothing is grabbed, encoded or published: the camera's
        `keep_alive()` runs at the capture rate instead, or, when it returns False, the
        capture thread sleeps. When someone comes, the next pair is grabbed at once."""
        with self._watch:
            self._watched = watched
            self._watch.notify_all()

    @property
    def watched(self) -> bool:
        return self._watched

    def set_level(self, level: Level) -> None:
        """Encode from the next pair at `level`'s JPEG quality and size, and capture at the
        configured rate divided by its stride (adapt.VideoAdapter)."""
        with self._lock:
            self._level = level

    @property
    def level(self) -> Level:
        with self._lock:
            return self._level

    @property
    def running(self) -> bool:
        return any(th.is_alive() for th in self._threads)

    def __enter__(self) -> StereoPipeline:
        self.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self.stop()

    # -- statistics ------------------------------------------------------------------------

    def stats(self) -> dict[str, Any]:
        """A snapshot for `vision/stats`: rates (pairs/s), counts, and p50/max in ms of
        grab (render time for the simulator), encode (both eyes), publish, left→right
        capture skew and latency (capture → publish returned)."""
        with self._lock:
            out: dict[str, Any] = {
                "camera": self.camera.name,
                "camera_ok": self._camera_ok,
                "idle": not self._watched,
                "width": self._size[0],
                "height": self._size[1],
                "encoding": self.config.encoding,
                "fps_target": self.config.fps / self._level.stride,
                "quality": self._level.quality,
                "scale": self._level.scale,
                "stride": self._level.stride,
                "fps": _rate(self._publish_times),
                "fps_captured": _rate(self._capture_times),
                "seq": self._last_published_seq,
                "captured": self._captured,
                "encoded": self._encoded,
                "published": self._published,
                "dropped_encode": self._to_encode.dropped,
                "dropped_publish": self._to_publish.dropped,
                "dropped": self._to_encode.dropped + self._to_publish.dropped,
                "late_ticks": self._late_ticks,
                "kept_alive": self._kept_alive,
                "idle_waits": self._idle_waits,
                "grab_errors": self._grab_errors,
                "grab_misses": self._grab_misses,
                "encode_errors": self._encode_errors,
                "publish_errors": self._publish_errors,
                "emit_errors": self._emit_errors,
                "bytes_per_pair": float(np.mean(self._bytes)) if self._bytes else 0.0,
            }
            for key, window in (
                ("grab_ms", self._grab_ms),
                ("encode_ms", self._encode_ms),
                ("publish_ms", self._publish_ms),
                ("skew_ms", self._skew_ms),
                ("latency_ms", self._latency_ms),
            ):
                out[f"{key}_p50"] = float(np.median(window)) if window else 0.0
                out[f"{key}_max"] = float(max(window)) if window else 0.0
        return out

    def stats_fields(self) -> dict[str, Any]:
        """The fields of a VisionStats message (docs/protocol-extensions.md) but `seq` and
        `t_ns`: `fps` (published pairs/s), `encode_ms` (p50, both eyes), `dropped`,
        `skew_ms` (the worst left→right skew of the last STATS_WINDOW pairs: sync is only
        as good as its worst pair), `width`, `height`, `encoding`, and every other figure
        of `stats()` in `data`."""
        s = self.stats()
        main = {
            "fps": s.pop("fps"),
            "encode_ms": s["encode_ms_p50"],
            "dropped": s.pop("dropped"),
            "skew_ms": s["skew_ms_max"],
            "width": s.pop("width"),
            "height": s.pop("height"),
            "encoding": s.pop("encoding"),
        }
        return {**main, "data": s}

    # -- threads ---------------------------------------------------------------------------

    def _capture_loop(self) -> None:
        opened = False
        reopen_at = 0.0
        next_tick = time.monotonic()
        try:
            while not self._stop.is_set():
                now = time.monotonic()
                if not opened and now >= reopen_at:
                    try:
                        self.camera.open()
                        opened = True
                        # Opening may take long (the simulator ray-casts its scene): the
                        # fixed-rate schedule starts now, not late.
                        next_tick = time.monotonic()
                    except Exception as exc:
                        self._camera_failed(f"cannot open camera {self.camera.name}: {exc}")
                        reopen_at = now + self.config.reopen_s
                if opened:
                    watched = self.watched
                    pair: StereoPair | None = None
                    ticking = True
                    try:
                        t0 = time.perf_counter()
                        if watched:
                            pair = self.camera.grab()
                        else:
                            ticking = self.camera.keep_alive()
                        grab_ms = (time.perf_counter() - t0) * 1e3
                    except Exception as exc:
                        self._camera_failed(f"camera {self.camera.name} failed: {exc}")
                        self._close_camera()
                        opened = False
                        reopen_at = time.monotonic() + self.config.reopen_s
                    else:
                        if watched:
                            self._on_grab(pair, grab_ms)
                        elif ticking:
                            self._camera_recovered()
                            with self._lock:
                                self._kept_alive += 1
                                self._camera_ok = True
                        else:
                            # Nothing to do until someone watches: sleep until then, and
                            # grab at once when they come (within one frame).
                            self._wait_watched()
                            next_tick = time.monotonic()
                            continue
                period = self.config.period_s * self.level.stride
                next_tick += period
                now = time.monotonic()
                if now > next_tick + period:
                    # Over a period late: skip the missed ticks instead of bursting.
                    self._late_ticks += 1
                    next_tick = now
                self._sleep_until(next_tick)
        finally:
            if opened:
                self._close_camera()

    def _wait_watched(self) -> None:
        with self._watch:
            self._idle_waits += 1
            while not self._watched and not self._stop.is_set():
                self._watch.wait()

    def _sleep_until(self, t_s: float) -> None:
        """Sleep until monotonic `t_s`; cut short by `stop()` or by the stream becoming
        watched while idle (so a new viewer gets a frame at once, not a tick later)."""
        with self._watch:
            was_watched = self._watched
            while not self._stop.is_set() and self._watched == was_watched:
                left = t_s - time.monotonic()
                if left <= 0 or not self._watch.wait(left):
                    return

    def _on_grab(self, pair: StereoPair | None, grab_ms: float) -> None:
        if pair is None:
            self._misses += 1
            with self._lock:
                self._grab_misses += 1
            if self._misses >= self._dead_after:
                self._report_camera_failure(
                    f"camera {self.camera.name} delivered no frame for {self._misses} ticks "
                    f"({self._misses * self.config.period_s:.1f} s)"
                )
            return
        self._camera_recovered()
        self._misses = 0
        self._seq += 1
        with self._lock:
            self._camera_ok = True
            self._captured += 1
            self._grab_ms.append(grab_ms)
            self._skew_ms.append(abs(pair.skew_ns) / 1e6)
            self._capture_times.append(time.monotonic())
        self._to_encode.put(_Captured(self._seq, pair))

    def _camera_recovered(self) -> None:
        if self._camera_failing:
            self._camera_failing = False
            self._send(
                "status",
                f"camera {self.camera.name} recovered",
                {"camera": self.camera.name, "grab_errors": self._grab_errors},
            )

    def _camera_failed(self, message: str) -> None:
        with self._lock:
            self._grab_errors += 1
        self._report_camera_failure(message)

    def _report_camera_failure(self, message: str) -> None:
        with self._lock:
            self._camera_ok = False
        if not self._camera_failing:
            self._camera_failing = True
            self._send(
                "error",
                f"{message}; retrying every {self.config.reopen_s:g} s",
                {"camera": self.camera.name},
            )

    def _close_camera(self) -> None:
        try:
            self.camera.close()
        except Exception as exc:
            self._send("error", f"closing camera {self.camera.name} failed: {exc}", {})

    def _encode_loop(self) -> None:
        cfg = self.config
        while not self._stop.is_set():
            item = self._to_encode.take(0.1)
            if item is None:
                continue
            pair = item.pair
            level = self.level
            t0 = time.perf_counter()
            try:
                img_l, img_r = scaled(pair.left, level.scale), scaled(pair.right, level.scale)
                data_l = encode_image(img_l, cfg.encoding, level.quality)
                data_r = encode_image(img_r, cfg.encoding, level.quality)
            except Exception as exc:
                with self._lock:
                    self._encode_errors += 1
                if not self._encode_failing:
                    self._encode_failing = True
                    self._send("error", f"encoding stereo pair {item.seq} failed: {exc}", {})
                continue
            self._encode_failing = False
            encode_ms = (time.perf_counter() - t0) * 1e3
            t_ns = pair.t_ns_left
            sc = level.scale
            left = frame_fields(item.seq, t_ns, "l", img_l, data_l, cfg.encoding, pair, sc)
            right = frame_fields(item.seq, t_ns, "r", img_r, data_r, cfg.encoding, pair, sc)
            with self._lock:
                self._encoded += 1
                self._encode_ms.append(encode_ms)
                self._bytes.append(len(data_l) + len(data_r))
                self._size = (int(img_l.shape[1]), int(img_l.shape[0]))
            self._to_publish.put(_Encoded(item.seq, t_ns, left, right))

    def _publish_loop(self) -> None:
        while not self._stop.is_set():
            item = self._to_publish.take(0.1)
            if item is None or self._stop.is_set():
                continue
            t0 = time.perf_counter()
            try:
                self._publish(item.left, item.right)
            except Exception as exc:
                with self._lock:
                    self._publish_errors += 1
                if not self._publish_failing:
                    self._publish_failing = True
                    self._send("error", f"publishing stereo pair failed: {exc}", {})
                continue
            self._publish_failing = False
            done = time.perf_counter()
            with self._lock:
                self._published += 1
                self._last_published_seq = item.seq
                self._publish_ms.append((done - t0) * 1e3)
                self._latency_ms.append((time.time_ns() - item.t_ns) / 1e6)
                self._publish_times.append(time.monotonic())

    def _send(self, kind: str, message: str, data: dict[str, Any]) -> None:
        # A broken event channel must not take the video down with it; it is counted.
        try:
            self._emit(kind, message, data)
        except Exception:
            with self._lock:
                self._emit_errors += 1


def _rate(times: deque[float]) -> float:
    """Events per second over the last FPS_WINDOW_S of monotonic `times`."""
    if len(times) < 2:
        return 0.0
    ts = list(times)
    last = ts[-1]
    recent = [t for t in ts if t >= last - FPS_WINDOW_S]
    if len(recent) < 2 or time.monotonic() - last > FPS_WINDOW_S:
        return 0.0
    return (len(recent) - 1) / (recent[-1] - recent[0])
