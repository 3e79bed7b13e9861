"""`telerobot report FILE.mcap`: rates, latencies, seq gaps and events of a recording; plots.

Read from the raw channels (the exact payloads), decoded with the contract's codec:

- rate per key: (n − 1) / (last − first receive time);
- publish → record per key: receive time at the recorder − the sender's `t_ns`. Not an
  end-to-end latency (nothing downstream of the bus is in it); across machines it includes
  their clock offset;
- sequence gaps per key and sender (an Event's `source`, a command's `master`): a `seq`
  more than one above the previous is a gap of `seq − prev − 1` missing messages; a `seq`
  not above the previous is counted as out of order (or a restarted sender);
- stalls per periodic stream (every latest-wins key but the commands, which stop while
  nobody is engaged): a wait of more than STALL_PERIODS mean periods between two
  samples. `gaps` counts both, so a stream that stopped for a while is never "0 gaps";
- events: every `robot/events` message;
- tracking: the distance from the arm's tool point (`robot/state` while `ready` or
  `moving`) to the newest supervised target (`robot/arm/target`) at that moment.

`--plots DIR` writes `force.png` (force and moment at the tool point over time; a line
stops where the stream stalled instead of bridging the gap) and `path.png` (the tool path
against the command targets, top and side views, each axis spanning at least
MIN_PATH_SPAN_M so that sensor noise does not look like motion).
"""

from __future__ import annotations

import argparse
import json
import sys
from collections.abc import Callable, Sequence
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any, Protocol, cast

import numpy as np
from numpy.typing import NDArray

from services.bus import codec, keys
from services.bus.errors import ProtocolError
from services.bus.messages import (
    ArmTarget,
    Event,
    ForceSample,
    MasterFeedback,
    MasterState,
    Message,
    OperatorCommand,
    PassivityState,
    RobotState,
    mat3,
)
from services.geometry import tool_target_point
from services.tools.record import plots
from services.tools.record.archive import Recording

#: command streams whose targets are drawn, with their plot labels
COMMAND_KEYS = {keys.ARM_TARGET.key: "supervised target", keys.CMD.key: "operator command"}
#: robot states whose tool pose is the arm's (before calibration it is not)
POSED = ("ready", "moving")
STALL_PERIODS = 10.0
"""A periodic stream is stalled when no sample came for this many of its mean periods."""
MIN_STALL_SAMPLES = 10
"""Fewer samples than this give no period to judge a stall by."""
MIN_PATH_SPAN_M = 0.05
"""The path plot's axes span at least 5 cm: a still arm's µm of noise stay a dot."""
#: streams that pause by design: commands flow only while an operator is engaged, and so do
#: the passivity figures (each side publishes them only while it observes an engagement);
#: the arm's description comes only when it changes
NOT_PERIODIC = frozenset(
    {
        keys.CMD.key,
        keys.ARM_TARGET.key,
        keys.ARM_DESCRIPTION.key,
        keys.PASSIVITY_MASTER.key,
        keys.PASSIVITY_SLAVE.key,
    }
)


def periodic(key: str) -> bool:
    """Whether `key` is a stream expected to flow at a steady rate (stalls are counted)."""
    topic = keys.topic_for(key)
    return topic is not None and topic.latest_wins and key not in NOT_PERIODIC


def stalls(times_ns: Sequence[int], periods: float = STALL_PERIODS) -> tuple[int, float, float]:
    """(number of stalls, longest stall in s, the stream's period in s) of receive times: a
    stall is a wait longer than `periods` periods. The period is the mean one (the span over
    the samples), not the median gap: samples that arrive in bursts (Zenoh batches a few
    1 kHz samples together under load) make the median gap a fraction of the real period,
    and every pause between two bursts a "stall"."""
    if len(times_ns) < MIN_STALL_SAMPLES:
        return 0, 0.0, 0.0
    t = np.asarray(times_ns, dtype=np.int64)
    dt = np.diff(t).astype(np.float64) / 1e9
    period = float(t[-1] - t[0]) / 1e9 / dt.size
    if period <= 0.0:
        return 0, 0.0, period
    long = dt[dt > periods * period]
    return int(long.size), float(long.max()) if long.size else 0.0, period


@dataclass(frozen=True, slots=True)
class Spread:
    """Summary of a set of values (ms or mm)."""

    n: int
    mean: float
    p50: float
    p95: float
    max: float
    min: float

    @staticmethod
    def of(values: Sequence[float]) -> Spread | None:
        if not values:
            return None
        a = np.asarray(values, dtype=float)
        return Spread(
            n=int(a.size),
            mean=float(a.mean()),
            p50=float(np.percentile(a, 50)),
            p95=float(np.percentile(a, 95)),
            max=float(a.max()),
            min=float(a.min()),
        )


