"""The video phases: force + stereo at one size and rate, with the video's figures (fps
per eye, capture→decoded latency, pair skew, bit rate) and the force in flight."""

from __future__ import annotations

import time
from collections.abc import Sequence
from typing import Any

from services.bus.keys import VISION_STATS
from services.bus.messages import VisionStats
from services.bus.node import Node
from services.tools.bench import stats
from services.tools.bench.force_phases import (
    force_counters,
    force_figures,
    force_line,
    force_probe,
    measure_window,
)
from services.tools.bench.options import BenchOptions, RunResult, Say
from services.tools.bench.probes import FrameRecord, StreamProbe, VideoProbe
from services.tools.bench.report import ms_text
from services.tools.cell.procs import Children, telerobot_argv, wait_alive

VIDEO_WARMUP_S = 1.0

# --- video --------------------------------------------------------------------------------


def phase_video(
    kids: Children,
    node: Node,
    zargs: list[str],
    key: str,
    size: tuple[int, int],
    fps: float,
    opts: BenchOptions,
    res: RunResult,
    say: Say,
) -> None:
    w, h = size
    say(f"[video_{key}] starting vision at {w}x{h} @ {fps:g} fps …")
    kids.spawn(
        "vision", telerobot_argv("vision", "--size", f"{w}x{h}", "--fps", f"{fps:g}", *zargs)
    )
    try:
        wait_alive(kids, node.alive.wait, "vision", opts.startup_timeout_s)
        video = VideoProbe(node).start()
        vstats = StreamProbe(node, VISION_STATS, lambda m: (m,)).start()
        if not video.wait_frames(3, opts.startup_timeout_s):
            kids.check("vision")
            raise TimeoutError(f"no stereo frames at {w}x{h} within {opts.startup_timeout_s} s")
        # The renderer's first frames come while its caches fill: not what an operator sees.
        time.sleep(VIDEO_WARMUP_S)
        say(f"[force_stereo_{key}] force + stereo {w}x{h}@{fps:g} for {opts.phase_s:g} s …")
        probe = force_probe(node)
        before = force_counters(node)
        t0, t1 = measure_window(lambda: probe.wait_count(1, 10.0), opts.phase_s)
        after = force_counters(node)
        force_rec = probe.stop()
        frames = video.stop()
        newest_stats = vstats.stop()
        last_stats: VisionStats | None = newest_stats[-1][1][0] if newest_stats else None
    finally:
        kids.stop("vision")
    frames = [f for f in frames if t0 <= f.rx_ns <= t1]
    vfig, windows = video_figures(frames, t0, t1, w, h, fps)
    vfig["decode_errors"] = video.decode_errors
    if last_stats is not None:
        vfig["vision_stats"] = {
            "fps": last_stats.fps,
            "encode_ms": last_stats.encode_ms,
            "dropped": last_stats.dropped,
            "capture_skew_ms": last_stats.skew_ms,
        }
    ffig, trace = force_figures(force_rec, t0, t1)
    ffig["service"] = stats.counters_delta(before, after)
    inflight = stats.rate_in_windows([r[0] for r in force_rec if t0 <= r[0] <= t1], windows)
    ffig["in_flight"] = {
        "count": inflight.count,
        "covered_s": inflight.covered_s,
        "rate_hz": inflight.rate_hz if inflight.covered_s > 0 else None,
    }
    if inflight.covered_s <= 0:
        ffig["na"] = {"in_flight": "no stereo pair was complete inside the window"}
    res.phases[f"video_{key}"] = vfig
    res.phases[f"force_stereo_{key}"] = ffig
    res.traces[f"with stereo {w}x{h}@{fps:g}"] = trace
    say(force_line(ffig) + f"; {inflight.rate_hz:.0f} Hz while a pair is in flight")
    lat = vfig["latency_ms"]
    say(
        f"    video {vfig['fps_l']:.1f}/{vfig['fps_r']:.1f} fps (l/r), capture→decoded p50 "
        f"{ms_text(lat['p50'])} p99 {ms_text(lat['p99'])}, {vfig['mbit_s']:.1f} Mbit/s"
    )


def video_figures(
    frames: Sequence[FrameRecord], t0: int, t1: int, w: int, h: int, fps: float
) -> tuple[dict[str, Any], list[tuple[int, int]]]:
    """The video phase's figures from the decoded frames (already cut to the window
    [t0, t1]): fps per eye, capture→decoded latency, arrival skew, missing pairs, bit rate;
    and each complete pair's in-flight window (capture t_ns, arrival of its later eye)."""
    duration_s = (t1 - t0) / stats.NS_PER_S
    eyes = {e: [f for f in frames if f.eye == e] for e in ("l", "r")}
    # From the delivered frames' own capture stamps: (n − 1) periods over their span, free of
    # where the window happened to cut the frame train.
    fps_l = stats.rate_from_times([f.t_ns for f in eyes["l"]])
    fps_r = stats.rate_from_times([f.t_ns for f in eyes["r"]])
    lat = [(f.decoded_ns - f.t_ns) / stats.NS_PER_MS for f in frames]
    left = {f.seq: f.rx_ns for f in eyes["l"]}
    right = {f.seq: f.rx_ns for f in eyes["r"]}
    both = sorted(set(left) & set(right))
    t_of = {f.seq: f.t_ns for f in frames}
    windows = [(t_of[s], max(left[s], right[s])) for s in both]
    pair_loss = stats.seq_loss(sorted(set(left) | set(right)))
    fig = {
        "width": w,
        "height": h,
        "fps_target": fps,
        "duration_s": duration_s,
        "frames_l": len(eyes["l"]),
        "frames_r": len(eyes["r"]),
        "fps_l": fps_l,
        "fps_r": fps_r,
        "fps_min": min(fps_l, fps_r),
        "pairs_complete": len(both),
        "pairs_missing": pair_loss.lost,
        "latency_ms": stats.summarize(lat).as_dict(),
        "arrival_skew_ms": stats.summarize(stats.pair_skew_ms(left, right)).as_dict(),
        "bytes_per_pair": (sum(f.nbytes for f in frames) / len(both)) if both else None,
        "mbit_s": sum(f.nbytes for f in frames) * 8 / 1e6 / duration_s if duration_s else 0.0,
    }
    return fig, windows
