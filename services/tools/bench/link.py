"""`telerobot bench link`: the operator's link per transport on the emulated bad link.

For every condition (transport × round trip, with the loss, jitter and rate cap asked for)
a fresh link (services.tools.tdpa.netem: the kernel's netem or the userspace delay line,
which carries any IP packet: TCP, UDP, QUIC datagrams) joins two network namespaces:

- the robot host: the router (listening on the link with the transport, and on loopback),
  arm (sim, autostart), force (sim, 1 kHz), decision and vision (sim, VGA stereo at 30 fps
  asked for, adapting: adapt.py), each its own `telerobot` process as deployed, plus a probe
  (`python -m services.tools.bench.link probe`) that counts, on loopback, the commands the
  decision forwarded to the arm;
- the operator station: one process (`… link operator`) that is a master streaming
  `robot/cmd` at `--rate-hz` through the decision (engaging again after a hold), reads
  robot/force, robot/state and both eyes, and reports the video it gets on
  `vision/arrival` once a second as the console does.

Measured (all on one clock: namespaces share the host's): the round trip the system itself
shows (a command's `t_ns` → the arm's `robot/state` naming it as `cmd_origin_t_ns` back at
the station), the age of a command when the arm takes it (`cmd_rx_ns − cmd_origin_t_ns`),
the age of a force sample at the master (arrival − `t_ns`), force and command rates at the
far end, and the video's fps, age and level. One table and one JSON document, like the main
bench. The transports: tcp, tls, udp (Zenoh's, reliable), quic (reliable streams) and
quic-mixed (`?mixed_rel=1`: best-effort streams on QUIC datagrams; the QUIC profile).
"""

from __future__ import annotations

import argparse
import json
import math
import os
import subprocess
import sys
import tempfile
import threading
import time
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from services.tools.bench import link_floor
from services.tools.tdpa.transports import TRANSPORTS, endpoint, secure, write_tls_configs

MODULE = "services.tools.bench.link"
ROUND_TRIPS_MS = (0, 50, 200, 700)
LOSS = 0.01
JITTER = 0.1
RATE_MBIT = 2.0
QUEUE_MS = 200.0
"""With a rate cap: the bottleneck's buffer each way (delayline.py `queue_ms`). Without a
bound the line held up to 16 MB, a minute at 2 Mbit/s, of video before the force."""
LEASE_MS = 2000
"""The longest lease the contract allows: a TCP retransmission at 700 ms round trip outlasts
the default 1 s (services.tools.tdpa.link_bench.LEASE_MS)."""
REPO = Path(__file__).resolve().parents[3]
STARTUP_S = 120.0
SERVICES = ("arm", "force", "decision", "vision")
MASTER_ID = "link"
HOLD_KINDS = ("watchdog", "rejected", "estop", "busy")
"""Decision events after which the station engages anew (a hold of its engagement)."""


def station_downsampling(robot_if: str) -> list[dict[str, Any]]:
    """The shipped router's downsampling toward operator stations
    (deploy/router/robot-router.json5, `state-to-stations`), applied here by the link's
    interface instead of its protocol, so every transport's row gets the same."""
    import zenoh

    shipped = zenoh.Config.from_file(str(REPO / "deploy" / "router" / "robot-router.json5"))
    rules: list[dict[str, Any]] = json.loads(shipped.get_json("downsampling"))
    for rule in rules:
        rule.pop("link_protocols", None)
        rule["interfaces"] = [robot_if]
    return rules


def write_router_config(out: Path, tls_file: Path | None, robot_if: str) -> Path:
    """The bench router's Zenoh file: its TLS block (TLS, QUIC) and the stations'
    downsampling on the link's interface."""
    doc: dict[str, Any] = json.loads(tls_file.read_text()) if tls_file is not None else {}
    doc["downsampling"] = station_downsampling(robot_if)
    path = out / "bench-router.json5"
    path.write_text(json.dumps(doc))
    return path


# --- the operator station (in its namespace) ---------------------------------------------


@dataclass
class _Seen:
    """What the station's callbacks record (appended on Zenoh's threads)."""

    force: list[tuple[int, int, int]]  # rx_ns, seq, t_ns
    frames: list[tuple[int, int, int, int, int, int]]  # rx_ns, seq, t_ns, w, h, bytes
    levels: list[tuple[int, int]]  # rx_ns, level (vision/stats)
    events: list[tuple[int, str, str, str]]  # rx_ns, source, kind, code