@dataclass(frozen=True, slots=True)
class KeyReport:
    """One key's figures: times in s from the start of the recording, latency in ms."""

    key: str
    type: str
    count: int
    rate_hz: float
    first_s: float
    last_s: float
    bytes: int
    rejected: int
    publish_to_record_ms: Spread | None
    """Receive time at the recorder − the sender's t_ns (not an end-to-end latency)."""
    senders: int
    gaps: int
    """seq_gaps + stalls."""
    missing: int
    out_of_order: int
    seq_gaps: int = 0
    stalls: int = 0
    """Waits longer than STALL_PERIODS mean periods (periodic streams only)."""
    max_stall_s: float = 0.0


@dataclass(frozen=True, slots=True)
class EventRow:
    """An event as received: time (s from the start), source, kind, message, data."""

    t_s: float
    source: str
    kind: str
    message: str
    data: dict[str, Any] | None


@dataclass
class Traces:
    """The series the plots draw (times in s from the start; world frame, m; tool frame for
    force, N and N·m)."""

    force_t_s: list[float] = field(default_factory=list)
    force_f: list[tuple[float, ...]] = field(default_factory=list)
    force_c: list[tuple[float, ...]] = field(default_factory=list)
    tool_t_s: list[float] = field(default_factory=list)
    tool_p: list[tuple[float, ...]] = field(default_factory=list)
    targets: dict[str, tuple[list[float], list[tuple[float, ...]]]] = field(default_factory=dict)
    passivity: dict[str, tuple[list[float], list[tuple[float, float, float]]]] = field(
        default_factory=dict
    )
    """side → (times, (e_in, e_out, dissipated_j) in J), from robot/passivity/<side>."""
    passivity_rot: dict[str, tuple[list[float], list[tuple[float, float]]]] = field(
        default_factory=dict
    )
    """side → (times, (rot_e_in, rot_e_out) in J): the side's rotational port, when it runs
    one (docs/passivity.md, "Rotations")."""


@dataclass
class Report:
    """Everything `telerobot report` prints, plus the plot series."""

    files: list[str]
    start_ns: int
    end_ns: int
    messages: int
    keys: list[KeyReport]
    events: list[EventRow]
    truncated: list[str]
    recorder: dict[str, Any] | None
    tracking_mm: Spread | None
    traces: Traces

    @property
    def duration_s(self) -> float:
        return (self.end_ns - self.start_ns) / 1e9 if self.messages else 0.0

    def key(self, key: str) -> KeyReport:
        return next(k for k in self.keys if k.key == key)

    def as_dict(self) -> dict[str, Any]:
        d = {
            "files": self.files,
            "start_ns": self.start_ns,
            "duration_s": round(self.duration_s, 6),
            "messages": self.messages,
            "keys": [asdict(k) for k in self.keys],
            "events": [asdict(e) for e in self.events],
            "truncated": self.truncated,
            "recorder": self.recorder,
            "tracking_mm": asdict(self.tracking_mm) if self.tracking_mm else None,
        }
        out: dict[str, Any] = codec.jsonable(d)
        return out


class _Stamped(Protocol):
    """Every contract message has these (messages.py's base class does not declare them)."""

    seq: int
    t_ns: int


def _sender(msg: Message) -> str:
    if isinstance(msg, Event):
        return msg.source
    if isinstance(msg, OperatorCommand | MasterState | MasterFeedback):
        return msg.master
    if isinstance(msg, PassivityState) and msg.side == "master":
        return msg.master  # each master counts its own; the decision server counts for all
    return ""


@dataclass
class _KeyAcc:
    type: str
    count: int = 0
    first_ns: int = 0
    last_ns: int = 0
    bytes: int = 0
    rejected: int = 0
    latency_ms: list[float] = field(default_factory=list)
    times_ns: list[int] = field(default_factory=list)
    last_seq: dict[str, int] = field(default_factory=dict)
    gaps: int = 0
    missing: int = 0
    out_of_order: int = 0

    def seq(self, sender: str, seq: int) -> None:
        prev = self.last_seq.get(sender)
        self.last_seq[sender] = seq
        if prev is None or seq == prev + 1:
            return
        if seq > prev + 1:
            self.gaps += 1
            self.missing += seq - prev - 1
        else:
            self.out_of_order += 1


@dataclass
class _Engagement:
    engage: int
    p0: NDArray[np.float64]
    R0: NDArray[np.float64]


