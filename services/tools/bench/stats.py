"""The bench's statistics, free of I/O: percentiles, seq loss, rates, command matching.

Times are integers in nanoseconds from `time.time_ns()` (the contract's `t_ns`); every
process of a run shares the machine's clock, so `receive − t_ns` is a one-way latency.
Latencies come out in milliseconds. Nothing here measures: it only reduces what the probes
recorded, so each function is tested on hand-worked inputs.
"""

from __future__ import annotations

import math
from collections.abc import Collection, Iterable, Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np

NS_PER_MS = 1_000_000
NS_PER_S = 1_000_000_000


@dataclass(frozen=True, slots=True)
class Summary:
    """Order statistics of one sample (ms, or whatever unit went in). `n` = 0: all NaN."""

    n: int
    p50: float
    p99: float
    max: float
    mean: float
    min: float

    def as_dict(self) -> dict[str, float | int | None]:
        """JSON-ready: NaN (no data) becomes None."""
        return {
            "n": self.n,
            "p50": _finite_or_none(self.p50),
            "p99": _finite_or_none(self.p99),
            "max": _finite_or_none(self.max),
            "mean": _finite_or_none(self.mean),
            "min": _finite_or_none(self.min),
        }


def _finite_or_none(x: float) -> float | None:
    return float(x) if math.isfinite(x) else None


def percentile(values: Sequence[float] | np.ndarray, q: float) -> float:
    """The q-th percentile (0 ≤ q ≤ 100), linear between order statistics (numpy's default,
    so p50 of an even count is the mean of the middle two). Empty input → NaN."""
    if not 0.0 <= q <= 100.0:
        raise ValueError(f"percentile {q} outside [0, 100]")
    a = np.asarray(values, dtype=float)
    if a.size == 0:
        return math.nan
    return float(np.percentile(a, q))


def summarize(values: Sequence[float] | np.ndarray) -> Summary:
    """p50, p99, max, mean and min of `values` (NaN everywhere when empty)."""
    a = np.asarray(values, dtype=float)
    if a.size == 0:
        nan = math.nan
        return Summary(0, nan, nan, nan, nan, nan)
    return Summary(
        n=int(a.size),
        p50=percentile(a, 50.0),
        p99=percentile(a, 99.0),
        max=float(a.max()),
        mean=float(a.mean()),
        min=float(a.min()),
    )


def latencies_ms(rx_ns: Sequence[int] | np.ndarray, t_ns: Sequence[int] | np.ndarray) -> np.ndarray:
    """One-way latencies (ms): arrival time minus the sender's stamp, element by element."""
    rx = np.asarray(rx_ns, dtype=np.int64)
    tx = np.asarray(t_ns, dtype=np.int64)
    if rx.shape != tx.shape:
        raise ValueError(f"{rx.size} arrival times for {tx.size} stamps")
    return (rx - tx).astype(float) / NS_PER_MS


@dataclass(frozen=True, slots=True)
class SeqLoss:
    """What a stream's `seq` numbers say about delivery.

    Loss is counted between the first and the last `seq` received (a probe that joins a
    running stream cannot see what was sent before it, nor after it stops): `expected` =
    last − first + 1, `lost` = expected − distinct seqs received. `duplicates` counts
    repeated seqs; `reordered` counts arrivals lower than a seq already received.
    """

    received: int
    unique: int
    first: int | None
    last: int | None
    expected: int
    lost: int
    duplicates: int
    reordered: int

    @property
    def loss_ratio(self) -> float:
        return self.lost / self.expected if self.expected else 0.0

    def as_dict(self) -> dict[str, float | int | None]:
        return {
            "received": self.received,
            "unique": self.unique,
            "first": self.first,
            "last": self.last,
            "expected": self.expected,
            "lost": self.lost,
            "loss_ratio": self.loss_ratio,
            "duplicates": self.duplicates,
            "reordered": self.reordered,
        }


def seq_loss(seqs: Sequence[int]) -> SeqLoss:
    """Loss, duplicates and reordering in a list of received `seq` numbers, in arrival order."""
    if not seqs:
        return SeqLoss(0, 0, None, None, 0, 0, 0, 0)
    seen: set[int] = set()
    duplicates = reordered = 0
    high = None
    for s in seqs:
        if s in seen:
            duplicates += 1
        else:
            seen.add(s)
        if high is not None and s < high:
            reordered += 1
        high = s if high is None else max(high, s)
    first, last = min(seen), max(seen)
    expected = last - first + 1
    return SeqLoss(
        received=len(seqs),
        unique=len(seen),
        first=first,
        last=last,
        expected=expected,
        lost=expected - len(seen),
        duplicates=duplicates,
        reordered=reordered,
    )