def operator(
    ep: str, zenoh_config: str, rate_hz: float, duration_s: float, video: bool = True
) -> dict[str, Any]:
    """The station's run; its figures (printed as one JSON line by `main`)."""
    from services.bus import codec, keys
    from services.bus.config import NodeConfig
    from services.bus.errors import ProtocolError
    from services.bus.messages import Event, ForceSample, StereoFrame, VisionStats
    from services.bus.node import Node
    from services.control.vision.adapt import VIDEO_ARRIVAL, ArrivalMeter
    from services.tools.bench.commands import (
        S_ORIGIN,
        S_RX,
        command_figures,
        state_fields,
        step_for,
    )
    from services.tools.bench.probes import CommandDriver, StreamProbe

    cfg = NodeConfig(
        mode="client",
        connect=(ep,),
        lease_ms=LEASE_MS,
        zenoh_config=zenoh_config,
    )
    node = Node("master", cfg, instance=MASTER_ID)
    seen = _Seen([], [], [], [])
    meter = ArrivalMeter(f"bench/{MASTER_ID}")
    lock = threading.Lock()
    try:
        node.announce()
        for name in SERVICES if video else SERVICES[:-1]:
            if not node.alive.wait(name, STARTUP_S):
                raise SystemExit(f"no {name} over the link (alive: {sorted(node.alive.names())})")
        state = node.subscribe(keys.STATE)
        if state.wait_for(lambda s: s.status == "ready", STARTUP_S) is None:
            raise SystemExit("the arm never reported ready over the link")

        def on_force(m: ForceSample) -> None:
            seen.force.append((time.time_ns(), m.seq, m.t_ns))

        def on_left(sample: Any) -> None:
            rx = time.time_ns()
            try:
                f = codec.decode(StereoFrame, sample.payload.to_bytes())
            except ProtocolError:
                return
            seen.frames.append((rx, f.seq, f.t_ns, f.width, f.height, len(f.data)))
            with lock:
                meter.on_pair(f.seq, f.t_ns, rx)

        def on_stats(m: VisionStats) -> None:
            level = (m.data or {}).get("level")
            if isinstance(level, int):
                seen.levels.append((time.time_ns(), level))

        last_hold = [0]

        def on_event(e: Event) -> None:
            rx = time.time_ns()
            code = str((e.data or {}).get("code", ""))
            seen.events.append((rx, e.source, e.kind, code))
            if e.source == "decision" and e.kind in HOLD_KINDS:
                last_hold[0] = rx

        node.subscribe(keys.FORCE, on_force)
        node.subscribe(keys.VISION_STATS, on_stats)
        node.subscribe(keys.EVENTS, on_event)
        handles = [node.subscribe_raw(keys.STEREO_L.key, on_left)]
        handles.append(node.subscribe_raw(keys.STEREO_R.key, lambda s: None))
        reports = node.publisher(VIDEO_ARRIVAL)
        stop = threading.Event()

        def report_loop() -> None:
            while not stop.wait(1.0):
                with lock:
                    r = meter.report()
                if r is not None:
                    reports.put(r)

        reporter = threading.Thread(target=report_loop, name="bench-arrival", daemon=True)
        reporter.start()
        # the video's first pairs come while the renderer's caches fill
        deadline = time.monotonic() + 30.0
        while video and len(seen.frames) < 3 and time.monotonic() < deadline:
            time.sleep(0.05)
        # What a master station reads and no more (a 2 Mbit/s link does not carry
        # robot/arm/target at 500 Hz besides): a hold is told by the decision's event, and
        # the station engages again as an operator would.
        t0 = time.time_ns()
        driver = CommandDriver(node, MASTER_ID)
        states = StreamProbe(node, keys.STATE, state_fields).start()
        step = step_for(rate_hz, duration_s, 1.0)
        run = driver.stream(rate_hz, duration_s, step, held=lambda start: last_hold[0] > start)
        t1 = time.time_ns()
        time.sleep(1.0)  # the states naming the last commands, up to a 700 ms round trip
        st_rec = states.stop()
        stop.set()
        reporter.join(2.0)
        del handles
    finally:
        node.close()
    sent = [t for _, t in run.sent]
    sent_set = set(sent)
    cmd = command_figures(rate_hz, run, step, [], st_rec)
    # The round trip as the system shows it: a command out, the arm's state naming it back.
    rtt = [
        (rx - s[S_ORIGIN]) / 1e6
        for rx, s in st_rec
        if s[S_ORIGIN] in sent_set and s[S_RX] is not None
    ]
    first_rtt: dict[int, float] = {}
    for rx, s in st_rec:
        o = s[S_ORIGIN]
        if o in sent_set and o not in first_rtt:
            first_rtt[o] = (rx - o) / 1e6
    force = [f for f in seen.force if t0 <= f[0] <= t1]
    frames = [f for f in seen.frames if t0 <= f[0] <= t1]
    return {
        "t0_ns": t0,
        "t1_ns": t1,
        "sent_t_ns": sent,
        "commands": {k: v for k, v in cmd.items() if k not in ("hops_ms",)},
        "round_trip_ms": list(first_rtt.values()) or rtt,
        "force": force,
        "frames": frames,
        "levels": seen.levels,
        "events": seen.events[-200:],
    }


