"""Scripted master: plays a recorded or generated hand trajectory.

Trajectory files (see docs/master.md, "Trajectory files"), hand pose in the master frame:

- JSON lines (`.jsonl`, `.ndjson`, `.json`): one object per line,
  `{"t": 0.5, "p": [x, y, z], "R": [9 floats, row-major], "clutch": false, "grip": 0.0}`;
  `"w": [wx, wy, wz]` (rotation vector, rad) may replace `"R"`; `R`/`w`, `clutch` (default
  false) and `grip` (default null) are optional.
- CSV (`.csv`): a header naming the columns `t,px,py,pz` and optionally `wx,wy,wz`,
  `clutch` (0/1/true/false), `grip` (empty = none); `#` starts a comment line.

Times (s) strictly increase. Between samples the position is interpolated linearly and the
orientation along the geodesic; clutch and grip hold the earlier sample's value, so a clutch
change takes effect exactly at its sample.
"""

from __future__ import annotations

import bisect
import csv
import io
import itertools
import json
import math
from collections.abc import Callable, Iterable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any, ClassVar

import numpy as np
from numpy.typing import ArrayLike

from services.control.master.config import string
from services.control.master.device import DeviceOptions, HandReading, MasterDevice
from services.control.master.devices.virtual import VirtualMaster
from services.geometry import exp_so3, is_rotation, rot_z, slerp

if TYPE_CHECKING:
    from services.control.master.config import MasterConfig

GENERATED_MOTIONS = ("circle", "line", "square")


class TrajectoryError(ValueError):
    """A trajectory file or sample list that cannot be played."""


@dataclass(frozen=True, slots=True)
class TrajectorySample:
    """One keyframe: t_s (s), p (3, m), R (9, row-major), clutch, grip (0 … 1 or None)."""

    t_s: float
    p: tuple[float, float, float]
    R: tuple[float, ...]
    clutch: bool = False
    grip: float | None = None

    def __post_init__(self) -> None:
        if not math.isfinite(self.t_s) or self.t_s < 0.0:
            raise TrajectoryError(f"t = {self.t_s}: must be finite and ≥ 0")
        if len(self.p) != 3 or not all(math.isfinite(v) for v in self.p):
            raise TrajectoryError(f"t = {self.t_s}: p must be 3 finite numbers")
        if len(self.R) != 9 or not is_rotation(np.array(self.R, dtype=float).reshape(3, 3)):
            raise TrajectoryError(f"t = {self.t_s}: R must be a rotation (9 floats)")
        if self.grip is not None and not 0.0 <= self.grip <= 1.0:
            raise TrajectoryError(f"t = {self.t_s}: grip must be within 0 … 1")

    @classmethod
    def make(
        cls,
        t_s: float,
        p: ArrayLike,
        R: ArrayLike | None = None,
        clutch: bool = False,
        grip: float | None = None,
    ) -> TrajectorySample:
        """Build from arrays (R: 3×3, 9 floats or None for identity)."""
        pv = np.asarray(p, dtype=float).reshape(-1)
        Rv = np.eye(3) if R is None else np.asarray(R, dtype=float)
        if pv.shape != (3,):
            raise TrajectoryError(f"t = {t_s}: p must be 3 numbers")
        if Rv.size != 9:
            raise TrajectoryError(f"t = {t_s}: R must be 9 numbers")
        Rv = Rv.reshape(3, 3)
        return cls(
            float(t_s),
            (float(pv[0]), float(pv[1]), float(pv[2])),
            tuple(float(v) for v in Rv.reshape(9)),
            bool(clutch),
            None if grip is None else float(grip),
        )


