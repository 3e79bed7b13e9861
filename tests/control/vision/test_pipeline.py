from __future__ import annotations

import threading
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st

from services.control.vision.backends import open_camera
from services.control.vision.camera import CameraError
from services.control.vision.config import VisionConfig
from services.control.vision.pipeline import LatestSlot, StereoPipeline
from services.control.vision.sim_camera import SimStereoCamera
from tests.conftest import wait_until

from .fakes import FakeCamera, Recorder, write_video

STEREO_FRAME_FIELDS = {
    "seq": int,
    "t_ns": int,
    "eye": str,
    "width": int,
    "height": int,
    "encoding": str,
    "data": bytes,
    "fx": float,
    "fy": float,
    "cx": float,
    "cy": float,
    "baseline": float,
}
# At most one pair waits in each of the two slots, one is being encoded, one published,
# one is between grab and its slot.
MAX_IN_FLIGHT = 5


def check_fields(f: dict[str, Any], eye: str) -> None:
    assert set(f) == set(STEREO_FRAME_FIELDS)
    for key, typ in STEREO_FRAME_FIELDS.items():
        assert type(f[key]) is typ, key
    assert f["eye"] == eye


def test_sim_pairs_are_synchronized_and_decode() -> None:
    cfg = VisionConfig(width=160, height=120, fps=60.0)
    cam = SimStereoCamera(cfg, supersample=1)
    rec = Recorder()
    with StereoPipeline(cam, cfg, rec.publish, rec.emit) as pipe:
        assert wait_until(lambda: len(rec.pairs) >= 12, what="12 published pairs")
    assert not pipe.running
    pairs = list(rec.pairs)
    seqs = [left["seq"] for left, _ in pairs]
    assert seqs == sorted(set(seqs)) and seqs[0] >= 1
    for left, right in pairs:
        check_fields(left, "l")
        check_fields(right, "r")
        assert left["seq"] == right["seq"] and left["t_ns"] == right["t_ns"]
        assert left["encoding"] == right["encoding"] == "jpeg"
        assert (left["width"], left["height"]) == (160, 120)
        assert right["baseline"] == pytest.approx(0.065)
        assert right["fx"] == pytest.approx(cam.rig.intrinsics.fx)
        for f in (left, right):
            img = cv2.imdecode(np.frombuffer(f["data"], np.uint8), cv2.IMREAD_COLOR)
            assert img is not None and img.shape == (120, 160, 3)
    assert rec.events == []
    s = pipe.stats()
    assert s["published"] >= 12 and s["camera_ok"] and s["skew_ms_max"] == 0.0
    assert s["encode_ms_p50"] > 0.0 and s["grab_ms_p50"] > 0.0 and s["bytes_per_pair"] > 0


def test_bgr8_is_the_raw_rows() -> None:
    cfg = VisionConfig(width=16, height=16, fps=100.0, encoding="bgr8")
    cam, rec = FakeCamera(), Recorder()
    with StereoPipeline(cam, cfg, rec.publish, rec.emit) as pipe:
        assert wait_until(lambda: len(rec.pairs) >= 3)
    left, right = rec.pairs[-1]
    assert left["encoding"] == "bgr8" and len(left["data"]) == 16 * 16 * 3
    img = np.frombuffer(left["data"], np.uint8).reshape(16, 16, 3)
    assert (img == img[0, 0, 0]).all()
    assert left["seq"] == right["seq"]
    assert pipe.stats()["skew_ms_max"] == pytest.approx(0.001)  # the fake's 1 µs