# --- the robot host's probe (in its namespace) -----------------------------------------------


def probe(connect: str) -> None:
    """Counts, on the robot host, the station's commands that arrived (robot/cmd, its `t_ns`)
    and those the decision forwarded to the arm (the `origin_t_ns` of its active targets):
    prints `ready`, reads `stop`, prints both lists as one JSON line."""
    from services.bus import keys
    from services.bus.config import NodeConfig
    from services.bus.messages import ArmTarget, OperatorCommand
    from services.bus.node import Node

    origins: set[int] = set()
    arrived: set[int] = set()

    def on_target(t: ArmTarget) -> None:
        if not t.hold:
            origins.add(t.origin_t_ns)

    def on_cmd(c: OperatorCommand) -> None:
        if c.master == MASTER_ID:
            arrived.add(c.t_ns)

    with Node("probe", NodeConfig(mode="client", connect=(connect,), lease_ms=LEASE_MS)) as node:
        node.subscribe(keys.ARM_TARGET, on_target)
        node.subscribe(keys.CMD, on_cmd)
        print("ready", flush=True)
        sys.stdin.readline()
        print(json.dumps({"arrived": sorted(arrived), "forwarded": sorted(origins)}), flush=True)


# --- a link cut (tests/tools/bench/test_link_safety.py) --------------------------------------

CUT_SPEED_M_S = 0.02
"""The station's hand speed during a cut scenario (world +x)."""
CUT_RATE_HZ = 200.0


def cut_operator(ep: str, zenoh_config: str) -> None:
    """The station of a link cut: streams engagement A (+x at CUT_SPEED_M_S) and prints
    `engaged` once the arm follows it (5 mm); keeps streaming A (through the cut the parent
    makes and after it: these are the stale commands) until `new` on stdin; then streams a
    new engagement B from where its hand is until the arm has followed it 10 mm, and prints
    its times as one JSON line."""
    from services.bus import keys
    from services.bus.config import NodeConfig
    from services.bus.messages import IDENTITY_R, OperatorCommand
    from services.bus.node import Node

    cfg = NodeConfig(mode="client", connect=(ep,), lease_ms=LEASE_MS, zenoh_config=zenoh_config)
    with Node("master", cfg, instance=MASTER_ID) as node:
        node.announce()
        for name in SERVICES[:-1]:
            if not node.alive.wait(name, STARTUP_S):
                raise SystemExit(f"no {name} over the link")
        state = node.subscribe(keys.STATE)
        if state.wait_for(lambda s: s.status == "ready", STARTUP_S) is None:
            raise SystemExit("the arm never reported ready over the link")
        pub = node.publisher(keys.CMD)
        go_new = threading.Event()

        def read_stdin() -> None:
            if sys.stdin.readline().strip() == "new":
                go_new.set()

        threading.Thread(target=read_stdin, daemon=True).start()
        seq = time.time_ns() // 1000
        engage = time.time_ns() // 1_000_000
        period = 1.0 / CUT_RATE_HZ

        def x_now() -> float:
            st = state.latest
            return st.tool_p[0] if st is not None else math.nan

        def follow(until: Callable[[float], bool], reengage: Callable[[], bool]) -> None:
            """Stream +x from a new engagement until `until(moved_m)`; with `reengage`, a
            hold before that (the decision's watchdog on a loaded machine) is met with a new
            engagement, as a station does."""
            nonlocal seq, engage
            engage += 1
            t_start, x0 = time.monotonic(), x_now()
            last_x, last_move = x0, time.monotonic()
            while True:
                x = x_now()
                if until(x - x0):
                    return
                if x > last_x + 1e-4:
                    last_x, last_move = x, time.monotonic()
                elif reengage() and time.monotonic() - last_move > 1.0:
                    engage += 1
                    t_start, x0, last_x, last_move = time.monotonic(), x, x, time.monotonic()
                seq += 1
                dx = CUT_SPEED_M_S * (time.monotonic() - t_start)
                pub.put(
                    OperatorCommand(
                        seq=seq, t_ns=time.time_ns(), master=MASTER_ID, engage=engage,
                        active=True, frame="world", dp=(dx, 0.0, 0.0), dR=IDENTITY_R,
                    )
                )  # fmt: skip
                time.sleep(period)

        # A: until the arm follows (5 mm), then on, through the cut and after it, the same
        # engagement, until the parent says `new`
        announced = False

        def a_until(moved: float) -> bool:
            nonlocal announced
            if moved >= 0.005 and not announced:
                announced = True
                print("engaged", flush=True)
            return go_new.is_set()

        # once the arm followed A, never again: what A sends from then on is what the test
        # is about (its hold must last)
        follow(a_until, reengage=lambda: not announced)
        engage_a = engage
        t_new = time.time_ns()
        follow(lambda moved: moved >= 0.01, reengage=lambda: True)
        print(json.dumps({"t_new_ns": t_new, "engage_a": engage_a}), flush=True)


