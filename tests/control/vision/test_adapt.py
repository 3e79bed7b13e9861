"""Video that gives way first (issue 41): the level ladder, a receiver's arrival report, the
adapter's decisions on a clock of the test's, the pipeline at a level, and the service
reacting to reports on the bus with an event."""

from __future__ import annotations

import itertools
import time

import cv2
import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st

from services.bus import keys
from services.bus.errors import ConfigError
from services.bus.messages import Event, StereoFrame
from services.control.vision.adapt import (
    DOWN_HOLD_S,
    VIDEO_ARRIVAL,
    ArrivalMeter,
    Level,
    VideoAdapter,
    VideoArrival,
    ladder,
)
from services.control.vision.config import VisionConfig
from services.control.vision.pipeline import StereoPipeline
from services.control.vision.service import VisionService
from services.control.vision.sim_camera import SimStereoCamera
from tests.bus.test_node import Events
from tests.conftest import Net, wait_until

from .fakes import Recorder


def test_the_ladder_lowers_quality_then_size_then_rate() -> None:
    levels = ladder(80)
    assert levels[0] == Level(80, 1.0, 1)
    assert [lv.quality for lv in levels[:4]] == [80, 60, 40, 25]
    assert [(lv.scale, lv.stride) for lv in levels[3:]] == [(1.0, 1), (0.5, 1), (0.5, 2), (0.5, 4)]
    # each step costs less in every respect and never more in any
    for hi, lo in itertools.pairwise(levels):
        assert lo.quality <= hi.quality and lo.scale <= hi.scale and lo.stride >= hi.stride
        assert (lo.quality, lo.scale, -lo.stride) != (hi.quality, hi.scale, -hi.stride)
    assert ladder(30)[0].quality == 30 and all(lv.quality <= 30 for lv in ladder(30))
    assert Level(25, 0.5, 1).size(640, 480) == (320, 240)


def test_an_arrival_report_counts_pairs_ages_and_gaps() -> None:
    meter = ArrivalMeter("console", window_s=2.0)
    t0 = 10_000_000_000
    for seq in (1, 2, 3, 5, 6, 9, 10):  # 4, 7, 8 lost
        meter.on_pair(seq, t0 + seq * 50_000_000, t0 + seq * 50_000_000 + seq * 10_000_000)
    r = meter.report(t0 + 1_000_000_000)
    assert r is not None and r.receiver == "console"
    # the stream began 0.94 s before the report (first arrival at t0 + 60 ms): its rate
    # counts over that time, not the whole window (else a new stream looks half lost)
    assert r.pairs == 7 and r.lost == 3 and r.fps == pytest.approx(7 / 0.94)
    assert r.age_p50_ms == pytest.approx(50.0) and r.age_p90_ms == pytest.approx(100.0)
    # a window later, nothing of it is left
    assert meter.report(t0 + 5_000_000_000) is None


def test_a_stream_that_just_began_reports_its_rate_not_a_loss() -> None:
    meter = ArrivalMeter("console")
    t0 = 10**12
    for seq in range(1, 11):  # 10 pairs/s for one second, into a 2 s window
        meter.on_pair(seq, t0 + seq * 100_000_000, t0 + seq * 100_000_000 + 5_000_000)
    r = meter.report(t0 + 1_105_000_000)
    assert r is not None and r.fps == pytest.approx(10.0)
    adapter = VideoAdapter(ladder(80), 150.0, 8.0)
    adapter.offer(r, 0.0)
    assert adapter.update(0.0, 10.0) is None and adapter.level == 0


def report(who: str, age_p50: float, age_p90: float, fps: float, seq: int = 1) -> VideoArrival:
    return VideoArrival(
        seq=seq, t_ns=1, receiver=who, window_s=2.0, pairs=int(fps * 2), fps=fps,
        age_p50_ms=age_p50, age_p90_ms=age_p90, lost=0,
    )  # fmt: skip


def drive(adapter: VideoAdapter, ages: list[tuple[float, float]], fps: float, sent: float,
          offset_ms: float = 0.0) -> list[int]:  # fmt: skip
    """One report a second with these (p50, p90) ages; the level after each."""
    out = []
    for i, (p50, p90) in enumerate(ages):
        adapter.offer(report("c", p50 + offset_ms, p90 + offset_ms, fps, i + 1), float(i))
        adapter.update(float(i), sent)
        out.append(adapter.level)
    return out


def test_queueing_video_steps_down_one_level_per_hold_and_recovers_slowly() -> None:
    adapter = VideoAdapter(ladder(80), queue_ms=150.0, up_s=8.0)
    # the link's own delay is 100 ms; for 10 s the video queues 400 ms on top of it
    ages = [(100.0, 110.0)] * 3 + [(300.0, 500.0)] * 10 + [(100.0, 110.0)] * 30
    levels = drive(adapter, ages, fps=30.0, sent=30.0)
    assert levels[:3] == [0, 0, 0]
    downs = [i for i in range(1, len(levels)) if levels[i] > levels[i - 1]]
    assert downs[0] == 3, "the first bad report lowers the level at once"
    assert all(b - a >= DOWN_HOLD_S for a, b in itertools.pairwise(downs))
    assert max(levels) == len(downs) >= 3
    ups = [i for i in range(1, len(levels)) if levels[i] < levels[i - 1]]
    assert ups and ups[0] >= 13 + 8 - 1, "good reports for up_s before the first step up"
    assert all(b - a >= 8 for a, b in itertools.pairwise(ups))
    assert all(abs(b - a) <= 1 for a, b in itertools.pairwise(levels))