def test_slow_publish_drops_pairs_instead_of_queueing_them() -> None:
    cfg = VisionConfig(width=16, height=16, fps=200.0)
    cam, rec = FakeCamera(), Recorder()
    gate = threading.Event()
    blocked_seq: list[int] = []

    def slow_publish(left: dict[str, Any], right: dict[str, Any]) -> None:
        if not blocked_seq:
            blocked_seq.append(left["seq"])
            gate.wait(10.0)  # a stalled network: this publish takes "forever"
        rec.publish(left, right)

    pipe = StereoPipeline(cam, cfg, slow_publish, rec.emit)
    pipe.start()
    try:
        assert wait_until(lambda: bool(blocked_seq), what="first publish")
        assert wait_until(
            lambda: pipe.stats()["captured"] >= blocked_seq[0] + 40, what="40 captures"
        )
        s = pipe.stats()
        assert s["published"] == 0
        in_flight = s["captured"] - s["published"] - s["dropped"]
        assert 0 <= in_flight <= MAX_IN_FLIGHT  # no growth while publish is stuck
        assert s["dropped"] >= 40 - MAX_IN_FLIGHT
        gate.set()
        assert wait_until(lambda: len(rec.pairs) >= 3, what="publishing to resume")
    finally:
        gate.set()
        pipe.stop()
    seqs = [left["seq"] for left, _ in rec.pairs]
    assert seqs[0] == blocked_seq[0]
    # After the stall comes the newest pair, not the backlog.
    assert seqs[1] >= blocked_seq[0] + 40 - MAX_IN_FLIGHT
    s = pipe.stats()
    assert s["captured"] - s["published"] - s["dropped"] <= MAX_IN_FLIGHT
    assert s["dropped"] == s["dropped_encode"] + s["dropped_publish"]


def test_dead_camera_is_reported_once_and_the_pipeline_keeps_retrying() -> None:
    cfg = VisionConfig(width=16, height=16, fps=100.0, reopen_s=0.02)
    cam, rec = FakeCamera(), Recorder()
    with StereoPipeline(cam, cfg, rec.publish, rec.emit) as pipe:
        assert wait_until(lambda: len(rec.pairs) >= 2)
        cam.fail = CameraError("fake: grab failed on device 0 (disconnected?)")
        assert wait_until(lambda: pipe.stats()["grab_errors"] >= 5, what="repeated failures")
        assert pipe.running
        assert cam.open_calls >= 5 and cam.close_calls >= 4  # closed and reopened each time
        errors = [e for e in rec.events if e[0] == "error"]
        assert len(errors) == 1
        assert "fake" in errors[0][1] and "disconnected" in errors[0][1]
        assert errors[0][2] == {"camera": "fake"}
        assert not pipe.stats()["camera_ok"]
        n = len(rec.pairs)
        cam.fail = None
        assert wait_until(lambda: len(rec.pairs) >= n + 2, what="recovery")
        assert rec.kinds() == ["error", "status"]
        assert "recovered" in rec.events[1][1]
        assert pipe.stats()["camera_ok"]


def test_unexpected_exception_from_a_backend_is_reported_not_fatal() -> None:
    cfg = VisionConfig(width=16, height=16, fps=100.0, reopen_s=0.02)
    cam, rec = FakeCamera(), Recorder()
    cam.fail = RuntimeError("driver bug")
    with StereoPipeline(cam, cfg, rec.publish, rec.emit) as pipe:
        assert wait_until(lambda: pipe.stats()["grab_errors"] >= 3)
        assert pipe.running
    assert rec.kinds() == ["error"] and "driver bug" in rec.events[0][1]


def test_camera_that_stops_delivering_is_reported_after_the_stall_time() -> None:
    cfg = VisionConfig(width=16, height=16, fps=100.0)
    cam, rec = FakeCamera(), Recorder()
    with StereoPipeline(cam, cfg, rec.publish, rec.emit, stall_s=0.1) as pipe:
        assert wait_until(lambda: len(rec.pairs) >= 2)
        cam.starve = True
        assert wait_until(lambda: "error" in rec.kinds(), what="stall error")
        assert pipe.stats()["grab_misses"] >= 10  # ≥ 0.1 s at 100 fps
        assert wait_until(lambda: pipe.stats()["grab_misses"] >= 30)
        assert rec.kinds() == ["error"] and "no frame" in rec.events[0][1]
        cam.starve = False
        assert wait_until(lambda: rec.kinds() == ["error", "status"], what="recovered event")