def watch(connect: str) -> None:
    """The robot host's record of a cut: every robot/state and every event, on loopback;
    prints `ready`, reads `stop`, prints them as one JSON line."""
    from services.bus import keys
    from services.bus.config import NodeConfig
    from services.bus.messages import Event, RobotState
    from services.bus.node import Node

    states: list[tuple[int, list[float], str]] = []
    events: list[tuple[int, str, str, str]] = []

    def on_state(m: RobotState) -> None:
        states.append((m.t_ns, list(m.tool_p), m.status))

    def on_event(e: Event) -> None:
        events.append((e.t_ns, e.source, e.kind, e.message[:200]))

    with Node("watch", NodeConfig(mode="client", connect=(connect,), lease_ms=LEASE_MS)) as node:
        node.subscribe(keys.STATE, on_state)
        node.subscribe(keys.EVENTS, on_event)
        print("ready", flush=True)
        sys.stdin.readline()
        print(json.dumps({"states": states, "events": events}), flush=True)


def run_cut(transport: str, cut_s: float, logs: Path, after_s: float = 1.0) -> dict[str, Any]:
    """A link cut on a fresh link (0 ms round trip, no loss: the cut is the fault): the
    station streams, the link goes down for `cut_s` (the delay line stopped: nothing passes)
    and comes back, the station keeps streaming its engagement for `after_s`, then engages
    anew. Returns the robot host's record and the times (one clock)."""
    from services.tools.cell.ports import free_port
    from services.tools.tdpa.netem import ROBOT_IP, LinkShape, in_ns, netem_link, shape

    cond = Condition(transport, 0.0, loss=0.0, jitter=0.0, video=False)
    ep = endpoint(transport, ROBOT_IP, free_port())
    how = LinkShape(0.0)
    with tempfile.TemporaryDirectory(prefix="bench-cut-") as tmp:
        router_cfg = client_cfg = None
        if secure(transport):
            router_cfg, client_cfg = write_tls_configs(Path(tmp), ROBOT_IP)
        with netem_link(how, emulator="delayline") as link_:
            assert link_.delayline is not None
            with _robot_side(link_, cond, ep, router_cfg, logs, lambda _: None, "watch") as rec:
                argv = [sys.executable, "-m", MODULE, "cut-operator", ep, str(client_cfg or "")]
                with subprocess.Popen(
                    in_ns(link_.operator, *argv),
                    stdin=subprocess.PIPE,
                    stdout=subprocess.PIPE,
                    stderr=subprocess.PIPE,
                    text=True,
                ) as op:
                    assert op.stdin is not None and op.stdout is not None
                    assert op.stderr is not None
                    line = op.stdout.readline().strip()
                    if line != "engaged":
                        raise RuntimeError(f"the station did not engage: {op.stderr.read()[-800:]}")
                    t_cut = time.time_ns()
                    link_.delayline.stop()
                    time.sleep(cut_s)
                    shape(link_, how)
                    t_back = time.time_ns()
                    time.sleep(after_s)
                    op.stdin.write("new\n")
                    op.stdin.flush()
                    out, err = op.communicate(timeout=60)
                    if op.returncode != 0:
                        raise RuntimeError(f"the station failed: {err[-800:]}")
                times = json.loads(out.strip().splitlines()[-1])
                time.sleep(1.0)  # the last states of B
                got, err = rec.communicate("stop\n", timeout=30)
                if rec.returncode != 0:
                    raise RuntimeError(f"the watcher failed: {err[-800:]}")
    doc = json.loads(got.strip().splitlines()[-1])
    return {**doc, "t_cut_ns": t_cut, "t_back_ns": t_back, **times}


# --- one condition ---------------------------------------------------------------------------