class Trajectory:
    """An immutable, time-ordered list of samples that can be sampled at any time."""

    def __init__(self, samples: Iterable[TrajectorySample]) -> None:
        self.samples: tuple[TrajectorySample, ...] = tuple(samples)
        if not self.samples:
            raise TrajectoryError("a trajectory needs at least one sample")
        times = [s.t_s for s in self.samples]
        if any(b <= a for a, b in itertools.pairwise(times)):
            raise TrajectoryError("sample times must strictly increase")
        self._times = times

    @property
    def duration_s(self) -> float:
        """Time of the last sample (s)."""
        return self._times[-1]

    def sample(self, t_s: float) -> HandReading:
        """The hand at t_s: first sample before the start, last one after the end."""
        i = bisect.bisect_right(self._times, t_s) - 1
        if i < 0:
            return _reading(self.samples[0])
        if i >= len(self.samples) - 1:
            return _reading(self.samples[-1])
        a, b = self.samples[i], self.samples[i + 1]
        u = (t_s - a.t_s) / (b.t_s - a.t_s)
        p = (1.0 - u) * np.array(a.p) + u * np.array(b.p)
        R = slerp(np.array(a.R).reshape(3, 3), np.array(b.R).reshape(3, 3), u)
        return HandReading(p, R, a.clutch, a.grip, 0)


def _reading(s: TrajectorySample) -> HandReading:
    return HandReading(np.array(s.p), np.array(s.R).reshape(3, 3), s.clutch, s.grip, 0)


def _parse_bool(value: Any, where: str) -> bool:
    if isinstance(value, bool):
        return value
    text = str(value).strip().lower()
    if text in ("1", "true", "yes"):
        return True
    if text in ("0", "false", "no", ""):
        return False
    raise TrajectoryError(f"{where}: clutch must be 0/1/true/false, got {value!r}")


def _rotation(record: dict[str, Any], where: str) -> np.ndarray:
    if record.get("R") is not None:
        R = np.asarray(record["R"], dtype=float)
        if R.size != 9:
            raise TrajectoryError(f"{where}: R must have 9 numbers")
        return R.reshape(3, 3)
    if record.get("w") is not None:
        w = np.asarray(record["w"], dtype=float)
        if w.size != 3:
            raise TrajectoryError(f"{where}: w must have 3 numbers")
        return exp_so3(w)
    return np.eye(3)


def _sample_from(record: dict[str, Any], where: str) -> TrajectorySample:
    try:
        grip = record.get("grip")
        return TrajectorySample.make(
            float(record["t"]),
            record["p"],
            _rotation(record, where),
            _parse_bool(record.get("clutch", False), where),
            None if grip in (None, "") else float(grip),
        )
    except KeyError as exc:
        raise TrajectoryError(f"{where}: missing field {exc}") from exc
    except TrajectoryError as exc:
        raise TrajectoryError(f"{where}: {exc}") from exc
    except (TypeError, ValueError) as exc:
        raise TrajectoryError(f"{where}: {exc}") from exc


def parse_jsonl(text: str, source: str = "<jsonl>") -> Trajectory:
    """Parse the JSON-lines format (blank lines skipped)."""
    samples = []
    for n, line in enumerate(text.splitlines(), start=1):
        if not line.strip():
            continue
        where = f"{source}:{n}"
        try:
            record = json.loads(line)
        except json.JSONDecodeError as exc:
            raise TrajectoryError(f"{where}: {exc.msg}") from exc
        if not isinstance(record, dict):
            raise TrajectoryError(f"{where}: each line must be a JSON object")
        samples.append(_sample_from(record, where))
    return Trajectory(samples)


def parse_csv(text: str, source: str = "<csv>") -> Trajectory:
    """Parse the CSV format (header row first; `#` lines are comments)."""
    lines = [ln for ln in text.splitlines() if ln.strip() and not ln.lstrip().startswith("#")]
    reader = csv.DictReader(io.StringIO("\n".join(lines)), skipinitialspace=True)
    header = set(reader.fieldnames or [])
    missing = {"t", "px", "py", "pz"} - header
    if missing:
        raise TrajectoryError(f"{source}: header lacks {', '.join(sorted(missing))}")
    has_w = {"wx", "wy", "wz"} <= header
    samples = []
    for n, row in enumerate(reader, start=2):
        record: dict[str, Any] = {
            "t": row["t"],
            "p": [row["px"], row["py"], row["pz"]],
            "clutch": row.get("clutch") or "0",
            "grip": row.get("grip") or None,
        }
        if has_w:
            record["w"] = [row["wx"], row["wy"], row["wz"]]
        samples.append(_sample_from(record, f"{source}: row {n}"))
    return Trajectory(samples)