def analyze(paths: Sequence[str | Path], select: Callable[[str], bool] | None = None) -> Report:
    """Read the recording (all its parts, in order) and compute the report."""
    acc: dict[str, _KeyAcc] = {}
    events: list[EventRow] = []
    traces = Traces()
    truncated: list[str] = []
    recorder: dict[str, Any] | None = None
    start_ns: int | None = None
    end_ns = 0
    total = 0
    tool: tuple[NDArray[np.float64], NDArray[np.float64]] | None = None
    engaged: dict[tuple[str, str], _Engagement] = {}
    target: NDArray[np.float64] | None = None
    tracking: list[float] = []

    for path in paths:
        rec = Recording(Path(path))
        for m in rec.raw(select):
            if start_ns is None:
                start_ns = m.log_time_ns
            end_ns = max(end_ns, m.log_time_ns)
            total += 1
            t_s = (m.log_time_ns - start_ns) / 1e9
            topic = keys.topic_for(m.key)
            a = acc.get(m.key)
            if a is None:
                a = acc[m.key] = _KeyAcc(topic.type.name if topic else "", first_ns=m.log_time_ns)
            a.count += 1
            a.last_ns = m.log_time_ns
            a.times_ns.append(m.log_time_ns)
            a.bytes += len(m.payload)
            if topic is None:
                continue
            try:
                msg = codec.decode(topic.type, m.payload)
            except ProtocolError:
                a.rejected += 1
                continue
            stamped = cast(_Stamped, msg)
            a.latency_ms.append((m.log_time_ns - stamped.t_ns) / 1e6)
            a.seq(_sender(msg), stamped.seq)

            if isinstance(msg, ForceSample):
                traces.force_t_s.append(t_s)
                traces.force_f.append(msg.f)
                traces.force_c.append(msg.c)
            elif isinstance(msg, RobotState):
                if msg.status not in POSED:
                    continue
                tool = (np.asarray(msg.tool_p), mat3(msg.tool_R))
                traces.tool_t_s.append(t_s)
                traces.tool_p.append(msg.tool_p)
                if target is not None:
                    tracking.append(float(np.linalg.norm(tool[0] - target)) * 1e3)
            elif isinstance(msg, PassivityState):
                ts, es = traces.passivity.setdefault(msg.side, ([], []))
                ts.append(t_s)
                es.append((msg.e_in, msg.e_out, msg.dissipated_j))
                if msg.rot_e_in is not None and msg.rot_e_out is not None:
                    rts, res_ = traces.passivity_rot.setdefault(msg.side, ([], []))
                    rts.append(t_s)
                    res_.append((msg.rot_e_in, msg.rot_e_out))
            elif isinstance(msg, Event):
                events.append(EventRow(t_s, msg.source, msg.kind, msg.message, msg.data))
            elif isinstance(msg, ArmTarget) and m.key in COMMAND_KEYS and not msg.hold:
                ts, ps = traces.targets.setdefault(m.key, ([], []))
                ts.append(t_s)
                ps.append(msg.p)
                target = np.asarray(msg.p)
            elif isinstance(msg, OperatorCommand) and m.key in COMMAND_KEYS and msg.active:
                k = (m.key, msg.master)
                eng = engaged.get(k)
                if (eng is None or eng.engage != msg.engage) and tool is not None:
                    eng = engaged[k] = _Engagement(msg.engage, tool[0].copy(), tool[1].copy())
                if eng is None or eng.engage != msg.engage:
                    continue  # no arm pose known yet: the target is unknown
                p = tool_target_point(eng.p0, eng.R0, msg.dp, msg.frame)
                ts, ps = traces.targets.setdefault(m.key, ([], []))
                ts.append(t_s)
                ps.append(tuple(float(x) for x in p))
        if rec.truncated:
            truncated.append(str(path))
        stats = rec.metadata.get("telerobot.stats", {}).get("stats")
        if stats:
            recorder = json.loads(stats)

    start = start_ns or 0
    reports = []
    for key in sorted(acc):
        a = acc[key]
        span_s = (a.last_ns - a.first_ns) / 1e9
        n_stalls, max_stall_s, _ = stalls(a.times_ns) if periodic(key) else (0, 0.0, 0.0)
        reports.append(
            KeyReport(
                key=key,
                type=a.type,
                count=a.count,
                rate_hz=(a.count - 1) / span_s if span_s > 0 else 0.0,
                first_s=(a.first_ns - start) / 1e9,
                last_s=(a.last_ns - start) / 1e9,
                bytes=a.bytes,
                rejected=a.rejected,
                publish_to_record_ms=Spread.of(a.latency_ms),
                senders=len(a.last_seq),
                gaps=a.gaps + n_stalls,
                missing=a.missing,
                out_of_order=a.out_of_order,
                seq_gaps=a.gaps,
                stalls=n_stalls,
                max_stall_s=max_stall_s,
            )
        )
    return Report(
        files=[str(p) for p in paths],
        start_ns=start,
        end_ns=end_ns,
        messages=total,
        keys=reports,
        events=events,
        truncated=truncated,
        recorder=recorder,
        tracking_mm=Spread.of(tracking),
        traces=traces,
    )