@dataclass(frozen=True, slots=True)
class Condition:
    transport: str
    rtt_ms: float
    rate_mbit: float = 0.0
    loss: float = LOSS
    jitter: float = JITTER
    video: bool = True
    queue_ms: float = QUEUE_MS

    @property
    def key(self) -> str:
        cap = f"_{self.rate_mbit:g}mbit" if self.rate_mbit > 0 else ""
        novideo = "" if self.video else "_novideo"
        return f"{self.transport}_{self.rtt_ms:g}ms{cap}{novideo}"


def _summary(values: list[float]) -> dict[str, float | int | None]:
    from services.tools.bench.stats import summarize

    return summarize(values).as_dict()


def figures(cond: Condition, op: dict[str, Any], robot: dict[str, list[int]]) -> dict[str, Any]:
    """A condition's figures from the station's record and the robot host's counts (pure)."""
    t0, t1 = op["t0_ns"], op["t1_ns"]
    dur_s = max((t1 - t0) / 1e9, 1e-9)
    sent = op["sent_t_ns"]
    arrived = set(robot["arrived"]) & set(sent)
    got = set(robot["forwarded"]) & set(sent)
    one_way = cond.rtt_ms / 2.0
    rtt = _summary(op["round_trip_ms"])
    cmd_age = op["commands"].get("arm_ms", {})
    force = op["force"]
    ages = [(rx - t) / 1e6 for rx, _, t in force]
    seqs = sorted({s for _, s, _ in force})
    span = seqs[-1] - seqs[0] + 1 if seqs else 0
    frames = op["frames"]
    vid_ages = [(rx - t) / 1e6 for rx, _, t, *_ in frames]
    levels = [lv for _, lv in op["levels"]]
    last = frames[-1] if frames else None
    holds = sum(1 for _, src, kind, _ in op["events"] if src == "decision" and kind == "watchdog")
    changes = sum(1 for *_, code in op["events"] if code == "video_level")

    def ratio(x: Any) -> float | None:
        return None if x is None or cond.rtt_ms <= 0 or not math.isfinite(x) else x / cond.rtt_ms

    return {
        "transport": cond.transport,
        "rtt_ms": cond.rtt_ms,
        "loss": cond.loss,
        "jitter": cond.jitter,
        "rate_mbit": cond.rate_mbit,
        "duration_s": dur_s,
        "round_trip_ms": rtt,
        "round_trip_p50_ratio": ratio(rtt["p50"]),
        "round_trip_p99_ratio": ratio(rtt["p99"]),
        "cmd_age_ms": cmd_age,
        "cmd_age_p99_over_one_way_ms": (
            None if cmd_age.get("p99") is None else cmd_age["p99"] - one_way
        ),
        "cmds_sent": len(sent),
        "cmds_arrived": len(arrived),
        "cmds_arrived_pct": 100.0 * len(arrived) / len(sent) if sent else None,
        "cmds_reached": len(got),
        "cmds_reached_pct": 100.0 * len(got) / len(sent) if sent else None,
        "force_rate_hz": len(seqs) / dur_s,
        "force_lost_pct": 100.0 * (1 - len(seqs) / span) if span else None,
        "force_age_ms": _summary(ages),
        "video_fps": len({f[1] for f in frames}) / dur_s,
        "video_age_ms": _summary(vid_ages),
        "video_size": f"{last[3]}x{last[4]}" if last else None,
        "video_kb_per_frame": (float(np.mean([f[5] for f in frames])) / 1e3 if frames else None),
        "video_level_final": levels[-1] if levels else None,
        "video_level_max": max(levels) if levels else None,
        "video_level_changes": changes,
        "watchdog_holds": holds,
        "commands_engagements": op["commands"].get("engagements"),
    }