def load_trajectory(path: str | Path) -> Trajectory:
    """Read a .jsonl/.ndjson/.json or .csv trajectory file (other suffixes: sniffed)."""
    file = Path(path)
    try:
        text = file.read_text(encoding="utf-8")
    except OSError as exc:
        raise TrajectoryError(f"cannot read {file}: {exc}") from exc
    suffix = file.suffix.lower()
    if suffix == ".csv":
        return parse_csv(text, str(file))
    if suffix in (".jsonl", ".ndjson", ".json"):
        return parse_jsonl(text, str(file))
    first = next((ln.strip() for ln in text.splitlines() if ln.strip()), "")
    return parse_jsonl(text, str(file)) if first.startswith("{") else parse_csv(text, str(file))


def save_trajectory(path: str | Path, trajectory: Trajectory) -> None:
    """Write a trajectory as JSON lines (the format `load_trajectory` reads back)."""
    with Path(path).open("w", encoding="utf-8") as out:
        for s in trajectory.samples:
            record = {"t": s.t_s, "p": list(s.p), "R": list(s.R), "clutch": s.clutch}
            record["grip"] = s.grip
            out.write(json.dumps(record) + "\n")


PoseFn = Callable[[float], tuple[np.ndarray, np.ndarray]]


@dataclass(frozen=True, slots=True)
class _Segment:
    duration_s: float
    pose: PoseFn
    clutch: bool


def _linear(p0: ArrayLike, p1: ArrayLike, duration_s: float) -> PoseFn:
    a, b = np.array(p0, dtype=float), np.array(p1, dtype=float)
    return lambda t: (a + (b - a) * min(max(t / duration_s, 0.0), 1.0), np.eye(3))


def _render(segments: Sequence[_Segment], dt_s: float) -> Trajectory:
    """Sample segments every dt_s. A segment's clutch holds from its first sample until the
    next segment's; poses are continuous at the joins, so a clutch change is a keyframe with
    the hand in the same place on both sides."""
    samples: list[TrajectorySample] = []
    t0 = 0.0
    for seg in segments:
        n = max(1, math.ceil(seg.duration_s / dt_s - 1e-9))
        for i in range(n):
            p, R = seg.pose(i * seg.duration_s / n)
            samples.append(TrajectorySample.make(t0 + i * seg.duration_s / n, p, R, seg.clutch))
        t0 += seg.duration_s
    last = segments[-1]
    p, R = last.pose(last.duration_s)
    samples.append(TrajectorySample.make(t0, p, R, last.clutch))
    return Trajectory(samples)


def generate_motion(
    kind: str,
    *,
    size_m: float = 0.1,
    period_s: float = 4.0,
    cycles: int = 2,
    dt_s: float = 0.02,
) -> Trajectory:
    """A test motion starting at the origin with identity orientation.

    circle: radius size_m/2 in the x–y plane, one turn per period_s, with a ±0.2 rad wrist
        twist about z; no clutch.
    line: a ratchet along +x: stroke size_m forward, master-shift, return with the
        master-shift held, release; the slave should advance size_m per cycle while the
        hand stays near the origin.
    square: four edges of size_m (x, y, −x, −y); at each corner the master-shift is held
        while the hand rises 0.02 m, so the hand climbs a staircase while the slave draws a
        flat square.

    Every master-shift press and release happens in a pause (hand still, `pause_s`, at
    least a few command ticks long), so no hand motion falls between the last command
    before a press or the first one after a release and the slave loses none of it.
    """
    if kind not in GENERATED_MOTIONS:
        raise TrajectoryError(f"unknown motion {kind!r}; one of {', '.join(GENERATED_MOTIONS)}")
    if size_m <= 0.0 or period_s <= 0.0 or cycles < 1 or dt_s <= 0.0:
        raise TrajectoryError("size_m, period_s, dt_s must be > 0 and cycles ≥ 1")
    if kind == "circle":
        r, omega = size_m / 2.0, 2.0 * math.pi / period_s

        def circle(t: float) -> tuple[np.ndarray, np.ndarray]:
            p = np.array([r * (math.cos(omega * t) - 1.0), r * math.sin(omega * t), 0.0])
            return p, rot_z(0.2 * math.sin(omega * t))

        return _render([_Segment(period_s * cycles, circle, False)], dt_s)
    pause_s = min(0.1, period_s / 10.0)

    def still(at: ArrayLike, clutch: bool) -> _Segment:
        return _Segment(pause_s, _linear(at, at, pause_s), clutch)

    origin = np.zeros(3)
    segments: list[_Segment] = [still(origin, False)]
    if kind == "line":
        stroke_s = period_s / 2.0 - pause_s
        end = np.array([size_m, 0.0, 0.0])
        for _ in range(cycles):
            segments += [
                _Segment(stroke_s, _linear(origin, end, stroke_s), False),
                still(end, False),
                _Segment(stroke_s, _linear(end, origin, stroke_s), True),
                still(origin, False),
            ]
        return _render(segments, dt_s)
    edge_s = period_s / 4.0 - 2.0 * pause_s
    if edge_s <= 0.0:
        raise TrajectoryError("period_s too short for a square")
    p = origin
    for _ in range(cycles):
        for dx, dy in ((1, 0), (0, 1), (-1, 0), (0, -1)):
            q = p + np.array([dx * size_m, dy * size_m, 0.0])
            up = q + np.array([0.0, 0.0, 0.02])
            segments += [
                _Segment(edge_s, _linear(p, q, edge_s), False),
                still(q, False),
                _Segment(pause_s, _linear(q, up, pause_s), True),
                still(up, False),
            ]
            p = up
    return _render(segments, dt_s)


