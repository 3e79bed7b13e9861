"""The simulated wrist sensor: the cell's physics at the wrist, through eq. (4) inverted.

With the workcell's physics running (MuJoCo, docs/sim.md), each `read()` takes the wrench
its solver computes on the tool (`update_physics`, from `sim/arm/state`: contacts, the
tool's and the carried object's weight and inertia, what the object touches), adds an
optional external push and small noise, and turns it into the six sensing signals with the
inverse of eq. (4): the simulated elastic wrist deflects, and the service recovers the
wrench with the forward eq. (4) exactly as on the real wrist.

Without a physics wrench for `PHYSICS_STALE_S` (an arm on its own physics, `[arm]
sim_physics = "own"`: the arm alone, no cell around it) the wrist is in free space and
measures what a wrist in free space measures: the tool's weight and, with `inertia`, its
inertial force from the tool's acceleration (estimated from robot/state), the optional
push, and noise. Nothing is touched and nothing carried: contact is the cell's physics'
alone (there is no second contact model).
"""

from __future__ import annotations

import threading
import time

import numpy as np
from numpy.typing import ArrayLike

from services.control.force.events import EventSink, ignore_event
from services.control.force.gravity import ToolLoad
from services.control.force.kernel import (
    ZERO3,
    WristKernel,
    cross,
    mat9,
    mul,
    transpose,
    vec3,
    weight_wrench,
)
from services.control.force.model import Vec, WristModel, as_rotation
from services.control.force.sensors import Reading, SensorError, Six
from services.geometry import M9, V3

NOISE_BLOCK = 256
"""Samples' worth of Gaussian noise drawn at once."""
ACCEL_MAX_MPS2 = 20.0
"""The tool acceleration estimate is clipped to this (m/s²): a timestamp glitch in
robot/state must not read as a kilonewton."""
ACCEL_TAU_S = 0.03
"""Low-pass time constant (s) of the acceleration estimate (second differences of the
tool position at the robot/state rate are noisy)."""
ACCEL_DT_RANGE_S = (2e-4, 0.1)
"""robot/state intervals outside this (s) restart the acceleration estimate."""
PHYSICS_STALE_S = 0.1
"""A physics wrench older than this (s) is not the wrist's any more."""


class _Accel:
    """The tool point's acceleration (world, m/s²) from successive robot/state positions."""

    def __init__(self) -> None:
        self.reset()

    def reset(self) -> None:
        self._p: V3 | None = None
        self._t = 0
        self._v: V3 | None = None
        self.a: V3 = ZERO3

    def update(self, p: V3, t_ns: int) -> V3:
        lo, hi = ACCEL_DT_RANGE_S
        if self._p is None or not lo <= (t_ns - self._t) * 1e-9 <= hi:
            self.reset()
            self._p, self._t = p, t_ns
            return self.a
        dt = (t_ns - self._t) * 1e-9
        v = ((p[0] - self._p[0]) / dt, (p[1] - self._p[1]) / dt, (p[2] - self._p[2]) / dt)
        if self._v is not None:
            k = dt / (ACCEL_TAU_S + dt)
            a = self.a
            raw = ((v[0] - self._v[0]) / dt, (v[1] - self._v[1]) / dt, (v[2] - self._v[2]) / dt)
            a = tuple(  # type: ignore[assignment]
                min(ACCEL_MAX_MPS2, max(-ACCEL_MAX_MPS2, a[i] + k * (raw[i] - a[i])))
                for i in range(3)
            )
            self.a = a
        self._p, self._t, self._v = p, t_ns, v
        return self.a