@contextmanager
def _robot_side(
    link: Any,
    cond: Condition,
    ep: str,
    router_cfg: Path | None,
    logs: Path,
    say: Callable[[str], None],
    role: str = "probe",
) -> Iterator[subprocess.Popen[str]]:
    """The robot host's processes in its namespace, and a recorder (`role`: probe | watch)
    on its loopback, yielded once it said `ready`."""
    from services.tools.cell.ports import free_port
    from services.tools.cell.procs import Children, telerobot_argv, wait_log
    from services.tools.tdpa.netem import in_ns

    local = f"tcp/127.0.0.1:{free_port()}"
    lease = ["--lease-ms", str(LEASE_MS)]
    zargs = ["--mode", "client", "--connect", local, *lease]
    with Children(logs) as kids:
        router_args = ["--listen", ep, "--listen", local, *lease]
        if router_cfg is not None:
            router_args += ["--zenoh-config", str(router_cfg)]
        router = kids.spawn("router", in_ns(link.robot, *telerobot_argv("router", *router_args)))
        wait_log(router, "router up", STARTUP_S)
        for name, args in (
            ("arm", ["--autostart"]),
            ("force", ["--priority", "normal"]),
            ("decision", []),
            ("vision", ["--size", "640x480", "--fps", "30"]),
        ):
            if name == "vision" and not cond.video:
                continue
            kids.spawn(name, in_ns(link.robot, *telerobot_argv(name, *args, *zargs)))
        say(f"  robot host up on {ep} (router, arm, force, decision, vision)")
        with subprocess.Popen(
            in_ns(link.robot, sys.executable, "-m", MODULE, role, local),
            stdin=subprocess.PIPE,
            stdout=subprocess.PIPE,
            stderr=subprocess.PIPE,
            text=True,
        ) as counter:
            try:
                assert counter.stdout is not None and counter.stderr is not None
                if counter.stdout.readline().strip() != "ready":
                    raise RuntimeError(f"the probe did not start: {counter.stderr.read()[-800:]}")
                yield counter
            finally:
                if counter.poll() is None:
                    counter.kill()
        kids.check()


def run_condition(
    cond: Condition,
    duration_s: float,
    rate_hz: float,
    logs: Path,
    say: Callable = print,
    floor_s: float = link_floor.FLOOR_S,
) -> dict[str, Any]:
    """One condition over a fresh link: its figures, and first (`floor`) bare Zenoh's over the
    same link for `floor_s` (0: none; link_floor.py). Raises RuntimeError when a side fails."""
    from services.tools.cell.ports import free_port
    from services.tools.tdpa.netem import ROBOT_IP, LinkShape, in_ns, netem_link

    shape = LinkShape(cond.rtt_ms, cond.jitter, cond.loss, cond.rate_mbit, queue_ms=cond.queue_ms)
    ep = endpoint(cond.transport, ROBOT_IP, free_port())
    with tempfile.TemporaryDirectory(prefix="bench-link-") as tmp:
        router_cfg = client_cfg = None
        if secure(cond.transport):
            router_cfg, client_cfg = write_tls_configs(Path(tmp), ROBOT_IP)
        bare = None
        if floor_s > 0:
            # A link of its own, shaped the same: over the delay line a second UDP session
            # between the same namespaces got nothing downstream (seen 2026-12-02).
            with netem_link(shape) as flink:
                files = str(write_router_config(Path(tmp), router_cfg, flink.robot_if))
                bare = link_floor.run(flink, ep, files, str(client_cfg or ""), floor_s)
        with netem_link(shape) as link:
            cond_logs = logs / cond.key
            router_cfg = write_router_config(Path(tmp), router_cfg, link.robot_if)
            with _robot_side(link, cond, ep, router_cfg, cond_logs, say) as counter:
                argv = [sys.executable, "-m", MODULE, "operator", ep, str(client_cfg or "")]
                argv += [str(rate_hz), str(duration_s), "1" if cond.video else "0"]
                op = subprocess.run(
                    in_ns(link.operator, *argv),
                    capture_output=True,
                    text=True,
                    timeout=STARTUP_S * 2 + duration_s + 60,
                    check=False,
                )
                reached_out, err = counter.communicate("stop\n", timeout=30)
            emulator = link.emulator
            line = link.delayline
        counts = line.runs[-1] if line is not None and line.runs else None
    if op.returncode != 0:
        raise RuntimeError(f"the operator side failed: {op.stderr.strip()[-1500:]}")
    if counter.returncode != 0:
        raise RuntimeError(f"the robot probe failed: {err.strip()[-800:]}")
    doc = json.loads(op.stdout.strip().splitlines()[-1])
    fig = figures(cond, doc, json.loads(reached_out.strip().splitlines()[-1]))
    fig["floor"] = bare
    fig["emulator"] = emulator
    fig["emulator_counts"] = counts
    fig["load1"] = round(os.getloadavg()[0], 2)
    return fig


# --- the sweep, the table, the document --------------------------------------------------------


def conditions(
    transports: tuple[str, ...],
    rtts: tuple[float, ...],
    rate_mbit: float,
    loss: float,
    jitter: float,
    video: bool = True,
    queue_ms: float = QUEUE_MS,
) -> list[Condition]:
    return [
        Condition(t, float(r), rate_mbit, loss, jitter, video, queue_ms)
        for t in transports
        for r in rtts
    ]


