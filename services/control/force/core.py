"""`ForceCore`: the force service without the bus — sampler, eq. (4), gravity, bias, RPCs.

Per sample (on the sampling thread): the sensor's reading → (F_t, C_t) at the tool point in
the tool frame (eq. 4 for six signals; a frame change for a calibrated wrench) → minus the
tool's weight (when the arm's orientation is known) → minus the bias → a ForceSample,
handed to `publish` through the sampler's non-blocking queue.

The service wiring (`__main__.py`/`service.py`) owns the bus: it passes `publish` (put on
`robot/force`) and `emit` (put an Event on `robot/events`), serves the `rpc_*` methods as
the IForceSensor queryables of PROTOCOL.md §4 (an `RpcError` becomes the error reply), and
feeds `update_robot_state` from `robot/state`.
"""

from __future__ import annotations

import threading
import time
from collections.abc import Callable, Sequence
from typing import Any

import numpy as np
from numpy.typing import ArrayLike

from services.bus import codec
from services.bus.bounds import check_each, short
from services.bus.errors import ProtocolError, RpcError
from services.bus.messages import ForceSample
from services.control.force.backends import open_force_sensor
from services.control.force.config import ForceConfig
from services.control.force.events import EventSink, EventThrottle
from services.control.force.kernel import (
    ZERO3,
    WristKernel,
    mat9,
    mul,
    transpose,
    vec3,
    weight_wrench,
)
from services.control.force.model import Vec, WristModel, as_rotation, as_vec3
from services.control.force.priority import PRIORITY_LEVELS
from services.control.force.sampler import MonotonicClock, Sampler, SamplerClock, check_period_ms
from services.control.force.sensors import (
    ForceSensor,
    IdlingSensor,
    PoseAwareSensor,
    SensorError,
    WorldAwareSensor,
)
from services.geometry import M9, V3

IDLE_PERIOD_MS = 20.0
"""The simulated sensor's period while nobody uses the samples (`ForceCore.set_unused`)."""
TOOL_CHANGE_TOL = 1e-6
"""m and rad: a flange→tool placement from robot/state that differs more is a new tool."""


class _BiasRequest:
    """Averages the next `n` (weight-compensated, unbiased) wrenches on the sampling thread."""

    def __init__(self, n: int) -> None:
        self.n = n
        self.count = 0
        self.f_sum = [0.0, 0.0, 0.0]
        self.c_sum = [0.0, 0.0, 0.0]
        self.done = threading.Event()

    def add(self, f: V3, c: V3) -> bool:
        fs, cs = self.f_sum, self.c_sum
        for i in range(3):
            fs[i] += f[i]
            cs[i] += c[i]
        self.count += 1
        return self.count >= self.n

    def mean(self) -> tuple[V3, V3]:
        n = self.n
        fs, cs = self.f_sum, self.c_sum
        return (fs[0] / n, fs[1] / n, fs[2] / n), (cs[0] / n, cs[1] / n, cs[2] / n)