@dataclass(frozen=True, slots=True)
class ScriptedOptions(DeviceOptions):
    """`device = "scripted"`: its `[master]` key; nobody holds it, so it engages at once.

    script: a trajectory file (.jsonl/.csv) or a generated motion (`circle`, `line`,
        `square`).
    """

    engages_on_start: ClassVar[bool] = True

    script: str = "circle"

    def __post_init__(self) -> None:
        string(self, "script")

    def build(self, config: MasterConfig) -> MasterDevice:
        return ScriptedMaster(self.script)


class ScriptedMaster(VirtualMaster):
    """Plays a trajectory as a `MasterDevice`; time advances by each read's dt_s.

    script: a generated motion name (`circle`, `line`, `square`), a trajectory file path,
    or a Trajectory. loop: start again at the end; the tick that wraps around reports the
    master-shift pressed, so the jump back to the first sample never reaches the slave.
    A call to `set_hand` (the virtual master's entry point) takes over from the script.
    """

    def __init__(
        self, script: str | Path | Trajectory = "circle", *, loop: bool = False, **motion: Any
    ) -> None:
        if isinstance(script, Trajectory):
            trajectory, label = script, "trajectory"
        elif isinstance(script, str) and script in GENERATED_MOTIONS:
            trajectory, label = generate_motion(script, **motion), script
        else:
            trajectory, label = load_trajectory(script), Path(script).name
        super().__init__(f"scripted:{label}")
        self.trajectory = trajectory
        self._loop = loop
        self._t_s = 0.0
        self._manual = False

    @property
    def t_s(self) -> float:
        """Playback time (s)."""
        return self._t_s

    @property
    def finished(self) -> bool:
        """True once a non-looping script has reached its last sample."""
        return not self._loop and self._t_s >= self.trajectory.duration_s

    @property
    def can_display_force(self) -> bool:
        return True

    def open(self) -> None:
        self._t_s = 0.0

    def set_hand(
        self,
        p: ArrayLike,
        R: ArrayLike | None = None,
        clutch: bool = False,
        grip: float | None = None,
        buttons: int = 0,
    ) -> None:
        """Stop the script and hold the given hand from now on (see VirtualMaster)."""
        super().set_hand(p, R, clutch, grip, buttons)
        self._manual = True

    def read(self, dt_s: float) -> HandReading:
        if self._manual:
            return super().read(dt_s)
        self._t_s += max(float(dt_s), 0.0)
        duration = self.trajectory.duration_s
        if self._loop and duration > 0.0 and self._t_s > duration:
            self._t_s = math.fmod(self._t_s, duration)
            r = self.trajectory.sample(self._t_s)
            return HandReading(r.hand_p, r.hand_R, True, r.grip, r.buttons)
        return self.trajectory.sample(self._t_s)