def _num(x: Any, fmt: str = "{:.0f}") -> str:
    return "–" if x is None or (isinstance(x, float) and not math.isfinite(x)) else fmt.format(x)


def _floor_cells(floor: dict[str, Any] | None) -> str:
    """The bare-Zenoh floor's force-sized stream toward the station: delivered %, age."""
    if not floor or "error" in floor:
        return f"{'–':>9} {'–':>11} {'–':>11}"
    d = floor["down"]
    return (
        f"{_num(d['delivered_pct'], '{:.1f}'):>9} {_num(d['age_p50_ms'], '{:.1f}'):>11} "
        f"{_num(d['age_p99_ms'], '{:.1f}'):>11}"
    )


def table(rows: dict[str, dict[str, Any]]) -> str:
    """One line per condition: what the issue's targets are about."""
    head = (
        f"{'condition':<24} {'rt p50':>7} {'rt p99':>7} {'×p50':>5} {'×p99':>5} "
        f"{'cmd age p99':>11} {'cmds %':>7} {'force Hz':>8} {'force age p99':>13} "
        f"{'video fps':>9} {'video age p50':>13} {'level':>5} {'size':>8} {'holds':>5} "
        f"{'floor ↓ %':>9} {'floor ↓ p50':>11} {'floor ↓ p99':>11}"
    )
    lines = [head, "-" * len(head)]
    for key, f in rows.items():
        if "error" in f:
            lines.append(f"{key:<24} failed: {str(f['error'])[:90]}")
            continue
        rt, age, fa, va = f["round_trip_ms"], f["cmd_age_ms"], f["force_age_ms"], f["video_age_ms"]
        lines.append(
            f"{key:<24} {_num(rt.get('p50')):>7} {_num(rt.get('p99')):>7} "
            f"{_num(f['round_trip_p50_ratio'], '{:.2f}'):>5} "
            f"{_num(f['round_trip_p99_ratio'], '{:.2f}'):>5} "
            f"{_num(age.get('p99'), '{:.1f}'):>11} {_num(f['cmds_arrived_pct'], '{:.1f}'):>7} "
            f"{_num(f['force_rate_hz']):>8} {_num(fa.get('p99'), '{:.1f}'):>13} "
            f"{_num(f['video_fps'], '{:.1f}'):>9} {_num(va.get('p50')):>13} "
            f"{_num(f['video_level_final']):>5} {f['video_size'] or '–':>8} "
            f"{f['watchdog_holds']:>5} {_floor_cells(f.get('floor'))}"
        )
    return "\n".join(lines)


NOTES = (
    "rt: the round trip the system shows — an operator command's t_ns to the first robot/state "
    "naming it (cmd_origin_t_ns) back at the station; ×: over the link's own round trip.",
    "cmd age: robot/state cmd_rx_ns − cmd_origin_t_ns (the arm's receipt of the decision's "
    "target carrying the command), over the commands robot/state showed.",
    "cmds %: the station's commands that arrived on the robot host (robot/cmd); JSON "
    "cmds_reached_pct: those the decision forwarded to the arm (latest-wins: a command "
    "superseded within one decision tick is not forwarded); force Hz / age: robot/force at "
    "the station (arrival − t_ns, one clock).",
    "video: distinct pairs/s at the station, age = arrival − capture t_ns, level = the vision "
    "service's adaptation level at the end (0: as configured; adapt.py), size the last pair's.",
    "holds: the decision's watchdog events (no fresh command for its watchdog_ms).",
    "floor ↓: bare Zenoh over the same link first (link_floor.py): a 150 B sample at 1 kHz "
    "with robot/force's QoS from the robot side, its share delivered and age at the station "
    "(one way); JSON floor.up: 500 Hz the other way. The transport's own limit on that link.",
)