def test_camera_that_cannot_open_is_retried() -> None:
    cfg = VisionConfig(width=16, height=16, fps=100.0, reopen_s=0.02)
    cam, rec = FakeCamera(), Recorder()
    cam.fail_open = True
    with StereoPipeline(cam, cfg, rec.publish, rec.emit):
        assert wait_until(lambda: cam.open_calls >= 3, what="open retries")
        assert rec.kinds() == ["error"] and "no such device" in rec.events[0][1]
        cam.fail_open = False
        assert wait_until(lambda: len(rec.pairs) >= 1, what="first pair after the camera appeared")


def test_failing_publish_is_counted_and_reported_once() -> None:
    cfg = VisionConfig(width=16, height=16, fps=100.0)
    cam, rec = FakeCamera(), Recorder()

    def broken(left: dict[str, Any], right: dict[str, Any]) -> None:
        raise OSError("session closed")

    with StereoPipeline(cam, cfg, broken, rec.emit) as pipe:
        assert wait_until(lambda: pipe.stats()["publish_errors"] >= 5)
        assert pipe.running
    assert rec.kinds() == ["error"] and "session closed" in rec.events[0][1]


def test_video_file_end_is_an_error_event(tmp_path: Path) -> None:
    frames = [np.full((24, 32, 3), 10 * i, np.uint8) for i in range(5)]
    left = write_video(tmp_path / "l.avi", frames)
    right = write_video(tmp_path / "r.avi", frames)
    cfg = VisionConfig(
        camera="opencv",
        files=(str(left), str(right)),
        width=32,
        height=24,
        fps=100.0,
        reopen_s=30.0,
    )
    cam, rec = open_camera(cfg), Recorder()
    with StereoPipeline(cam, cfg, rec.publish, rec.emit) as pipe:
        assert wait_until(lambda: "error" in rec.kinds(), what="end of file")
        assert wait_until(lambda: pipe.stats()["published"] + pipe.stats()["dropped"] == 5)
    assert "end of file" in rec.events[0][1]
    assert rec.kinds() == ["error"]
    assert pipe.stats()["skew_ms_max"] > 0.0  # two files, grabbed one after the other


def test_stop_closes_the_camera_and_publishes_no_more() -> None:
    cfg = VisionConfig(width=16, height=16, fps=100.0)
    cam, rec = FakeCamera(), Recorder()
    pipe = StereoPipeline(cam, cfg, rec.publish, rec.emit)
    pipe.start()
    assert wait_until(lambda: len(rec.pairs) >= 2)
    pipe.stop()
    # Every thread has ended, so publish cannot be called again.
    assert not pipe.running and not cam.is_open
    with pytest.raises(RuntimeError):
        pipe.start()


def test_nothing_is_grabbed_or_published_while_nobody_watches() -> None:
    """A simulator-like camera: the capture thread sleeps while unwatched (no grab, no
    keep-alive ticks), works while watched, and sleeps again when the viewer leaves."""
    cfg = VisionConfig(width=16, height=16, fps=100.0)
    cam, rec = FakeCamera(), Recorder()
    with StereoPipeline(cam, cfg, rec.publish, rec.emit, watched=False) as pipe:
        assert wait_until(lambda: pipe.stats()["idle_waits"] == 1, what="the capture thread asleep")
        assert cam.is_open, "the camera is opened at start, ready for the first viewer"
        assert (cam.frames, cam.keep_alives, len(rec.pairs)) == (0, 1, 0)
        assert pipe.stats()["idle"] is True

        pipe.set_watched(True)
        assert wait_until(lambda: len(rec.pairs) >= 5, what="pairs once watched")
        assert pipe.stats()["idle"] is False

        pipe.set_watched(False)
        assert wait_until(lambda: pipe.stats()["idle_waits"] == 2, what="the capture thread asleep")
        frames, published = cam.frames, pipe.stats()["published"]
        # Asleep on a condition, not polling: a second viewer coming and going wakes it
        # exactly once more, and no frame was grabbed in between.
        assert pipe.stats()["captured"] == frames and cam.keep_alives == 2

        pipe.set_watched(True)
        assert wait_until(lambda: pipe.stats()["published"] >= published + 3, what="resumed pairs")
    assert not pipe.running and not cam.is_open