class SimSensor:
    """A simulated compliant wrist: the cell's physics at the wrist, or free space.

    `model` is the physical truth of the simulated wrist (its calibration, stiffness and
    placements); the service's own model may differ, as it may on a real wrist. `load` is
    the tool's weight. Noise is Gaussian, `noise_n` (N) per force axis and `noise_nm` (N·m)
    per moment axis.

    With a fresh physics wrench (`update_physics`, the workcell's MuJoCo solver) that
    wrench is the wrist's: the tool's weight and inertia, every contact, a carried
    object's weight and what it touches. Without one (the arm on its own physics) the
    wrist is in free space: the tool's weight and, with `inertia` (off by default), m·(−a)
    at its centre of mass from the tool's acceleration (robot/state); no contact, nothing
    carried. Off because the force service compensates the tool's weight, not its inertia:
    with the decision's compliance on, the tool's own acceleration read as a push moves the
    target, which accelerates the tool again (the arm never came to rest in the compose run,
    2026-12-02). Without
    a pose there is nothing to sense then: `read()` returns None until the first
    `update_pose`. `push` adds an external wrench either way.
    """

    #: its data is computed, not streamed by a device: sampled slower while unused
    may_idle = True

    def __init__(
        self,
        model: WristModel | None = None,
        load: ToolLoad | None = None,
        *,
        noise_n: float = 0.0,
        noise_nm: float = 0.0,
        seed: int | None = None,
        inertia: bool = False,
        on_event: EventSink = ignore_event,
    ) -> None:
        if not (noise_n >= 0.0 and noise_nm >= 0.0):
            raise ValueError("noise_n and noise_nm must be ≥ 0")
        self.on_event = on_event
        self._model = model or WristModel()
        self._kernel = WristKernel(self._model)
        self._load = load or ToolLoad()
        self._noise_n = noise_n
        self._noise_nm = noise_nm
        self._inertia = inertia
        self._rng = np.random.default_rng(seed)
        self._noise: list[float] = []
        self._noise_at = 0
        self._lock = threading.Lock()  # pose updates and reads come from two threads
        self._accel = _Accel()
        # Per pose: (p, Rᵀ, the tool's weight and inertia: force and moment, tool frame).
        self._pose: tuple[V3, M9, V3, V3] | None = None
        self._push: tuple[V3, V3] = (ZERO3, ZERO3)
        self._open = False
        self._count = 0
        self._physics: tuple[V3, V3, float] | None = None
        self.physics_updates = 0

    @property
    def name(self) -> str:
        return "sim"

    @property
    def bad(self) -> int:
        return 0

    @property
    def gaps(self) -> int:
        return 0

    @property
    def model(self) -> WristModel:
        return self._model

    @property
    def acceleration(self) -> V3:
        """The tool point's estimated acceleration (m/s², world) from robot/state."""
        return self._accel.a

    @property
    def physics_fresh(self) -> bool:
        """A physics wrench arrived within `PHYSICS_STALE_S`: the wrist is the cell's."""
        ph = self._physics
        return ph is not None and time.monotonic() - ph[2] <= PHYSICS_STALE_S

    def open(self) -> None:
        self._open = True

    def close(self) -> None:
        self._open = False

    def update_pose(self, tool_p: ArrayLike, tool_R: ArrayLike, t_ns: int | None = None) -> None:
        """The tool frame in the world (m; R world←tool), from robot/state at `t_ns`
        (the state's own time stamp, ns; None: no acceleration estimate)."""
        p = vec3(tool_p)
        R = mat9(as_rotation(tool_R, "tool_R"))
        self._set_pose(p, R, t_ns)

    def update_pose_checked(self, p: V3, R: M9, t_ns: int | None = None) -> None:
        """`update_pose` for a pose already validated (a decoded RobotState)."""
        self._set_pose(p, R, t_ns)

    def _set_pose(self, p: V3, R: M9, t_ns: int | None) -> None:
        with self._lock:
            a = self._accel.update(p, t_ns) if t_ns is not None else ZERO3
            f, c = self._free(R, a if self._inertia else ZERO3)
            self._pose = (p, transpose(R), f, c)

    def _free(self, R: M9, a: V3) -> tuple[V3, V3]:
        """The tool's weight and inertia in free space, tool frame: m (g⃗ − a⃗) at its
        centre of mass."""
        load = self._load
        m, g = load.mass_kg, load.gravity_mps2
        if a == ZERO3:
            return weight_wrench(m, g, vec3(load.com_m), R)
        fo = mul(transpose(R), -m * a[0], -m * a[1], -m * (g + a[2]))
        return fo, cross(vec3(load.com_m), fo)

    def set_tool(self, p_et: ArrayLike, R_et: ArrayLike) -> None:
        """The simulated tool is mounted at a new placement eMt in the flange frame."""
        self._model = self._model.with_tool(p_et, R_et)
        self._kernel = WristKernel(self._model)

    def push(self, f_t: ArrayLike, c_t: ArrayLike = (0.0, 0.0, 0.0)) -> None:
        """An extra external wrench on the tool (N, N·m about the tool point, tool frame),
        e.g. a hand pushing the tool; zero to release."""
        self._push = (vec3(f_t), vec3(c_t))

    def wrench_t(self) -> tuple[Vec, Vec] | None:
        """The noiseless wrench on the tool now (tool frame, weights included); None: no pose."""
        w = self._wrench()
        if w is None:
            return None
        return np.array(w[0]), np.array(w[1])

    def update_physics(self, f_t: V3, c_t: V3) -> None:
        """The wrench of the world on the tool (N, N·m about the tool point, tool frame) as
        the cell's physics computes it now (validated: a decoded `sim/arm/state`)."""
        self._physics = (
            (float(f_t[0]), float(f_t[1]), float(f_t[2])),
            (float(c_t[0]), float(c_t[1]), float(c_t[2])),
            time.monotonic(),
        )
        self.physics_updates += 1

    def _wrench(self) -> tuple[V3, V3] | None:
        ph = self._physics
        (px, py, pz), (qx, qy, qz) = self._push
        if ph is not None and time.monotonic() - ph[2] <= PHYSICS_STALE_S:
            (fx, fy, fz), (cx, cy, cz) = ph[0], ph[1]
            return (fx + px, fy + py, fz + pz), (cx + qx, cy + qy, cz + qz)
        pose = self._pose
        if pose is None:
            return None
        _, _, (fx, fy, fz), (cx, cy, cz) = pose
        return (fx + px, fy + py, fz + pz), (cx + qx, cy + qy, cz + qz)

    def read(self) -> Reading | None:
        if not self._open:
            raise SensorError("sim sensor is not open")
        w = self._wrench()
        if w is None:
            return None
        f, c = w
        if self._noise_n > 0.0 or self._noise_nm > 0.0:
            i = self._noise_at
            if i >= len(self._noise):
                # Unit normals drawn NOISE_BLOCK samples at a time: one numpy call per
                # block instead of six Python gauss() calls (~6 µs) per sample.
                self._noise = self._rng.standard_normal(6 * NOISE_BLOCK).tolist()
                i = 0
            self._noise_at = i + 6
            z, sn, sm = self._noise, self._noise_n, self._noise_nm
            f = (f[0] + sn * z[i], f[1] + sn * z[i + 1], f[2] + sn * z[i + 2])
            c = (c[0] + sm * z[i + 3], c[1] + sm * z[i + 4], c[2] + sm * z[i + 5])
        values: Six = self._kernel.signals_from_wrench(f, c)
        self._count += 1
        return Reading("signals", values, self._count)