def main(argv: list[str] | None = None) -> int:
    args_in = sys.argv[1:] if argv is None else argv
    if args_in[:1] == ["operator"]:
        _, ep, cfg, rate, dur, video = args_in
        print(json.dumps(operator(ep, cfg, float(rate), float(dur), video == "1")), flush=True)
        return 0
    if args_in[:1] == ["probe"]:
        probe(args_in[1])
        return 0
    if args_in[:1] == ["watch"]:
        watch(args_in[1])
        return 0
    if args_in[:1] == ["cut-operator"]:
        cut_operator(args_in[1], args_in[2])
        return 0
    p = argparse.ArgumentParser(
        prog="telerobot bench link",
        description=__doc__,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument("--transports", default=",".join(TRANSPORTS), help="comma-separated")
    p.add_argument(
        "--rtt-ms", default=",".join(str(r) for r in ROUND_TRIPS_MS), help="round trips (ms)"
    )
    p.add_argument("--loss", type=float, default=LOSS, help="per packet, each way (default 0.01)")
    p.add_argument("--jitter", type=float, default=JITTER, help="fraction of the one-way delay")
    p.add_argument(
        "--rate-mbit",
        type=float,
        default=0.0,
        help=f"a cap each way (0: none; {RATE_MBIT:g} is the issue's thin link)",
    )
    p.add_argument(
        "--queue-ms",
        type=float,
        default=QUEUE_MS,
        help=f"with --rate-mbit: the bottleneck's buffer each way (default {QUEUE_MS:g} ms)",
    )
    p.add_argument(
        "--duration-s",
        type=float,
        default=15.0,
        help="commands streamed per condition (s; default 15: the 20 conditions in ~10 min "
        "plus start-up)",
    )
    p.add_argument("--rate-hz", type=float, default=500.0, help="the station's command rate")
    p.add_argument(
        "--no-video", action="store_true", help="no vision service: force and commands alone"
    )
    p.add_argument(
        "--floor-s",
        type=float,
        default=link_floor.FLOOR_S,
        help="bare Zenoh over the same link before each condition, for this long (0: none)",
    )
    p.add_argument("--json", default="artifacts/bench_link.json", metavar="FILE")
    p.add_argument("--logs", default="artifacts/bench-link-logs", metavar="DIR")
    args = p.parse_args(args_in)
    transports = tuple(t.strip() for t in args.transports.split(",") if t.strip())
    bad = [t for t in transports if t not in TRANSPORTS]
    if bad or not transports:
        p.error(f"--transports: {bad or 'none'} not in {', '.join(TRANSPORTS)}")
    try:
        rtts = tuple(float(r) for r in args.rtt_ms.split(",") if r.strip())
    except ValueError:
        p.error("--rtt-ms takes numbers, e.g. 0,50,200,700")
    if not rtts or any(not 0 <= r <= 10_000 for r in rtts):
        p.error("--rtt-ms: each within 0 … 10000")
    if not 0 <= args.loss < 1 or not 0 <= args.jitter <= 1 or args.rate_mbit < 0:
        p.error("--loss in [0, 1), --jitter in [0, 1], --rate-mbit ≥ 0")
    if not 0 <= args.queue_ms <= 10_000:
        p.error("--queue-ms in 0 … 10000")
    if not 1.0 <= args.duration_s <= 3600 or not 1.0 <= args.rate_hz <= 2000:
        p.error("--duration-s in 1 … 3600, --rate-hz in 1 … 2000")
    if not 0 <= args.floor_s <= 600:
        p.error("--floor-s in 0 … 600")
    from services.tools.tdpa.netem import unavailable

    why = unavailable()
    if why is not None:
        print(f"telerobot bench link: no emulated link here: {why}")
        return 1
    t0 = time.monotonic()
    rows: dict[str, dict[str, Any]] = {}
    conds = conditions(
        transports, rtts, args.rate_mbit, args.loss, args.jitter, not args.no_video, args.queue_ms
    )
    for i, cond in enumerate(conds, 1):
        print(f"{time.monotonic() - t0:6.1f} s  [{i}/{len(conds)}] {cond.key} …", flush=True)
        try:
            rows[cond.key] = run_condition(
                cond, args.duration_s, args.rate_hz, Path(args.logs), floor_s=args.floor_s
            )
        except (RuntimeError, subprocess.TimeoutExpired, TimeoutError) as e:
            rows[cond.key] = {"error": str(e)[-2000:]}
            print(f"    failed: {str(e)[-300:]}", flush=True)
    print(table(rows))
    for n in NOTES:
        print(f"  {n}")
    doc = {
        "settings": {
            "transports": list(transports),
            "rtt_ms": list(rtts),
            "loss": args.loss,
            "jitter": args.jitter,
            "rate_mbit": args.rate_mbit,
            "queue_ms": args.queue_ms if args.rate_mbit > 0 else None,
            "duration_s": args.duration_s,
            "rate_hz": args.rate_hz,
            "floor_s": args.floor_s,
            "video_asked": "640x480 stereo @ 30 fps, JPEG 80, adapting",
            "wall_s": round(time.monotonic() - t0, 1),
        },
        "conditions": rows,
        "notes": list(NOTES),
    }
    out = Path(args.json)
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps(doc, indent=1, default=float))
    print(f"wrote {out}")
    return 0 if all("error" not in r for r in rows.values()) else 1


if __name__ == "__main__":
    sys.exit(main())