def test_a_new_viewer_gets_a_pair_at_once_not_at_the_next_tick() -> None:
    # One frame per 100 s: a pair within the wait's deadline can only come from the
    # capture thread being woken by set_watched.
    cfg = VisionConfig(width=16, height=16, fps=0.01)
    cam, rec = FakeCamera(), Recorder()
    with StereoPipeline(cam, cfg, rec.publish, rec.emit, watched=False) as pipe:
        assert wait_until(lambda: pipe.stats()["idle_waits"] == 1, what="the capture thread asleep")
        pipe.set_watched(True)
        assert wait_until(lambda: len(rec.pairs) == 1, what="a pair for the new viewer")
        assert cam.frames == 1


def test_a_device_keeps_being_read_but_nothing_is_encoded_while_unwatched() -> None:
    cfg = VisionConfig(width=16, height=16, fps=100.0)
    cam, rec = FakeCamera(), Recorder()
    cam.device = True
    with StereoPipeline(cam, cfg, rec.publish, rec.emit, watched=False) as pipe:
        assert wait_until(lambda: cam.keep_alives >= 10, what="the device kept fresh")
        s = pipe.stats()
        assert (cam.frames, s["captured"], s["encoded"], s["published"]) == (0, 0, 0, 0)
        assert s["kept_alive"] >= 10 and s["idle_waits"] == 0 and rec.events == []
        pipe.set_watched(True)
        assert wait_until(lambda: len(rec.pairs) >= 3, what="pairs once watched")


def test_a_device_that_dies_while_unwatched_is_reported_and_reopened() -> None:
    cfg = VisionConfig(width=16, height=16, fps=100.0, reopen_s=0.01)
    cam, rec = FakeCamera(), Recorder()
    cam.device = True
    with StereoPipeline(cam, cfg, rec.publish, rec.emit, watched=False):
        assert wait_until(lambda: cam.keep_alives >= 2)
        cam.fail = CameraError("fake: unplugged")
        assert wait_until(lambda: cam.open_calls >= 3, what="reopen attempts")
        assert rec.kinds() == ["error"]
        cam.fail = None
        assert wait_until(lambda: rec.kinds() == ["error", "status"], what="the recovered event")


def test_stop_wakes_an_idle_pipeline() -> None:
    cam, rec = FakeCamera(), Recorder()
    pipe = StereoPipeline(
        cam, VisionConfig(width=16, height=16), rec.publish, rec.emit, watched=False
    )
    pipe.start()
    assert wait_until(lambda: pipe.stats()["idle_waits"] == 1)
    pipe.stop()
    assert not pipe.running and not cam.is_open


@given(st.lists(st.one_of(st.just("take"), st.integers(0, 1000)), max_size=60))
def test_latest_slot_keeps_only_the_newest(ops: list[str | int]) -> None:
    """Whatever the interleaving, a take gets the newest put, nothing is delivered twice,
    and every put is delivered, dropped, or still pending (at most one)."""
    slot: LatestSlot[tuple[int, int]] = LatestSlot()
    puts = taken = 0
    last: tuple[int, int] | None = None
    delivered: list[int] = []
    for op in ops:
        if op == "take":
            item = slot.take(0.0)
            assert item == last
            if item is not None:
                delivered.append(item[0])
                taken += 1
            last = None
        else:
            last = (puts, int(op))
            slot.put(last)
            puts += 1
        assert slot.pending in (0, 1)
        assert puts == taken + slot.dropped + slot.pending
    assert delivered == sorted(set(delivered))