def sent_stream(
    sent: int, records: Sequence[tuple[int, tuple[Any, ...]]], first: int = 0
) -> dict[str, Any]:
    """Figures of a stream the bench knows the sending of: samples `first`+1 … `first`+`sent`
    were sent; `records` are a probe's `(arrival_ns, (seq, t_ns))` (others, such as a route
    set-up's, are left out). Received, rate from the arrivals, one-way latency summary, seq
    loss with `lost` = sent − distinct received."""
    timed = [r for r in records if first < int(r[1][0]) <= first + sent]
    seqs = [int(r[1][0]) for r in timed]
    loss = seq_loss(seqs)
    rx = np.array([r[0] for r in timed], dtype=np.int64)
    return {
        "sent": sent,
        "received": len(seqs),
        "rate_hz": rate_from_times(rx),
        "latency_ms": summarize(latencies_ms(rx, [int(r[1][1]) for r in timed])).as_dict(),
        "loss": {**loss.as_dict(), "lost": sent - loss.unique},
    }


def counters_delta(
    a: Mapping[str, int] | None, b: Mapping[str, int] | None
) -> dict[str, int] | None:
    """b − a per counter read both times, around a measuring window (None if either reading
    failed)."""
    if a is None or b is None:
        return None
    return {k: b[k] - a[k] for k in b if k in a}


def rate_hz(count: int, duration_s: float) -> float:
    """Events per second over a window of `duration_s` (0 for an empty window)."""
    if count < 0:
        raise ValueError("count must be ≥ 0")
    return count / duration_s if duration_s > 0 else 0.0


def rate_from_times(times_ns: Sequence[int] | np.ndarray) -> float:
    """Events per second from their own times: (n − 1) intervals over first → last."""
    t = np.asarray(times_ns, dtype=np.int64)
    if t.size < 2:
        return 0.0
    span = int(t.max() - t.min())
    return (t.size - 1) * NS_PER_S / span if span > 0 else 0.0


def merge_windows(windows: Sequence[tuple[int, int]]) -> list[tuple[int, int]]:
    """The union of closed intervals [start, end] as sorted, disjoint intervals."""
    out: list[tuple[int, int]] = []
    for start, end in sorted((min(a, b), max(a, b)) for a, b in windows):
        if out and start <= out[-1][1]:
            out[-1] = (out[-1][0], max(out[-1][1], end))
        else:
            out.append((start, end))
    return out


@dataclass(frozen=True, slots=True)
class WindowRate:
    """Events that fell inside a set of time windows, and their rate over the windows' union."""

    count: int
    covered_s: float
    rate_hz: float


def rate_in_windows(
    times_ns: Sequence[int] | np.ndarray, windows: Sequence[tuple[int, int]]
) -> WindowRate:
    """How many of `times_ns` fall inside the union of `windows`, per second of that union.

    The paper's "76 Hz during active video intervals": force samples received while a
    stereo pair was in flight, per second of in-flight time.
    """
    merged = merge_windows(windows)
    if not merged:
        return WindowRate(0, 0.0, 0.0)
    t = np.sort(np.asarray(times_ns, dtype=np.int64))
    starts = np.array([w[0] for w in merged], dtype=np.int64)
    ends = np.array([w[1] for w in merged], dtype=np.int64)
    inside = int(
        (np.searchsorted(t, ends, side="right") - np.searchsorted(t, starts, side="left")).sum()
    )
    covered_s = float((ends - starts).sum()) / NS_PER_S
    return WindowRate(inside, covered_s, inside / covered_s if covered_s > 0 else 0.0)


def pair_skew_ms(left_rx_ns: Mapping[int, int], right_rx_ns: Mapping[int, int]) -> list[float]:
    """|right − left| arrival time (ms) of each pair whose two eyes both arrived, by seq."""
    both = sorted(set(left_rx_ns) & set(right_rx_ns))
    return [abs(right_rx_ns[s] - left_rx_ns[s]) / NS_PER_MS for s in both]


