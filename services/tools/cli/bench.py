"""`telerobot bench`: the paper's §3 figures and issue 16's targets measured on the real
services, beside the floor.

Starts the router and the services as separate processes on 127.0.0.1 (client mode, as
deployed), measures force, video, commands, method calls, IK and each service's CPU (idle,
and during 1 kHz teleop with VGA stereo), runs a bare-Zenoh floor (pub/sub and get→reply),
a raw-TCP floor and an XML-RPC baseline in the same run, and prints one table: ours, the
floor's, the baseline's, the paper's, the target, the ratios, and plainly which figures
miss. Writes the JSON (--json) and a force-latency plot (--plot). See docs/bench.md.
"""

from __future__ import annotations

import argparse
import json
import signal
import sys
import threading
import time
from pathlib import Path
from types import FrameType

from services.bus.errors import RpcError, Unavailable


def _exit_on_sigterm(signum: int, frame: FrameType | None) -> None:
    # SIGTERM's default would end the bench without its `finally` blocks and leave the
    # services running; as an exception it stops every child first.
    raise SystemExit(128 + signum)


def main(argv: list[str] | None = None) -> int:
    args_in = sys.argv[1:] if argv is None else argv
    if args_in[:1] == ["passivity"]:  # `telerobot bench passivity …` (docs/passivity.md)
        from services.tools.tdpa.sim_bench import main as passivity_main

        return passivity_main(args_in[1:])
    if args_in[:1] == ["link"]:  # `telerobot bench link …` (docs/bench.md, "The link")
        from services.tools.bench.link import main as link_main

        return link_main(args_in[1:])
    p = argparse.ArgumentParser(
        prog="telerobot bench",
        description=__doc__,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument(
        "--quick",
        action="store_true",
        help="5 s phases and windows, fewer calls (about 2 min on 2 cores)",
    )
    p.add_argument("--phase-s", type=float, default=None, help="length of each phase (s)")
    p.add_argument("--rpc-calls", type=int, default=None, help="calls per method")
    p.add_argument("--ik-n", type=int, default=None, help="poses for the IK throughput")
    p.add_argument(
        "--busy-s",
        type=float,
        default=None,
        help="the busy-host phase: a 100 Hz master beside two nice-19 busy loops this long "
        "(default 60 s, 10 s with --quick; 0: skip it)",
    )
    p.add_argument("--port", type=int, default=0, help="router port on 127.0.0.1 (0: free)")
    p.add_argument(
        "--force-priority",
        default="highest",
        choices=["lowest", "below_normal", "normal", "above_normal", "highest"],
        help="the force sampler's priority (default: highest, as deploy/robot.toml)",
    )
    p.add_argument(
        "--model",
        default="puma560",
        metavar="MODEL",
        help="the arm model: puma560 (default), fr3, ur5e or the path of an arm's TOML",
    )
    p.add_argument(
        "--arm",
        default="sim",
        choices=["sim", "libfranka"],
        help="libfranka: measure the FR3 through libfranka instead (docs/franka.md)",
    )
    p.add_argument(
        "--robot-ip", default="", help="with --arm libfranka: the robot (default: franky-sim)"
    )
    p.add_argument("--json", default="artifacts/bench.json", metavar="FILE")
    p.add_argument(
        "--plot",
        default="artifacts/bench_force_latency.png",
        metavar="FILE",
        help="the force-latency plot ('' for none)",
    )
    p.add_argument("--logs", default="artifacts/bench-logs", metavar="DIR", help="children's logs")
    args = p.parse_args(args_in)

    from services.tools.bench.options import BenchOptions
    from services.tools.bench.plot import force_latency_plot
    from services.tools.bench.report import document, machine, table
    from services.tools.bench.run import run_bench
    from services.tools.cell.procs import ChildFailed

    overrides = {
        k: v
        for k, v in (
            ("phase_s", args.phase_s),
            ("rpc_calls", args.rpc_calls),
            ("ik_n", args.ik_n),
            ("busy_s", args.busy_s),
        )
        if v is not None
    }
    overrides["port"] = args.port
    overrides["force_priority"] = args.force_priority
    overrides["logs_dir"] = Path(args.logs)
    overrides["model"] = args.model
    overrides["arm"] = args.arm
    overrides["robot_ip"] = args.robot_ip
    opts = BenchOptions.quick_options(**overrides) if args.quick else BenchOptions(**overrides)
    if opts.phase_s <= 0 or opts.rpc_calls < 1 or opts.ik_n < 1:
        p.error("--phase-s, --rpc-calls and --ik-n must be positive")
    if not 0.0 <= opts.busy_s <= 3600.0:
        p.error("--busy-s must be within 0 … 3600 s")
    if opts.arm == "libfranka":
        return _franka(opts, Path(args.json))

    main_thread = threading.current_thread() is threading.main_thread()
    previous = signal.signal(signal.SIGTERM, _exit_on_sigterm) if main_thread else None
    t0 = time.monotonic()
    try:
        res = run_bench(
            opts, say=lambda text: print(f"{time.monotonic() - t0:6.1f} s  {text}", flush=True)
        )
    except (ChildFailed, TimeoutError, Unavailable, RpcError) as e:
        print(f"telerobot bench: the run failed: {e}\n(children's logs: {opts.logs_dir})")
        return 1
    finally:
        if main_thread:
            signal.signal(signal.SIGTERM, previous)
    res.settings["wall_s"] = round(time.monotonic() - t0, 1)
    notes = [
        *res.notes,
        "force latency: bench arrival − ForceSample.t_ns (the sensor read), one clock; the "
        "bare-Zenoh floor sends the same bytes from a minimal zenoh-python process through "
        "the same router to the same probe.",
        "ours/floor: one-way latencies against the bare-Zenoh pub/sub floor's same "
        "percentile, master→arm and master→setpoint against the two-hop bare relay's at "
        "the same rate, calls against the get→reply floor; CPU in % of one core.",
    ]
    doc = document(res.phases, machine(), res.settings, notes)
    json_path = Path(args.json)
    json_path.parent.mkdir(parents=True, exist_ok=True)
    json_path.write_text(json.dumps(doc, indent=2) + "\n")
    plot_path = force_latency_plot(res.traces, args.plot) if args.plot else "none"
    print()
    print(table(doc))
    wall_s = doc["settings"]["wall_s"]
    print(f"\nJSON: {json_path}  plot: {plot_path}  logs: {opts.logs_dir}  ({wall_s} s)")
    return 0


def _franka(opts: object, json_path: Path) -> int:
    """`--arm libfranka`: services.tools.bench.franka_phase's run, its table and JSON."""
    from services.tools.bench.franka_phase import run_franka, table
    from services.tools.bench.options import BenchOptions
    from services.tools.cell.procs import ChildFailed

    assert isinstance(opts, BenchOptions)
    t0 = time.monotonic()
    try:
        out = run_franka(
            opts, say=lambda text: print(f"{time.monotonic() - t0:6.1f} s  {text}", flush=True)
        )
    except (ChildFailed, TimeoutError, Unavailable, RpcError, RuntimeError) as e:
        print(f"telerobot bench: the run failed: {e}\n(children's logs: {opts.logs_dir})")
        return 1
    out["settings"]["wall_s"] = round(time.monotonic() - t0, 1)
    json_path.parent.mkdir(parents=True, exist_ok=True)
    json_path.write_text(json.dumps(out, indent=2, default=float) + "\n")
    print()
    print(table(out))
    print(f"\nJSON: {json_path}  logs: {opts.logs_dir}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