@given(st.floats(0.0, 5000.0))
def test_a_clock_offset_between_the_hosts_changes_nothing(offset_ms: float) -> None:
    """The age is measured on two hosts' clocks; the adapter compares it with the lowest age
    seen (the link's delay on those same clocks), so any constant offset cancels (a clock
    behind gives ages floored at 0 on the wire: an offset ≥ 0 here)."""
    ages = [(100.0, 110.0)] * 3 + [(300.0, 500.0)] * 6 + [(100.0, 110.0)] * 12
    base = drive(VideoAdapter(ladder(80), 150.0, 8.0), ages, 30.0, 30.0)
    shifted = drive(VideoAdapter(ladder(80), 150.0, 8.0), ages, 30.0, 30.0, offset_ms)
    assert shifted == base and max(base) >= 2


def test_pairs_lost_on_the_link_lower_the_level_and_no_reports_hold_it() -> None:
    adapter = VideoAdapter(ladder(80), 150.0, 8.0)
    adapter.offer(report("c", 100.0, 110.0, 21.0), 0.0)  # 70 % of the pairs sent arrive
    change = adapter.update(0.0, 30.0)
    assert change is not None and change.new == 1 and "70 % of the pairs sent" in change.reason
    levels = drive(adapter, [(100.0, 110.0)] * 3, fps=21.0, sent=30.0)
    assert levels == [1, 2, 3], levels
    assert adapter.last["arrival"] == pytest.approx(0.7)
    # far off (40 % arrive): two levels a step
    far = VideoAdapter(ladder(80), 150.0, 8.0)
    assert drive(far, [(100.0, 110.0)] * 3, fps=12.0, sent=30.0) == [2, 4, 6]
    # no report for longer than FRESH_S: the level holds, whatever the time
    for t in range(10, 60):
        assert adapter.update(float(t), 30.0) is None
    assert adapter.level == 3 and adapter.last == {"state": "no reports"}
    adapter.forget()
    assert adapter.level == 0


def test_the_worst_receiver_decides() -> None:
    adapter = VideoAdapter(ladder(80), 150.0, 8.0)
    adapter.offer(report("fast", 50.0, 60.0, 30.0), 0.0)
    adapter.offer(report("slow", 200.0, 210.0, 30.0), 0.0)
    adapter.update(0.0, 30.0)
    adapter.offer(report("slow", 200.0, 600.0, 30.0, 2), 1.0)
    change = adapter.update(1.0, 30.0)
    assert change is not None and change.new == 1 and change.reason.startswith("slow")


def test_the_pipeline_encodes_at_its_level() -> None:
    cfg = VisionConfig(width=160, height=120, fps=30.0)
    cam = SimStereoCamera(cfg, supersample=1)
    rec = Recorder()
    with StereoPipeline(cam, cfg, rec.publish, rec.emit) as pipe:
        assert wait_until(lambda: len(rec.pairs) >= 3, what="3 pairs at the top level")
        full = list(rec.pairs)[-1][0]
        pipe.set_level(Level(25, 0.5, 2))
        n = len(rec.pairs)
        assert wait_until(lambda: len(rec.pairs) >= n + 4, what="pairs at the new level")
        small = list(rec.pairs)[-1][0]
        stats = pipe.stats()
    assert (full["width"], full["height"]) == (160, 120)
    assert (small["width"], small["height"]) == (80, 60)
    img = cv2.imdecode(np.frombuffer(small["data"], np.uint8), cv2.IMREAD_COLOR)
    assert img is not None and img.shape == (60, 80, 3)
    assert small["fx"] == pytest.approx(full["fx"] / 2)
    assert small["cx"] == pytest.approx((full["cx"] + 0.5) / 2 - 0.5)
    assert len(small["data"]) < len(full["data"]) / 2
    assert stats["quality"] == 25 and stats["stride"] == 2 and stats["fps_target"] == 15.0
    assert (stats["width"], stats["height"]) == (80, 60)


def test_bad_adaptation_settings_fail_naming_the_key() -> None:
    for key, value in (("adapt_queue_ms", 0.0), ("adapt_up_s", 1e9), ("adapt", "yes")):
        with pytest.raises(ConfigError, match=f"vision.{key}"):
            VisionConfig.from_mapping({key: value})


def test_the_service_lowers_the_video_on_reports_and_says_so(net: Net) -> None:
    vision_node = net.node("vision")
    viewer = net.node("viewer")
    events = Events(viewer)
    frames = viewer.subscribe(keys.STEREO_L)
    viewer.subscribe(keys.STEREO_R)
    stats = viewer.subscribe(keys.VISION_STATS)
    reports = viewer.publisher(VIDEO_ARRIVAL)
    svc = VisionService(vision_node, VisionConfig(width=160, height=120, fps=10.0))

    def is_level(ev: Event) -> bool:
        return (ev.data or {}).get("code") == "video_level"

    try:
        assert frames.wait_count(2, 20.0)
        first: StereoFrame | None = frames.latest
        assert first is not None and first.width == 160
        # a receiver that sees the link's delay (80 ms), then the video queueing behind it
        seq = 0
        deadline = time.monotonic() + 20.0
        while not any(map(is_level, events.seen)) and time.monotonic() < deadline:
            seq += 1
            reports.put(report("console", 80.0, 90.0 if seq <= 2 else 400.0, 10.0, seq))
            wait_until(lambda: any(map(is_level, events.seen)), 0.5)
        ev = events.wait(is_level, 1.0)
        assert ev.source == "vision" and ev.data is not None
        assert ev.data["from"] == 0 and ev.data["level"] == 1 and ev.data["quality"] == 60
        assert "video level 0 → 1" in ev.message and "queues" in ev.message
        assert stats.wait_for(lambda s: (s.data or {}).get("level") == 1, 5.0) is not None
        assert viewer.call("vision", "status", {}, 5.0)["quality"] == 60
    finally:
        svc.close()
