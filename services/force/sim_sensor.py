"""The simulated wrist sensor: contact with the simulated workcell, through eq. (4) inverted.

Each `read()` takes the latest tool pose (from robot/state, via `update_pose`), asks the
workcell for the contact force on a probe sphere at the tool point, adds the tool's weight,
an optional external push and small noise, expresses it in the tool frame and turns it into
the six sensing signals with the inverse of eq. (4): the simulated elastic wrist deflects,
and the service recovers the wrench with the forward eq. (4) exactly as on the real wrist.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike

from services.force.events import EventSink, ignore_event
from services.force.gravity import ToolLoad
from services.force.model import Vec, WristModel, as_rotation
from services.force.sensors import Reading, SensorError, Six
from services.workcell.scene import Scene, default_scene


class SimSensor:
    """A simulated compliant wrist in the simulated workcell.

    `model` is the physical truth of the simulated wrist (its calibration, stiffness and
    placements); the service's own model may differ, as it may on a real wrist. `load` is
    the tool's weight. Noise is Gaussian, `noise_n` (N) per force axis and `noise_nm` (N·m)
    per moment axis. Contact moments about the tool point are zero: the probe is a sphere
    of `probe_radius_m` centred on the tool point. Without a pose there is nothing to
    sense: `read()` returns None until the first `update_pose`.
    """

    def __init__(
        self,
        model: WristModel | None = None,
        load: ToolLoad | None = None,
        scene: Scene | None = None,
        *,
        noise_n: float = 0.0,
        noise_nm: float = 0.0,
        probe_radius_m: float = 0.005,
        seed: int | None = None,
        on_event: EventSink = ignore_event,
    ) -> None:
        if not (noise_n >= 0.0 and noise_nm >= 0.0 and probe_radius_m >= 0.0):
            raise ValueError("noise_n, noise_nm and probe_radius_m must be ≥ 0")
        self.on_event = on_event
        self._model = model or WristModel()
        self._load = load or ToolLoad()
        self._scene = scene or default_scene()
        self._noise_n = noise_n
        self._noise_nm = noise_nm
        self._radius_m = probe_radius_m
        self._rng = np.random.default_rng(seed)
        self._pose: tuple[Vec, Vec] | None = None
        self._push: tuple[Vec, Vec] = (np.zeros(3), np.zeros(3))
        self._open = False
        self._count = 0

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

    def open(self) -> None:
        self._open = True

    def close(self) -> None:
        self._open = False

    def update_pose(self, tool_p: ArrayLike, tool_R: ArrayLike) -> None:
        """The tool frame in the world (m; R world←tool), from robot/state."""
        p = np.asarray(tool_p, dtype=float).reshape(3)
        R = as_rotation(tool_R, "tool_R")
        self._pose = (p, R)

    def set_tool(self, p_et: ArrayLike, R_et: ArrayLike) -> None:
        """The simulated tool is mounted at a new placement eMt in the flange frame."""
        self._model = self._model.with_tool(p_et, R_et)

    def push(self, f_t: ArrayLike, c_t: ArrayLike = (0.0, 0.0, 0.0)) -> None:
        """An extra external wrench on the tool (N, N·m about the tool point, tool frame),
        e.g. a hand pushing the tool; zero to release."""
        self._push = (
            np.asarray(f_t, dtype=float).reshape(3),
            np.asarray(c_t, dtype=float).reshape(3),
        )

    def wrench_t(self) -> tuple[Vec, Vec] | None:
        """The noiseless wrench on the tool now (tool frame, weight included); None: no pose."""
        pose = self._pose
        if pose is None:
            return None
        p, R = pose
        f_w = self._scene.contact_force(p, self._radius_m)
        fg, cg = self._load.wrench(R)
        push_f, push_c = self._push
        return R.T @ f_w + fg + push_f, cg + push_c

    def read(self) -> Reading | None:
        if not self._open:
            raise SensorError("sim sensor is not open")
        w = self.wrench_t()
        if w is None:
            return None
        f, c = w
        if self._noise_n > 0.0:
            f = f + self._rng.normal(0.0, self._noise_n, 3)
        if self._noise_nm > 0.0:
            c = c + self._rng.normal(0.0, self._noise_nm, 3)
        s = self._model.signals_from_wrench(f, c)
        self._count += 1
        values: Six = (float(s[0]), float(s[1]), float(s[2]), float(s[3]), float(s[4]), float(s[5]))
        return Reading("signals", values, self._count)