# --- plots ---------------------------------------------------------------------------------
AXES = ("x", "y", "z")


def force_plot(report: Report) -> plots.Image:
    """Force (N) and moment (N·m) at the tool point, tool frame, over time."""
    tr = report.traces
    t = np.asarray(tr.force_t_s, dtype=float)
    f = np.asarray(tr.force_f, dtype=float).reshape(-1, 3)
    c = np.asarray(tr.force_c, dtype=float).reshape(-1, 3)
    # A line stops where the stream stalled (as `stalls` counts them) instead of bridging.
    _, _, period_s = stalls((t * 1e9).astype(np.int64).tolist())
    if period_s > 0.0:
        t, cols = plots.break_gaps(t, [*f.T, *c.T], STALL_PERIODS * period_s)
        f, c = np.stack(cols[:3], axis=1), np.stack(cols[3:], axis=1)
    fs = [plots.Series.of(f"f{a}", t, f[:, i]) for i, a in enumerate(AXES)]
    fs.append(plots.Series.of("|f|", t, np.linalg.norm(f, axis=1), plots.BLACK))
    cs = [plots.Series.of(f"c{a}", t, c[:, i]) for i, a in enumerate(AXES)]
    return plots.stack(
        [
            plots.panel(fs, "robot/force: force at the tool point", "time (s)", "force (N)"),
            plots.panel(cs, "robot/force: moment at the tool point", "time (s)", "moment (N*m)"),
        ]
    )


def path_plot(report: Report) -> plots.Image:
    """The tool path (robot/state) against the command targets: top (x–y) and side (x–z)."""
    tr = report.traces
    # Drawn in this order, widest first, so every line stays visible where they overlap.
    lines: list[tuple[str, NDArray[np.float64], plots.BGR, int]] = [
        (
            "arm tool point (robot/state)",
            np.asarray(tr.tool_p, float).reshape(-1, 3),
            plots.BLACK,
            5,
        )
    ]
    for i, (key, label) in enumerate(COMMAND_KEYS.items()):
        if key in tr.targets:
            pts = np.asarray(tr.targets[key][1], dtype=float).reshape(-1, 3)
            lines.append((f"{label} ({key})", pts, plots.PALETTE[1 + i], 3 - 2 * i))
    views = []
    for (i, j), name in (((0, 1), "top view"), ((0, 2), "side view")):
        series = [plots.Series.of(lb, p[:, i], p[:, j], col, w) for lb, p, col, w in lines]
        views.append(
            plots.panel(
                series,
                f"tool path, {name}",
                f"{AXES[i]} (m, world)",
                f"{AXES[j]} (m, world)",
                size=(640, 560),
                equal_aspect=True,
                min_span=(MIN_PATH_SPAN_M, MIN_PATH_SPAN_M),
            )
        )
    return plots.stack(views, horizontal=True)


def passivity_plot(report: Report) -> plots.Image:
    """The passivity figures of each port over time (docs/passivity.md): energy in, out and
    dissipated (J, cumulative within an engagement, so each falls to 0 at a new one), and
    the rotational port's in and out where a side runs one."""
    panels = []
    for side in ("master", "slave"):
        if side not in report.traces.passivity:
            continue
        ts, es = report.traces.passivity[side]
        t = np.asarray(ts, dtype=float)
        e = np.asarray(es, dtype=float).reshape(-1, 3)
        series = [
            plots.Series.of(label, t, e[:, i])
            for i, label in enumerate(("in", "out", "dissipated"))
        ]
        if side in report.traces.passivity_rot:
            rts, res_ = report.traces.passivity_rot[side]
            r = np.asarray(res_, dtype=float).reshape(-1, 2)
            rt = np.asarray(rts, dtype=float)
            series += [
                plots.Series.of(label, rt, r[:, i])
                for i, label in enumerate(("rotation in", "rotation out"))
            ]
        title = f"robot/passivity/{side}: {side} port energies"
        panels.append(plots.panel(series, title, "time (s)", "energy (J)"))
    return plots.stack(panels)