@dataclass(frozen=True, slots=True)
class StampedCommands:
    """The operator's path timed from the contract-extension fields (docs/protocol-extensions.md),
    every figure on the machine's one clock.

    reached: distinct bench commands (by `t_ns`) that a `robot/arm/target` carried as its
      `origin_t_ns`: what the arm was given;
    arm_ms: per command `robot/state` showed, `cmd_rx_ns − cmd_origin_t_ns`: master → arm;
    setpoint_ms: per command `robot/state` showed with a `setpoint_ns`, `setpoint_ns −
      cmd_origin_t_ns`: master → the first arm setpoint computed from it;
    sampled: commands `robot/state` showed (a sample: the state stream runs slower than a
      1 kHz master, so it shows only the command newest at each state).

    The same path hop by hop, where the decision's send stamps are known (`sent_at`):
    decision_ms: per reached command, the `t_ns` of the first `robot/arm/target` carrying it
      (the decision's tick) − `origin_t_ns`: master → decision, through the router;
    to_arm_ms: per command shown, `cmd_rx_ns` − that `t_ns`: the decision's tick → the
      arm's receipt (the supervision, the put, the router);
    apply_ms: per command shown with both, `setpoint_ns − cmd_rx_ns`: the arm's receipt →
      the setpoint (its control thread waking, IK and the checks, the tick).
    """

    reached: int
    arm_ms: np.ndarray
    setpoint_ms: np.ndarray
    sampled: int
    decision_ms: np.ndarray = field(default_factory=lambda: np.zeros(0))
    to_arm_ms: np.ndarray = field(default_factory=lambda: np.zeros(0))
    apply_ms: np.ndarray = field(default_factory=lambda: np.zeros(0))


def first_carriers(arm_cmds: Sequence[tuple[int, int | None]]) -> dict[int, int]:
    """`origin_t_ns` → the lowest `robot/arm/target` seq that carried it, from `(seq,
    origin_t_ns)` records (those without an origin, holds and task steps, are left out)."""
    out: dict[int, int] = {}
    for seq, origin in arm_cmds:
        if origin is not None and (origin not in out or seq < out[origin]):
            out[origin] = seq
    return out


def stamped_commands(
    sent_t_ns: Collection[int],
    arm_cmds: Sequence[tuple[int, int | None]],
    states: Sequence[tuple[int, int | None, int | None, int | None]],
    sent_at: Mapping[int, int] | None = None,
) -> StampedCommands:
    """The operator's path from the extension fields.

    sent_t_ns: the `t_ns` of every command the bench sent in the phase;
    arm_cmds: `(seq, origin_t_ns)` per `robot/arm/target` seen (any order);
    states: `(cmd_seq, cmd_rx_ns, setpoint_ns, cmd_origin_t_ns)` per `robot/state`, in
      arrival order;
    sent_at: `robot/arm/target` seq → its `t_ns` (the decision's tick), for the hops.

    Each bench command counts once, through the first arm command that carried it: a later
    arm command carrying the same origin (a re-send) arrived later than the operator's
    command did, so its receive time would overstate the path. Where the arm commands
    were not seen (an empty `arm_cmds`), every state whose origin is ours counts, by its
    first `cmd_seq`. The first state with `cmd_rx_ns` gives master → arm, the first with
    `setpoint_ns` gives master → setpoint (it may come a state later than the receive).
    """
    ours = set(sent_t_ns)
    carriers = first_carriers(arm_cmds)
    reached = sum(1 for origin in carriers if origin in ours)
    rx: dict[int, int] = {}
    setpoint: dict[int, int] = {}
    seq_of: dict[int, int] = {}
    for cmd_seq, cmd_rx_ns, setpoint_ns, origin in states:
        if origin is None or origin not in ours:
            continue
        want = carriers.get(origin) if carriers else seq_of.setdefault(origin, cmd_seq)
        if want != cmd_seq:
            continue
        if cmd_rx_ns is not None:
            rx.setdefault(origin, cmd_rx_ns)
        if setpoint_ns is not None:
            setpoint.setdefault(origin, setpoint_ns)
    shown = set(rx) | set(setpoint)
    at = sent_at or {}
    tick = {o: at[seq] for o, seq in carriers.items() if o in ours and seq in at}

    def ms(pairs: Iterable[tuple[int, int]]) -> np.ndarray:
        return np.array([(b - a) / NS_PER_MS for a, b in pairs], dtype=float)

    return StampedCommands(
        reached=reached,
        arm_ms=ms((o, rx[o]) for o in sorted(rx)),
        setpoint_ms=ms((o, setpoint[o]) for o in sorted(setpoint)),
        sampled=len(shown),
        decision_ms=ms((o, tick[o]) for o in sorted(tick)),
        to_arm_ms=ms((tick[o], rx[o]) for o in sorted(rx) if o in tick),
        apply_ms=ms((rx[o], setpoint[o]) for o in sorted(rx) if o in setpoint),
    )