class ForceCore:
    """The force sensing component: one sensor, one sampling thread, the IForceSensor calls.

    `publish(fields)` and `emit(kind, message, data)` are called on the sampler's publisher
    thread, never on the sampling thread. RPC methods may be called from any thread; they
    raise RpcError with a PROTOCOL.md §4 code. The sampling thread exists (idle) from
    construction; `close()` ends it and closes the sensor.
    """

    def __init__(
        self,
        sensor: ForceSensor,
        config: ForceConfig,
        publish: Callable[[ForceSample], None],
        emit: EventSink,
        *,
        clock: SamplerClock | None = None,
    ) -> None:
        self._sensor = sensor
        self._config = config
        self._model = config.wrist_model()
        self._kernel = WristKernel(self._model)
        self._tool_eMt: tuple[V3, M9] = (vec3(self._model.p_et), mat9(self._model.R_et))
        self._load = config.tool_load()
        self._load_com: V3 = vec3(self._load.com_m)
        self._posed: PoseAwareSensor | None = (
            sensor if isinstance(sensor, PoseAwareSensor) else None
        )
        self._worldly: WorldAwareSensor | None = (
            sensor if isinstance(sensor, WorldAwareSensor) else None
        )
        self._may_idle = isinstance(sensor, IdlingSensor) and bool(sensor.may_idle)
        self._tool_R: M9 | None = None
        # The tool's weight in the tool frame for the latest orientation (None: unknown).
        self._gravity: tuple[V3, V3] | None = None
        self._bias: tuple[V3, V3] = (ZERO3, ZERO3)
        self._bias_req: _BiasRequest | None = None
        self._seq = 0
        self._latest: ForceSample | None = None
        self._ctl = threading.RLock()
        self._sampler: Sampler[ForceSample] = Sampler(
            self._acquire,
            publish,
            period_ms=config.period_ms,
            priority=config.priority,
            on_event=emit,
            queue_len=config.queue_len,
            handoff=config.handoff,
            stale_after_periods=config.stale_after_periods,
            clock=clock or MonotonicClock(spin_us=config.spin_us),
        )
        sensor.on_event = EventThrottle(self._sampler.post_event, config.event_interval_s)
        self._unused = False

    @classmethod
    def from_config(
        cls,
        config: ForceConfig,
        publish: Callable[[ForceSample], None],
        emit: EventSink,
    ) -> ForceCore:
        """The core with the sensor backend `config.sensor` (not yet opened)."""
        return cls(open_force_sensor(config), config, publish, emit)

    @property
    def sensor(self) -> ForceSensor:
        return self._sensor

    @property
    def sampler(self) -> Sampler[ForceSample]:
        return self._sampler

    @property
    def latest(self) -> ForceSample | None:
        return self._latest

    def set_unused(self, unused: bool) -> None:
        """Nobody uses the samples (nobody subscribes to robot/force): a sensor that may
        idle (the simulated one: its data is computed, not streamed by a device) is sampled
        every IDLE_PERIOD_MS instead, so status, `sensor_read` and the stale watch stay
        current; used again, the next sample is taken at once. A real sensor is read at its
        rate whatever (its device streams)."""
        with self._ctl:
            self._unused = unused
            self._apply_idle()

    def _apply_idle(self) -> None:
        idle = self._unused and self._bias_req is None and self._may_idle
        self._sampler.set_slow(IDLE_PERIOD_MS if idle else None)

    @property
    def idle(self) -> bool:
        """Sampled at IDLE_PERIOD_MS (see `set_unused`)."""
        return self._sampler.slow

    def close(self) -> None:
        """Stop sensing, end the threads, close the sensor. Idempotent."""
        with self._ctl:
            self._sampler.close()
            self._sensor.close()

    # --- from robot/state and arm's set_tool -------------------------------------------

    def update_robot_state(
        self,
        tool_p: ArrayLike,
        tool_R: ArrayLike,
        flange_p: ArrayLike | None = None,
        flange_R: ArrayLike | None = None,
        t_ns: int | None = None,
    ) -> None:
        """The arm's pose from robot/state (world; R world←tool, 9 row-major or 3×3).

        The tool orientation drives gravity compensation; a simulated sensor also senses
        at this pose (and, with the state's `t_ns`, estimates the tool's acceleration). With
        the flange pose too, the tool placement eMt = flange⁻¹·tool is derived, and a
        changed placement (arm's set_tool) updates the model. Validates its input; a
        decoded RobotState (already validated) may use `update_robot_state_checked`.
        """
        p = np.asarray(tool_p, dtype=float).reshape(3)
        if not np.all(np.isfinite(p)):
            raise ProtocolError("tool_p", "not finite")
        try:
            R = as_rotation(tool_R, "tool_R")
        except ValueError as e:
            raise ProtocolError("tool_R", str(e)) from None
        flange: tuple[V3, M9] | None = None
        if flange_p is not None and flange_R is not None:
            fp = np.asarray(flange_p, dtype=float).reshape(3)
            if not np.all(np.isfinite(fp)):
                raise ProtocolError("flange_p", "not finite")
            try:
                flange = (vec3(fp), mat9(as_rotation(flange_R, "flange_R")))
            except ValueError as e:
                raise ProtocolError("flange_R", str(e)) from None
        self.update_robot_state_checked(vec3(p), mat9(R), flange, t_ns)

    def update_robot_state_checked(
        self, p: V3, R: M9, flange: tuple[V3, M9] | None = None, t_ns: int | None = None
    ) -> None:
        """`update_robot_state` for values already validated (finite, R a rotation), as a
        decoded RobotState's: plain floats, nothing recomputed per sample."""
        self._tool_R = R
        self._gravity = weight_wrench(
            self._load.mass_kg, self._load.gravity_mps2, self._load_com, R
        )
        if self._worldly is not None:
            self._worldly.update_pose_checked(p, R, t_ns)
        elif self._posed is not None:
            self._posed.update_pose(p, np.asarray(R).reshape(3, 3))
        if flange is None:
            return
        fp, Rf = flange
        Rft = transpose(Rf)
        # eMt = flange⁻¹ · tool: R_et = R_fᵀ R (columns of R through R_fᵀ), p_et = R_fᵀ (p − fp)
        cols = [mul(Rft, R[j], R[3 + j], R[6 + j]) for j in range(3)]
        R_et = (
            cols[0][0], cols[1][0], cols[2][0],
            cols[0][1], cols[1][1], cols[2][1],
            cols[0][2], cols[1][2], cols[2][2],
        )  # fmt: skip
        p_et = mul(Rft, p[0] - fp[0], p[1] - fp[1], p[2] - fp[2])
        old_p, old_R = self._tool_eMt
        if (
            max(abs(a - b) for a, b in zip(p_et, old_p, strict=True)) > TOOL_CHANGE_TOL
            or max(abs(a - b) for a, b in zip(R_et, old_R, strict=True)) > TOOL_CHANGE_TOL
        ):
            self.set_tool(np.asarray(p_et), np.asarray(R_et).reshape(3, 3))

    def update_physics(self, f_t: V3, c_t: V3) -> None:
        """The wrench the cell's physics computes on the tool now (`sim/arm/state`, tool
        frame): what a simulated sensor reads. Other sensors ignore it."""
        if self._worldly is not None:
            self._worldly.update_physics(f_t, c_t)

    @property
    def physics_updates(self) -> int:
        """Physics wrenches the sensor took (0: a real sensor, or no cell's physics yet)."""
        return self._worldly.physics_updates if self._worldly is not None else 0

    def set_tool(self, p: ArrayLike, R: ArrayLike) -> None:
        """The tool placement eMt in the flange frame (m; R flange←tool), as arm's set_tool."""
        p_et = np.asarray(p, dtype=float).reshape(3)
        if not np.all(np.isfinite(p_et)):
            raise ProtocolError("p", "not finite")
        try:
            R_et = as_rotation(R, "R")
        except ValueError as e:
            raise ProtocolError("R", str(e)) from None
        self._set_model(self._model.with_tool(p_et, R_et))
        self._tool_eMt = (vec3(p_et), mat9(R_et))
        if self._posed is not None:
            self._posed.set_tool(p_et, R_et)
        self._sampler.post_event(
            "status",
            "force model: new tool placement",
            {"tool_p": p_et.tolist(), "tool_R": R_et.reshape(9).tolist()},
        )

    def _set_model(self, model: WristModel) -> None:
        # The sampling thread reads the kernel only: swap it in one assignment.
        self._model = model
        self._kernel = WristKernel(model)

    # --- IForceSensor (PROTOCOL.md §4) -------------------------------------------------

    def rpc_sensor_status(self, args: dict[str, Any]) -> dict[str, Any]:
        """{running, period_ms, priority, rate_hz, samples} and the details behind them."""
        st = self._sampler.stats().as_dict()
        f_b, c_b = self._bias
        latest = self._latest
        st.update(
            sensor=self._sensor.name,
            bad=self._sensor.bad,
            gaps=self._sensor.gaps,
            seq=latest.seq if latest else 0,
            gravity_compensated=self._gravity is not None,
            bias={"f": list(f_b), "c": list(c_b)},
            K_l=self._model.K_l.tolist(),
            K_r=self._model.K_r.tolist(),
        )
        return st

    def rpc_sensor_start(self, args: dict[str, Any]) -> dict[str, Any]:
        """Open the sensor and trigger sensing (no-op when running)."""
        with self._ctl:
            if self._sampler.closed:
                raise RpcError("not_ready", "the force service is shutting down")
            if not self._sampler.running:
                try:
                    self._sensor.open()
                except (SensorError, OSError) as e:
                    raise RpcError("unreachable", f"{self._sensor.name}: {e}") from None
                self._sampler.start()
                self._sampler.post_event(
                    "status",
                    "force sensing started",
                    {"running": True, "sensor": self._sensor.name},
                )
        return self.rpc_sensor_status({})

    def rpc_sensor_stop(self, args: dict[str, Any]) -> dict[str, Any]:
        """Halt sensing and close the sensor."""
        with self._ctl:
            was_running = self._sampler.running
            if not self._sampler.stop():
                raise RpcError("busy", "the sampling thread did not stop in time")
            self._sensor.close()
            if was_running:
                self._sampler.post_event(
                    "status",
                    "force sensing stopped",
                    {"running": False, "sensor": self._sensor.name},
                )
        return self.rpc_sensor_status({})

    def rpc_sensor_config(self, args: dict[str, Any]) -> dict[str, Any]:
        """{period_ms?, priority?}: TimerValue and SensorThreadPriority, applied live.

        Both are checked before either is applied. The reply is the status, whose
        `priority_applied` says what the OS granted.
        """
        period: float | None = None
        if "period_ms" in args:
            try:
                period = check_period_ms(args["period_ms"])
            except ValueError as e:
                raise RpcError("bad_request", str(e)) from None
        level = args.get("priority")
        if level is not None and level not in PRIORITY_LEVELS:
            raise RpcError(
                "bad_request", f"priority: one of {list(PRIORITY_LEVELS)}, got {level!r}"
            )
        with self._ctl:
            if period is not None:
                self._sampler.set_period_ms(period)
            if level is not None:
                self._sampler.set_priority(level)
        return self.rpc_sensor_status({})

    def rpc_sensor_bias(self, args: dict[str, Any]) -> dict[str, Any]:
        """Tare: the mean of the next `bias_samples` readings becomes the zero.

        `{"clear": true}` removes the bias instead. Needs running sensing.
        """
        clear = args.get("clear", False)
        if not isinstance(clear, bool):
            raise RpcError("bad_request", f"clear: expected true/false, got {clear!r}")
        if clear:
            self._bias = (ZERO3, ZERO3)
            return self._bias_reply(0)
        with self._ctl:
            if not self._sampler.running:
                raise RpcError("not_ready", "sensing is stopped: call sensor_start first")
            req = _BiasRequest(self._config.bias_samples)
            self._bias_req = req
            self._apply_idle()  # the bias is taken at the sensor's rate
            timeout_s = max(1.0, 20.0 * req.n * self._sampler.period_ms / 1e3)
            try:
                if not req.done.wait(timeout_s):
                    raise RpcError("unreachable", f"no data from {self._sensor.name} to bias with")
            finally:
                self._bias_req = None
                self._apply_idle()
        return self._bias_reply(req.n)

    def rpc_sensor_compliance(self, args: dict[str, Any]) -> dict[str, Any]:
        """{K_l?, K_r?}: the wrist stiffness (N/m, N·m/rad), a number or 3, positive, finite.

        Replies with the stiffness now in use (an empty call just reads it).
        """
        values: dict[str, Vec] = {}
        for key in ("K_l", "K_r"):
            if key in args:
                values[key] = _stiffness(key, args[key])
        if values:
            self._set_model(self._model.with_compliance(values.get("K_l"), values.get("K_r")))
        return {"K_l": self._model.K_l.tolist(), "K_r": self._model.K_r.tolist()}

    def rpc_sensor_read(self, args: dict[str, Any]) -> dict[str, Any]:
        """The latest ForceSample's fields."""
        latest = self._latest
        if latest is None:
            raise RpcError("not_ready", "no force sample yet")
        return codec.to_fields(latest)

    def _bias_reply(self, n: int) -> dict[str, Any]:
        f_b, c_b = self._bias
        return {"f_bias": list(f_b), "c_bias": list(c_b), "samples": n}

    # --- sampling thread ----------------------------------------------------------------

    def _acquire(self) -> ForceSample | None:
        reading = self._sensor.read()
        if reading is None:
            return None
        t_ns = time.time_ns()
        v = reading.values
        if reading.kind == "signals":
            f, c = self._kernel.wrench_from_signals(v)
        else:
            f, c = self._kernel.wrench_from_sensor_wrench((v[0], v[1], v[2]), (v[3], v[4], v[5]))
        g = self._gravity
        if g is not None:
            (gx, gy, gz), (hx, hy, hz) = g
            f = (f[0] - gx, f[1] - gy, f[2] - gz)
            c = (c[0] - hx, c[1] - hy, c[2] - hz)
        req = self._bias_req
        if req is not None and req.add(f, c):
            self._bias = req.mean()
            self._bias_req = None
            req.done.set()
        (bx, by, bz), (dx, dy, dz) = self._bias
        self._seq += 1
        sample = ForceSample(
            self._seq,
            t_ns,
            (f[0] - bx, f[1] - by, f[2] - bz),
            (c[0] - dx, c[1] - dy, c[2] - dz),
            v,
            True if reading.estimate else None,
        )
        self._latest = sample
        return sample


def _stiffness(key: str, value: Any) -> Vec:
    ok_number = isinstance(value, int | float) and not isinstance(value, bool)
    ok_list = (
        isinstance(value, Sequence)
        and not isinstance(value, str | bytes)
        and len(value) == 3
        and all(isinstance(x, int | float) and not isinstance(x, bool) for x in value)
    )
    if not (ok_number or ok_list):
        raise RpcError("bad_request", f"{key}: a number or 3 numbers, got {short(value)}")
    try:
        v = as_vec3(value, key)
    except ValueError as e:
        raise RpcError("bad_request", short(str(e))) from None
    check_each(key, [float(x) for x in v], "stiffness_n_m" if key == "K_l" else "stiffness_nm_rad")
    return v
