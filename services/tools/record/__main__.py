"""`telerobot record -o FILE.mcap`: record every stream of the namespace to MCAP.

Open the file in Foxglove for plots and video; replay it with `telerobot replay`, summarize
it with `telerobot report`. Ctrl-C or SIGTERM finishes the file. See docs/record.md.
"""

from __future__ import annotations

import argparse
import json
import sys
import time

from services.bus.lifecycle import ServiceContext, run_service, service_parser
from services.tools.record.recorder import Recorder, RecorderConfig, RecorderStats

PROGRESS_S = 3.0
POLL_S = 0.1


def arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("-o", "--output", required=True, metavar="FILE.mcap", help="output file")
    p.add_argument(
        "--keys",
        action="append",
        default=[],
        metavar="KEYEXPR",
        help="record only keys in this Zenoh key expression, e.g. 'robot/**' (repeatable; "
        "default: everything, '**')",
    )
    p.add_argument("--no-video", action="store_true", help="leave out vision/stereo/*")
    p.add_argument(
        "--ros",
        action="store_true",
        help="also record the ROS 2 view's copies of the streams (left out by default)",
    )
    p.add_argument(
        "--no-3d",
        action="store_true",
        help="leave out /tf, /robot_model, /robot_description, /workcell (what a 3D viewer "
        "draws of the arm and the workcell)",
    )
    p.add_argument(
        "--max-size-mb", type=float, default=0.0, help="end (or split) at this size (0: none)"
    )
    p.add_argument(
        "--max-duration-s", type=float, default=0.0, help="end (or split) after this (0: none)"
    )
    p.add_argument(
        "--split",
        action="store_true",
        help="at a limit start the next part (FILE_000.mcap, FILE_001.mcap, …) instead of ending",
    )
    p.add_argument("--chunk-size-kb", type=int, default=1024, help="chunk size (uncompressed)")
    p.add_argument(
        "--chunk-interval-s",
        type=float,
        default=1.0,
        help="close a chunk at least this often: at most this much is lost if killed",
    )
    p.add_argument("--compression", choices=["zstd", "lz4", "none"], default="zstd")
    p.add_argument("--queue-len", type=int, default=50_000, help="inbox bound (samples)")
    p.add_argument(
        "--progress-s",
        type=float,
        default=PROGRESS_S,
        metavar="S",
        help=f"log the samples per topic every S seconds ({PROGRESS_S:g}; 0: never)",
    )


def parser() -> argparse.ArgumentParser:
    return service_parser("record", __doc__, arguments)


def progress(st: RecorderStats, elapsed_s: float) -> str:
    """One progress line: samples received per topic, written, dropped, the arm, the file."""
    per_key = ", ".join(f"{k} {v.received}" for k, v in sorted(st.keys.items())) or "no sample"
    where = st.files[-1] if st.files else "-"
    arm = f"arm {st.arm_model}" if st.arm_model else "no arm description"
    return (
        f"{elapsed_s:.0f} s: {per_key}; {st.written} written, {st.dropped} dropped, {arm} → {where}"
    )


def start(ctx: ServiceContext) -> int:
    """Record until SIGINT/SIGTERM or a limit; print the summary as one JSON line."""
    args = ctx.args
    config = RecorderConfig(
        output=args.output,
        keys=tuple(args.keys),
        video=not args.no_video,
        ros=args.ros,
        view3d=not args.no_3d,
        max_size_mb=args.max_size_mb,
        max_duration_s=args.max_duration_s,
        split=args.split,
        queue_len=args.queue_len,
        chunk_size_kb=args.chunk_size_kb,
        chunk_interval_s=args.chunk_interval_s,
        compression=args.compression,
    )
    recorder = Recorder(ctx.open(), config)
    start_s = time.monotonic()
    every = args.progress_s if args.progress_s > 0 else float("inf")
    next_status = start_s + every
    try:
        while not ctx.stop.is_set() and not recorder.ended.wait(POLL_S):
            if time.monotonic() >= next_status:
                next_status += every
                ctx.log.info("%s", progress(recorder.stats(), time.monotonic() - start_s))
    finally:
        final = recorder.stop()
    summary = final.as_dict()
    ctx.log.info(
        "recorded %d messages (%d dropped) in %s; %s",
        summary["written"],
        summary["dropped"],
        ", ".join(summary["files"]),
        f"arm {final.arm_model}" if final.arm_model else "no arm description: no /robot_model",
    )
    print(
        json.dumps({k: summary[k] for k in ("written", "dropped", "files", "error", "arm_model")})
    )
    return 1 if final.error else 0


def main(argv: list[str] | None = None) -> int:
    return run_service("record", argv, start, description=__doc__, add_arguments=arguments)


if __name__ == "__main__":
    sys.exit(main())