def write_plots(report: Report, folder: str | Path) -> list[Path]:
    """Write `force.png` and `path.png` into `folder`, and `passivity.png` when the
    recording holds passivity figures; their paths."""
    d = Path(folder)
    written = [
        plots.save_png(d / "force.png", force_plot(report)),
        plots.save_png(d / "path.png", path_plot(report)),
    ]
    if report.traces.passivity:
        written.append(plots.save_png(d / "passivity.png", passivity_plot(report)))
    return written


# --- text ----------------------------------------------------------------------------------
def _ms(s: Spread | None, attr: str) -> str:
    return f"{getattr(s, attr):.2f}" if s is not None else "-"


def format_report(report: Report, max_events: int = 50) -> str:
    """The report as text for people."""
    lines = [
        f"recording: {', '.join(report.files)}",
        f"duration {report.duration_s:.3f} s, {report.messages} messages, {len(report.keys)} keys",
    ]
    if report.truncated:
        lines.append(f"cut short (recorder killed?): {', '.join(report.truncated)}")
    if report.recorder is not None:
        r = report.recorder
        arm = ""
        if "arm_model" in r:  # recorders before the arm's description did not say
            model = r["arm_model"]
            arm = f"; arm {model}" if model else "; no arm description (no /robot_model)"
        lines.append(
            f"recorder: {r.get('received', 0)} received, {r.get('dropped', 0)} dropped, "
            f"{r.get('written', 0)} written{arm}"
        )
    lines.append("")
    head = (
        f"{'KEY':<22} {'TYPE':<16} {'COUNT':>7} {'RATE Hz':>9} {'PUB→REC':>9} "
        f"{'p95':>8} {'max ms':>8} {'GAPS':>5} {'SEQ':>4} {'STALL':>5} {'MISSING':>8} "
        f"{'OOO':>4} {'BAD':>4}"
    )
    lines.append(head)
    for k in report.keys:
        lat = k.publish_to_record_ms
        lines.append(
            f"{k.key:<22} {k.type or '?':<16} {k.count:>7} {k.rate_hz:>9.1f} "
            f"{_ms(lat, 'mean'):>9} {_ms(lat, 'p95'):>8} {_ms(lat, 'max'):>8} "
            f"{k.gaps:>5} {k.seq_gaps:>4} {k.stalls:>5} {k.missing:>8} {k.out_of_order:>4} "
            f"{k.rejected:>4}"
        )
    lines += [
        "",
        "PUB→REC: the recorder's receive time − the sender's t_ns (mean, p95, max; ms):",
        "  the bus's share only, not end-to-end latency; across machines it includes clock offset.",
        "GAPS = SEQ (sequence gaps) + STALL (a periodic stream silent for more than",
        f"  {STALL_PERIODS:g} of its mean periods; longest: "
        + (", ".join(f"{k.key} {k.max_stall_s:.3f} s" for k in report.keys if k.stalls) or "none")
        + ").",
    ]
    if report.tracking_mm is not None:
        t = report.tracking_mm
        lines += [
            "",
            f"tracking (tool point → supervised target): mean {t.mean:.1f} mm, "
            f"p95 {t.p95:.1f} mm, max {t.max:.1f} mm",
        ]
    lines += ["", f"events ({len(report.events)}):"]
    for e in report.events[:max_events]:
        lines.append(f"  {e.t_s:9.3f} s  {e.source:<10} {e.kind:<10} {e.message}")
    if len(report.events) > max_events:
        lines.append(f"  … {len(report.events) - max_events} more (--max-events)")
    return "\n".join(lines)


def parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="telerobot report", description=__doc__)
    p.add_argument("files", nargs="+", metavar="FILE.mcap", help="recording (or its parts)")
    p.add_argument(
        "--plots",
        metavar="DIR",
        default=None,
        help="write force.png, path.png (and passivity.png) here",
    )
    p.add_argument("--json", action="store_true", help="print JSON instead of text")
    p.add_argument("--max-events", type=int, default=50, help="events listed in the text")
    return p


def main(argv: list[str] | None = None) -> int:
    args = parser().parse_args(argv)
    for f in args.files:
        if not Path(f).is_file():
            print(f"telerobot report: no such file {f!r}", file=sys.stderr)
            return 2
    report = analyze(args.files)
    written = write_plots(report, args.plots) if args.plots else []
    if args.json:
        out = report.as_dict()
        out["plots"] = [str(p) for p in written]
        print(json.dumps(out))
    else:
        print(format_report(report, args.max_events))
        for p in written:
            print(f"plot: {p}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
